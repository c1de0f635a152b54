"""Pose initialisation (METHOD.md "Pose initialisation"): pure geometry, no neural code.

Three initialisers, all returning world-to-camera poses in the conventions of
:mod:`manifoldneus.cameras` (OpenCV camera frame, ``w2c``, pixel centres at +0.5):

* :func:`init_from_matches` ("matches", the default for the anchors): relative poses from the
  verified essential matrices chained along a maximum spanning tree of the co-visibility graph,
  per-edge translation scales fixed by triangulation (incremental SfM-lite: each new view gets the
  tree edge's pose scaled against the points triangulated so far, or a PnP-RANSAC pose against
  them, whichever explains more points), a robust bundle adjustment of poses and points
  (:func:`bundle_adjust`: Levenberg-Marquardt with a Schur complement, Huber loss), and a gauge
  fix: a similarity that centres the triangulated points' median at the origin and scales their
  robust radius (``gauge_percentile``-th percentile distance from the median) to ``gauge_radius``
  (0.8), so the object sits inside the unit sphere. The world's orientation is the root camera's.
* :func:`identity_init` ("identity", the paper's wording): every view at the same canonical pose.
* Successors: :func:`place_by_pnp` (PnP-RANSAC of a view's matches to already-optimised views,
  the placed views' keypoints lifted to 3D with depth rendered from the current model or with given
  3D points), :func:`fallback_neighbour_pose` (the best-matching optimised neighbour's pose) and
  :func:`place_successor`, which chains the two and reports what happened.

Pair input (the ``matching`` stage's layout, ``stages/matching.py``): one :class:`PairMatch` per
pair ``(i, j)`` with the verified inliers as keypoint-index pairs ``[M,2]`` (index in view i,
index in view j) and the relative pose of the essential matrix, camera i -> camera j:
``x_j = R @ x_i + t`` with ``|t| = 1`` (``w2c_j = [R | t] @ w2c_i`` up to the scale of t).
:func:`pairs_from_matches` builds the list from the arrays of ``matches.zarr``. Typical use::

    feats, _ = artifacts.load_features(features_dir / "features.zarr")
    arrays, _ = artifacts.load_matches(matches_dir / "matches.zarr")
    pairs = pose_init.pairs_from_matches(arrays)
    kps = [f["keypoints"] for f in feats]
    res = pose_init.init_from_matches(anchors, K, kps, pairs, W)      # res.w2c [A,4,4], res.diagnostics
    # successors, later (placed = {view: current w2c} of the optimised views):
    w2c, info = pose_init.place_successor(v, K, kps, pairs, placed, W, depth_at=render_z_depth)

Intrinsics: ``K[1, 0] = K[2, 0] = K[2, 1] = 0``, ``K[2, 2] = 1`` (skew allowed; OpenCV's PnP ignores it).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Sequence

import numpy as np

from .cameras import (camera_centers, pixels_to_normalised, project_points, rotvec_to_matrix, sim3_matrix, skew, to_4x4,
                      transform_w2c)
from .mavos import covisibility_matrix

# --------------------------------------------------------------------------- inputs


class PairMatch(NamedTuple):
    """Verified matches of one view pair (global view indices) and its relative pose.

    ``matches`` [M,2] int: (keypoint index in view i, keypoint index in view j).
    ``R`` [3,3], ``t`` [3]: camera i -> camera j, ``x_j = R @ x_i + t``, ``|t| = 1``.
    ``valid``: False when the pair has matches but no relative pose (fundamental-only)."""

    i: int
    j: int
    matches: np.ndarray
    R: np.ndarray
    t: np.ndarray
    valid: bool = True


def pairs_from_matches(arrays: dict, min_inliers: int = 1) -> list[PairMatch]:
    """``matches.zarr`` arrays (``artifacts.load_matches(path)[0]``) -> list of :class:`PairMatch`
    for the pairs with at least ``min_inliers`` verified inliers."""
    pairs = np.asarray(arrays["pairs"])
    off = np.asarray(arrays["inlier_offsets"])
    inl = np.asarray(arrays["inlier_matches"])
    valid = np.asarray(arrays.get("pose_valid", np.ones(len(pairs), bool)))
    out = []
    for p in range(len(pairs)):
        m = inl[off[p] : off[p + 1]]
        if len(m) < max(min_inliers, 1):
            continue
        out.append(
            PairMatch(int(pairs[p, 0]), int(pairs[p, 1]), np.asarray(m, np.int64),
                      np.asarray(arrays["R"][p], np.float64),
                      np.asarray(arrays["t"][p], np.float64), bool(valid[p]))
        )
    return out


def _as_pair(p) -> PairMatch:
    if isinstance(p, PairMatch):
        return p
    p = tuple(p)
    return PairMatch(int(p[0]), int(p[1]), np.asarray(p[2], np.int64).reshape(-1, 2), np.asarray(p[3], np.float64),
                     np.asarray(p[4], np.float64).reshape(3), bool(p[5]) if len(p) > 5 else True)


def covisibility_from_pairs(pairs: Sequence, n_views: int) -> np.ndarray:
    """W [N,N]: :func:`~manifoldneus.mavos.covisibility_matrix` of the pairs' verified inlier counts."""
    pairs = [_as_pair(p) for p in pairs]
    return covisibility_matrix(n_views, [(p.i, p.j) for p in pairs], [len(p.matches) for p in pairs])


