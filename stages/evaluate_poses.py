"""evaluate_poses: pose errors of an estimated pose artifact against ground truth (METHOD.md stage 10).

Evaluates the pycolmap ``reference`` stage now; :func:`evaluate_pose_artifact` is the reusable
entry point for any artifact holding ``poses.zarr`` (``w2c`` [N,4,4], optional ``registered`` bool
[N]; non-finite poses count as missing). Metric definitions: ``manifoldneus/geometry/pose_metrics.py``
(Sim3/Umeyama alignment of camera centres est -> GT, then rotation and centre errors; gauge-free
relative pose errors PRE_r / PRE_t over all pairs of valid views).

Outputs (``<label>`` = the evaluated stage, here ``reference``):
- ``<label>_pose_metrics.json``: summary (mean / median / max), per-view errors, alignment (s, R, t)
  mapping the estimate's world into the GT object-normalised frame, missing views, units.
- ``<label>_cameras.png``: aligned estimated vs GT cameras (3D).
- ``<label>_aligned_poses.zarr``: ``w2c`` [N,4,4] in the GT object-normalised frame (NaN where
  missing) and ``valid`` bool [N], for novel-view evaluation with aligned test poses.
If the scene has no GT poses, only the JSON is written, with ``evaluated: false``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manifoldneus.data import artifacts, io
from manifoldneus.config import param
from manifoldneus.geometry.pose_metrics import evaluate_poses, json_summary, plot_cameras


@dataclass
class Params:
    """Section `evaluate_poses` of params.yaml."""

    with_scale: bool = param(True, "Align with a similarity (Sim3, Umeyama); false: rigid SE3 only")


UPSTREAM = ("ingest", "ground_truth", "reference")
SECTIONS = ("evaluate_poses",)
OUTPUTS = (artifacts.REFERENCE_POSE_METRICS,)


def _units_scale(gt_dir: Path, normalization: np.ndarray) -> tuple[float, str]:
    meta = artifacts.load_gt_meta(gt_dir)
    units = meta.get("units") or "unit"
    scale = meta.get("units_per_scene_unit")
    if scale is None:
        scale = float(abs(np.linalg.det(np.asarray(normalization)[:3, :3])) ** (1 / 3))
    return float(scale), str(units)


def evaluate_pose_artifact(est_dir, gt_dir, out_dir, label: str, names=None, with_scale: bool = True,
                           log=None) -> dict:
    """Evaluate ``est_dir/poses.zarr`` against ``gt_dir`` (a ``ground_truth`` artifact); write
    ``<label>_pose_metrics.json``, ``<label>_cameras.png`` and ``<label>_aligned_poses.zarr`` into
    ``out_dir``. Returns the JSON-safe summary dict (also written)."""
    est_dir, gt_dir, out_dir = Path(est_dir), Path(gt_dir), Path(out_dir)
    json_path = out_dir / f"{label}_pose_metrics.json"  # with label "reference": artifacts.REFERENCE_POSE_METRICS
    plot_name = f"{label}_cameras.png"  # artifacts.REFERENCE_CAMERAS_PLOT
    gt_meta = artifacts.load_gt_meta(gt_dir)
    if not gt_meta.get("has_poses", (gt_dir / artifacts.POSES).exists()):
        out = {"label": label, "evaluated": False, "reason": "the scene has no ground-truth poses"}
        io.save_json(json_path, out)
        if log:
            log.info("%s: no ground-truth poses, pose errors not evaluated", label)
        return out
    gt = artifacts.load_ground_truth_poses(gt_dir, ["w2c", "normalization"])
    est = artifacts.load_pose_estimate(est_dir)
    w2c_est, w2c_gt = est["w2c"], gt["w2c"]
    if len(w2c_est) != len(w2c_gt):
        raise ValueError(f"{label}: {len(w2c_est)} estimated poses for {len(w2c_gt)} ground-truth views")
    valid = est.get("registered")
    n_valid = int(len(w2c_est) if valid is None else np.asarray(valid, bool).sum())
    if n_valid < 3:  # a Sim3 needs three centres: report the failure instead of failing the stage
        out = {"label": label, "evaluated": False, "n_valid": n_valid, "n_views": int(len(w2c_est)),
               "reason": f"only {n_valid} registered view(s); at least 3 are needed for a Sim3 alignment"}
        io.save_json(json_path, out)
        if log:
            log.warning("%s: %s", label, out["reason"])
        return out
    scale, units = _units_scale(gt_dir, gt["normalization"])
    res = evaluate_poses(w2c_est, w2c_gt, valid=valid, units_scale=scale, with_scale=with_scale)
    out = {"label": label, "evaluated": True, "units": units, "gt_frame": "object-normalised (unit sphere)",
           **json_summary(res, names)}
    io.save_json(json_path, out)
    io.save_arrays(out_dir / f"{label}_aligned_poses.zarr", {"w2c": res["w2c_aligned"], "valid": res["valid"]},
                   attrs={"frame": "ground-truth object-normalised", "alignment": out["alignment"]},
                   chunk_first=False)
    s = out["summary"]
    plot_cameras(res["w2c_aligned"], w2c_gt, out_dir / plot_name, valid=res["valid"],
                 title=f"{label} vs GT (Sim3-aligned): rot {s['rot_err_deg']['mean']:.3f} deg mean, "
                       f"centre {s['center_err_units']['mean']:.3f} {units} mean "
                       f"({s['center_err_pct']['mean']:.2f} %), {res['n_valid']}/{res['n_views']} views")
    if log:
        log.info("%s: %d/%d views; rotation %.4f / %.4f deg (mean/median); centre %.4f %s (%.3f %%); "
                 "PRE_r %.4f deg, PRE_t %.4f deg", label, res["n_valid"], res["n_views"],
                 s["rot_err_deg"]["mean"], s["rot_err_deg"]["median"], s["center_err_units"]["mean"], units,
                 s["center_err_pct"]["mean"], s["pre_r_deg"]["mean"], s["pre_t_deg"]["mean"])
        if res["n_missing"]:
            log.warning("%s: %d view(s) missing/unregistered, excluded: %s", label, res["n_missing"],
                        out["missing_names"])
    return out


def metrics_for_manifest(out: dict, prefix: str) -> dict:
    """Flat scalar metrics of an evaluation result, for ``ctx.metrics``."""
    if not out.get("evaluated"):
        return {f"{prefix}_evaluated": False}
    s = out["summary"]
    return {
        f"{prefix}_n_valid": out["n_valid"],
        f"{prefix}_n_missing": out["n_missing"],
        f"{prefix}_rot_err_deg_mean": s["rot_err_deg"]["mean"],
        f"{prefix}_rot_err_deg_median": s["rot_err_deg"]["median"],
        f"{prefix}_center_err_units_mean": s["center_err_units"]["mean"],
        f"{prefix}_center_err_pct_mean": s["center_err_pct"]["mean"],
        f"{prefix}_pre_r_deg_mean": s["pre_r_deg"]["mean"],
        f"{prefix}_pre_t_deg_mean": s["pre_t_deg"]["mean"],
    }


def run(ctx) -> None:
    names = artifacts.load_views_meta(ctx.input("ingest"))["names"]
    out = evaluate_pose_artifact(ctx.input("reference"), ctx.input("ground_truth"), ctx.out, "reference",
                                 names=names, with_scale=ctx.params.with_scale, log=ctx.log)
    ctx.metrics.update(metrics_for_manifest(out, "reference"))
