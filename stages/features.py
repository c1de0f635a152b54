"""features: SIFT keypoints and descriptors per view (OpenCV).

Output ``features.zarr`` (zarr v3 group; all views concatenated along the first axis,
view ``v`` owns rows ``offsets[v]:offsets[v + 1]``):

- ``offsets``      int64   [N+1]
- ``keypoints``    float32 [T,2]   (x, y) in the project's pixel convention
  (``manifoldneus/geometry/cameras.py``: centre of the top-left pixel at (0.5, 0.5)); OpenCV reports
  integer pixel centres, so 0.5 is added here. Usable with ``K`` as is.
- ``scales``       float32 [T]     OpenCV ``KeyPoint.size`` in pixels (= 2 x the keypoint's
  Gaussian scale sigma in input-image pixels).
- ``orientations`` float32 [T]     radians, OpenCV ``KeyPoint.angle`` converted (image frame,
  x right, y down).
- ``responses``    float32 [T]     detector response (DoG contrast).
- ``descriptors``  float32 [T,128] unit L2 norm: RootSIFT (L1 normalise, sqrt) when
  ``root_sift``, else the raw SIFT vector L2-normalised. A dot product is a cosine similarity.
- ``featureless``  bool    [N]     views with fewer than ``min_features`` keypoints; they are
  stored with zero keypoints and every later stage treats them as unmatched.

Attributes: ``names`` (view names), ``n_views``, ``root_sift``, ``pixel_convention``.
Use :func:`manifoldneus.data.artifacts.load_features` to read it back as per-view lists.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manifoldneus.data import artifacts
from manifoldneus.data.views import own
from manifoldneus.config import param
from manifoldneus.data.io import save_arrays


@dataclass
class Params:
    """Section `features` of params.yaml."""

    max_features: int = param(8000, "Maximum SIFT keypoints kept per view (strongest responses)", lo=1)
    root_sift: bool = param(True, "Apply RootSIFT (L1 normalise, sqrt) to descriptors")
    use_mask: bool = param(False, "Detect only inside the foreground mask (ignored, with a warning, if the scene has none)")
    contrast_threshold: float = param(
        0.02,
        "OpenCV SIFT contrastThreshold (divided by n_octave_layers inside OpenCV; 0.02 = COLMAP's peak_threshold 0.0067)",
        lo=0.0,
    )
    edge_threshold: float = param(10.0, "OpenCV SIFT edgeThreshold (larger keeps more edge-like features)", lo=1.0)
    n_octave_layers: int = param(3, "Scale levels per octave", lo=1, hi=8)
    min_features: int = param(8, "A view with fewer keypoints is recorded as featureless (warning)", lo=0)
    workers: int = param(2, "Threads for extraction over images (OpenCV releases the GIL)", lo=1)
    max_image_size: int = param(3200, "Images whose longer side exceeds this (px) are downscaled for extraction and "
                                "their keypoints scaled back (COLMAP's default too): SIFT's memory grows with the "
                                "pixels, about 4 GiB per 48-megapixel photo; 0 = never", lo=0)


UPSTREAM = ("ingest",)
SECTIONS = ("features",)
OUTPUTS = (artifacts.FEATURES,)


# --------------------------------------------------------------------------- plain functions


def to_gray(image: np.ndarray) -> np.ndarray:
    """uint8 RGB [H,W,3] (or already gray [H,W]) -> uint8 gray [H,W]."""
    import cv2

    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    if image.ndim == 2:
        return image
    return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)


def normalize_descriptors(desc: np.ndarray, root_sift: bool = True) -> np.ndarray:
    """SIFT descriptors [K,128] -> float32 rows of unit L2 norm (RootSIFT or L2-normalised)."""
    desc = np.asarray(desc, np.float32)
    if desc.size == 0:
        return desc.reshape(0, 128)
    if root_sift:
        desc = desc / np.maximum(np.abs(desc).sum(1, keepdims=True), 1e-12)
        desc = np.sqrt(desc)
        # sqrt of an L1-normalised non-negative vector has unit L2 norm; renormalise for float error
    return desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)


def extract_sift(
    image: np.ndarray,
    mask: np.ndarray | None = None,
    *,
    max_features: int = 8000,
    root_sift: bool = True,
    contrast_threshold: float = 0.02,
    edge_threshold: float = 10.0,
    n_octave_layers: int = 3,
    max_image_size: int = 0,
) -> dict:
    """SIFT on one image (downscaled to ``max_image_size`` on its longer side first, when larger and not 0).
    Returns a dict of keypoints [K,2] (project pixel convention, the image's own pixels), scales [K],
    orientations [K] (radians), responses [K], descriptors [K,128] (unit rows)."""
    import cv2

    gray = to_gray(image)
    h, w = gray.shape[:2]
    scale = max_image_size / max(h, w) if max_image_size and max(h, w) > max_image_size else 1.0
    if scale < 1.0:
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
        mask = None if mask is None else cv2.resize((np.asarray(mask) > 0).astype(np.uint8), size,
                                                    interpolation=cv2.INTER_NEAREST)
        scale = np.array([size[0] / w, size[1] / h])  # [2]: the resize's own factor per axis
    sift = cv2.SIFT_create(
        nfeatures=int(max_features),
        nOctaveLayers=int(n_octave_layers),
        contrastThreshold=float(contrast_threshold),
        edgeThreshold=float(edge_threshold),
        sigma=1.6,
        enable_precise_upscale=True,  # keypoints without the 0.25 px bias of the 2x upscale
    )
    m = None if mask is None else (np.asarray(mask) > 0).astype(np.uint8)
    kps, desc = sift.detectAndCompute(gray, m)
    kps = list(kps)
    if len(kps) > max_features:  # OpenCV may keep ties / duplicated orientations beyond nfeatures
        order = np.argsort([-k.response for k in kps], kind="stable")[:max_features]
        kps = [kps[i] for i in order]
        desc = desc[order]
    n = len(kps)
    if n == 0 or desc is None:
        return empty_features()
    return {
        # pixel edges at integers (+0.5 from OpenCV's centres), then back to the image's own pixels
        "keypoints": ((np.array([k.pt for k in kps], np.float64).reshape(n, 2) + 0.5) / scale).astype(np.float32),
        "scales": (np.array([k.size for k in kps], np.float64) / np.mean(scale)).astype(np.float32),
        "orientations": np.radians(np.array([k.angle for k in kps], np.float32)),
        "responses": np.array([k.response for k in kps], np.float32),
        "descriptors": normalize_descriptors(desc, root_sift),
    }


def empty_features() -> dict:
    return {
        "keypoints": np.zeros((0, 2), np.float32),
        "scales": np.zeros(0, np.float32),
        "orientations": np.zeros(0, np.float32),
        "responses": np.zeros(0, np.float32),
        "descriptors": np.zeros((0, 128), np.float32),
    }


def extract_all(images, masks=None, *, workers: int = 2, progress=None, **kw) -> list[dict]:
    """extract_sift over a list/array of images with a thread pool; results in input order."""
    import cv2

    n = len(images)

    def one(i):
        return extract_sift(images[i], None if masks is None else masks[i], **kw)

    if workers <= 1:
        it = map(one, range(n))
        return list(progress(it, total=n) if progress else it)
    # one level of parallelism: threads over images, OpenCV single-threaded inside (restored after)
    prev = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            it = pool.map(one, range(n))
            return list(progress(it, total=n) if progress else it)
    finally:
        cv2.setNumThreads(prev)


def pack_features(feats: list[dict]) -> dict:
    """Per-view dicts -> concatenated arrays + ``offsets`` [N+1]."""
    counts = np.array([len(f["keypoints"]) for f in feats], np.int64)
    out = {"offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)}
    for key in ("keypoints", "scales", "orientations", "responses", "descriptors"):
        out[key] = np.concatenate([f[key] for f in feats], 0) if feats else empty_features()[key]
    return out


# --------------------------------------------------------------------------- stage


def run(ctx) -> None:
    p: Params = ctx.params
    src = Path(ctx.input("ingest"))
    meta = artifacts.load_views_meta(src)
    names = list(meta["names"])
    wanted = ["images", "sizes"] + (["masks"] if p.use_mask and meta.get("has_masks") else [])
    arrays = artifacts.load_views_arrays(src, wanted)
    # each view at its own size: the canvas' padding would give SIFT an edge to detect on
    images = [own(im, hw) for im, hw in zip(arrays["images"], arrays["sizes"])]
    masks = None if arrays.get("masks") is None else [own(m, hw) for m, hw in zip(arrays["masks"], arrays["sizes"])]
    if p.use_mask and masks is None:
        ctx.log.warning("features.use_mask is on but the scene has no masks: detecting on the whole image")

    t0 = time.perf_counter()
    feats = extract_all(
        images,
        masks,
        workers=p.workers,
        progress=lambda it, total: ctx.progress(it, total=total, desc="SIFT"),
        max_features=p.max_features,
        root_sift=p.root_sift,
        contrast_threshold=p.contrast_threshold,
        edge_threshold=p.edge_threshold,
        n_octave_layers=p.n_octave_layers,
        max_image_size=p.max_image_size,
    )
    seconds = time.perf_counter() - t0

    featureless = np.zeros(len(names), bool)
    for v, f in enumerate(feats):
        if len(f["keypoints"]) < p.min_features:
            featureless[v] = True
            ctx.log.warning(
                f"view {names[v]} has {len(f['keypoints'])} SIFT keypoints (< features.min_features="
                f"{p.min_features}): recorded as featureless, it will have no matches"
            )
            feats[v] = empty_features()
    if featureless.all():
        raise RuntimeError(
            f"all {len(names)} views are featureless (< {p.min_features} SIFT keypoints each): the images are "
            "blank or too small; check the ingest output, or lower features.contrast_threshold / features.min_features"
        )

    packed = pack_features(feats)
    packed["featureless"] = featureless
    save_arrays(
        Path(ctx.out) / artifacts.FEATURES,
        packed,
        attrs={
            "names": names,
            "n_views": len(names),
            "root_sift": p.root_sift,
            "pixel_convention": "top-left pixel centre at (0.5, 0.5)",
            "orientation_units": "radians",
            "scale_definition": "OpenCV KeyPoint.size (px)",
        },
        chunk_first=False,
    )
    counts = np.diff(packed["offsets"])
    ctx.log.info(
        f"SIFT on {len(names)} views in {seconds:.2f} s: keypoints per view min {counts.min()}, "
        f"mean {counts.mean():.0f}, max {counts.max()}"
    )
    ctx.metrics["n_views"] = len(names)
    ctx.metrics["n_keypoints_total"] = int(counts.sum())
    ctx.metrics["n_keypoints_mean"] = float(counts.mean())
    ctx.metrics["n_keypoints_min"] = int(counts.min())
    ctx.metrics["n_keypoints_max"] = int(counts.max())
    ctx.metrics["n_featureless"] = int(featureless.sum())
    ctx.metrics["featureless_views"] = ", ".join(names[v] for v in np.flatnonzero(featureless))
    ctx.metrics["seconds"] = float(seconds)