def relative_pose(p: PairMatch, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose camera a -> camera b (``x_b = R x_a + t``, ``|t| = 1``) from the pair {a, b}."""
    if (p.i, p.j) == (a, b):
        return p.R, p.t
    if (p.i, p.j) == (b, a):
        return p.R.T, -p.R.T @ p.t
    raise ValueError(f"pair ({p.i}, {p.j}) is not ({a}, {b})")


# --------------------------------------------------------------------------- small helpers


def _padded(groups: np.ndarray, n_groups: int) -> np.ndarray:
    """Item indices grouped by ``groups`` -> [n_groups, max_count] (pad -1), stable order."""
    groups = np.asarray(groups, np.int64)
    if len(groups) == 0:
        return -np.ones((n_groups, 0), np.int64)
    order = np.argsort(groups, kind="stable")
    g = groups[order]
    counts = np.bincount(g, minlength=n_groups)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pos = np.arange(len(g)) - starts[g]
    out = -np.ones((n_groups, int(counts.max())), np.int64)
    out[g, pos] = order
    return out


def triangulate_multiview(R: np.ndarray, t: np.ndarray, xn: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Batched linear (DLT) triangulation.

    R [O,3,3], t [O,3]: w2c of the camera of each observation; xn [O,2] normalised coordinates;
    idx [T,m] observation indices per point (-1 = padding). Returns X [T,3] (NaN when degenerate)."""
    T, m = idx.shape
    X = np.full((T, 3), np.nan)
    if T == 0 or m == 0:
        return X
    valid = idx >= 0
    k = np.where(valid, idx, 0)
    P = np.concatenate([R[k], t[k][..., None]], -1)  # [T,m,3,4]
    x = xn[k]  # [T,m,2]
    r1 = x[..., 0:1] * P[..., 2, :] - P[..., 0, :]
    r2 = x[..., 1:2] * P[..., 2, :] - P[..., 1, :]
    A = np.stack([r1, r2], 2) * valid[..., None, None]  # [T,m,2,4]
    A = A.reshape(T, 2 * m, 4)
    A = A / np.maximum(np.linalg.norm(A, axis=-1, keepdims=True), 1e-12)
    _, _, Vt = np.linalg.svd(A)
    h = Vt[:, -1, :]
    ok = np.abs(h[:, 3]) > 1e-12
    X[ok] = h[ok, :3] / h[ok, 3:4]
    return X


# --------------------------------------------------------------------------- bundle adjustment


class _SegmentSum:
    """Repeated sums of values grouped by fixed integer keys: ``self(values)[k] = sum(values[keys == k])``
    (a sparse indicator matrix times the values)."""

    def __init__(self, keys: np.ndarray, n: int):
        from scipy.sparse import csr_matrix

        keys = np.asarray(keys, np.int64)
        self.n = n
        self.M = csr_matrix((np.ones(len(keys)), (keys, np.arange(len(keys)))), shape=(n, len(keys)))

    def __call__(self, values: np.ndarray) -> np.ndarray:
        v = values.reshape(len(values), -1)
        return np.asarray(self.M @ v).reshape((self.n,) + values.shape[1:])


def _solve_spd(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve a small dense symmetric positive definite system (Cholesky, torch on one thread: a
    multi-threaded BLAS on a loaded 2-core machine makes a 300x300 factorisation ~100x slower)."""
    import torch

    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        At, bt = torch.from_numpy(np.ascontiguousarray(A)), torch.from_numpy(np.ascontiguousarray(b))[:, None]
        L, info = torch.linalg.cholesky_ex(At)
        if int(info) == 0:
            return torch.cholesky_solve(bt, L)[:, 0].numpy()
        return torch.linalg.lstsq(At, bt, driver="gelsd").solution[:, 0].numpy()
    finally:
        torch.set_num_threads(prev)


def _inv3(A: np.ndarray) -> np.ndarray:
    """Inverse of 3x3 matrices [...,3,3] (adjugate / determinant; callers pass damped SPD blocks)."""
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    d, e, f = A[..., 1, 0], A[..., 1, 1], A[..., 1, 2]
    g, h, i = A[..., 2, 0], A[..., 2, 1], A[..., 2, 2]
    co = np.stack([e * i - f * h, c * h - b * i, b * f - c * e,
                   f * g - d * i, a * i - c * g, c * d - a * f,
                   d * h - e * g, b * g - a * h, a * e - b * d], -1).reshape(A.shape)
    det = a * co[..., 0, 0] + b * co[..., 1, 0] + c * co[..., 2, 0]
    return co / det[..., None, None]


def _robust(sq: np.ndarray, loss: str, delta: float) -> tuple[np.ndarray, np.ndarray]:
    """Robust cost rho(s) and weight rho'(s) of squared residual norms s (scipy's loss conventions)."""
    d2 = delta * delta
    if loss == "linear":
        return sq, np.ones_like(sq)
    if loss == "huber":
        big = sq > d2
        root = np.sqrt(np.where(big, sq, d2))
        return np.where(big, 2 * delta * root - d2, sq), np.where(big, delta / root, 1.0)
    if loss == "soft_l1":
        a = np.sqrt(1 + sq / d2)
        return 2 * d2 * (a - 1), 1 / a
    if loss == "cauchy":
        return d2 * np.log1p(sq / d2), 1 / (1 + sq / d2)
    raise ValueError(f"unknown robust loss {loss!r} (linear | huber | soft_l1 | cauchy)")


def bundle_adjust(
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    X: np.ndarray,
    cam: np.ndarray,
    pt: np.ndarray,
    uv: np.ndarray,
    free: np.ndarray | None = None,
    *,
    loss: str = "huber",
    f_scale: float = 1.0,
    max_iter: int = 50,
    ftol: float = 1e-4,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Robust bundle adjustment of poses and points: Levenberg-Marquardt with the Schur complement
    on the points (dense reduced camera system), robust loss by iteratively reweighted normal
    equations (losses and ``f_scale`` as in ``scipy.optimize.least_squares``).

    K [V,3,3]; R [V,3,3], t [V,3] initial w2c; X [P,3] initial points; observation o of point
    pt[o] in camera cam[o] at pixel uv[o]. Pose updates ``R <- exp(dw) R``, ``t <- t + dt`` (so a
    fixed translation coordinate stays exactly fixed: that is how callers pin the scale).
    free [V,6] bool: which of (dw, dt) per camera are
    optimised (default: all but camera 0; the caller fixes the remaining gauge freedom, e.g. one
    translation coordinate of a second camera for the scale). Residuals are in pixels.
    Returns (R, t, X, info) with per-observation errors before/after (``err_before``, ``err_after``).

    (``scipy.optimize.least_squares`` with an analytic sparse Jacobian and lsmr was tried first:
    its inexact trust-region steps stalled in the bas-relief valley of narrow-FOV cameras, far
    from the optimum, at several times the cost.)"""
    from scipy.sparse import bsr_matrix, coo_matrix

    K = np.asarray(K, np.float64)
    R = np.asarray(R, np.float64).copy()
    t = np.asarray(t, np.float64).copy()
    X = np.asarray(X, np.float64).copy()
    cam = np.asarray(cam, np.int64)
    pt = np.asarray(pt, np.int64)
    uv = np.asarray(uv, np.float64)
    V, P, O = len(R), len(X), len(cam)
    if free is None:
        free = np.ones((V, 6), bool)
        free[0] = False
    free = np.asarray(free, bool)
    fidx = np.flatnonzero(free.ravel())
    Ko = K[cam]

    by_cam, by_pt = _SegmentSum(cam, V), _SegmentSum(pt, P)
    # sparse structure of W (camera-point coupling blocks, 6V x 3P) and of blockdiag(V^-1) (3P x 3P)
    w_rows = np.broadcast_to(6 * cam[:, None, None] + np.arange(6)[None, :, None], (O, 6, 3)).ravel()
    w_cols = np.broadcast_to(3 * pt[:, None, None] + np.arange(3)[None, None, :], (O, 6, 3)).ravel()
    v_ptr = np.arange(P + 1)
    v_idx = np.arange(P)
    diag = np.arange(V)

    def residuals(R, t, X):
        Xc = (R[cam] @ X[pt][:, :, None])[:, :, 0] + t[cam]
        with np.errstate(divide="ignore", invalid="ignore"):
            r = project_points(Ko, Xc) - uv
        return r, Xc

    def cost_of(r):
        sq = (r**2).sum(1)
        rho, w = _robust(sq, loss, f_scale)
        c = 0.5 * rho.sum()
        return (c if np.isfinite(c) else np.inf), w

    r, Xc = residuals(R, t, X)
    err_before = np.linalg.norm(r, axis=1)
    cost, w = cost_of(r)
    cost0 = cost
    lam = 1e-4
    it = n_acc = 0
    status = "max_iter"
    for it in range(1, max_iter + 1):
        z = Xc[:, 2]
        iz = 1.0 / z
        d = np.zeros((O, 2, 3))
        d[:, 0, 0] = Ko[:, 0, 0] * iz
        d[:, 0, 1] = Ko[:, 0, 1] * iz
        d[:, 0, 2] = -(Ko[:, 0, 0] * Xc[:, 0] + Ko[:, 0, 1] * Xc[:, 1]) * iz * iz
        d[:, 1, 1] = Ko[:, 1, 1] * iz
        d[:, 1, 2] = -Ko[:, 1, 1] * Xc[:, 1] * iz * iz
        Jc = np.concatenate([d @ -skew(Xc - t[cam]), d], 2)  # [O,2,6]: d Xc / d(dw, dt) = [-[R X]x, I]
        Jp = d @ R[cam]  # [O,2,3]
        wJcT = (Jc * w[:, None, None]).transpose(0, 2, 1)  # [O,6,2]
        wJpT = (Jp * w[:, None, None]).transpose(0, 2, 1)  # [O,3,2]
        U = by_cam(wJcT @ Jc)  # [V,6,6]
        Vp = by_pt(wJpT @ Jp)  # [P,3,3]
        Wo = wJcT @ Jp  # [O,6,3]
        gc = by_cam(-(wJcT @ r[:, :, None])[:, :, 0])  # [V,6]
        gp = by_pt(-(wJpT @ r[:, :, None])[:, :, 0])  # [P,3]
        Wm = coo_matrix((Wo.ravel(), (w_rows, w_cols)), shape=(6 * V, 3 * P)).tocsr()
        while True:
            Ud = U + lam * (U * np.eye(6)) + 1e-12 * np.eye(6)
            Vd = Vp + lam * (Vp * np.eye(3)) + 1e-12 * np.eye(3)
            Vinv = _inv3(Vd)
            T = (Wm @ bsr_matrix((Vinv, v_idx, v_ptr), shape=(3 * P, 3 * P))).tocsr()  # W V^-1
            S = -(T @ Wm.T).toarray()
            Sb = S.reshape(V, 6, V, 6)
            Sb[diag, :, diag, :] += Ud
            rhs = gc.ravel() - T @ gp.ravel()
            dx = np.zeros(6 * V)
            if len(fidx):
                dx[fidx] = _solve_spd(S[np.ix_(fidx, fidx)], rhs[fidx])
            dc = dx.reshape(V, 6)
            dp = (Vinv @ (gp - (Wm.T @ dx).reshape(P, 3))[:, :, None])[:, :, 0]
            R_new = rotvec_to_matrix(dc[:, :3]) @ R
            t_new = t + dc[:, 3:]
            X_new = X + dp
            r_new, Xc_new = residuals(R_new, t_new, X_new)
            cost_new, w_new = cost_of(r_new)
            if cost_new < cost:
                break
            lam *= 10.0
            if lam > 1e10:
                break
        if not cost_new < cost:
            status = "no_decrease"
            break
        n_acc += 1
        rel = (cost - cost_new) / max(cost, 1e-300)
        R, t, X, r, Xc, cost, w = R_new, t_new, X_new, r_new, Xc_new, cost_new, w_new
        lam = max(lam / 10.0, 1e-9)
        if rel < ftol:
            status = "converged"
            break
    info = {
        "n_obs": int(O), "n_points": int(P), "n_free_camera_params": int(len(fidx)), "iterations": int(it),
        "accepted": int(n_acc), "status": status, "cost_before": float(cost0), "cost_after": float(cost),
        "err_before": err_before, "err_after": np.linalg.norm(r, axis=1),
    }
    return R, t, X, info


# --------------------------------------------------------------------------- anchors: init from matches


@dataclass
class InitResult:
    """Output of :func:`init_from_matches`. Arrays follow ``view_ids`` order."""

    view_ids: list[int]
    w2c: np.ndarray  # [V,4,4] in the gauge frame (every view has a pose; see `placed`/`method`)
    placed: np.ndarray  # bool [V]: pose from the reconstruction (False: fallback pose, see method)
    method: list[str]  # per view: root | edge | pnp | fallback:<view id> | root-copy
    points: np.ndarray  # [P,3] triangulated points (gauge frame) kept after the final BA
    point_obs: np.ndarray  # int [P]: number of observations of each point
    point_in_mask: np.ndarray  # bool [P]: majority of the observations in the foreground (all True without masks)
    gauge: np.ndarray  # [4,4] similarity reconstruction frame -> gauge frame (y = s x + t)
    root: int  # global id of the root view
    tree_edges: list[tuple[int, int]]  # (parent, child) global ids of the maximum spanning tree
    unplaced: list[int]  # global ids of the views the reconstruction could not place
    diagnostics: dict = field(default_factory=dict)  # JSON-able numbers (reprojection errors, timings, ...)
    # the inlier observations of `points` after the final BA: view (global id), point index, pixel [O,2]
    obs_view: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    obs_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    obs_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


def _err_stats(e: np.ndarray) -> dict:
    e = np.asarray(e, np.float64)
    bad = int((~np.isfinite(e)).sum())
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"n": 0, "n_nonfinite": bad, "mean": None, "median": None, "rms": None, "p90": None}
    return {"n": int(e.size), "n_nonfinite": bad, "mean": float(e.mean()), "median": float(np.median(e)),
            "rms": float(np.sqrt((e**2).mean())), "p90": float(np.percentile(e, 90))}


