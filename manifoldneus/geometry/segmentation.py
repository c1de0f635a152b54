"""Object masks from the photos and their SfM tracks alone (no mask files, no segmentation weights).

A field trained without masks lets its background model and its surface trade what the images show, and
on DTU's objects that cost the surface 1.6-2.4x the Chamfer of a masked run, where the layout's masks given
to the same poses close the gap (docs/EXPERIMENTS.md). GrabCut (OpenCV) separates an object from its
background by colour, once told roughly where each is; the tracks of the final round tell it:

* a point the views' common frustum holds, inside the object's region and above its support, is the
  object's: a small disk of sure foreground where each view observed it;
* a point on or below the support plane, or outside the region's ball, is background: a disk of sure
  background where each view observed it (a white skull on a white table is told apart by these);
* the convex hull of the object's points is probable foreground, a band around it probable background,
  the rest of the image sure background.

Only observed pixels become seeds, so a point the object hides from a view seeds nothing there.

GrabCut errs in a few views (a white top on a white table left out, a patch of background taken in), and a
field trained on such masks as if they were the layout's carves the object or grows the background into
surface. So the views vote (:func:`vote_masks`: a voxel is the object's where nearly all the views that hold it
have it inside their mask, and its projection is each view's share of the vote), and :func:`object_labels`
decides only the pixels where a view's own mask and the vote agree (by default only that they are background);
the rest are left to the photos.
"""
from __future__ import annotations

import cv2
import numpy as np

from .cameras import project_points, transform_points
from .object_region import ObjectRegion, seen_fraction

FOREGROUND_SEED_PX = 2  # radii of the seed disks, in pixels of the images GrabCut sees
BACKGROUND_SEED_PX = 3


def classify_points(points: np.ndarray, seen: np.ndarray, region: ObjectRegion | None, min_seen: float,
                    support_margin: float) -> tuple[np.ndarray, np.ndarray]:
    """(object [P] bool, background [P] bool) of the points [P,3] that the fraction ``seen`` [P] of the views
    hold in their frame: object = seen by ``min_seen`` of the views, inside the region and more than
    ``support_margin`` (of the region's radius) above its support plane; background = outside the region's
    ball, or on or below that margin above the plane. Without a region, no point is background."""
    obj = seen >= min_seen
    if region is None:
        return obj, np.zeros(len(points), bool)
    margin = support_margin * region.radius
    obj &= region.contains(points, margin)
    background = ~region.contains(points, None)
    if region.plane is not None:
        background |= np.asarray(points) @ np.asarray(region.plane[:3]) + region.plane[3] <= margin
    return obj & ~background, background


def grabcut_mask(image: np.ndarray, hull: np.ndarray, foreground_uv: np.ndarray, background_uv: np.ndarray,
                 band: int, iters: int = 5, seed: int = 0) -> np.ndarray:
    """bool [H,W]: GrabCut of the image [H,W,3] uint8 started from the hull [H,W] bool (probable foreground), a
    ``band``-pixel ring around it (probable background), the rest background, and seed disks at the pixels
    foreground_uv [F,2] / background_uv [B,2] (x, y). All background when the hull is empty."""
    H, W = hull.shape
    if not hull.any():
        return np.zeros((H, W), bool)
    h = hull.astype(np.uint8)
    ring = cv2.dilate(h, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band + 1, 2 * band + 1)))
    trimap = np.full((H, W), cv2.GC_BGD, np.uint8)
    trimap[ring > 0] = cv2.GC_PR_BGD
    trimap[h > 0] = cv2.GC_PR_FGD
    for uv, label, radius in ((background_uv, cv2.GC_BGD, BACKGROUND_SEED_PX),
                              (foreground_uv, cv2.GC_FGD, FOREGROUND_SEED_PX)):
        for x, y in np.round(uv).astype(int):
            cv2.circle(trimap, (int(x), int(y)), radius, int(label), -1)
    if not (trimap == cv2.GC_FGD).any() and not (trimap == cv2.GC_PR_FGD).any():
        return np.zeros((H, W), bool)
    cv2.setRNGSeed(seed)  # GrabCut's k-means draws from OpenCV's generator: the same masks on every run
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    cv2.grabCut(np.ascontiguousarray(image), trimap, None, bgd, fgd, iters, cv2.GC_INIT_WITH_MASK)
    return (trimap == cv2.GC_FGD) | (trimap == cv2.GC_PR_FGD)


