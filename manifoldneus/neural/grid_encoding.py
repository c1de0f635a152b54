"""Multi-level feature grids: trilinear look-up of L channel-last tables at points.

Convention (owned here): a dense level l is a parameter of shape [R_l, R_l, R_l, C] indexed
[z, y, x, c]; a point's normalised coordinate u in [-1, 1]^3 (x, y, z) maps to (u + 1) / 2 * (R_l - 1),
as ``grid_sample(mode="bilinear", padding_mode="zeros", align_corners=True)``; corners outside a table
read zero. A hashed level is a [T, C] table for a resolution R_l with R_l^3 > T cells: cell (x, y, z)
reads row (x ^ 2654435761 y ^ 805459861 z) mod T in uint32 arithmetic (instant-NGP's spatial hash), so
a fine level costs T rows whatever its resolution; colliding cells share a row. :func:`encode` returns
the levels' features side by side, [N, L*C].

Two kernels compute the same thing:

* ``fused`` (CPU): ``csrc/grid_encoding.cpp``, built once per torch version and source with the machine's C++
  compiler (about 30 s, cached under ``~/.cache/manifoldneus``). One pass over the points for all
  levels forward, one backward (threads split the levels, so no atomics); about half the CPU time of
  ``grid_sample`` here (docs/PERFORMANCE.md). Not twice differentiable.
* ``torch``: ``F.grid_sample`` per dense level, a gather of the 8 corners' rows per hashed level;
  any device, twice differentiable.

``kernel="auto"`` takes ``fused`` for CPU tensors when it builds, else ``torch`` (once, a warning
names what is missing). A field whose SDF gradients come from autograd (their own gradient is taken
for the Eikonal loss) asks for ``torch``.
"""
from __future__ import annotations

import fcntl
import functools
import hashlib
import logging
import os
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from manifoldneus.data import io

log = logging.getLogger(__name__)

KERNELS = ("auto", "fused", "torch")
__native_sources__ = ("csrc/grid_encoding.cpp",)  # part of the code fingerprint of the stages using it
_SOURCE = Path(__file__).parent / __native_sources__[0]
_ext = None
_ext_error: str | None = None


def _build_dir() -> Path:
    # one folder per torch version, source and checkout: torch's build file names the source's path, so two
    # checkouts on one machine (a worktree beside the main one) sharing a folder rebuilt it (40 s) each time
    # the other had loaded it
    digest = hashlib.sha256(_SOURCE.read_bytes() + str(_SOURCE.resolve()).encode()).hexdigest()[:10]
    return io.cache_root() / f"grid_encoding-torch{torch.__version__.replace('+', '_')}-{digest}"