def _max_spanning_tree(Wsub: np.ndarray, root: int) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Maximum spanning forest of Wsub; returns (parent, child) edges of root's tree in BFS order
    and the component mask of the root."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    mst = minimum_spanning_tree(csr_matrix(-Wsub))  # weights are negative: maximum spanning tree
    A = (mst + mst.T).tocsr()
    order, pred = breadth_first_order(A, root, directed=False, return_predecessors=True)
    edges = [(int(pred[c]), int(c)) for c in order[1:]]
    comp = np.zeros(len(Wsub), bool)
    comp[order] = True
    return edges, comp


class _Recon:
    """Incremental reconstruction state over the anchors (local indices 0..V-1)."""

    def __init__(self, Kl, kps, pairs_local, V, reproj_px, min_angle_deg):
        self.K = Kl
        self.V = V
        self.thr = reproj_px
        self.min_cos = np.cos(np.radians(min_angle_deg))
        self.R = np.tile(np.eye(3), (V, 1, 1))
        self.t = np.zeros((V, 3))
        self.placed = np.zeros(V, bool)
        self._build_tracks(kps, pairs_local)

    def _build_tracks(self, kps, pairs_local):
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        n_kp = np.array([len(k) for k in kps], np.int64)
        off = np.concatenate([[0], np.cumsum(n_kp)])
        a, b = [], []
        for (li, lj, m) in pairs_local:
            if len(m):
                a.append(off[li] + m[:, 0])
                b.append(off[lj] + m[:, 1])
        if not a:
            self.obs_view = np.zeros(0, np.int64)
            self.obs_track = np.zeros(0, np.int64)
            self.obs_uv = np.zeros((0, 2))
            self.n_tracks = 0
            self._finish_tracks()
            return
        a, b = np.concatenate(a), np.concatenate(b)
        n = int(off[-1])
        G = coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
        _, labels = connected_components(G, directed=False)
        nodes = np.unique(np.concatenate([a, b]))
        view = np.searchsorted(off, nodes, side="right") - 1
        track = labels[nodes]
        # a track seen twice in one view is inconsistent there: drop those observations
        key = track * self.V + view
        uniq, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
        ok = cnt[inv] == 1
        nodes, view, track = nodes[ok], view[ok], track[ok]
        # keep tracks with >= 2 observations, relabel compactly
        tl, tinv, tcnt = np.unique(track, return_inverse=True, return_counts=True)
        ok = tcnt[tinv] >= 2
        nodes, view = nodes[ok], view[ok]
        _, track = np.unique(track[ok], return_inverse=True)
        self.n_conflicts = int((cnt > 1).sum())
        self.obs_view = view.astype(np.int64)
        self.obs_track = track.astype(np.int64)
        uv = np.zeros((len(nodes), 2))
        for v in range(self.V):
            sel = view == v
            uv[sel] = np.asarray(kps[v], np.float64)[nodes[sel] - off[v]]
        self.obs_uv = uv
        self.n_tracks = int(track.max() + 1) if len(track) else 0
        self._finish_tracks()

    def _finish_tracks(self):
        O = len(self.obs_view)
        self.obs_active = np.ones(O, bool)
        self.obs_xn = pixels_to_normalised(self.K[self.obs_view], self.obs_uv) if O else np.zeros((0, 2))
        self.X = np.full((self.n_tracks, 3), np.nan)
        self.has_point = np.zeros(self.n_tracks, bool)

    # -- per-observation geometry
    def errors(self, obs: np.ndarray, R=None, t=None, X=None) -> tuple[np.ndarray, np.ndarray]:
        """(reprojection error px, depth) of observations `obs` with their track's point."""
        R = self.R if R is None else R
        t = self.t if t is None else t
        X = self.X if X is None else X
        v = self.obs_view[obs]
        Xc = np.einsum("oij,oj->oi", R[v], X[self.obs_track[obs]]) + t[v]
        with np.errstate(divide="ignore", invalid="ignore"):
            e = np.linalg.norm(project_points(self.K[v], Xc) - self.obs_uv[obs], axis=1)
        return np.where(np.isfinite(e), e, np.inf), Xc[:, 2]

    def correspondences(self, v: int) -> np.ndarray:
        """Observations in view v whose track has a point."""
        return np.flatnonzero((self.obs_view == v) & self.has_point[self.obs_track] & self.obs_active)

    def count_inliers(self, v, R, t) -> int:
        obs = self.correspondences(v)
        if len(obs) == 0:
            return 0
        Xc = self.X[self.obs_track[obs]] @ R.T + t
        with np.errstate(divide="ignore", invalid="ignore"):
            e = np.linalg.norm(project_points(self.K[v], Xc) - self.obs_uv[obs], axis=1)
        return int(((e < self.thr) & (Xc[:, 2] > 0)).sum())

    # -- placement candidates
    def edge_pose(self, parent: int, child: int, Rpc, tpc, min_points: int):
        """Pose of `child` from the parent's pose and the relative pose, translation scaled so the
        pair's two-view triangulation agrees with the parent's existing points (median depth ratio).
        Returns (R, t, n_scale_points) or None."""
        Rc = Rpc @ self.R[parent]
        first = self.placed.sum() == 1
        if first:
            return Rc, Rpc @ self.t[parent] + tpc, 0
        # tracks seen in both views, with a point
        op = np.flatnonzero((self.obs_view == parent) & self.obs_active)
        oc = np.flatnonzero((self.obs_view == child) & self.obs_active)
        common, ip, ic = np.intersect1d(self.obs_track[op], self.obs_track[oc], return_indices=True)
        keep = self.has_point[common]
        common, op, oc = common[keep], op[ip[keep]], oc[ic[keep]]
        if len(common) < min_points:
            return None
        # two-view triangulation in parent's camera frame with |baseline| = 1
        Rs = np.stack([np.eye(3), Rpc])
        ts = np.stack([np.zeros(3), tpc])
        xn = np.concatenate([self.obs_xn[op], self.obs_xn[oc]])
        Rall = np.concatenate([np.repeat(Rs[:1], len(op), 0), np.repeat(Rs[1:], len(oc), 0)])
        tall = np.concatenate([np.repeat(ts[:1], len(op), 0), np.repeat(ts[1:], len(oc), 0)])
        idx = np.stack([np.arange(len(op)), len(op) + np.arange(len(oc))], 1)
        Xp = triangulate_multiview(Rall, tall, xn, idx)
        z_unit = Xp[:, 2]
        z_map = (self.X[common] @ self.R[parent].T + self.t[parent])[:, 2]
        ok = np.isfinite(z_unit) & (z_unit > 1e-9) & (z_map > 0)
        if ok.sum() < min_points:
            return None
        s = float(np.median(z_map[ok] / z_unit[ok]))
        if not np.isfinite(s) or s <= 0:
            return None
        return Rc, Rpc @ self.t[parent] + s * tpc, int(ok.sum())

    def pnp_pose(self, v: int, min_points: int, iterations: int, confidence: float):
        obs = self.correspondences(v)
        if len(obs) < min_points:
            return None
        w2c, n = place_by_pnp(self.K[v], self.obs_uv[obs], self.X[self.obs_track[obs]], reproj_px=self.thr,
                              min_inliers=min_points, iterations=iterations, confidence=confidence)
        if w2c is None:
            return None
        return w2c[:3, :3], w2c[:3, 3], n

    def check_view(self, v: int, factor: float = 2.0) -> int:
        """Deactivate view v's observations of existing points that reproject worse than
        factor * thr (or behind the camera); returns how many."""
        obs = self.correspondences(v)
        if len(obs) == 0:
            return 0
        e, z = self.errors(obs)
        bad = (e >= factor * self.thr) | (z <= 0)
        self.obs_active[obs[bad]] = False
        return int(bad.sum())

    # -- triangulation
    def triangulate(self):
        """Triangulate tracks without a point that have >= 2 active observations in placed views."""
        obs = np.flatnonzero(self.obs_active & self.placed[self.obs_view] & ~self.has_point[self.obs_track])
        if len(obs) == 0:
            return 0
        cnt = np.bincount(self.obs_track[obs], minlength=self.n_tracks)
        obs = obs[cnt[self.obs_track[obs]] >= 2]
        if len(obs) == 0:
            return 0
        tracks, local = np.unique(self.obs_track[obs], return_inverse=True)
        added = 0
        for attempt in range(2):
            idx = _padded(local, len(tracks))
            idx_obs = np.where(idx >= 0, obs[np.maximum(idx, 0)], -1)
            Xt = self._tri(idx_obs)
            X_full = self.X.copy()
            X_full[tracks] = Xt
            e, z = self.errors(obs, X=X_full)
            good_obs = (e < self.thr) & (z > 0)
            n_good = np.bincount(local, weights=good_obs, minlength=len(tracks))
            n_all = np.bincount(local, minlength=len(tracks))
            all_good = (n_good == n_all) & np.isfinite(Xt).all(1)
            ang_ok = self._angle_ok(idx_obs)
            accept = all_good & ang_ok
            self.X[tracks[accept]] = Xt[accept]
            self.has_point[tracks[accept]] = True
            added += int(accept.sum())
            # retry once without the bad observations of tracks that keep >= 2 good ones
            retry = ~all_good & (n_good >= 2) & (n_all >= 3)
            if attempt == 1 or not retry.any():
                break
            bad = ~good_obs & retry[local]
            self.obs_active[obs[bad]] = False
            sel = retry[local] & good_obs
            obs = obs[sel]
            tracks, local = np.unique(self.obs_track[obs], return_inverse=True)
        return added

    def _tri(self, idx_obs):
        T, m = idx_obs.shape
        safe = np.maximum(idx_obs, 0)
        v = self.obs_view[safe]
        Robs = self.R[v].reshape(-1, 3, 3)
        tobs = self.t[v].reshape(-1, 3)
        xn = self.obs_xn[safe].reshape(-1, 2)
        idx = np.where(idx_obs >= 0, np.arange(T * m).reshape(T, m), -1)
        return triangulate_multiview(Robs, tobs, xn, idx)

    def _angle_ok(self, idx_obs):
        """Largest angle between the viewing rays of a track's observations >= min angle."""
        safe = np.maximum(idx_obs, 0)
        v = self.obs_view[safe]
        xn = self.obs_xn[safe]
        d = np.concatenate([xn, np.ones(xn.shape[:-1] + (1,))], -1)
        d = np.einsum("tmji,tmj->tmi", self.R[v], d)  # world ray directions R^T x
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        c = np.einsum("tai,tbi->tab", d, d)
        valid = idx_obs >= 0
        c = np.where(valid[:, :, None] & valid[:, None, :], c, 1.0)
        return c.min(axis=(1, 2)) < self.min_cos

    # -- bundle adjustment
    def bundle_adjust(self, gauge_views, loss, f_scale, max_iter, ftol):
        obs = np.flatnonzero(self.obs_active & self.placed[self.obs_view] & self.has_point[self.obs_track])
        tracks, pt = np.unique(self.obs_track[obs], return_inverse=True)
        cams, cam = np.unique(self.obs_view[obs], return_inverse=True)
        free = np.ones((len(cams), 6), bool)
        root, second = gauge_views
        if root in cams:
            free[np.searchsorted(cams, root)] = False
        if second is not None and second in cams and root in cams:
            # fix the scale: the second view's largest translation coordinate
            k = int(np.argmax(np.abs(self.t[second])))
            free[np.searchsorted(cams, second), 3 + k] = False
        R, t, X, info = bundle_adjust(self.K[cams], self.R[cams], self.t[cams], self.X[tracks], cam, pt,
                                      self.obs_uv[obs], free, loss=loss, f_scale=f_scale, max_iter=max_iter, ftol=ftol)
        self.R[cams], self.t[cams], self.X[tracks] = R, t, X
        return obs, info

    def filter_outliers(self):
        """Deactivate observations with error > thr or behind the camera; drop points with < 2 left."""
        obs = np.flatnonzero(self.obs_active & self.placed[self.obs_view] & self.has_point[self.obs_track])
        e, z = self.errors(obs)
        bad = (e >= self.thr) | (z <= 0)
        self.obs_active[obs[bad]] = False
        left = np.bincount(self.obs_track[obs[~bad]], minlength=self.n_tracks)
        drop = self.has_point & (left < 2)
        self.has_point[drop] = False
        self.X[drop] = np.nan
        return int(bad.sum()), int(drop.sum())


