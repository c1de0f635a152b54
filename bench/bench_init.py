#!/usr/bin/env python
"""Initialisation benchmark: how good are the anchors' starting poses, before any neural training?

    python -m bench.bench_init [--scenes synthetic,scan24,scan24_idr] [--settings default,alpha=0.5,...]
                               [--label NAME] [--artifacts DIR] [--out-dir DIR]

Per scene and setting (a setting is a name and ``--set`` overrides, see SETTINGS): the front-end
up to the schedule (cached like any run), then ``stages.anchors.initial_poses`` alone, timed, and
scored against the ground truth after a Sim3 alignment on the anchors: mean / max rotation error
(deg), mean centre error (scene units), anchors registered. Then the round-1 views are placed
against the initialisation's own points (its tracks' 3D points, the way a successor round sees a
scaffold) with the successors' solver, and scored in the same alignment. No training: this
isolates the structure-from-motion part (a before/after table). Writes
``<out-dir>/init/<label>-<date>.json`` and prints a table.
"""
from __future__ import annotations

import argparse
import datetime as dt
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

import runner
from manifoldneus.geometry import cameras, pose_metrics
from manifoldneus.data import io, scenes
from manifoldneus.sfm import pose_init
from manifoldneus import posefree
from stages import anchors as anchors_stage

ROOT = Path(__file__).resolve().parent.parent

# the supplement's A3/A7 settings that lost the old initialisation (docs/REFINEMENT.md), and the default
SETTINGS = {
    "default": [],
    "alpha=0.5": ["schedule.alpha=0.5"],
    "alpha=0.35": ["schedule.alpha=0.35"],
    "fps-se": ["schedule.strategy=fps", "schedule.coverage=SE"],
    # the images alone (the photos-alone preset's ingest) and its self-calibration's principal-point test
    "photos-alone": ["ingest.use_calibration=false", "ingest.load_masks=false"],
    "photos-alone-pp-p0.1": ["ingest.use_calibration=false", "ingest.load_masks=false", "anchors.principal_point_p=0.1"],
    "photos-alone-pp-free": ["ingest.use_calibration=false", "ingest.load_masks=false", "anchors.principal_point_p=1.0"],
}


def scaffold_points(inputs, anchors: list[int], obs: dict) -> dict[int, np.ndarray]:
    """Per anchor, [n_keypoints,3] world points of its keypoints (NaN: no 3D point) from the
    initialisation's observations (uv matched back to the view's keypoints)."""
    out = {}
    for a in anchors:
        kp = np.asarray(inputs.keypoints[a], np.float64)
        X = np.full((len(kp), 3), np.nan)
        sel = obs["obs_view"] == a
        if sel.any():
            # the observations carry the keypoints' exact coordinates: nearest keypoint
            from scipy.spatial import cKDTree

            d, k = cKDTree(kp).query(obs["obs_uv"][sel])
            good = d < 1e-3
            X[k[good]] = obs["points"][obs["obs_point"][sel][good]]
        out[a] = X
    return out