def convex_hull_mask(points: np.ndarray, K: np.ndarray, w2c: np.ndarray, hw) -> np.ndarray:
    """bool [H,W]: the convex hull of the points [P,3] in front of the camera (K [3,3], w2c [4,4]), projected."""
    H, W = hw
    out = np.zeros((H, W), np.uint8)
    xc = transform_points(w2c, points)  # [P,3]
    xc = xc[xc[:, 2] > 1e-9]
    if len(xc) >= 3:
        uv = np.clip(project_points(K, xc), -4 * max(H, W), 5 * max(H, W))  # far points still bound it, as ints
        cv2.fillConvexPoly(out, cv2.convexHull(uv.astype(np.float32)).astype(np.int32), 1)
    return out > 0


def object_masks(images: np.ndarray, sizes: np.ndarray, K: np.ndarray, w2c: np.ndarray, ids: np.ndarray,
                 tracks: dict, region: ObjectRegion | None, min_seen: float, support_margin: float, band: int,
                 progress=iter) -> np.ndarray:
    """bool [len(ids),H,W]: the object's mask in each view ``ids`` of images [N,H,W,3] uint8 (each view's own
    part sizes [N,2] (H, W) of the canvas; False beyond it), posed by K [N,3,3], w2c [N,4,4], from the round's
    ``tracks``: ``track_points`` [P,3] (w2c's frame), ``track_obs_view`` / ``track_obs_point`` [O] and
    ``track_obs_uv`` [O,2] px. ``progress`` wraps the loop over the views (a progress bar)."""
    points = tracks["track_points"]
    seen = seen_fraction(points, K[ids], w2c[ids], sizes[ids])
    obj, background = classify_points(points, seen, region, min_seen, support_margin)
    view, point, uv = tracks["track_obs_view"], tracks["track_obs_point"], tracks["track_obs_uv"]
    masks = np.zeros((len(ids), *images.shape[1:3]), bool)
    for j in progress(range(len(ids))):
        i = ids[j]
        h, w = sizes[i]
        here = view == i
        masks[j, :h, :w] = grabcut_mask(images[i, :h, :w, :3], convex_hull_mask(points[obj], K[i], w2c[i], (h, w)),
                                         uv[here & obj[point]], uv[here & background[point]], band, seed=int(i))
    return masks


def vote_masks(masks: np.ndarray, K: np.ndarray, w2c: np.ndarray, sizes: np.ndarray, points: np.ndarray,
               resolution: int = 160, agree: float = 0.9, min_seen: float = 0.3, pad: float = 1.4) -> np.ndarray:
    """bool [V,H,W]: the views' masks [V,H,W] (posed by K [V,3,3], w2c [V,4,4], own sizes [V,2] (H, W)) voted
    across the views. A voxel of a ``resolution``^3 grid over the box of the object's points [P,3] (their 0.5-99.5
    percentiles, grown ``pad`` times) is the object's where ``min_seen`` of the views hold it in their frame and at
    least ``agree`` of those have it inside their mask; the kept voxels, projected (each a disk of its footprint),
    are each view's vote. A view's mask that left a part out gets it back where the others hold it."""
    V, H, W = masks.shape
    lo, hi = np.percentile(points, 0.5, axis=0), np.percentile(points, 99.5, axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * pad
    axes = [np.linspace(centre[k] - half[k], centre[k] + half[k], resolution) for k in range(3)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # [G,3]
    inside = np.zeros(len(X), np.int32)
    held = np.zeros(len(X), np.int32)
    for i in range(V):
        u, v, ok = _pixels(X, K[i], w2c[i], sizes[i])
        held += ok
        inside[ok] += masks[i, v[ok], u[ok]]
    keep = (held >= min_seen * V) & (inside >= agree * np.maximum(held, 1))
    kept = X[keep]  # [Q,3]
    voxel = 2 * half.max() / (resolution - 1)
    out = np.zeros_like(masks, dtype=bool)
    for i in range(V):
        u, v, ok = _pixels(kept, K[i], w2c[i], sizes[i])
        if not ok.any():
            continue
        depth = np.median(transform_points(w2c[i], kept[ok])[:, 2])
        radius = max(1, int(np.ceil(K[i, 0, 0] * voxel / max(depth, 1e-9))))
        img = np.zeros((H, W), np.uint8)
        img[v[ok], u[ok]] = 1
        out[i] = cv2.dilate(img, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))) > 0
    return out