def init_from_matches(
    view_ids: Sequence[int],
    K: np.ndarray,
    keypoints: Sequence[np.ndarray],
    pairs: Sequence,
    W: np.ndarray | None = None,
    *,
    reproj_px: float = 3.0,
    min_angle_deg: float = 1.5,
    min_scale_points: int = 4,
    min_pnp_points: int = 8,
    pnp_iterations: int = 2000,
    pnp_confidence: float = 0.9999,
    ba_loss: str = "huber",
    ba_f_scale: float = 1.0,
    ba_max_iter: int = 50,
    ba_ftol: float = 1e-4,
    ba_rounds: int = 2,
    gauge_radius: float = 0.8,
    gauge_percentile: float = 95.0,
    masks: Sequence[np.ndarray] | None = None,
    log: Callable[[str], None] | None = None,
) -> InitResult:
    """Initial poses of the views ``view_ids`` (the anchors) from verified matches.

    K [N,3,3], keypoints (length N, [K_v,2] pixels), pairs (:class:`PairMatch` or tuples
    ``(i, j, matches [M,2], R_ij, t_ij[, valid])``) and W [N,N] are indexed by **global** view id;
    only pairs with both views in ``view_ids`` are used. W defaults to the inlier counts of the pairs.
    masks (optional, one [H,W] bool per entry of ``view_ids``): the gauge's robust extent is then
    measured on the points seen mostly inside the foreground (when there are >= 20 of them).

    1. maximum spanning tree of W restricted to the views (``minimum_spanning_tree`` of -W);
       root = the view of largest co-visibility within the set (it keeps w2c = I until the gauge);
    2. tracks = connected components of the pairwise inlier matches (a track seen twice in one view
       loses those observations);
    3. incremental placement: the next view is an unplaced tree child of a placed view (the one with
       the most 2D-3D correspondences first; then non-tree neighbours of placed views). Candidate
       poses: (a) the tree edge's essential-matrix rotation chained onto the parent, translation
       direction from the edge and its scale from the median ratio of the existing points' depths
       to the pair's unit-baseline two-view triangulation (>= ``min_scale_points`` shared points; the
       root's first child fixes the unit: its baseline is 1); (b) PnP-RANSAC on the existing points
       (>= ``min_pnp_points`` inliers). The one with more reprojection inliers (< ``reproj_px``) wins;
       the view's observations of existing points that then reproject worse than 2 ``reproj_px`` are
       dropped;
    4. after each placement, tracks with >= 2 placed observations that all reproject within
       ``reproj_px`` (in front of the cameras) and whose rays span >= ``min_angle_deg`` are
       triangulated (linear multi-view DLT; one retry without the bad observations);
    5. ``ba_rounds`` robust bundle adjustments (:func:`bundle_adjust`; root fixed, one translation
       coordinate of the first placed child fixed for the scale), outlier observations
       (>= ``reproj_px``) removed after each; views still unplaced get a second chance against the
       refined points (and one more BA round if any is placed);
    6. gauge: y = s (x - median(points)), s = gauge_radius / percentile(|x - median|, gauge_percentile).

    Views that cannot be placed keep the pose of their best-matching placed neighbour (method
    ``fallback:<id>``; ``root-copy`` if they have none) and are listed in ``unplaced``.
    """
    import cv2  # noqa: F401  (fail early if OpenCV is missing)

    t_start = time.perf_counter()
    say = log or (lambda s: None)
    view_ids = [int(v) for v in view_ids]
    V = len(view_ids)
    if V == 0:
        raise ValueError("init_from_matches: no views")
    if len(set(view_ids)) != V:
        raise ValueError("init_from_matches: duplicate view ids")
    K = np.asarray(K, np.float64)
    loc = {g: a for a, g in enumerate(view_ids)}
    pairs = [_as_pair(p) for p in pairs]
    pairs = [p for p in pairs if p.i in loc and p.j in loc and p.i != p.j]
    if W is None:
        W = covisibility_from_pairs(pairs, int(max(max(view_ids) + 1, len(K))))
    W = np.asarray(W, np.float64)
    Wsub = W[np.ix_(view_ids, view_ids)].copy()
    np.fill_diagonal(Wsub, 0.0)
    pair_of = {}
    for p in pairs:
        pair_of[(loc[p.i], loc[p.j])] = pair_of[(loc[p.j], loc[p.i])] = p

    root = int(np.argmax(Wsub.sum(1)))
    tree, comp = _max_spanning_tree(Wsub, root)
    tree_parent = {c: par for par, c in tree}

    Kl = K[view_ids]
    kps = [np.asarray(keypoints[g], np.float64).reshape(-1, 2) for g in view_ids]
    rec = _Recon(Kl, kps, [(loc[p.i], loc[p.j], p.matches) for p in pairs], V, reproj_px, min_angle_deg)
    say(f"init_from_matches: {V} views, {len(pairs)} pairs, {rec.n_tracks} tracks, {len(rec.obs_view)} observations, "
        f"root {view_ids[root]}")

    method = [""] * V
    rec.placed[root] = True
    method[root] = "root"
    second = None

    def place_all() -> int:
        """Place views one at a time until none can be; returns how many were placed."""
        nonlocal second
        n_placed = 0
        while True:
            # candidates: unplaced views with a placed neighbour (tree children first)
            cands = [c for c in range(V) if not rec.placed[c] and c in tree_parent and rec.placed[tree_parent[c]]]
            others = [c for c in range(V) if not rec.placed[c] and c not in cands
                      and any(rec.placed[n] and (n, c) in pair_of for n in range(V))]
            done = False
            for group in (cands, others):
                order = sorted(group, key=lambda c: (-len(rec.correspondences(c)), -Wsub[c].max()))
                for c in order:
                    parents = [n for n in np.argsort(-Wsub[c])
                               if rec.placed[n] and (n, c) in pair_of and Wsub[c, n] > 0]
                    if c in tree_parent and tree_parent[c] in parents:
                        parents.remove(tree_parent[c])
                        parents.insert(0, tree_parent[c])
                    best = None
                    for par in parents:
                        p = pair_of[(par, c)]
                        if not p.valid:
                            continue
                        Rpc, tpc = relative_pose(p, view_ids[par], view_ids[c])
                        est = rec.edge_pose(par, c, Rpc, tpc / max(np.linalg.norm(tpc), 1e-12), min_scale_points)
                        if est is not None:
                            n_in = rec.count_inliers(c, est[0], est[1])
                            best = (est[0], est[1], n_in, "edge", int(par))
                            break
                    pnp = rec.pnp_pose(c, min_pnp_points, pnp_iterations, pnp_confidence)
                    if pnp is not None:
                        n_in = rec.count_inliers(c, pnp[0], pnp[1])
                        if best is None or n_in > best[2]:
                            best = (pnp[0], pnp[1], n_in, "pnp", None)
                    if best is None:
                        continue
                    if rec.placed.sum() > 1 and best[2] < min_scale_points:
                        continue
                    rec.R[c], rec.t[c] = best[0], best[1]
                    rec.placed[c] = True
                    method[c] = best[3]
                    if second is None:
                        second = c
                    rec.check_view(c)
                    n_new = rec.triangulate()
                    src = "" if best[4] is None else f" from {view_ids[best[4]]}"
                    say(f"  placed view {view_ids[c]} ({best[3]}{src}): "
                        f"{best[2]} inliers, +{n_new} points ({int(rec.has_point.sum())} total)")
                    done = True
                    n_placed += 1
                    break
                if done:
                    break
            if not done:
                return n_placed

    ba_infos = []
    n_removed = 0

    def ba_round(r: int) -> np.ndarray:
        nonlocal n_removed
        _, info = rec.bundle_adjust((root, second), ba_loss, ba_f_scale, ba_max_iter, ba_ftol)
        removed, dropped = rec.filter_outliers()
        n_removed += removed
        ba_infos.append({"iterations": info["iterations"], "status": info["status"], "n_obs": info["n_obs"],
                         "n_points": info["n_points"], "cost_before": info["cost_before"],
                         "cost_after": info["cost_after"],
                         "removed_obs": removed, "dropped_points": dropped})
        say(f"  BA round {r}: {info['n_obs']} obs, {info['n_points']} points, {info['iterations']} iterations "
            f"({info['status']}), median error {np.median(info['err_before']):.3f} -> "
            f"{np.median(info['err_after']):.3f} px, "
            f"{removed} outlier observations removed")
        rec.triangulate()  # refined poses may triangulate tracks that failed the checks before
        return info["err_after"]

    t_inc = time.perf_counter()
    place_all()
    t_ba = time.perf_counter()
    obs0 = np.flatnonzero(rec.obs_active & rec.placed[rec.obs_view] & rec.has_point[rec.obs_track])
    err_before = rec.errors(obs0)[0] if len(obs0) else np.zeros(0)
    err_first_ba = err_before
    can_ba = rec.has_point.any() and rec.placed.sum() >= 2
    for r in range(max(ba_rounds, 0) if can_ba else 0):
        e = ba_round(r)
        if r == 0:
            err_first_ba = e
    n_retry = 0
    if not rec.placed.all() and can_ba and ba_rounds > 0:
        # second chance for the views that could not be placed, against the refined points
        n_retry = place_all()
        if n_retry:
            ba_round(len(ba_infos))
    obs1 = np.flatnonzero(rec.obs_active & rec.placed[rec.obs_view] & rec.has_point[rec.obs_track])
    err_after = rec.errors(obs1)[0] if len(obs1) else np.zeros(0)
    t_gauge = time.perf_counter()

    # gauge: median-centred, robust radius -> gauge_radius
    pts_ids = np.flatnonzero(rec.has_point)
    point_of_track = np.full(rec.n_tracks, -1, np.int64)
    point_of_track[pts_ids] = np.arange(len(pts_ids))
    pts = rec.X[pts_ids]
    n_obs_pt = np.bincount(rec.obs_track[obs1], minlength=rec.n_tracks)[pts_ids]
    in_mask = np.ones(len(pts_ids), bool)
    if masks is not None and len(obs1):
        fg = np.zeros(len(obs1), bool)
        for v in range(V):
            sel = rec.obs_view[obs1] == v
            if not sel.any() or masks[v] is None:
                fg[sel] = True
                continue
            m = np.asarray(masks[v], bool)
            uv = rec.obs_uv[obs1[sel]]
            c = np.clip(np.floor(uv[:, 0]).astype(int), 0, m.shape[1] - 1)
            r_ = np.clip(np.floor(uv[:, 1]).astype(int), 0, m.shape[0] - 1)
            fg[sel] = m[r_, c]
        n_fg = np.bincount(rec.obs_track[obs1], weights=fg, minlength=rec.n_tracks)[pts_ids]
        in_mask = n_fg > 0.5 * np.maximum(n_obs_pt, 1)
    gpts = pts[in_mask] if in_mask.sum() >= 20 else pts
    if len(gpts) >= 3:
        s, centre = gauge_from_points(gpts, gauge_radius, gauge_percentile)
    else:  # no structure (e.g. a single view): the root looks at the origin from identity_init's distance
        centre = camera_centers(np.concatenate([rec.R[root], rec.t[root][:, None]], 1)) + 3.0 * rec.R[root][2]
        s = 1.0
    G = sim3_matrix(s, np.eye(3), -s * centre)
    w2c_rec = to_4x4(np.concatenate([rec.R, rec.t[..., None]], -1))
    w2c = transform_w2c(w2c_rec, s, np.eye(3), -s * centre)
    points = s * (pts - centre)

    # views the reconstruction could not place: best-matching placed neighbour's pose
    unplaced = [view_ids[a] for a in range(V) if not rec.placed[a]]
    for a in range(V):
        if rec.placed[a]:
            continue
        nb = [n for n in np.argsort(-Wsub[a]) if rec.placed[n] and Wsub[a, n] > 0]
        if nb:
            w2c[a] = w2c[nb[0]]
            method[a] = f"fallback:{view_ids[nb[0]]}"
        else:
            w2c[a] = w2c[root]
            method[a] = "root-copy"
    if unplaced:
        say(f"  could not place views {unplaced}: neighbour poses used")

    t_end = time.perf_counter()
    kinds = [m.split(":")[0] for m in method]
    diag = {
        "n_views": V,
        "n_placed": int(rec.placed.sum()),
        "n_pairs": len(pairs),
        "n_tracks": int(rec.n_tracks),
        "n_track_conflicts": int(getattr(rec, "n_conflicts", 0)),
        "n_points": int(len(points)),
        "n_points_in_mask": int(in_mask.sum()),
        "n_observations": int(len(obs1)),
        "root_component_size": int(comp.sum()),
        "reproj_before_ba_px": _err_stats(err_before),  # incremental poses, observations entering BA
        "reproj_after_first_ba_px": _err_stats(err_first_ba),  # same observations after the first BA round
        "reproj_after_ba_px": _err_stats(err_after),  # final poses/points, final inlier observations
        "ba_rounds": ba_infos,
        "ba_removed_obs": int(n_removed),
        "placed_after_ba": int(n_retry),
        "gauge_scale": float(s),
        "gauge_centre": centre.tolist(),
        "gauge_radius_before": gauge_radius / s,
        "gauge_points": "foreground" if (masks is not None and in_mask.sum() >= 20) else "all",
        "methods": {m: kinds.count(m) for m in sorted(set(kinds))},
        "seconds_incremental": t_ba - t_inc,
        "seconds_ba": t_gauge - t_ba,
        "seconds_total": t_end - t_start,
    }
    return InitResult(
        view_ids=view_ids, w2c=w2c, placed=rec.placed.copy(), method=method, points=points, point_obs=n_obs_pt,
        point_in_mask=in_mask, gauge=G, root=view_ids[root], tree_edges=[(view_ids[a], view_ids[b]) for a, b in tree],
        unplaced=unplaced, diagnostics=diag, obs_view=np.asarray(view_ids, np.int64)[rec.obs_view[obs1]],
        obs_point=point_of_track[rec.obs_track[obs1]], obs_uv=np.asarray(rec.obs_uv[obs1], np.float64),
    )


