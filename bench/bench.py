#!/usr/bin/env python
"""Benchmark: run the pipeline on a scene in one sitting, print a markdown table, write JSON.

    python bench/bench.py --scene scan24 [--set section.key=value ...] [--force-all]

Times and peak memory come from each stage's manifest (measured by the runner); `--force-all`
recomputes every stage so that the times are of this sitting. Results go to
``bench/<scene>/<YYYY-MM-DD>.json``. Speed targets are checked here, never in tests.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import pipeline  # noqa: E402

FRONT_END = ("features", "matching", "covisibility", "spectral", "schedule")


def collect(scene: str, artifacts: Path) -> dict:
    stages = pipeline.load_stages()
    store = pipeline.Store(artifacts, pipeline.resolve_scene(scene).name)
    rows = {}
    for name in stages:
        m = store.manifest(name)
        if m is not None:
            rows[name] = {k: m[k] for k in ("fingerprint", "wall_seconds", "cpu_seconds", "peak_rss_mib", "metrics")}
    return rows


def summarise(rows: dict) -> dict:
    out = {}
    front = [rows[s]["wall_seconds"] for s in FRONT_END if s in rows]
    if len(front) == len(FRONT_END):
        out["front_end_seconds"] = round(sum(front), 2)
        ref = rows.get("reference", {}).get("metrics", {})
        if "extract_match_seconds" in ref:
            out["pycolmap_extract_match_seconds"] = ref["extract_match_seconds"]
            out["front_end_over_pycolmap"] = round(out["front_end_seconds"] / ref["extract_match_seconds"], 3)
    return out


def table(rows: dict) -> str:
    lines = ["| stage | wall s | cpu s | peak MiB | key metrics |", "|---|---:|---:|---:|---|"]
    for name, r in rows.items():
        metrics = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                            for k, v in list(r["metrics"].items())[:8] if not isinstance(v, (dict, list)))
        lines.append(f"| {name} | {r['wall_seconds']:.1f} | {r['cpu_seconds']:.1f} | {r['peak_rss_mib']:.0f} | {metrics} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="scan24")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--until", default=None)
    ap.add_argument("--force-all", action="store_true", help="recompute every stage (fresh timings)")
    ap.add_argument("--force", action="append", default=[], metavar="STAGE", help="recompute this stage")
    ap.add_argument("--artifacts", type=Path, default=pipeline.DEFAULT_ARTIFACTS)
    args = ap.parse_args(argv)
    stages = list(pipeline.load_stages())
    started = time.time()
    pipeline.run(args.scene, until=args.until, overrides=args.overrides,
                 force=stages if args.force_all else args.force, artifacts=args.artifacts)
    rows = collect(args.scene, args.artifacts)
    result = {
        "scene": args.scene,
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": __import__("os").cpu_count()},
        "overrides": args.overrides,
        "total_wall_seconds": round(time.time() - started, 1),
        "stages": rows,
        "summary": summarise(rows),
    }
    out_dir = ROOT / "bench" / pipeline.resolve_scene(args.scene).name
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{dt.date.today().isoformat()}.json"
    path.write_text(json.dumps(result, indent=2, default=str) + "\n")
    print(table(rows))
    for k, v in result["summary"].items():
        print(f"- {k}: {v}")
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
