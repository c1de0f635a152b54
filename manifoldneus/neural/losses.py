"""Training losses (supplement Table A6). Each term has a weight; a term whose input is absent
(no masks, no mono priors) or whose weight is 0 switches itself off, and ``compute_losses``
reports which terms were on (and why the others were off).

* rgb: L1 between rendered and observed colour (on foreground rays only when masks exist).
* eikonal: mean (|grad f| - 1)^2.
* mask: BCE between the rendered opacity and the foreground mask.
* photo_mask: the same BCE against masks made from the photos (runs without masks), on the pixels they
  decide only (:mod:`manifoldneus.geometry.segmentation`); the rgb term and the background stay as without masks.
* depth: monocular depth, scale-and-shift invariant: per view in the batch, (a, b) minimising
  sum (a * d_mono + b - d_render)^2 (closed-form least squares, no gradient through a, b), then the
  mean squared residual (MonoSDF aligns per image the same way; here the prior is aligned to the
  render so the loss is in scene units). Rays: foreground (if masks) and opacity > 0.5.
* normal: monocular normal in the view's camera frame: rendered world normals rotated by the
  w2c rotation, L1 + (1 - cos) against the prior (unit, OpenCV camera frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from manifoldneus.config import param


@dataclass
class LossParams:
    """Section `loss`: loss weights."""

    w_rgb: float = param(1.0, "Photometric L1 weight", lo=0.0)
    w_eikonal: float = param(0.1, "Eikonal weight", lo=0.0)
    w_mask: float = param(0.1, "Mask BCE weight (used only when masks exist)", lo=0.0)
    w_photo_mask: float = param(0.1, "Without the layout's masks: BCE between the rendered opacity and the masks the "
                                "surface stage made from the photos (surface.photo_masks), on the pixels they decide "
                                "only (the object's, 1, or the background's, 0)", lo=0.0)
    w_depth: float = param(0.1, "Monocular depth weight (scale-and-shift invariant; only with depth priors)", lo=0.0)
    w_normal: float = param(0.05, "Monocular normal weight (L1 + 1 - cos, camera frame; only with normal priors)", lo=0.0)
    depth_min_rays: int = param(8, "Minimum valid rays of a view in the batch to fit its depth scale/shift", lo=3)
    w_free_space: float = param(1.0, "Without masks: weight of the free-space term (SightLines), which keeps the SDF "
                                "positive (no surface) along the lines of sight between cameras and the SfM points "
                                "they observe (anchors.sight_lines_from); 0 = off. scan24_idr photos alone, seeds "
                                "0/1: Chamfer 15.05 / 6.61 mm off, 5.81 / 4.99 at 1; 5.60 at 3 (seed 1)", lo=0.0)
    sight_stop: float = param(0.05, "sight_lines: the free segment stops this far (gauge units) before the point",
                              lo=0.0)


LOSS_NAMES = ("rgb", "eikonal", "mask", "photo_mask", "depth", "normal")
DECIDED = 0.4  # an object label decides a pixel where it lies this close to 0 or 1 (0.5: undecided)


def ssi_depth_loss(d_render, d_mono, view, valid, min_rays: int = 8):
    """Per-view least-squares (scale, shift) of the mono depth onto the rendered depth, then the mean
    squared residual over the valid rays of views with at least ``min_rays`` valid rays.
    Returns (loss or None, number of rays used)."""
    valid = valid & torch.isfinite(d_mono)
    if int(valid.sum()) < min_rays:
        return None, 0
    v = view[valid]
    x = d_mono[valid].to(d_render.dtype)
    y = d_render[valid]
    yd = y.detach()
    nv = int(v.max()) + 1
    z = x.new_zeros(nv)
    n = z.index_add(0, v, torch.ones_like(x))
    sx, sy = z.index_add(0, v, x), z.index_add(0, v, yd)
    sxx, sxy = z.index_add(0, v, x * x), z.index_add(0, v, x * yd)
    det = n * sxx - sx * sx
    ok = (n >= min_rays) & (det.abs() > 1e-12)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    a = (n * sxy - sx * sy) / det_safe
    b = (sxx * sy - sx * sxy) / det_safe
    use = ok[v]
    if int(use.sum()) == 0:
        return None, 0
    res = a[v] * x + b[v] - y
    return (res[use] ** 2).mean(), int(use.sum())


def normal_loss(n_world, n_prior_cam, R_w2c, valid):
    """L1 + (1 - cos) between rendered normals rotated into the camera frame and the prior."""
    if int(valid.sum()) == 0:
        return None
    n_cam = torch.einsum("rij,rj->ri", R_w2c[valid], n_world[valid])
    n_cam = F.normalize(n_cam, dim=-1)
    prior = F.normalize(n_prior_cam[valid].to(n_cam.dtype), dim=-1)
    l1 = (n_cam - prior).abs().sum(-1).mean()
    cos = (1.0 - (n_cam * prior).sum(-1)).mean()
    return l1 + cos


def compute_losses(out: dict, batch: dict, p: LossParams, host: bool = True):
    """out: render_rays output (rgb, opacity, depth, normal, eik_grad); batch: rgb [R,3] and optional
    mask [R] bool, mono_depth [R], mono_normal [R,3], view [R] long, R_w2c [R,3,3].
    Returns (total loss, {name: float value}, {name: "on" | "off: <reason>"}); with ``host`` False the
    values are detached 0-dim tensors (reading them is a host-device synchronisation on a GPU)."""
    terms, status = {}, {}
    mask = batch.get("mask")

    def off(name, why):
        status[name] = f"off: {why}"

    # photometric
    if p.w_rgb > 0:
        err = (out["rgb"] - batch["rgb"]).abs().sum(-1)
        if mask is not None:
            m = mask.to(err.dtype)
            terms["rgb"] = (err * m).sum() / (3 * m.sum().clamp_min(1.0))
        else:
            terms["rgb"] = err.mean() / 3
        status["rgb"] = "on"
    else:
        off("rgb", "weight 0")
    # eikonal
    if p.w_eikonal > 0 and out.get("eik_grad") is not None and out["eik_grad"].numel():
        terms["eikonal"] = ((out["eik_grad"].norm(dim=-1) - 1.0) ** 2).mean()
        status["eikonal"] = "on"
    else:
        off("eikonal", "weight 0" if p.w_eikonal <= 0 else "no gradients")
    # the masks, the layout's or those made from the photos; the latter only where they decide, so that a view whose
    # segmentation the other views dispute neither carves nor fills
    label = batch.get("object_label")
    for name, given, weight, absent in (("mask", mask, p.w_mask, "no masks"),
                                        ("photo_mask", label, p.w_photo_mask, "no masks from the photos")):
        if given is None or weight <= 0:
            off(name, absent if given is None else "weight 0")
            continue
        op = out["opacity"].clamp(1e-3, 1 - 1e-3)
        target = given.to(op.dtype) if name == "mask" else (given > 0.5).to(op.dtype)
        if name == "mask" and host:
            terms[name] = F.binary_cross_entropy(op, target)
        else:  # the same BCE without torch's range check of the input: a host read, and on NaN an error, not a NaN
            bce = -(target * torch.log(op) + (1.0 - target) * torch.log1p(-op))
            decided = None if name == "mask" else ((given - 0.5).abs() > DECIDED).to(op.dtype)
            terms[name] = bce.mean() if decided is None else (bce * decided).sum() / decided.sum().clamp_min(1.0)
        status[name] = "on"
    # where geometric priors apply
    fg = mask if mask is not None else torch.ones_like(out["opacity"], dtype=torch.bool)
    # depth
    if batch.get("mono_depth") is None:
        off("depth", "no depth prior")
    elif p.w_depth <= 0:
        off("depth", "weight 0")
    else:
        op = out["opacity"].detach()
        d_r = out["depth"] / op.clamp_min(1e-4)
        valid = fg & (op > 0.5)
        loss, n = ssi_depth_loss(d_r, batch["mono_depth"], batch["view"], valid, p.depth_min_rays)
        if loss is None:
            off("depth", "too few valid rays in this batch")
        else:
            terms["depth"] = loss
            status["depth"] = "on"
    # normal
    if batch.get("mono_normal") is None:
        off("normal", "no normal prior")
    elif p.w_normal <= 0:
        off("normal", "weight 0")
    elif out.get("normal") is None:
        off("normal", "normals not rendered")
    else:
        valid = fg & (out["opacity"].detach() > 0.5)
        loss = normal_loss(out["normal"], batch["mono_normal"], batch["R_w2c"], valid)
        if loss is None:
            off("normal", "no valid rays in this batch")
        else:
            terms["normal"] = loss
            status["normal"] = "on"
    weights = {"rgb": p.w_rgb, "eikonal": p.w_eikonal, "mask": p.w_mask, "photo_mask": p.w_photo_mask,
               "depth": p.w_depth, "normal": p.w_normal}
    total = sum(weights[k] * v for k, v in terms.items())
    return total, {k: float(v.detach()) if host else v.detach() for k, v in terms.items()}, status


class SightLines:
    """Free space along lines of sight: a camera that observes an SfM point sees nothing in front of it, so
    between the camera centre and the point (``lines`` [O,2,3]: origin, point; the field's frame) the SDF is
    positive. At ``n_samples`` random points on random segments, stopped ``stop`` before the point and kept
    inside the ball of ``radius``: mean(relu(margin - sdf)). The object's own points and the background's
    both carve: the first clear what stands in front of the object, the second what hangs around its
    silhouette."""

    def __init__(self, lines: np.ndarray, stop: float, radius: float, n_samples: int = 2048, margin: float = 0.01,
                 device="cpu"):
        lines = np.asarray(lines, np.float64).reshape(-1, 2, 3)
        o, seg = lines[:, 0], lines[:, 1] - lines[:, 0]  # [O,3]
        length = np.linalg.norm(seg, axis=1)
        d = seg / np.maximum(length, 1e-12)[:, None]  # [O,3] unit
        b = np.einsum("oi,oi->o", o, d)  # the ball: |o + t d| = radius
        disc = b ** 2 - (np.einsum("oi,oi->o", o, o) - radius ** 2)
        root = np.sqrt(np.maximum(disc, 0.0))
        t0, t1 = np.maximum(-b - root, 0.0), np.minimum(-b + root, length - stop)  # in the ball, short of the point
        ok = (disc > 0) & (t1 > t0)
        as_t = lambda a: torch.as_tensor(a[ok], dtype=torch.float32, device=device)  # noqa: E731
        self.origin, self.direction, self.t0, self.span = as_t(o), as_t(d), as_t(t0), as_t(t1 - t0)
        self.n_samples, self.margin = int(n_samples), float(margin)

    def __call__(self, sdf_fn, generator: torch.Generator) -> torch.Tensor:
        if len(self.origin) == 0:
            return self.origin.new_zeros(())
        dev = self.origin.device
        pick = torch.randint(len(self.origin), (self.n_samples,), generator=generator).to(dev)
        t = self.t0[pick] + torch.rand(self.n_samples, generator=generator).to(dev) * self.span[pick]  # [S]
        x = self.origin[pick] + t[:, None] * self.direction[pick]  # [S,3]
        return F.relu(self.margin - sdf_fn(x).reshape(-1)).mean()