# --------------------------------------------------------------------------- identity


def gauge_from_points(points: np.ndarray, radius: float = 0.8, percentile: float = 95.0) -> tuple[float, np.ndarray]:
    """Scale s and centre c of the gauge y = s (x - c): median-centred, the ``percentile``-th
    percentile distance of the points mapped to ``radius`` (the object fits the unit sphere)."""
    centre = np.median(points, axis=0)
    extent = float(np.percentile(np.linalg.norm(points - centre, axis=1), percentile))
    return radius / max(extent, 1e-12), centre


def identity_init(n: int, distance: float = 3.0) -> np.ndarray:
    """The paper's "identity" initialisation: n copies of one canonical pose, [n,4,4].

    Rotation = identity (camera axes = world axes: x right, y down, the camera looks along +z),
    camera centre at (0, 0, -distance), so every camera looks at the origin (the object's centre in
    the unit-sphere frame) from ``distance`` (default 3, outside the unit sphere):
    ``w2c = [I | (0, 0, distance)]``."""
    w2c = np.tile(np.eye(4), (int(n), 1, 1))
    w2c[:, 2, 3] = float(distance)
    return w2c


# --------------------------------------------------------------------------- successors


def lift_points(
    K: np.ndarray, w2c: np.ndarray, uv: np.ndarray, depth: np.ndarray, ray_distance: bool = False
) -> np.ndarray:
    """Back-project pixels uv [M,2] of a view with depth [M] to world points [M,3].
    depth is the z-depth (along the optical axis) unless ``ray_distance`` (distance along the
    unit ray from the camera centre). Non-positive / non-finite depths give NaN points."""
    xn = pixels_to_normalised(K, uv)
    d = np.concatenate([xn, np.ones((len(xn), 1))], 1)
    depth = np.asarray(depth, np.float64).reshape(-1)
    if ray_distance:
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
    Xc = d * depth[:, None]
    w2c = to_4x4(w2c)
    R, t = w2c[:3, :3], w2c[:3, 3]
    X = (Xc - t) @ R
    X[~(np.isfinite(depth) & (depth > 0))] = np.nan
    return X


