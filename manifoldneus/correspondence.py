"""Correspondence term and guard of the joint field-and-pose rounds.

The photometric loss of a CPU-sized field is a noisy pose signal: Adam normalises the noise, so
the corrections random-walk by about ``pose_lr * sqrt(steps)`` and leave well-initialised poses
worse than they started. The verified matches of the front-end are an unbiased anchor that does
not depend on the field: every round adds, for the views it optimises, the robust Sampson error
of their verified matches under the current poses (PoRF and SPARF use the same kind of term),
so the poses keep a correspondence-consistent optimum while the field is soft, and the views a
round places from PnP are adjusted together with all the others (a multi-view refinement, not a
per-view one). The Sampson error needs no 3D points and is invariant to the similarity gauge the
field fixes.

A fraction of the matches (``holdout_frac``, drawn per pair with a fixed seed) never enters the
loss: the guard compares their error under the round's starting and final poses, and a round that
makes it worse by more than ``guard_tolerance`` gets its starting poses back (the field keeps what
it learned). The error is in pixels: Sampson distance in normalised coordinates times the focal.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from manifoldneus.config import param


@dataclass
class CorrespondenceParams:
    """Section `correspondence`: the matches-based pose term and the round guard."""

    weight: float = param(0.01, "Weight of the robust Sampson error (px^2) of the verified matches in the pose loss "
                          "(0 = photometric poses only)", lo=0.0)
    robust_px: float = param(1.5, "Cauchy scale of the Sampson error (px): matches far above it pull little", lo=0.01)
    batch: int = param(16384, "Matches per iteration (all of them when fewer)", lo=1)
    holdout_frac: float = param(0.1, "Fraction of the verified matches kept out of the loss for the guard",
                                lo=0.0, hi=0.9)
    guard: bool = param(True, "Give a round its starting poses back when it worsens the held-out matches' error")
    guard_tolerance: float = param(0.02, "Relative rise of the held-out error that the guard tolerates", lo=0.0)
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
                uv = np.asarray(keypoints[view], np.float64)[m[:, side]]  # [m,2] px
                h = np.concatenate([uv, np.ones((len(uv), 1))], 1) @ np.linalg.inv(K[view]).T
                out.append(h)
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
    zero = torch.zeros_like(t[:, 0])
    tx = torch.stack([zero, -t[:, 2], t[:, 1], t[:, 2], zero, -t[:, 0], -t[:, 1], t[:, 0], zero], -1).view(-1, 3, 3)
    E = tx @ R  # [M,3,3]: xb^T E xa = 0
    xa, xb = ms.xa[index], ms.xb[index]
    Exa = (E @ xa[..., None])[..., 0]  # [M,3]
    Etxb = (E.transpose(-1, -2) @ xb[..., None])[..., 0]
    num = (xb * Exa).sum(-1)
    den = Exa[:, 0] ** 2 + Exa[:, 1] ** 2 + Etxb[:, 0] ** 2 + Etxb[:, 1] ** 2
    return num.abs() / den.clamp_min(1e-18).sqrt() * ms.focal[index]


def cauchy(err_px: torch.Tensor, scale: float) -> torch.Tensor:
    """Robust cost of an error (px): scale^2 log(1 + (e/scale)^2), quadratic near 0."""
    return scale**2 * torch.log1p((err_px / scale) ** 2)


class CorrespondenceLoss:
    """The pose term a :class:`~manifoldneus.train.Trainer` adds to its loss (see module doc)."""

    def __init__(self, ms: MatchSet, p: CorrespondenceParams):
        self.ms, self.p = ms, p
        self.weight = p.weight

    def __call__(self, w2c: torch.Tensor, rng: torch.Generator) -> torch.Tensor | None:
        idx = self.ms.train_index
        if idx.numel() == 0 or self.p.weight <= 0:
            return None
        if idx.numel() > self.p.batch:
            pick = torch.randint(0, idx.numel(), (self.p.batch,), generator=rng).to(idx.device)
            idx = idx[pick]
        return cauchy(sampson_px(w2c, self.ms, idx), self.p.robust_px).mean()

    def held_out_error(self, w2c: torch.Tensor) -> float | None:
        """Mean robust error (px^2) of the held-out matches, or None without any."""
        if self.ms.held_index.numel() == 0:
            return None
        with torch.no_grad():
            return float(cauchy(sampson_px(w2c, self.ms, self.ms.held_index), self.p.robust_px).mean())

    def median_px(self, w2c: torch.Tensor, held_out: bool = True) -> float | None:
        idx = self.ms.held_index if held_out else self.ms.train_index
        if idx.numel() == 0:
            return None
        with torch.no_grad():
            return float(sampson_px(w2c, self.ms, idx).median())
