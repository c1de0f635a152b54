#!/usr/bin/env python
"""Own photos: a scene's images alone (no intrinsics, no masks) against the same scene calibrated and masked.

    python -m bench.bench_own_photos [--scene scan24_idr] [--seeds 0,1] [--set section.key=value ...]
                                     [--artifacts DIR] [--label NAME] [--out-dir DIR]
    python -m bench.bench_own_photos --merge A.json B.json ...   # runs made side by side, one table

Two systems through the whole pipeline, per seed (``run.seed``): ``calibrated-masked`` (the layout as
it is) and ``photos-alone`` (``ingest.use_calibration=false ingest.load_masks=false``: the focal length
starts at COLMAP's 1.2 x guess and the principal point at the centre, both self-calibrated on every
training view before the anchors' initialisation; the object is found from the SfM points). Both are scored against the same ground truth: the focal length's error, the
final poses, the mesh's Chamfer distance to the GT-pose reference surface (trained with the layout's
calibration and masks in both runs), held-out PSNR on the object (the layout's masks). Prints mean
+- std over seeds and the own-photos targets (focal within 1 %, rotation <= 1.5x and Chamfer <= 2x the
calibrated masked run's), writes ``<out-dir>/own_photos/<label>-<date>.json``.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path

import runner
from manifoldneus.data.artifacts import load_evaluation
from bench import bench
from bench.bench import git_commit, spread

ROOT = Path(__file__).resolve().parent.parent

SYSTEMS = {
    "calibrated-masked": [],
    "photos-alone": ["ingest.use_calibration=false", "ingest.load_masks=false"],
}
MEASURES = ("focal_err_pct", "rot_deg", "centre", "chamfer", "psnr_object", "pycolmap_rot_deg", "wall_seconds")


def one_run(scene: str, system: str, seed: int, overrides: list[str], artifacts: Path) -> dict:
    over = [*overrides, *SYSTEMS[system], f"run.seed={seed}"]
    t0 = time.time()
    runner.run(scene, overrides=over, artifacts=artifacts)
    store = runner.Store(artifacts, runner.resolve_scene(scene).name)
    ev = load_evaluation(store.version_dir("evaluate", store.current("evaluate")))
    final = ev["poses"][-1]["summary"]
    ref = bench.reference_scores(store.version_dir("evaluate_poses", store.current("evaluate_poses")))
    return {"system": system, "seed": seed, "overrides": over, "wall_seconds": time.time() - t0,
            "focal_err_pct": ev["intrinsics"]["final"].get("focal_err_pct"),
            "focal_px": ev["intrinsics"]["final"]["focal_px"], "intrinsics": ev["intrinsics"],
            "rot_deg": final["rot_err_deg"]["mean"], "centre": final["center_err_units"]["mean"],
            "chamfer": ev.get("geometry", {}).get("chamfer_units"), "units": ev.get("geometry", {}).get("units"),
            "psnr_object": ev.get("novel_views", {}).get("summary", {}).get("psnr_masked"),
            "pycolmap_rot_deg": ref.get("rot_err_deg_mean"),
            "versions": {s: store.current(s) for s in ("ingest", "anchors", "mesh", "reference_surface")}}


def summarise(runs: list[dict]) -> dict:
    return {system: {m: spread(r[m] for r in runs if r["system"] == system) for m in MEASURES}
            for system in SYSTEMS if any(r["system"] == system for r in runs)}


def targets(summary: dict) -> list[dict]:
    if len(summary) < 2:
        return []
    cal, alone = summary["calibrated-masked"], summary["photos-alone"]

    def ratio(m):
        a, b = alone[m]["mean"], cal[m]["mean"]
        return None if a is None or not b else a / b

    rows = [{"target": "focal length within 1 % of the ground truth", "value": alone["focal_err_pct"]["mean"],
             "limit": 1.0},
            {"target": "final rotation error <= 1.5x the calibrated masked run's", "value": ratio("rot_deg"),
             "limit": 1.5},
            {"target": "Chamfer to the GT-pose reference <= 2x the calibrated masked run's", "value": ratio("chamfer"),
             "limit": 2.0}]
    for t in rows:
        t["met"] = t["value"] is not None and abs(t["value"]) <= t["limit"]
    return rows


def table(result: dict) -> str:
    def pm(s, spec):
        return "n/a" if s["mean"] is None else f"{s['mean']:{spec}} ± {s['std']:{spec}}"

    lines = [f"{result['scene']}, seeds {result['seeds']} (commit {result['commit']}):",
             f"{'system':<20} {'focal err %':>15} {'rot deg':>17} {'centre':>17} {'Chamfer':>17} {'PSNR obj':>15} "
             f"{'pycolmap deg':>17} {'wall s':>13}"]
    for system, s in result["summary"].items():
        lines.append(f"{system:<20} {pm(s['focal_err_pct'], '.2f'):>15} {pm(s['rot_deg'], '.3f'):>17} "
                     f"{pm(s['centre'], '.3f'):>17} {pm(s['chamfer'], '.3f'):>17} {pm(s['psnr_object'], '.2f'):>15} "
                     f"{pm(s['pycolmap_rot_deg'], '.3f'):>17} {pm(s['wall_seconds'], '.0f'):>13}")
    for t in result["targets"]:
        v = "n/a" if t["value"] is None else f"{t['value']:.3f}"
        lines.append(f"  {'met ' if t['met'] else 'MISS'} {t['target']}: {v} (limit {t['limit']})")
    return "\n".join(lines)


def finish(scene: str, runs: list[dict], label: str, out_dir: Path, commit: str | None = None) -> Path:
    summary = summarise(runs)
    result = {"scene": scene, "seeds": sorted({r["seed"] for r in runs}), "commit": commit or git_commit(),
              "date": dt.date.today().isoformat(), "systems": SYSTEMS, "runs": runs, "summary": summary,
              "targets": targets(summary)}
    path = out_dir / "own_photos" / f"{label}-{result['date']}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1, default=float))
    print(table(result))
    print(f"wrote {path}")
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="scan24_idr")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--systems", default=",".join(SYSTEMS), help="comma-separated, of: " + ", ".join(SYSTEMS))
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    ap.add_argument("--artifacts", type=Path, default=runner.DEFAULT_ARTIFACTS)
    ap.add_argument("--label", default="own-photos")
    ap.add_argument("--out-dir", type=Path, default=bench.DEFAULT_OUT_DIR)
    ap.add_argument("--merge", nargs="+", type=Path, help="JSON files of runs made side by side: one table of all")
    a = ap.parse_args(argv)
    if a.merge:
        parts = [json.loads(p.read_text()) for p in a.merge]
        commits = sorted({str(p["commit"]) for p in parts})  # the code the runs measured, not the merge's
        finish(parts[0]["scene"], [r for p in parts for r in p["runs"]], a.label, a.out_dir, " + ".join(commits))
        return 0
    systems = [s.strip() for s in a.systems.split(",") if s.strip()]
    unknown = set(systems) - set(SYSTEMS)
    if unknown:
        ap.error(f"unknown systems {sorted(unknown)}; choose from {list(SYSTEMS)}")
    runs = [one_run(a.scene, system, int(seed), a.overrides, a.artifacts)
            for seed in a.seeds.split(",") for system in systems]
    finish(a.scene, runs, a.label, a.out_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