def place_by_pnp(
    K: np.ndarray,
    uv: np.ndarray,
    X: np.ndarray,
    *,
    reproj_px: float = 3.0,
    min_inliers: int = 12,
    iterations: int = 2000,
    confidence: float = 0.9999,
    refine: bool = True,
    flags: int | None = None,
) -> tuple[np.ndarray | None, int]:
    """PnP-RANSAC of one view from 2D-3D correspondences uv [M,2] (pixels) <-> X [M,3] (world).

    Non-finite points are ignored. Returns (w2c [4,4] or None, number of inliers); None when there
    are fewer than ``min_inliers`` usable correspondences or inliers (reprojection < reproj_px and
    in front of the camera) or RANSAC fails."""
    import cv2

    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    X = np.asarray(X, np.float64).reshape(-1, 3)
    ok = np.isfinite(X).all(1) & np.isfinite(uv).all(1)
    uv, X = uv[ok], X[ok]
    if len(X) < max(min_inliers, 4):
        return None, 0
    K = np.asarray(K, np.float64)
    flags = cv2.SOLVEPNP_EPNP if flags is None else flags
    # RANSAC draws from OpenCV's global generator: seed it from the input, so one input gives one pose
    cv2.setRNGSeed(len(X) * 7919 + int(1e3 * abs(float(X[0, 0]) + float(uv[0, 0]))) % 2**31)
    try:
        okr, rvec, tvec, inl = cv2.solvePnPRansac(
            X, uv, K, None, iterationsCount=int(iterations), reprojectionError=float(reproj_px),
            confidence=float(confidence), flags=flags)
    except cv2.error:
        return None, 0
    if not okr or inl is None or len(inl) < 4:
        return None, 0 if inl is None else int(len(inl))
    inl = inl.ravel()
    if refine:
        try:
            rvec, tvec = cv2.solvePnPRefineLM(X[inl], uv[inl], K, None, rvec, tvec)
        except cv2.error:
            pass
    R = cv2.Rodrigues(rvec)[0]
    t = tvec.ravel()
    Xc = X @ R.T + t
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.linalg.norm(project_points(K, Xc) - uv, axis=1)
    good = (e < reproj_px) & (Xc[:, 2] > 0)
    n = int(good.sum())
    if refine and n >= 6:  # one more refinement on the final inlier set
        try:
            rvec, tvec = cv2.solvePnPRefineLM(X[good], uv[good], K, None, rvec, tvec)
            R, t = cv2.Rodrigues(rvec)[0], tvec.ravel()
            Xc = X @ R.T + t
            with np.errstate(divide="ignore", invalid="ignore"):
                e = np.linalg.norm(project_points(K, Xc) - uv, axis=1)
            n = int(((e < reproj_px) & (Xc[:, 2] > 0)).sum())
        except cv2.error:
            pass
    if n < min_inliers:
        return None, n
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, t
    return w2c, n