def one(scene_name: str, setting: str, overrides: list[str], artifacts: Path) -> dict:
    runner.run(scene_name, until="schedule", overrides=overrides, artifacts=artifacts)
    stages = runner.load_stages()
    scene = runner.resolve_scene(scene_name)
    resolved = runner.resolve_params(stages, overrides=overrides)
    store = runner.Store(artifacts, scene.name)
    fps = runner.compute_fingerprints(stages, resolved, scene, store)
    upstream = fps["anchors"]["upstream"]
    inputs = posefree.load_inputs(**{s: store.version_dir(s, upstream[s]) for s in posefree.INPUT_STAGES})
    rounds = inputs.schedule["round"]
    anchors = [int(v) for v in np.flatnonzero((rounds == 0) & inputs.train_mask)]
    p = resolved["anchors"]
    with tempfile.TemporaryDirectory() as tmp:  # COLMAP's own log
        env = anchors_stage.InitEnv(logging.getLogger("bench_init"), Path(tmp) / "log.txt", resolved["run"].seed)
        t0 = time.perf_counter()
        inputs, refine, _, _ = anchors_stage.calibrated_inputs(env, inputs, p)
        res = anchors_stage.matches_init(env, inputs, anchors, p, refine)
        seconds = time.perf_counter() - t0
    principal_point = inputs.views.K[anchors][:, :2, 2].mean(0)  # [2] after the self-calibration, if any
    ids = res.view_ids
    row = {v: k for k, v in enumerate(ids)}
    w2c = np.tile(np.eye(4), (len(inputs.names), 1, 1))
    w2c[anchors] = res.w2c[[row[a] for a in anchors]]
    unplaced = [inputs.names[v] for v in res.unplaced if v in set(anchors)]
    gt = scenes.read_ground_truth(scene, resolved["ingest"])
    ev = pose_metrics.evaluate_poses(w2c[anchors], gt["w2c"][anchors])
    rot = np.asarray(ev["rot_err_deg"])
    out = {"scene": scene_name, "setting": setting, "overrides": overrides, "n_anchors": len(anchors),
           "n_unplaced": len(unplaced), "unplaced": unplaced,
           "bridges": len(ids) - len(anchors), "seconds": seconds,
           "rot_deg_mean": float(np.nanmean(rot)), "rot_deg_max": float(np.nanmax(rot)),
           "centre_mean": float(np.nanmean(ev["center_err_units"])), "principal_point": principal_point.tolist()}
    # round-1 placement against the initialisation's points
    obs = {"points": res.points, "obs_view": res.obs_view, "obs_point": res.obs_point, "obs_uv": res.obs_uv}
    new = [int(v) for v in np.flatnonzero((rounds == 1) & inputs.train_mask)]
    if new:
        placed = {a: w2c[a] for a in anchors}
        points3d = scaffold_points(inputs, anchors, obs)
        t0 = time.perf_counter()
        poses, ok = [], []
        for v in new:
            pose, pinfo = pose_init.place_successor(v, inputs.views.K, inputs.keypoints, inputs.pairs, placed, inputs.W,
                                                    points3d=points3d)
            poses.append(pose if pose is not None else np.eye(4))
            ok.append(pinfo["method"] == "pnp")
        out["placement_seconds"] = time.perf_counter() - t0
        al = ev["alignment"]
        moved = cameras.transform_w2c(np.stack(poses), al["s"], al["R"], al["t"])  # into the GT frame by the anchors' alignment
        rot_err = cameras.rotation_angle_deg(moved[:, :3, :3] @ np.transpose(gt["w2c"][new][:, :3, :3], (0, 2, 1)))
        ok = np.asarray(ok)
        out.update(round1_views=len(new), round1_solved=int(ok.sum()),
                   round1_rot_deg_mean=float(np.mean(rot_err[ok])) if ok.any() else None)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="synthetic,scan24,scan24_idr")
    ap.add_argument("--settings", default="default,alpha=0.5,alpha=0.35,fps-se")
    ap.add_argument("--label", default="init")
    ap.add_argument("--artifacts", type=Path, default=runner.DEFAULT_ARTIFACTS)
    ap.add_argument("--out-dir", type=Path, default=ROOT / "bench")
    args = ap.parse_args(argv)
    rows = []
    for scene in args.scenes.split(","):
        for setting in args.settings.split(","):
            row = one(scene, setting, SETTINGS[setting], args.artifacts)
            rows.append(row)
            print(f"{scene:11s} {setting:11s} anchors {row['n_anchors']:3d} unplaced {row['n_unplaced']:2d} "
                  f"rot {row['rot_deg_mean']:8.3f} (max {row['rot_deg_max']:8.3f}) deg  centre {row['centre_mean']:.4f}"
                  f"  {row['seconds']:6.1f} s  round 1: {row.get('round1_solved', '-')}/{row.get('round1_views', '-')} "
                  f"rot {row.get('round1_rot_deg_mean') or float('nan'):.3f} deg  principal point "
                  f"({row['principal_point'][0]:.1f}, {row['principal_point'][1]:.1f})", flush=True)
    out = args.out_dir / "init" / f"{args.label}-{dt.date.today().isoformat()}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    io.save_json(out, {"label": args.label, "rows": rows})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
