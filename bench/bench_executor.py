#!/usr/bin/env python
"""Benchmark of the executors: one reduced sweep run serially in this process and on a
Dask LocalCluster of 1 and of 2 single-threaded workers, each from an empty artifacts folder.

    python -m bench.bench_executor [--table A3] [--scene synthetic] [--values 1.0 0.85 0.65 0.5]
                                   [--executors in-process,dask:1,dask:2] [--set section.key=value ...]

Prints one row per executor: wall time of the whole sweep (shared upstream stages included), its
ratio to the one-worker cluster, and whether every setting's errors equal those of the first
executor bit for bit (every run is single-threaded, `run.threads=1`, so the numbers cannot depend
on where a run lands). Writes ``bench/executor/executor-<date>.json``. On this 2-core machine two
workers can at best halve the time; the shared upstream (ingest to the reference) runs once, first,
on one worker.
"""
from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

from bench import bench, sweep

ROOT = Path(__file__).resolve().parent.parent

# A sweep row of about a minute on one core: the synthetic scene at its defaults, short rounds,
# round 1 only (what the tables read), no GT-pose surface.
REDUCED = ["run.threads=1", "anchors.iters=100", "successors.iters=60", "successors.max_rounds=1",
           "successors.final_iters=0", "reference_surface.enabled=false"]


def parse_executor(text: str) -> tuple[str, int | None]:
    """'in-process' -> ('in-process', None); 'dask:2' -> ('dask', 2)."""
    name, _, workers = text.partition(":")
    return name, int(workers) if workers else None


def run(table: str, scene: str, values: list[str] | None, executors: list[str], overrides: list[str],
        work: Path) -> dict:
    rows = []
    for text in executors:
        name, workers = parse_executor(text)
        artifacts = work / text.replace(":", "-")
        shutil.rmtree(artifacts, ignore_errors=True)
        started = time.perf_counter()
        result = sweep.run_sweep(table, scene, values, [*REDUCED, *overrides], artifacts, out_root=work / "json",
                                 executor_name=name, workers=workers)
        rows.append({"executor": text, "workers": workers or 1, "wall_seconds": round(time.perf_counter() - started, 1),
                     "errors": {r["label"]: r.get("errors") for r in result["settings"]},
                     "failed": [r["label"] for r in result["settings"] if "error" in r]})
    one = next((r for r in rows if r["executor"] == "dask:1"), rows[0])
    for r in rows:
        r["time_ratio_to_one_worker"] = round(r["wall_seconds"] / one["wall_seconds"], 3)
        r["same_errors_as_first"] = r["errors"] == rows[0]["errors"]
    return {"table": table, "scene": scene, "values": values, "overrides": [*REDUCED, *overrides],
            "date": dt.datetime.now().isoformat(timespec="seconds"),
            "machine": {"platform": platform.platform(), "cpus": os.cpu_count()}, "rows": rows}


def markdown(result: dict) -> str:
    lines = ["| executor | workers | wall (s) | time / 1 worker | same errors as the first row | failed |",
             "|---|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['executor']} | {r['workers']} | {r['wall_seconds']:.1f} | {r['time_ratio_to_one_worker']:.2f} "
                     f"| {'yes' if r['same_errors_as_first'] else 'NO'} | {', '.join(r['failed']) or '-'} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--table", default="A3", choices=list(sweep.TABLES))
    ap.add_argument("--scene", default="synthetic")
    ap.add_argument("--values", nargs="+", default=["1.0", "0.85", "0.65", "0.5"])
    ap.add_argument("--executors", default="in-process,dask:1,dask:2")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "executor")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="manifoldneus_bench_executor_") as tmp:
        result = run(args.table, args.scene, args.values, args.executors.split(","), args.overrides, Path(tmp))
    result["markdown"] = markdown(result)
    bench.write_report(args.out / f"executor-{dt.date.today().isoformat()}.json", result, result["markdown"])
    return 0 if all(r["same_errors_as_first"] and not r["failed"] for r in result["rows"]) else 1


if __name__ == "__main__":
    sys.exit(main())