def successor_correspondences(
    view: int,
    keypoints: Sequence[np.ndarray],
    pairs: Sequence,
    placed: dict,
    K: np.ndarray | None = None,
    depth_at: Callable[[int, np.ndarray], np.ndarray] | None = None,
    points3d: dict | None = None,
    ray_distance: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D-3D correspondences of ``view`` from its matches to the placed views.

    placed: {global view id: w2c [4,4]} of the already-optimised views. The placed view's matched
    keypoints are lifted either with ``depth_at(j, uv [M,2]) -> depth [M]`` (z-depth, e.g. rendered
    from the current SDF; NaN/<= 0 = no surface) using K[j] and placed[j], or looked up in
    ``points3d[j]`` ([n_keypoints_j, 3] world points, NaN = unknown). Returns (uv of ``view`` [M,2],
    X [M,3], source view [M]) with non-finite points removed."""
    if depth_at is None and points3d is None:
        raise ValueError("successor_correspondences: give depth_at or points3d")
    uvs, Xs, srcs = [], [], []
    kv = np.asarray(keypoints[view], np.float64)
    for p in map(_as_pair, pairs):
        if view not in (p.i, p.j) or len(p.matches) == 0:
            continue
        j = p.j if p.i == view else p.i
        if j not in placed:
            continue
        mv, mj = (p.matches[:, 0], p.matches[:, 1]) if p.i == view else (p.matches[:, 1], p.matches[:, 0])
        uv_j = np.asarray(keypoints[j], np.float64)[mj]
        if points3d is not None and j in points3d:
            X = np.asarray(points3d[j], np.float64)[mj]
        elif depth_at is not None:
            X = lift_points(K[j], placed[j], uv_j, depth_at(j, uv_j), ray_distance)
        else:
            continue
        uvs.append(kv[mv])
        Xs.append(X)
        srcs.append(np.full(len(mv), j))
    if not uvs:
        return np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, np.int64)
    uv, X, src = np.concatenate(uvs), np.concatenate(Xs), np.concatenate(srcs)
    ok = np.isfinite(X).all(1)
    return uv[ok], X[ok], src[ok]


def fallback_neighbour_pose(view: int, placed: dict, W: np.ndarray) -> tuple[np.ndarray | None, int | None]:
    """The pose of ``view``'s best-matching placed neighbour (largest W[view, j] > 0 over j in
    ``placed``, a {global id: w2c} dict). Returns (w2c copy, neighbour id) or (None, None)."""
    W = np.asarray(W)
    best, best_w = None, 0.0
    for j in placed:
        if j != view and W[view, j] > best_w:
            best, best_w = j, float(W[view, j])
    if best is None:
        return None, None
    return to_4x4(placed[best]), int(best)


def place_successor(
    view: int,
    K: np.ndarray,
    keypoints: Sequence[np.ndarray],
    pairs: Sequence,
    placed: dict,
    W: np.ndarray | None = None,
    *,
    depth_at: Callable[[int, np.ndarray], np.ndarray] | None = None,
    points3d: dict | None = None,
    ray_distance: bool = False,
    reproj_px: float = 3.0,
    min_inliers: int = 12,
    iterations: int = 2000,
    confidence: float = 0.9999,
) -> tuple[np.ndarray | None, dict]:
    """Initial pose of a successor view: PnP-RANSAC on its matches to the placed (optimised) views
    lifted to 3D, else the best-matching placed neighbour's pose. K, keypoints, pairs and W use
    global view ids (W defaults to the pairs' inlier counts). Never raises for a view that cannot be
    placed: returns (None, info) with ``info["method"] == "unplaced"`` when it has no placed neighbour.
    info: method ("pnp" | "fallback" | "unplaced"), n_correspondences, n_inliers, neighbour."""
    pairs = [_as_pair(p) for p in pairs]
    uv, X, src = successor_correspondences(view, keypoints, pairs, placed, K, depth_at, points3d, ray_distance)
    w2c, n_in = place_by_pnp(K[view], uv, X, reproj_px=reproj_px, min_inliers=min_inliers, iterations=iterations,
                             confidence=confidence)
    info = {"view": int(view), "n_correspondences": int(len(uv)), "n_inliers": int(n_in), "neighbour": None}
    if w2c is not None:
        info["method"] = "pnp"
        return w2c, info
    if W is None:
        W = covisibility_from_pairs(pairs, int(max([view, *placed, len(K) - 1]) + 1))
    w2c, nb = fallback_neighbour_pose(view, placed, W)
    info["neighbour"] = nb
    info["method"] = "fallback" if w2c is not None else "unplaced"
    return w2c, info
