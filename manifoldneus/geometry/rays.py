"""Camera rays (torch, differentiable in the pose) and ray / sphere bounds.

Conventions are those of :mod:`manifoldneus.geometry.cameras` (OpenCV frame, ``w2c`` world-to-camera,
pixel centres at +0.5). Everything is batched over rays: pass one pose and one K *per ray*
(gather them with the ray's view index), so a per-view pose tensor that requires grad
(e.g. ``apply_correction(xi, w2c_init)``) propagates gradients to the poses.
"""
from __future__ import annotations

import torch


def pixel_grid(height: int, width: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Integer pixel coordinates (col, row) of a full image, row-major, each [H*W]."""
    rows, cols = torch.meshgrid(
        torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij"
    )
    return cols.reshape(-1), rows.reshape(-1)


def draw_pixels(n: int, sizes: torch.Tensor, height: int, width: int, generator: torch.Generator) -> torch.Tensor:
    """``n`` flat indices [n] (view * height * width + row * width + col, on the CPU) drawn uniformly over the
    own pixels of views on one ``height`` x ``width`` canvas, each view's own part its top-left ``sizes``
    [M,2] (H, W) (:mod:`manifoldneus.data.views`): the padding never becomes a ray."""
    sizes = torch.as_tensor(sizes, dtype=torch.long)
    area = sizes[:, 0] * sizes[:, 1]  # [M]
    start = torch.cumsum(area, 0) - area
    flat = torch.randint(0, int(area.sum()), (n,), generator=generator)
    view = torch.searchsorted(start, flat, right=True) - 1
    local = flat - start[view]
    w = sizes[view, 1]
    return view * (height * width) + (local // w) * width + local % w


def camera_rays(
    cols: torch.Tensor, rows: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor, jitter: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space rays through pixels.

    cols, rows: [R] pixel indices (the ray passes through (col + 0.5, row + 0.5), or through
    (col + jitter_x, row + jitter_y) when ``jitter`` [R,2] in [0,1) is given).
    K: [R,3,3] or [3,3]; w2c: [R,3|4,4] or [3|4,4]. Returns (origins [R,3], unit directions [R,3]).
    Differentiable with respect to ``w2c`` (and K).
    """
    dtype = w2c.dtype
    u = cols.to(dtype)
    v = rows.to(dtype)
    if jitter is None:
        u = u + 0.5
        v = v + 0.5
    else:
        u = u + jitter[:, 0].to(dtype)
        v = v + jitter[:, 1].to(dtype)
    if K.dim() == 2:
        K = K.expand(u.shape[0], 3, 3)
    if w2c.dim() == 2:
        w2c = w2c.expand(u.shape[0], *w2c.shape)
    K = K.to(dtype)
    fx, fy, cx, cy, skew = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 0, 1]
    y = (v - cy) / fy
    x = (u - cx - skew * y) / fx
    d_cam = torch.stack([x, y, torch.ones_like(x)], -1)  # [R,3]
    R = w2c[:, :3, :3]
    t = w2c[:, :3, 3]
    # world = R^T (cam - t): direction R^T d, origin -R^T t
    d = torch.einsum("rji,rj->ri", R, d_cam)
    o = -torch.einsum("rji,rj->ri", R, t)
    d = d / d.norm(dim=-1, keepdim=True)
    return o, d


def sphere_bounds(
    origins: torch.Tensor, dirs: torch.Tensor, radius: float = 1.0, min_near: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Intersections of rays (unit ``dirs``) with the sphere |x| = radius centred at the origin.

    Returns (near [R], far [R], hit [R] bool). Rays that miss get near = far = the distance of
    closest approach (a zero-length segment), so downstream code needs no special case beyond
    ``hit``. ``near`` is clamped to ``min_near`` (cameras inside the sphere).
    """
    b = (origins * dirs).sum(-1)  # t of closest approach = -b
    c = (origins * origins).sum(-1) - radius**2
    disc = b * b - c
    hit = disc > 0
    sq = disc.clamp_min(0).sqrt()
    near = (-b - sq).clamp_min(min_near)
    far = (-b + sq).clamp_min(min_near)
    hit = hit & (far > near)
    mid = (-b).clamp_min(min_near)
    near = torch.where(hit, near, mid)
    far = torch.where(hit, far, mid)
    return near, far, hit


def project(points: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Project world points [P,3] with one camera (K [3,3], w2c [3|4,4]).
    Returns (uv [P,2] in the +0.5 pixel-centre convention, depth z [P])."""
    xc = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = xc[:, 2]
    uvw = xc @ K.T
    uv = uvw[:, :2] / z.clamp_min(1e-9)[:, None]
    return uv, z