def _pixels(X: np.ndarray, K: np.ndarray, w2c: np.ndarray, size) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(column [G], row [G], in the view's own pixels and in front of it [G]) of the points X [G,3]."""
    xc = transform_points(w2c, X)  # [G,3]
    front = xc[:, 2] > 1e-9
    uv = project_points(K, np.where(front[:, None], xc, 1.0))
    u, v = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
    ok = front & (u >= 0) & (u < size[1]) & (v >= 0) & (v < size[0])
    return np.where(ok, u, 0), np.where(ok, v, 0), ok


def object_labels(masks: np.ndarray, voted: np.ndarray, erode: int, fill: bool = False) -> np.ndarray:
    """float32 [V,H,W]: 0 where neither a view's mask nor the views' vote (:func:`vote_masks`) holds the object,
    with ``fill`` 1 where both do, each region shrunk by ``erode`` pixels (the masks' edges are the least sure);
    0.5 (undecided) elsewhere. Both can hold what is not the object: a hole or a concavity the object's convex
    outline spans (the synthetic torus's hole), so filling is the riskier half."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode + 1, 2 * erode + 1)) if erode > 0 else None
    out = np.full(masks.shape, 0.5, np.float32)
    for i, (m, vote) in enumerate(zip(masks, voted)):
        for region, value in [(~m & ~vote, 0.0)] + ([(m & vote, 1.0)] if fill else []):
            r = region.astype(np.uint8)
            if kernel is not None:
                r = cv2.erode(r, kernel)
            out[i][r > 0] = value
    return out


def unfill_background_colours(labels: np.ndarray, images: np.ndarray, sizes: np.ndarray, margin: float,
                              clusters: int = 16, seed: int = 0) -> np.ndarray:
    """labels [V,H,W] float32 (:func:`object_labels`) with each view's filled pixels (1) whose colour lies within
    ``margin`` (RGB levels) of one its carved pixels (0) show set back to undecided (0.5), in a copy; images
    [V,H,W,3] uint8, sizes [V,2] (H, W) each view's own part. GrabCut keeps a hole the object encloses inside the
    mask (the background through it is as dark as a dark texture), and the vote with it: filling there grows
    surface across the hole. A pixel coloured as the background is left to the photos; the background's colours
    are ``clusters`` k-means centres of the view's carved pixels."""
    out = labels.copy()
    rng = np.random.default_rng(seed)
    cv2.setRNGSeed(seed)  # k-means++ draws from OpenCV's generator
    for j, (image, (h, w)) in enumerate(zip(images, sizes)):
        view = image[:h, :w, :3].astype(np.float32)  # [h,w,3]
        carved, filled = out[j, :h, :w] == 0, out[j, :h, :w] == 1
        if carved.sum() < clusters or not filled.any():
            continue
        background = view[carved]
        background = background[rng.choice(len(background), min(len(background), 20000), replace=False)]
        _, _, centres = cv2.kmeans(background, clusters, None, (cv2.TERM_CRITERIA_MAX_ITER, 10, 1.0), 1,
                                   cv2.KMEANS_PP_CENTERS)  # [clusters,3]
        nearest = np.linalg.norm(view[filled][:, None] - centres[None], axis=-1).min(1)  # [F]
        veto = np.zeros_like(filled)
        veto[filled] = nearest < margin
        out[j, :h, :w][veto] = 0.5
    return out


def labels_picture(images: np.ndarray, labels: np.ndarray, n: int = 6, size: int = 320) -> np.ndarray:
    """uint8 [h,w,3]: up to ``n`` of the views (images [V,H,W,3] uint8, evenly picked) side by side, each at most
    ``size`` px, the object's pixels of ``labels`` [V,H,W] tinted green, the background's red, the undecided as
    they are."""
    picked = np.linspace(0, len(images) - 1, min(n, len(images))).round().astype(int)
    tiles = []
    for i in picked:
        img = images[i, ..., :3].astype(np.float32)
        tint = np.zeros_like(img)
        tint[labels[i] >= 0.9] = (0, 255, 0)
        tint[labels[i] <= 0.1] = (255, 0, 0)
        decided = ((labels[i] >= 0.9) | (labels[i] <= 0.1))[..., None]
        img = np.where(decided, 0.6 * img + 0.4 * tint, img)
        s = size / max(img.shape[:2])
        tiles.append(cv2.resize(img, (round(img.shape[1] * s), round(img.shape[0] * s)), interpolation=cv2.INTER_AREA))
    h = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 2), (0, 0)), constant_values=255) for t in tiles]
    return np.concatenate(tiles, 1).clip(0, 255).astype(np.uint8)
