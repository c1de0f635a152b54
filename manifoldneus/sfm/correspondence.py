"""Correspondence term of the joint field-and-pose rounds, and the per-view acceptance of their pose updates.

The photometric loss of a CPU-sized field is a noisy pose signal: Adam normalises the noise, so
the corrections random-walk by about ``pose_lr * sqrt(steps)`` and leave well-initialised poses
worse than they started. The verified matches of the front-end are an unbiased anchor that does
not depend on the field: every round adds, for the views it optimises, a robust error of their
matches under the current poses (PoRF and SPARF use the same kind of term), so the poses keep a
correspondence-consistent optimum while the field is soft, and the views a round places are
adjusted together with all the others (a multi-view refinement, not a per-view one). The default
``reprojection`` kind takes the reprojection error of the bundle-adjusted tracks, their points
re-triangulated from the current poses; the ``sampson`` kind the epipolar error of the matches,
which needs no 3D points and is blind to each pair's baseline length.

A fraction of the tracks (or matches; ``holdout_frac``, drawn with a fixed seed) never enters the
loss: they decide, view by view, whether the round's pose update is kept (:func:`accept_per_view`).
A view keeps its new pose only when its held-out observations' robust error fell by more than z
standard errors of its own paired change (start -> end, the points re-triangulated under each), z
set so that a round keeps an update that changed nothing with probability ``accept_alpha`` at most
over all its views; otherwise it keeps the pose the round started from (the field keeps what it
learned). The standard error is measured per view from the held-out observations themselves, so the
noise threshold scales with how much evidence a view has. The kept poses together must not raise the
held-out error either (a view's update also moves the points its neighbours' errors are taken to);
when they do, every view keeps its start. The start poses of a round come from a bundle
adjustment that saw every track, so the test leans towards them: a pose update must beat the
structure-from-motion it starts from on evidence the update did not train on (docs/REFINEMENT.md).
Errors are in pixels: Sampson distance in normalised coordinates times the focal, or reprojection.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from manifoldneus.geometry.cameras import pixels_to_normalised, skew
from manifoldneus.config import param


@dataclass
class CorrespondenceParams:
    """Section `correspondence`: the matches-based pose term and the round guard (its weight is a
    stage's own: `anchors.correspondence_weight`, `successors.correspondence_weight`)."""

    kind: str = param("reprojection", "sampson: epipolar error of the verified matches (no 3D points); reprojection: error of "
                      "the bundle-adjusted tracks, points re-triangulated from the current poses every "
                      "`retriangulate_every` steps (the points tie the cameras' distances, which epipolar errors leave "
                      "loose)", choices=["sampson", "reprojection"])
    retriangulate_every: int = param(10, "reprojection: steps between re-triangulations of the points", lo=1)
    robust_px: float = param(1.5, "Cauchy scale of the Sampson error (px): matches far above it pull little", lo=0.01)
    batch: int = param(16384, "Matches per iteration (all of them when fewer)", lo=1)
    holdout_frac: float = param(0.1, "Fraction of the tracks (or matches) kept out of the loss: the evidence that "
                                "decides which views keep a round's pose update", lo=0.0, hi=0.9)
    guard: bool = param(True, "Keep a view's new pose only where its held-out tracks say it is better than the "
                        "round's start (False: every view keeps its new pose)")
    accept_alpha: float = param(0.05, "Chance that any of a round's views keeps an update that changed nothing (the "
                                "family-wise false acceptance): a view keeps its update when its held-out error fell "
                                "by more than z standard errors, z the normal quantile at 1 - accept_alpha / the "
                                "number of views tested (Bonferroni; 42 views: 3.04)", lo=1e-6, hi=0.5)
    accept_min_obs: int = param(8, "A view with fewer held-out observations than this keeps its start pose (too "
                                "little evidence to measure its noise)", lo=2)
    seed: int = param(0, "Seed of the held-out draw (fixed, so every round and rerun holds out the same matches)",
                      lo=0)


class MatchSet:
    """Verified matches among a set of views, flat, in normalised camera coordinates.

    ``view_a``/``view_b`` [M] index the views in ``ids`` order; ``xa``/``xb`` [M,3] homogeneous
    normalised coordinates (K^-1 [u, v, 1]); ``focal`` [M] the mean focal of the two views (px),
    to express errors in pixels; ``held_out`` [M] bool.
    """

    def __init__(self, ids, K: np.ndarray, keypoints: list, pairs: list, holdout_frac: float = 0.0, seed: int = 0):
        local = {int(g): k for k, g in enumerate(ids)}
        rng = np.random.default_rng(seed)
        va, vb, xa, xb, held = [], [], [], [], []
        for p in pairs:  # pose_init.PairMatch, global ids
            if p.i not in local or p.j not in local or len(p.matches) == 0:
                continue
            m = np.asarray(p.matches)
            for side, view, out in ((0, p.i, xa), (1, p.j, xb)):
                xn = pixels_to_normalised(K[view], np.asarray(keypoints[view])[m[:, side]])
                out.append(np.concatenate([xn, np.ones((len(xn), 1))], 1))
            va.append(np.full(len(m), local[p.i]))
            vb.append(np.full(len(m), local[p.j]))
            held.append(rng.random(len(m)) < holdout_frac)
        cat = (lambda a, shape: np.concatenate(a) if a else np.zeros(shape))
        self.view_a = torch.as_tensor(cat(va, (0,)), dtype=torch.long)
        self.view_b = torch.as_tensor(cat(vb, (0,)), dtype=torch.long)
        self.xa = torch.as_tensor(cat(xa, (0, 3)), dtype=torch.float32)
        self.xb = torch.as_tensor(cat(xb, (0, 3)), dtype=torch.float32)
        f = np.array([0.5 * (K[v][0, 0] + K[v][1, 1]) for v in ids]) if len(ids) else np.zeros(0)
        self.focal = torch.as_tensor(0.5 * (f[cat(va, (0,)).astype(int)] + f[cat(vb, (0,)).astype(int)]),
                                     dtype=torch.float32)
        self.held_out = torch.as_tensor(cat(held, (0,)).astype(bool))
        self.train_index = torch.nonzero(~self.held_out)[:, 0]
        self.held_index = torch.nonzero(self.held_out)[:, 0]

    def __len__(self) -> int:
        return int(self.view_a.shape[0])

    def to(self, device) -> "MatchSet":
        for k in ("view_a", "view_b", "xa", "xb", "focal", "held_out", "train_index", "held_index"):
            setattr(self, k, getattr(self, k).to(device))
        return self


def sampson_px(w2c: torch.Tensor, ms: MatchSet, index: torch.Tensor) -> torch.Tensor:
    """Sampson distance (px) of matches ``index`` under world-to-camera poses ``w2c`` [N,3,4]."""
    a, b = ms.view_a[index], ms.view_b[index]
    Ra, ta = w2c[a, :, :3], w2c[a, :, 3]  # [M,3,3], [M,3]
    Rb, tb = w2c[b, :, :3], w2c[b, :, 3]
    R = Rb @ Ra.transpose(-1, -2)  # camera a -> camera b
    t = tb - (R @ ta[..., None])[..., 0]
    t = t / t.norm(dim=-1, keepdim=True).clamp_min(1e-9)  # the epipolar error does not see the baseline length
    E = skew(t) @ R  # [M,3,3]: xb^T E xa = 0
    xa, xb = ms.xa[index], ms.xb[index]
    Exa = (E @ xa[..., None])[..., 0]  # [M,3]
    Etxb = (E.transpose(-1, -2) @ xb[..., None])[..., 0]
    num = (xb * Exa).sum(-1)
    den = Exa[:, 0] ** 2 + Exa[:, 1] ** 2 + Etxb[:, 0] ** 2 + Etxb[:, 1] ** 2
    return num.abs() / den.clamp_min(1e-18).sqrt() * ms.focal[index]


def cauchy(err_px: torch.Tensor, scale: float) -> torch.Tensor:
    """Robust cost of an error (px): scale^2 log(1 + (e/scale)^2), quadratic near 0."""
    return scale**2 * torch.log1p((err_px / scale) ** 2)


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


class TrackSet:
    """Multi-view tracks of a round's views (a bundle adjustment's inlier observations, e.g.
    ``pose_init.InitResult.obs_*``): ``view`` [O] (index in ``ids``), ``track`` [O], ``uv`` [O,2] px,
    ``xn`` [O,2] normalised. Tracks with fewer than two views in the round are dropped."""

    def __init__(self, ids, K: np.ndarray, obs_view: np.ndarray, obs_point: np.ndarray, obs_uv: np.ndarray):
        local = np.full(max(int(np.max(ids, initial=0)), int(np.max(obs_view, initial=0))) + 1, -1)
        local[np.asarray(ids, int)] = np.arange(len(ids))
        keep = local[np.asarray(obs_view, int)] >= 0
        view, point, uv = local[np.asarray(obs_view, int)[keep]], np.asarray(obs_point)[keep], np.asarray(obs_uv)[keep]
        n_views = np.bincount(point, minlength=int(point.max(initial=-1)) + 1)
        keep = n_views[point] >= 2
        _, track = np.unique(point[keep], return_inverse=True)
        self.view, self.track, self.uv = view[keep], track.astype(np.int64), uv[keep]
        Kv = np.asarray(K)[np.asarray(ids, int)]  # [V,3,3]
        self.K = Kv
        self.xn = pixels_to_normalised(Kv[self.view], self.uv) if len(self.view) else np.zeros((0, 2))
        self.n_tracks = int(track.max(initial=-1)) + 1
        self.by_track = _padded(self.track, self.n_tracks)  # [T,m] observation indices

    def triangulate(self, w2c: np.ndarray) -> np.ndarray:
        """Points [T,3] (DLT) under world-to-camera poses w2c [V,3|4,4] of the round's views."""
        P = np.asarray(w2c, np.float64)[self.view]
        return triangulate_multiview(P[:, :3, :3], P[:, :3, 3], self.xn, self.by_track)


def reprojection_px(w2c: torch.Tensor, K: torch.Tensor, view: torch.Tensor, X: torch.Tensor,
                    uv: torch.Tensor) -> torch.Tensor:
    """Pixel distance [O] between uv [O,2] and points X [O,3] projected by views ``view`` [O]."""
    Xc = (w2c[view, :, :3] @ X[..., None])[..., 0] + w2c[view, :, 3]  # [O,3]
    z = Xc[:, 2].clamp_min(1e-6)
    Kv = K[view]
    u = Kv[:, 0, 0] * Xc[:, 0] / z + Kv[:, 0, 1] * Xc[:, 1] / z + Kv[:, 0, 2]
    v = Kv[:, 1, 1] * Xc[:, 1] / z + Kv[:, 1, 2]
    return torch.stack([u, v], -1).sub(uv).norm(dim=-1)


class ReprojectionLoss:
    """The `reprojection` kind: tracks' reprojection error with points re-triangulated (no
    gradient) from the current poses every ``retriangulate_every`` steps: an alternating bundle
    adjustment inside the joint optimisation. Tracks drawn with ``holdout_frac`` stay out of the
    loss; the guard re-triangulates them under the start and the end poses."""

    def __init__(self, tracks: TrackSet, p: CorrespondenceParams, weight: float = 1.0, device="cpu"):
        self.tr, self.p, self.weight = tracks, p, weight
        rng = np.random.default_rng(p.seed)
        held_track = rng.random(tracks.n_tracks) < p.holdout_frac
        held = held_track[tracks.track]
        dev = torch.device(device)
        self.K = torch.as_tensor(tracks.K, dtype=torch.float32, device=dev)
        self.view = torch.as_tensor(tracks.view, device=dev)
        self.track = torch.as_tensor(tracks.track, device=dev)
        self.uv = torch.as_tensor(tracks.uv, dtype=torch.float32, device=dev)
        self.train_index = torch.as_tensor(np.flatnonzero(~held), device=dev)
        self.held_index = torch.as_tensor(np.flatnonzero(held), device=dev)
        self.points = None
        self._points_step = None

    def _error(self, w2c: torch.Tensor, X: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        e = reprojection_px(w2c, self.K, self.view[index], X[self.track[index]], self.uv[index])
        return torch.nan_to_num(e, nan=1e3)  # a degenerate point is an outlier, not a NaN loss

    def _points(self, w2c: torch.Tensor) -> torch.Tensor:
        X = self.tr.triangulate(w2c.detach().double().cpu().numpy())
        return torch.as_tensor(X, dtype=torch.float32, device=w2c.device)

    def __call__(self, w2c: torch.Tensor, rng: torch.Generator, step: int = 0) -> torch.Tensor | None:
        idx = self.train_index
        if idx.numel() == 0 or self.weight <= 0:
            return None
        if self.points is None or step - self._points_step >= self.p.retriangulate_every or step < self._points_step:
            self.points, self._points_step = self._points(w2c), step - step % self.p.retriangulate_every
        if idx.numel() > self.p.batch:
            idx = idx[torch.randint(0, idx.numel(), (self.p.batch,), generator=rng).to(idx.device)]
        return cauchy(self._error(w2c, self.points, idx), self.p.robust_px).mean()

    def held_out_px(self, w2c: torch.Tensor) -> torch.Tensor:
        """Pixel errors [H] of the held-out tracks, re-triangulated under ``w2c``."""
        return self._error(w2c, self._points(w2c), self.held_index)

    def median_px(self, w2c: torch.Tensor, held_out: bool = True) -> float | None:
        idx = self.held_index if held_out else self.train_index
        if idx.numel() == 0:
            return None
        with torch.no_grad():
            return float(self._error(w2c, self._points(w2c), idx).median())

    @property
    def n_held_out(self) -> int:
        return int(self.held_index.numel())


class CorrespondenceLoss:
    """The pose term a :class:`~manifoldneus.neural.train.Trainer` adds to its loss (see module doc)."""

    def __init__(self, ms: MatchSet, p: CorrespondenceParams, weight: float = 1.0):
        self.ms, self.p = ms, p
        self.weight = weight

    @property
    def n_held_out(self) -> int:
        return int(self.ms.held_index.numel())

    def __call__(self, w2c: torch.Tensor, rng: torch.Generator, step: int = 0) -> torch.Tensor | None:
        idx = self.ms.train_index
        if idx.numel() == 0 or self.weight <= 0:
            return None
        if idx.numel() > self.p.batch:
            pick = torch.randint(0, idx.numel(), (self.p.batch,), generator=rng).to(idx.device)
            idx = idx[pick]
        return cauchy(sampson_px(w2c, self.ms, idx), self.p.robust_px).mean()

    def held_out_px(self, w2c: torch.Tensor) -> torch.Tensor:
        """Sampson errors [H] (px) of the held-out matches under ``w2c``."""
        return sampson_px(w2c, self.ms, self.ms.held_index)

    def median_px(self, w2c: torch.Tensor, held_out: bool = True) -> float | None:
        idx = self.ms.held_index if held_out else self.ms.train_index
        if idx.numel() == 0:
            return None
        with torch.no_grad():
            return float(sampson_px(w2c, self.ms, idx).median())


def held_out_views(loss) -> torch.Tensor:
    """The view (local index) of each held-out error [H] ``loss.held_out_px`` returns; a held-out
    match counts for both its views, so the Sampson kind's errors are given twice (see :func:`_per_view_errors`)."""
    if isinstance(loss, ReprojectionLoss):
        return loss.view[loss.held_index]
    return torch.cat([loss.ms.view_a[loss.ms.held_index], loss.ms.view_b[loss.ms.held_index]])


def _per_view_errors(loss, w2c: torch.Tensor) -> torch.Tensor:
    e = loss.held_out_px(w2c)
    return e if isinstance(loss, ReprojectionLoss) else torch.cat([e, e])


def accept_per_view(loss, w2c_start: torch.Tensor, w2c_end: torch.Tensor, p: CorrespondenceParams) -> dict:
    """Which views keep their new pose (module doc). ``w2c_start``/``w2c_end`` [n,3,4] over the loss's
    views. Returns a JSON-able record with ``keep`` (bool per view), ``z`` (the paired change's mean over
    its standard error, per view; None where a view has too few observations) and the held-out robust
    error (mean of the Cauchy cost, px^2) under the start, the end and the kept poses."""
    n = int(w2c_start.shape[0])
    if loss.n_held_out == 0:
        return {"checked": False, "kind": p.kind, "held_out": 0, "keep": [not p.guard] * n, "kept": 0 if p.guard else n,
                "n_views": n, "why": "no held-out correspondences"}
    with torch.no_grad():
        views = held_out_views(loss).cpu().numpy()  # [H]
        e_start, e_end = _per_view_errors(loss, w2c_start), _per_view_errors(loss, w2c_end)  # [H] px each
        change = (cauchy(e_end, p.robust_px) - cauchy(e_start, p.robust_px)).double().cpu().numpy()  # [H]
    count = np.bincount(views, minlength=n)
    total = np.bincount(views, change, minlength=n)
    square = np.bincount(views, change**2, minlength=n)
    mean = total / np.maximum(count, 1)
    var = (square - count * mean**2) / np.maximum(count - 1, 1)  # unbiased, per view
    se = np.sqrt(np.maximum(var, 0) / np.maximum(count, 1))
    # a view that did not move has no change to test (se 0): it keeps its pose either way
    tested = (count >= p.accept_min_obs) & (se > 0)
    z = np.where(tested, mean / np.where(se > 0, se, 1), np.nan)
    # imported here: scipy.stats takes most of a second to import, which commands that decide no pose need not pay
    from scipy.stats import norm

    z_limit = float(norm.isf(p.accept_alpha / max(int(tested.sum()), 1)))
    keep = (tested & (z < -z_limit)) if p.guard else np.ones(n, bool)

    with torch.no_grad():
        kept_poses = torch.where(torch.as_tensor(keep, device=w2c_end.device)[:, None, None], w2c_end, w2c_start)
        e_kept = _per_view_errors(loss, kept_poses)
    robust = {f"error_{k}": float(cauchy(e, p.robust_px).mean())
              for k, e in (("start", e_start), ("end", e_end), ("kept", e_kept))}
    together_worse = bool(p.guard and keep.any() and robust["error_kept"] > robust["error_start"])
    if together_worse:
        keep = np.zeros(n, bool)
        e_kept, robust["error_kept"] = e_start, robust["error_start"]
    return {"checked": True, "kind": p.kind, "held_out": loss.n_held_out, "z_limit": z_limit, "n_views": n,
            "n_tested": int(tested.sum()), "together_worse": together_worse,
            "kept": int(keep.sum()), "keep": keep.tolist(), "held_out_per_view": count.tolist(),
            "z": [None if not np.isfinite(v) else round(float(v), 3) for v in z], **robust,
            "start_median_px": float(e_start.median()), "end_median_px": float(e_end.median()),
            "kept_median_px": float(e_kept.median())}