def fused_kernel():
    """The compiled CPU kernel, or None (the reason is in :func:`fused_unavailable_reason`)."""
    global _ext, _ext_error
    if _ext is None and _ext_error is None:
        try:
            from torch.utils.cpp_extension import load

            d = _build_dir()
            d.mkdir(parents=True, exist_ok=True)
            # the venv's ninja (requirements.txt) when the venv is not activated
            os.environ["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"
            # One build at a time under a lock the kernel releases when its holder dies. torch's own
            # lock file outlives a build killed half-way, and every later process would wait on it
            # forever: holding ours, no live build can own it, so it is stale and goes.
            with open(d / "build.flock", "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)
                (d / "lock").unlink(missing_ok=True)
                _ext = load("manifoldneus_grid_encoding", [str(_SOURCE)], build_directory=str(d),
                            extra_cflags=["-O3", "-fopenmp"], extra_ldflags=["-fopenmp"], verbose=False)
        except Exception as e:  # no compiler, no headers, a read-only home: grid_sample still works
            _ext_error = f"{type(e).__name__}: {str(e).strip().splitlines()[-1][:200] if str(e).strip() else ''}"
            log.warning("the fused grid kernel could not be built (%s); the grids use torch's grid_sample, "
                        "about twice as slow on the CPU. It needs a C++ compiler (g++) and Python's headers.",
                        _ext_error)
    return _ext


def fused_unavailable_reason() -> str | None:
    fused_kernel()
    return _ext_error


class _FusedEncoding(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, res, *tables):
        ext = fused_kernel()
        flat = [t.reshape(-1) for t in tables]
        C = tables[0].shape[-1]
        ctx.save_for_backward(u, *tables)
        ctx.res, ctx.C = res, C
        return ext.forward(u, flat, list(res), C)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        u, *tables = ctx.saved_tensors
        need_u = ctx.needs_input_grad[0]
        out = fused_kernel().backward(grad_out, u, [t.reshape(-1) for t in tables], list(ctx.res), ctx.C, need_u)
        grads = [g.view_as(t) for g, t in zip(out[: len(tables)], tables)]
        return (out[-1] if need_u else None), None, *grads


def resolve_kernel(kernel: str, device: torch.device) -> str:
    """The kernel ``kernel`` ('auto', 'fused', 'torch') means on ``device``."""
    if kernel not in KERNELS:
        raise ValueError(f"unknown grid kernel {kernel!r}; one of {KERNELS}")
    if kernel == "torch" or device.type != "cpu":
        return "torch"
    if fused_kernel() is None:
        if kernel == "fused":
            raise RuntimeError(f"field.grid_kernel=fused, but the kernel could not be built ({_ext_error}); "
                               "install g++ or set field.grid_kernel=torch")
        return "torch"
    return "fused"


_PRIMES = (1, 2654435761, 805459861)


def encode(u: torch.Tensor, tables, kernel: str = "auto", resolutions=None) -> torch.Tensor:
    """Features of the L tables (each dense [R,R,R,C] or hashed [T,C]) at u [N,3] in [-1,1] -> [N, L*C].
    resolutions: each level's R (needed for hashed levels; dense ones read it from their shape)."""
    res = tuple(int(r) for r in resolutions) if resolutions is not None else tuple(int(t.shape[0]) for t in tables)
    if resolve_kernel(kernel, u.device) == "fused":
        return _FusedEncoding.apply(u.contiguous().float(), res, *tables)
    g = u.view(1, -1, 1, 1, 3)
    feats = [F.grid_sample(t.permute(3, 0, 1, 2)[None], g, mode="bilinear", padding_mode="zeros",
                           align_corners=True).view(t.shape[-1], -1).T if t.dim() == 4 else _hashed_level(u, t, r)
             for t, r in zip(tables, res)]  # L x [N,C]
    return torch.cat(feats, 1)  # [N, L*C]


@functools.lru_cache(maxsize=None)
def _corners(device: torch.device) -> torch.Tensor:
    """The 8 corners' offsets [8,3] (x, y, z bits of the corner's number), made once per device: built per
    call they were 8 host-to-device copies a level, each a synchronisation on a GPU."""
    return torch.tensor([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], device=device)


def _hashed_level(u: torch.Tensor, table: torch.Tensor, R: int) -> torch.Tensor:
    """Trilinear look-up [N,C] of a hashed level (table [T,C], resolution R) at u [N,3] in [-1,1]."""
    p = (u + 1.0) * (0.5 * (R - 1))  # [N,3] in cells
    i0 = p.detach().floor()
    f = p - i0  # [N,3]; differentiable in u
    i0 = i0.long()
    out = u.new_zeros(u.shape[0], table.shape[1])
    corners = _corners(u.device) if not torch.compiler.is_compiling() else _corners.__wrapped__(u.device)
    for c in range(8):  # the cell's corners (8 vectorised gathers, not a loop over points)
        b = corners[c]
        idx = i0 + b  # [N,3]
        inside = ((idx >= 0) & (idx < R)).all(-1)  # [N]
        h = idx[:, 0] ^ ((idx[:, 1] * _PRIMES[1]) & 0xFFFFFFFF) ^ ((idx[:, 2] * _PRIMES[2]) & 0xFFFFFFFF)
        row = torch.where(inside, h % table.shape[0], torch.zeros_like(h))
        wc = torch.where(b.bool(), f, 1.0 - f)  # [N,3]
        # the product written out: prod's backward reads on the host whether a factor is 0 (a GPU waits on it)
        w = wc[:, 0] * wc[:, 1] * wc[:, 2] * inside  # [N]
        out = out + w[:, None] * table[row]
    return out

