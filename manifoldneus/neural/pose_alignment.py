"""Poses only, against a frozen field: photometric alignment of views to what the field renders.

Two users: the test-time alignment of held-out views before they are scored (`novel_views`, as BARF,
NoPe-NeRF and CF-3DGS score pose-free methods), and the pose polish that closes a joint round
(`successors.polish_steps`): every view of the round refined against the field the round trained, the
field held fixed. A field trained with the poses held is the consensus of every view, so a view's own
misalignment leaves a residual that the polish follows (docs/REFINEMENT.md).

The loss is the training loss's colour part: L1 on the foreground when there are masks, plus their
silhouette (binary cross-entropy of the opacity), else L1 on every pixel (the background model renders
the rest). Rays are drawn uniformly over the views' pixels.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from manifoldneus.neural.pose_correction import PoseCorrections
from manifoldneus.geometry.rays import camera_rays, draw_pixels
from manifoldneus.neural.render import render_rays

SILHOUETTE_WEIGHT = 0.1  # of the masks' BCE against the colour L1, as the trainer's default mask loss


def residuals(trainer, pose: torch.Tensor, view: torch.Tensor, pix: torch.Tensor, images: torch.Tensor,
              masks: torch.Tensor | None, K: torch.Tensor):
    """The loss's parts at pixels ``pix`` [R] of views ``view`` [R] seen from poses ``pose`` [R,3,4] through
    ``trainer``'s field: the colour L1 [R] against images [M,HW,3], the mask [R] (None without masks
    [M,HW]) and the rendered opacity [R], clamped for the cross-entropy."""
    o, d = camera_rays(pix % trainer.W, pix // trainer.W, K[view], pose)
    out = render_rays(trainer.field, o, d, trainer.rp, cache=trainer.cache, background=trainer.background,
                      want_normals=False)
    err = (out["rgb"] - images[view, pix]).abs().sum(-1)  # [R]
    m = None if masks is None else masks[view, pix].to(err.dtype)  # [R]
    return err, m, out["opacity"].clamp(1e-3, 1 - 1e-3)


def align_poses(trainer, start: torch.Tensor, images: torch.Tensor, masks: torch.Tensor | None, K: torch.Tensor, *,
                steps: int, rays: int, lr: float, seed: int = 0, translation: bool = True,
                progress=None, sizes: torch.Tensor | None = None) -> torch.Tensor:
    """Refine world-to-camera poses ``start`` [M,3,4] of M views with images [M,HW,3] at the trainer's
    resolution (masks [M,HW] or None, intrinsics K [M,3,3]) against ``trainer``'s frozen field:
    ``steps`` Adam steps of ``rays`` rays over all views, se(3) corrections with a peak lr ``lr``
    (cosine to a tenth). ``translation`` False learns rotations only: a correction on the left of a
    world-to-camera pose that is a pure rotation keeps the camera centre. Returns the poses [M,3,4] on
    ``start``'s device. ``sizes`` [M,2] (H, W): views of several sizes, rays drawn in each one's own pixels
    (:mod:`manifoldneus.data.views`); None: all the canvas'."""
    from manifoldneus.neural.train import lr_factor

    dev = trainer.device
    M = start.shape[0]
    HW = trainer.H * trainer.W
    cams = PoseCorrections(start.to(dev), np.arange(M), lr=lr, translation=translation)
    gen = torch.Generator(device="cpu").manual_seed(seed)
    frozen = [q for q in list(trainer.field.parameters()) + list(trainer.background.parameters()) if q.requires_grad]
    for q in frozen:
        q.requires_grad_(False)
    bar = progress(total=steps, desc="pose polish") if progress else None
    try:
        for step in range(steps):
            cams.set_lr(lr_factor(step, steps, 0, 0.1))
            if sizes is None:
                flat = torch.randint(0, M * HW, (rays,), generator=gen).to(dev)
            else:
                flat = draw_pixels(rays, sizes, trainer.H, trainer.W, gen).to(dev)
            view, pix = flat // HW, flat % HW  # [R], [R]
            err, m, opacity = residuals(trainer, cams.poses(step)[view], view, pix, images, masks, K)  # [R] each
            if m is None:
                loss = err.mean()
            else:
                loss = (err * m).sum() / m.sum().clamp_min(1.0) + SILHOUETTE_WEIGHT * F.binary_cross_entropy(opacity, m)
            cams.zero_grad()
            loss.backward()
            cams.step()
            if bar is not None:
                bar.update(1)
    finally:
        for q in frozen:
            q.requires_grad_(True)
        if bar is not None:
            bar.close()
    with torch.no_grad():
        return cams.poses(steps).detach().to(start.device)
