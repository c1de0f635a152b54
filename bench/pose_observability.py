#!/usr/bin/env python
"""What our matches and our field can see of the poses: errors under poses turned in known directions.

    python -m bench.pose_observability [--scenes synthetic,scan24,scan24_idr] [--control-deg 0.1]
                                       [--rays-per-view 2048] [--artifacts DIR] [--out-dir DIR]

Needs `make bench` (or runs of the default and `sfm-all` presets) in the artifacts root. Per scene:

- **Tracks.** Those of COLMAP's mapper and robust bundle adjustment on our matches of every training
  view (the `sfm-all` initialisation, rebuilt with the anchors stage's parameters: its artifact keeps
  the poses, not the tracks). Each track's point is re-triangulated (DLT) under a set of poses and its
  observations' reprojection error taken in pixels, for: `sfm-all`'s poses, the ground truth's, the
  method's final poses (the default preset's current run), and two controls made from `sfm-all`'s:
  every view turned by --control-deg about its own centre (a random axis per view), and every view
  swung by the same angle about the object (the tracks' median point), so that it keeps looking at it.
- **Field.** The method's final field (frozen) and its training views: the colour loss of the joint
  rounds (L1 on the masks' foreground, or on every pixel without masks) and the masks' silhouette
  cross-entropy over --rays-per-view fixed pixels of each view, under the final poses and the same two
  controls made from them (the swing about the model frame's origin, where the gauge puts the object).

A pose set that fits as well as the one the term was optimised on lies where that term cannot tell them
apart; the controls show what a rotation of that size costs in each direction, and the ratio of their
excess errors (swing / turn) how blind each term is to the swing. Prints a table and writes
``<out-dir>/observability/pose-observability-<date>.json``.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

import runner
from bench import bench
from manifoldneus.data import artifacts as art
from manifoldneus.output import evaluation
from manifoldneus.data import io
from manifoldneus.sfm import pose_init
from manifoldneus.geometry import pose_metrics
from manifoldneus import posefree
from manifoldneus.data.artifacts import load_ground_truth_poses
from manifoldneus.geometry.cameras import camera_centers
from manifoldneus.sfm.correspondence import TrackSet, reprojection_px
from manifoldneus.neural.pose_alignment import residuals


def sfm_all_tracks(store: runner.Store, seed: int = 0) -> tuple[list[int], pose_init.InitResult, TrackSet]:
    """(training view ids, the mapper's result on all of them, its tracks)."""
    inputs = posefree.load_inputs(**{s: store.version_dir(s, store.current(s)) for s in posefree.INPUT_STAGES})
    p = runner.resolve_params(runner.load_stages())["anchors"]
    ids = [int(v) for v in np.flatnonzero(inputs.train_mask)]
    with io.native_output_to(Path("/dev/null")):
        res = pose_init.init_from_matches(ids, inputs.views.K, inputs.keypoints, inputs.pairs, inputs.W,
                                          sizes=inputs.sizes, mapper=pose_init.MapperOptions(
                                              prior_focal=inputs.intrinsics_source != "default",
                                              reproj_px=p.reproj_px, final_ba_loss=p.ba_loss,
                                              final_ba_scale_px=p.ba_loss_px, seed=seed))
    return ids, res, TrackSet(ids, inputs.views.K, res.obs_view, res.obs_point, res.obs_uv)


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


@torch.no_grad()
def field_losses(trainer, w2c: np.ndarray, view: torch.Tensor, pix: torch.Tensor, chunk: int = 8192) -> dict:
    """The frozen field's colour L1 (masked foreground, or every pixel) and silhouette cross-entropy at
    pixels ``pix`` [R] of the trainer's views ``view`` [R] under poses w2c [M,4,4]: the parts of the
    loss the pose polish and the test-time alignment minimise."""
    P = torch.as_tensor(w2c[:, :3, :4], dtype=torch.float32, device=trainer.device)  # [M,3,4]
    l1 = weight = bce = 0.0
    for s in range(0, len(view), chunk):
        v, p = view[s:s + chunk], pix[s:s + chunk]
        err, m, opacity = residuals(trainer, P[v], v, p, trainer.images, trainer.masks, trainer.K)  # [r] each
        if m is None:
            l1, weight = l1 + float(err.sum()), weight + len(err)
        else:
            l1, weight = l1 + float((err * m).sum()), weight + float(m.sum())
            bce += float(torch.nn.functional.binary_cross_entropy(opacity, m, reduction="sum"))
    return {"colour_l1": l1 / max(weight, 1.0), "silhouette_bce": None if trainer.masks is None else bce / len(view)}


def field_report(store: runner.Store, version: str, control_deg: float, rays_per_view: int, seed: int = 0) -> dict:
    """field_losses under the final poses and the two controls made from them."""
    final_dir = store.version_dir("successors", version) / art.FINAL_ROUND
    final = art.load_round(final_dir)
    views = art.load_views(store.version_dir("ingest", store.current("ingest")), final["w2c"], final["K"],
                           final.get("distortion"))
    ids = np.flatnonzero(final["optimised"].astype(bool))
    trainer = evaluation.trainer_from_checkpoint(final_dir / art.MODEL, views.subset(ids, final["w2c"]))
    w2c = np.asarray(final["w2c"], np.float64)[ids]  # [M,4,4]
    gen = torch.Generator().manual_seed(seed)
    view = torch.arange(len(ids)).repeat_interleave(rays_per_view)  # [M*R]
    pix = torch.randint(0, trainer.H * trainer.W, (len(view),), generator=gen)  # [M*R]
    rng = np.random.default_rng(seed)
    poses = {"final": w2c, "turned": turned(w2c, control_deg, rng), "swung": turned(w2c, control_deg, rng, np.zeros(3))}
    return {label: field_losses(trainer, P, view.to(trainer.device), pix.to(trainer.device)) for label, P in poses.items()}


def scene_report(scene: str, artifacts: Path, control_deg: float, rays_per_view: int, seed: int = 0) -> dict:
    name = runner.resolve_scene(scene).name
    sfm_store, ours_store = runner.Store(artifacts, name, "sfm-all"), runner.Store(artifacts, name, None)
    ids, res, tracks = sfm_all_tracks(sfm_store, seed)
    gt = load_ground_truth_poses(sfm_store.version_dir("ground_truth", sfm_store.current("ground_truth")))["w2c"][ids]
    sfm = np.asarray(res.w2c, np.float64)
    rng = np.random.default_rng(seed)
    poses = {"sfm-all": sfm, "ground truth": gt}
    final_version, final_seed, field = ours_store.current("successors"), None, None
    if final_version:
        version_dir = ours_store.version_dir("successors", final_version)
        final_seed = json.loads((version_dir / "manifest.json").read_text())["params"]["run"]["seed"]
        poses["ManifoldNeuS final"] = art.load_pose_estimate(version_dir / art.FINAL_ROUND)["w2c"][ids]
        field = field_report(ours_store, final_version, control_deg, rays_per_view, seed)
    poses["sfm-all turned"] = turned(sfm, control_deg, rng)
    poses["sfm-all swung"] = turned(sfm, control_deg, rng, about=np.median(res.points, 0))
    rows = {}
    for label, w2c in poses.items():
        e = residual_px(tracks, np.asarray(w2c, np.float64))
        e = e[np.isfinite(e)]
        ev = pose_metrics.evaluate_poses(w2c, gt)
        rows[label] = {"median_px": float(np.median(e)), "mean_px": float(np.mean(e)),
                       "rot_err_deg": float(np.nanmean(ev["rot_err_deg"])), "pre_r_deg": float(np.mean(ev["pre_r_deg"]))}

    def blindness(base, turn, swing):  # the swing's excess error over the turn's
        return (swing - base) / (turn - base)

    out = {"views": len(ids), "tracks": tracks.n_tracks, "observations": len(tracks.view),
           "final_version": final_version, "final_seed": final_seed, "poses": rows, "field": field,
           "swing_over_turn": {"tracks": blindness(*(rows[k]["median_px"] for k in ("sfm-all", "sfm-all turned",
                                                                                   "sfm-all swung")))}}
    if field:
        out["swing_over_turn"]["field"] = blindness(*(field[k]["colour_l1"] for k in ("final", "turned", "swung")))
    return out


def markdown(result: dict) -> str:
    deg = f"{result['control_deg']:g} deg"
    names = {"sfm-all turned": f"sfm-all turned {deg} about each centre",
             "sfm-all swung": f"sfm-all swung {deg} about the object"}
    header = ["scene", "poses", "rotation error deg (Sim3 on centres)", "PRE_r deg", "track reprojection px median",
              "mean"]
    rows = [[scene, names.get(label, label), f"{r['rot_err_deg']:.3f}", f"{r['pre_r_deg']:.3f}",
             f"{r['median_px']:.3f}", f"{r['mean_px']:.3f}"]
            for scene, sc in result["scenes"].items() for label, r in sc["poses"].items()]
    parts = [bench.markdown_table(header, rows)]
    header = ["scene", "final field, poses", "colour L1", "silhouette BCE"]
    rows = [[scene, {"turned": f"turned {deg}", "swung": f"swung {deg}"}.get(label, label), f"{r['colour_l1']:.5f}",
             "-" if r["silhouette_bce"] is None else f"{r['silhouette_bce']:.5f}"]
            for scene, sc in result["scenes"].items() if sc["field"] for label, r in sc["field"].items()]
    if rows:
        parts.append(bench.markdown_table(header, rows))
    parts.append("swing / turn (excess error of the swing over the turn's; smaller = blinder to the swing): " + "; ".join(
        f"{scene}: " + ", ".join(f"{k} {v:.3f}" for k, v in sc["swing_over_turn"].items())
        for scene, sc in result["scenes"].items()))
    return "\n\n".join(parts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="synthetic,scan24,scan24_idr")
    ap.add_argument("--control-deg", type=float, default=0.1)
    ap.add_argument("--rays-per-view", type=int, default=2048)
    ap.add_argument("--artifacts", type=Path, default=runner.DEFAULT_ARTIFACTS)
    ap.add_argument("--out-dir", type=Path, default=bench.DEFAULT_OUT_DIR)
    args = ap.parse_args(argv)
    result = {"date": dt.datetime.now().isoformat(timespec="seconds"), "commit": bench.git_commit(),
              "control_deg": args.control_deg, "rays_per_view": args.rays_per_view,
              "scenes": {s: scene_report(s, args.artifacts, args.control_deg, args.rays_per_view)
                         for s in args.scenes.split(",")}}
    bench.write_report(args.out_dir / "observability" / f"pose-observability-{dt.date.today().isoformat()}.json",
                       result, markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
