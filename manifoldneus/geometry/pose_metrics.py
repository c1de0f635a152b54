"""Camera pose errors against ground truth (METHOD.md "Evaluation"). Pure numpy (+ matplotlib plot).

* Gauge: the estimated camera centres are aligned to the GT centres with a similarity
  (Umeyama, ``cameras.umeyama_sim3``) fitted on the valid views; the estimated poses are mapped
  into the GT frame with ``cameras.transform_w2c(w2c_est, s, R, t)``.
* Rotation error of view i: geodesic angle (degrees) between the aligned estimated and the GT
  camera rotations.
* Centre error of view i: ``|s R C_est + t - C_gt|`` in the GT (scene) frame, also in data units
  (``x units_scale``, e.g. mm for DTU) and in % of the mean distance of the GT centres from
  their centroid.
* Relative pose errors over all pairs (i < j) of valid views (NoPose-NeuS style, gauge-free):
  ``R_ij = R_j R_i^T``, ``t_ij = t_j - R_ij t_i`` (= R_j (C_i - C_j), the direction from camera j to
  camera i in camera j's frame); PRE_r = angle(R_ij_est^T R_ij_gt) in degrees; PRE_t = angle between
  ``t_ij_est`` and ``t_ij_gt`` in degrees (pairs whose baseline is ~0 in either are skipped).
* Views that are missing (``valid`` False, or non-finite poses) are excluded and counted; their
  per-view errors are NaN in the returned arrays (``json_summary`` turns them into null).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .cameras import camera_centers, rotation_angle_deg, to_4x4, transform_w2c, umeyama_sim3


def _stats(x: np.ndarray) -> dict:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"mean": None, "median": None, "max": None, "n": 0}
    return {"mean": float(x.mean()), "median": float(np.median(x)), "max": float(x.max()), "n": int(x.size)}


def _angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    cos = (a * b).sum(-1) / np.maximum(na * nb, 1e-300)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def relative_pose_errors(w2c_est: np.ndarray, w2c_gt: np.ndarray, eps: float = 1e-12):
    """PRE over all pairs i < j of the given poses. Returns (pairs [P,2], pre_r [P], pre_t [P]);
    pre_t is NaN for pairs with a (numerically) zero baseline in either set."""
    Pe, Pg = to_4x4(w2c_est), to_4x4(w2c_gt)
    n = len(Pe)
    ii, jj = np.triu_indices(n, k=1)
    Re, te = Pe[:, :3, :3], Pe[:, :3, 3]
    Rg, tg = Pg[:, :3, :3], Pg[:, :3, 3]
    Rij_e = Re[jj] @ np.swapaxes(Re[ii], -1, -2)
    Rij_g = Rg[jj] @ np.swapaxes(Rg[ii], -1, -2)
    tij_e = te[jj] - np.einsum("pab,pb->pa", Rij_e, te[ii])
    tij_g = tg[jj] - np.einsum("pab,pb->pa", Rij_g, tg[ii])
    pre_r = rotation_angle_deg(np.swapaxes(Rij_e, -1, -2) @ Rij_g)
    pre_t = _angle_between(tij_e, tij_g)
    # a zero baseline has no direction; scale the threshold with the scene size
    se = max(np.linalg.norm(tij_e, axis=-1).max(initial=0.0), 1.0) * eps
    sg = max(np.linalg.norm(tij_g, axis=-1).max(initial=0.0), 1.0) * eps
    bad = (np.linalg.norm(tij_e, axis=-1) <= se) | (np.linalg.norm(tij_g, axis=-1) <= sg)
    pre_t = np.where(bad, np.nan, pre_t)
    return np.stack([ii, jj], 1), pre_r, pre_t


def evaluate_poses(w2c_est, w2c_gt, valid=None, units_scale: float = 1.0, with_scale: bool = True) -> dict:
    """Pose errors of ``w2c_est`` [N,4,4] against ``w2c_gt`` [N,4,4] (same view order).

    valid: optional bool [N] (e.g. ``registered``); views with non-finite poses are also excluded.
    units_scale: data units per scene unit of the GT frame (e.g. mm per normalised unit).
    Returns a dict of scalars (summaries), per-view arrays (length N, NaN where excluded),
    the alignment ``(s, R, t)`` mapping estimated -> GT world, and ``w2c_aligned`` [N,4,4].
    """
    est = to_4x4(np.asarray(w2c_est, dtype=np.float64))
    gt = to_4x4(np.asarray(w2c_gt, dtype=np.float64))
    if est.shape != gt.shape or est.ndim != 3:
        raise ValueError(f"w2c_est {est.shape} and w2c_gt {gt.shape} must both be [N,4,4]")
    N = len(est)
    ok = np.ones(N, dtype=bool) if valid is None else np.asarray(valid, dtype=bool).reshape(-1).copy()
    if ok.shape != (N,):
        raise ValueError(f"valid: expected {N} flags, got {ok.shape}")
    ok &= np.isfinite(est).all((1, 2)) & np.isfinite(gt).all((1, 2))
    vidx = np.flatnonzero(ok)
    if len(vidx) < 3:
        raise ValueError(f"evaluate_poses: only {len(vidx)} valid views; at least 3 are needed for a Sim3 alignment")

    Ce, Cg = camera_centers(est[vidx]), camera_centers(gt[vidx])
    s, R, t = umeyama_sim3(Ce, Cg, with_scale=with_scale)
    aligned = np.full_like(est, np.nan)
    aligned[vidx] = transform_w2c(est[vidx], s, R, t)

    rot_err = np.full(N, np.nan)
    rot_err[vidx] = rotation_angle_deg(aligned[vidx, :3, :3] @ np.swapaxes(gt[vidx, :3, :3], -1, -2))
    c_err = np.full(N, np.nan)
    c_err[vidx] = np.linalg.norm(camera_centers(aligned[vidx]) - Cg, axis=1)
    mean_dist = float(np.linalg.norm(Cg - Cg.mean(0), axis=1).mean())
    c_err_pct = c_err / max(mean_dist, 1e-300) * 100.0

    pairs_local, pre_r, pre_t = relative_pose_errors(est[vidx], gt[vidx])
    pairs = vidx[pairs_local]

    return {
        "n_views": int(N),
        "n_valid": int(len(vidx)),
        "n_missing": int(N - len(vidx)),
        "missing": np.flatnonzero(~ok).tolist(),
        "valid": ok,
        "alignment": {"s": float(s), "R": R, "t": t, "with_scale": bool(with_scale),
                      "fitted_on": "camera centres of the valid views (Umeyama Sim3, est -> gt)"},
        "units_scale": float(units_scale),
        "mean_camera_distance": mean_dist,
        "rot_err_deg": rot_err,
        "center_err": c_err,
        "center_err_units": c_err * units_scale,
        "center_err_pct": c_err_pct,
        "pairs": pairs,
        "pre_r_deg": pre_r,
        "pre_t_deg": pre_t,
        "summary": {
            "rot_err_deg": _stats(rot_err),
            "center_err": _stats(c_err),
            "center_err_units": _stats(c_err * units_scale),
            "center_err_pct": _stats(c_err_pct),
            "pre_r_deg": _stats(pre_r),
            "pre_t_deg": _stats(pre_t),
        },
        "w2c_aligned": aligned,
    }


def json_summary(result: dict, names=None) -> dict:
    """A JSON-safe view of an ``evaluate_poses`` result (NaN -> null, per-view lists)."""

    def clean(a):
        a = np.asarray(a, dtype=np.float64)
        return [None if not np.isfinite(x) else float(x) for x in a.ravel()]

    N = result["n_views"]
    names = list(names) if names is not None else [f"{i:03d}" for i in range(N)]
    al = result["alignment"]
    per_view = []
    for i in range(N):
        per_view.append({
            "view": i,
            "name": names[i],
            "valid": bool(result["valid"][i]),
            "rot_err_deg": clean([result["rot_err_deg"][i]])[0],
            "center_err": clean([result["center_err"][i]])[0],
            "center_err_units": clean([result["center_err_units"][i]])[0],
            "center_err_pct": clean([result["center_err_pct"][i]])[0],
        })
    return {
        "n_views": N,
        "n_valid": result["n_valid"],
        "n_missing": result["n_missing"],
        "missing": result["missing"],
        "missing_names": [names[i] for i in result["missing"]],
        "alignment": {"s": al["s"], "R": np.asarray(al["R"]).tolist(), "t": np.asarray(al["t"]).tolist(),
                      "with_scale": al["with_scale"], "fitted_on": al["fitted_on"]},
        "units_scale": result["units_scale"],
        "mean_camera_distance": result["mean_camera_distance"],
        "summary": result["summary"],
        "n_pairs": int(len(result["pairs"])),
        "per_view": per_view,
    }


# --------------------------------------------------------------------------- plot


def _frustum_lines(w2c: np.ndarray, size: float, aspect: float = 4 / 3):
    """Line segments [8,2,3] of a camera pyramid (apex at the centre, +z forward, -y up)."""
    c2w = np.linalg.inv(to_4x4(w2c))
    w, h = 0.5 * size * aspect, 0.5 * size
    corners_c = np.array([[-w, -h, size], [w, -h, size], [w, h, size], [-w, h, size]])
    corners = corners_c @ c2w[:3, :3].T + c2w[:3, 3]
    C = c2w[:3, 3]
    segs = [(C, k) for k in corners] + [(corners[k], corners[(k + 1) % 4]) for k in range(4)]
    up_c = np.array([0, -1.6 * h, size])  # a tick marking the image "up" side
    segs.append((0.5 * (corners[0] + corners[1]), up_c @ c2w[:3, :3].T + c2w[:3, 3]))
    return np.array(segs)


def plot_cameras(w2c_aligned, w2c_gt, path, valid=None, title: str | None = None, labels=("estimated (aligned)", "ground truth"),
                 held_out=None):
    """3D figure of aligned estimated vs GT camera frusta and centres (supplement Fig. A2 style)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    from manifoldneus.data.io import save_figure

    est = to_4x4(np.asarray(w2c_aligned, dtype=np.float64))
    gt = to_4x4(np.asarray(w2c_gt, dtype=np.float64))
    N = len(gt)
    ok = np.ones(N, dtype=bool) if valid is None else np.asarray(valid, dtype=bool).copy()
    ok &= np.isfinite(est).all((1, 2))
    Cg = camera_centers(gt)
    Ce = camera_centers(est[ok]) if ok.any() else np.zeros((0, 3))
    extent = float(np.linalg.norm(Cg - Cg.mean(0), axis=1).mean()) or 1.0
    size = 0.08 * extent

    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(111, projection="3d")
    gsegs = np.concatenate([_frustum_lines(p, size) for p in gt])
    ax.add_collection3d(Line3DCollection(gsegs, colors="tab:gray", linewidths=0.8, label=labels[1]))
    if ok.any():
        esegs = np.concatenate([_frustum_lines(p, size) for p in est[ok]])
        ax.add_collection3d(Line3DCollection(esegs, colors="tab:red", linewidths=0.8, label=labels[0]))
        err = np.stack([Ce, Cg[ok]], 1)
        ax.add_collection3d(Line3DCollection(err, colors="tab:blue", linewidths=0.6, linestyles="dotted"))
        ax.scatter(*Ce.T, c="tab:red", s=8)
    ax.scatter(*Cg.T, c="tab:gray", s=8)
    held = np.zeros(N, bool) if held_out is None else np.asarray(held_out, bool) & ~ok
    if held.any():
        ax.scatter(*Cg[held].T, marker="^", c="tab:green", s=30, label="held out for evaluation (GT shown)")
    if (~ok & ~held).any():
        ax.scatter(*Cg[~ok & ~held].T, marker="x", c="k", s=30, label="not posed (GT shown)")
    for i in range(N):
        ax.text(*Cg[i], str(i), fontsize=6, color="dimgray")
    pts = np.concatenate([Cg, Ce]) if len(Ce) else Cg
    mid, half = pts.mean(0), (pts.max(0) - pts.min(0)).max() / 2 + size
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_xlabel("x (ground-truth frame)")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.legend(loc="upper left", fontsize=8)
    if title:
        ax.set_title(title, fontsize=9)
    save_figure(Path(path), fig)
