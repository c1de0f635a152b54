"""MaVOS-gated coarse-to-fine positional encoding (METHOD.md, "MaVOS-gated positional encoding").

BARF weight of band k (k = 0..L-1) at progress a in [0, L]:
    w_k(a) = (1 - cos(pi * clamp(a - k, 0, 1))) / 2
a(t) rises linearly from 0 to L over the coarse-to-fine window [start, end] (fractions of the
stage's T iterations). For a ray of view i, band k uses the shifted progress
    a_{i,k}(t) = a(t) + lambda * S~_i * eta_f(k) * eta_t(t) * L,
    eta_f(k) = (k + 1) / L,   eta_t(t) = t / T.
Easy views (S~ near 1) unlock fine bands earlier. Ablation switches turn S~, eta_f, eta_t into
constant 1; lambda = 0 is plain BARF. "Bands" are Fourier bands of the ``mlp`` field or levels of
the ``grid`` field: the field just multiplies band k by w_k.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from manifoldneus.config import param


@dataclass
class GateParams:
    """Section `gate`: the per-view coarse-to-fine gate of the pose-free stages."""

    enabled: bool = param(True, "Coarse-to-fine gating of bands/levels (False = all bands on from the start)")
    start: float = param(0.1, "Start of the coarse-to-fine window, fraction of a stage's iterations", lo=0.0, hi=1.0)
    end: float = param(0.5, "End of the window (all bands fully on for plain BARF), fraction of iterations",
                       lo=0.0, hi=1.0)
    lam: float = param(0.3, "lambda: scale of the MaVOS shift (0 = plain BARF)", lo=0.0, hi=10.0)
    use_s: bool = param(True, "Ablation: weight the shift by the view's optimisability S~_i (else 1)")
    use_eta_f: bool = param(True, "Ablation: frequency sensitivity eta_f(k) = (k+1)/L (else 1)")
    use_eta_t: bool = param(True, "Ablation: temporal sensitivity eta_t(t) = t/T (else 1)")


def barf_weights(progress: torch.Tensor | float, n_bands: int) -> torch.Tensor:
    """w_k(a) for progress a (scalar or [...]) -> [..., L]."""
    a = torch.as_tensor(progress, dtype=torch.float32)
    k = torch.arange(n_bands, dtype=torch.float32, device=a.device)
    return (1.0 - torch.cos(math.pi * (a[..., None] - k).clamp(0.0, 1.0))) / 2.0


def base_progress(step: int, total: int, p: GateParams, n_bands: int) -> float:
    """a(t): 0 before the window, L after it, linear inside."""
    t = step / max(total, 1)
    if p.end <= p.start:
        return float(n_bands) if t >= p.end else 0.0
    return min(max((t - p.start) / (p.end - p.start), 0.0), 1.0) * n_bands


def band_weights(view: torch.Tensor, step: int, total: int, s_tilde: torch.Tensor, n_bands: int,
                 p: GateParams, start: torch.Tensor | None = None) -> torch.Tensor | None:
    """Per-ray band weights [R, L] for rays of views ``view`` [R] (long) at iteration ``step`` of
    ``total``; ``s_tilde`` [N] is each view's optimisability in [0, 1]; ``start`` [N] (or None = 0) is
    the progress, in bands, below which a view's a(t) does not go: L = every band on from the start
    (a view an earlier round fitted keeps the field's bands). None = all bands on."""
    if not p.enabled or n_bands == 0:
        return None
    L = n_bands
    a = base_progress(step, total, p, L)
    if a >= L and p.lam == 0:
        return None
    k = torch.arange(L, dtype=torch.float32, device=view.device)
    eta_f = (k + 1) / L if p.use_eta_f else torch.ones(L, device=view.device)  # [L]
    eta_t = step / max(total, 1) if p.use_eta_t else 1.0
    s = s_tilde.to(view.device, torch.float32)[view] if p.use_s else torch.ones(view.shape[0], device=view.device)
    shift = p.lam * s[:, None] * eta_f[None, :] * eta_t * L  # [R,L]
    base = a if start is None else start.to(view.device, torch.float32)[view][:, None].clamp_min(a)  # [R,1]
    x = (base + shift - k[None, :]).clamp(0.0, 1.0)
    return (1.0 - torch.cos(math.pi * x)) / 2.0
