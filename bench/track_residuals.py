#!/usr/bin/env python
"""What our matches can see of the poses: the reprojection error of `sfm-all`'s tracks under other poses.

    python -m bench.track_residuals [--scenes synthetic,scan24,scan24_idr] [--control-deg 0.1]
                                    [--artifacts DIR] [--out-dir DIR]

Per scene, the tracks of COLMAP's mapper and robust bundle adjustment on our matches of every training
view (the `sfm-all` initialisation, rebuilt here with the anchors stage's parameters: its artifact keeps
the poses, not the tracks). Each track's point is re-triangulated (DLT) under a set of poses and its
observations' reprojection error taken in pixels, for: `sfm-all`'s poses, the ground truth's, the
method's final poses (the default preset's current run in the artifacts root, e.g. after `make bench`),
and two controls made from `sfm-all`'s: every view turned by --control-deg about its own centre (a
random axis per view), and every view swung by the same angle about the object (the tracks' median
point), so that it keeps looking at it. A pose set that fits the tracks as well as `sfm-all`'s lies
where the matches cannot tell it from them; the controls show how much a rotation of that size costs
in each direction. Prints a table and writes ``<out-dir>/tracks/track-residuals-<date>.json``.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

import pipeline
from bench import bench
from manifoldneus import io, pose_init, pose_metrics, posefree
from manifoldneus.artifacts import load_ground_truth_poses, load_pose_estimate
from manifoldneus.cameras import camera_centers
from manifoldneus.correspondence import TrackSet, reprojection_px


def sfm_all_tracks(store: pipeline.Store, seed: int = 0) -> tuple[list[int], pose_init.InitResult, TrackSet, np.ndarray]:
    """(training view ids, the mapper's result on all of them, its tracks, K [N,3,3])."""
    inputs = posefree.load_inputs(**{s: store.version_dir(s, store.current(s)) for s in posefree.INPUT_STAGES})
    p = pipeline.resolve_params(pipeline.load_stages())["anchors"]
    ids = [int(v) for v in np.flatnonzero(inputs.train_mask)]
    with io.native_output_to(Path("/dev/null")):
        res = pose_init.init_from_matches(ids, inputs.views.K, inputs.keypoints, inputs.pairs, inputs.W,
                                          sizes=inputs.sizes, prior_focal=inputs.intrinsics_source != "default",
                                          reproj_px=p.reproj_px, final_ba_loss=p.ba_loss,
                                          final_ba_scale_px=p.ba_loss_px, seed=seed)
    return ids, res, TrackSet(ids, inputs.views.K, res.obs_view, res.obs_point, res.obs_uv), inputs.views.K


def residual_px(tracks: TrackSet, w2c: np.ndarray) -> np.ndarray:
    """Reprojection errors [O] (px) of the tracks' observations, points re-triangulated under w2c [V,4,4]."""
    X = tracks.triangulate(w2c)
    e = reprojection_px(torch.as_tensor(w2c[:, :3, :], dtype=torch.float64), torch.as_tensor(tracks.K),
                        torch.as_tensor(tracks.view), torch.as_tensor(X)[tracks.track], torch.as_tensor(tracks.uv))
    return e.numpy()


def turned(w2c: np.ndarray, deg: float, rng: np.random.Generator, about: np.ndarray | None = None) -> np.ndarray:
    """w2c [V,4,4] with every view rotated by ``deg`` about a random axis: about its own centre, or
    (``about`` [3], world) about that point, the centre moving with the rotation."""
    out = w2c.copy()
    for i, P in enumerate(w2c):
        axis = rng.normal(size=3)
        S = Rotation.from_rotvec(np.deg2rad(deg) * axis / np.linalg.norm(axis)).as_matrix()  # world frame
        R, C = P[:3, :3], camera_centers(P[None])[0]
        if about is not None:
            C = about + S @ (C - about)
        out[i, :3, :3] = R @ S.T
        out[i, :3, 3] = -(R @ S.T) @ C
    return out


def scene_report(scene: str, artifacts: Path, control_deg: float, seed: int = 0) -> dict:
    name = pipeline.resolve_scene(scene).name
    sfm_store, ours_store = pipeline.Store(artifacts, name, "sfm-all"), pipeline.Store(artifacts, name, None)
    ids, res, tracks, _ = sfm_all_tracks(sfm_store, seed)
    gt = load_ground_truth_poses(sfm_store.version_dir("ground_truth", sfm_store.current("ground_truth")))["w2c"][ids]
    sfm = np.asarray(res.w2c, np.float64)
    rng = np.random.default_rng(seed)
    poses = {"sfm-all": sfm, "ground truth": gt}
    final_version, final_seed = ours_store.current("successors"), None
    if final_version:
        version_dir = ours_store.version_dir("successors", final_version)
        final_seed = json.loads((version_dir / "manifest.json").read_text())["params"]["run"]["seed"]
        final = load_pose_estimate(version_dir / "final")
        poses["ManifoldNeuS final"] = final["w2c"][ids]
    poses[f"sfm-all turned {control_deg:g} deg about each centre"] = turned(sfm, control_deg, rng)
    poses[f"sfm-all swung {control_deg:g} deg about the object"] = turned(sfm, control_deg, rng,
                                                                         about=np.median(res.points, 0))
    rows = {}
    for label, w2c in poses.items():
        e = residual_px(tracks, np.asarray(w2c, np.float64))
        e = e[np.isfinite(e)]
        ev = pose_metrics.evaluate_poses(w2c, gt)
        rows[label] = {"median_px": float(np.median(e)), "mean_px": float(np.mean(e)),
                       "rot_err_deg": float(np.nanmean(ev["rot_err_deg"])), "pre_r_deg": float(np.mean(ev["pre_r_deg"]))}
    return {"views": len(ids), "tracks": tracks.n_tracks, "observations": len(tracks.view),
            "final_version": final_version, "final_seed": final_seed, "poses": rows}


def markdown(result: dict) -> str:
    header = ["scene", "poses", "rotation error deg (Sim3 on centres)", "PRE_r deg", "track reprojection px median",
              "mean"]
    rows = [[scene, label, f"{r['rot_err_deg']:.3f}", f"{r['pre_r_deg']:.3f}", f"{r['median_px']:.3f}",
             f"{r['mean_px']:.3f}"]
            for scene, sc in result["scenes"].items() for label, r in sc["poses"].items()]
    return bench.markdown_table(header, rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="synthetic,scan24,scan24_idr")
    ap.add_argument("--control-deg", type=float, default=0.1)
    ap.add_argument("--artifacts", type=Path, default=pipeline.DEFAULT_ARTIFACTS)
    ap.add_argument("--out-dir", type=Path, default=bench.DEFAULT_OUT_DIR)
    args = ap.parse_args(argv)
    result = {"date": dt.datetime.now().isoformat(timespec="seconds"), "commit": bench.git_commit(),
              "control_deg": args.control_deg,
              "scenes": {s: scene_report(s, args.artifacts, args.control_deg) for s in args.scenes.split(",")}}
    path = args.out_dir / "tracks" / f"track-residuals-{dt.date.today().isoformat()}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    io.save_json(path, result)
    print(markdown(result))
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
