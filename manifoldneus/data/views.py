"""The trainer's plain-array input (:class:`Views`), apart from the trainer so that the artifacts'
readers (:mod:`manifoldneus.data.artifacts`) import neither torch nor the field: a stage's fingerprint
hashes every module it can import, and the front-end stages that write artifacts would otherwise
rerun for every change to the training code.

Photos of several sizes (COLMAP: one camera per size) share one array: each view's pixels sit at the
top-left of a common canvas [N,H,W] (the largest height and width), zero beyond, and ``sizes`` [N,2]
(H, W) says how much of it is the view's own. Pixel coordinates and K are each view's own, unchanged by
the padding. :func:`on_canvas` builds it, :func:`own` crops a view back; every reader of the pixels
(features, rays, metrics, exports) keeps to a view's own part.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def on_canvas(arrays: list) -> tuple[np.ndarray, np.ndarray]:
    """Per-view arrays [H_i,W_i,...] of one dtype -> (canvas [N,H,W,...], sizes int64 [N,2] (H_i, W_i)):
    each at the top-left, zeros beyond (see module doc). One size: the plain stack."""
    sizes = np.array([a.shape[:2] for a in arrays], np.int64).reshape(-1, 2)
    if len(arrays) == 0 or (sizes == sizes[0]).all():
        return np.stack(arrays), sizes
    H, W = sizes.max(0)
    out = np.zeros((len(arrays), H, W, *arrays[0].shape[2:]), arrays[0].dtype)
    for a, (h, w), o in zip(arrays, sizes, out):
        o[:h, :w] = a
    return out, sizes


def own(a: np.ndarray, size) -> np.ndarray:
    """A view's own part [h,w,...] of its canvas ``a`` [H,W,...] (``size`` (h, w); None: all of it)."""
    return a if size is None else a[: int(size[0]), : int(size[1])]


def canvas_sizes(sizes: np.ndarray | None, n: int, hw) -> np.ndarray:
    """[n,2] (H, W) of each view's own pixels: ``sizes``, or the canvas ``hw`` for every view when None."""
    return np.tile(np.asarray(hw, np.int64), (n, 1)) if sizes is None else np.asarray(sizes, np.int64)


@dataclass
class Views:
    """Plain-array input of the trainer (see module doc)."""

    images: np.ndarray
    K: np.ndarray
    w2c: np.ndarray
    masks: np.ndarray | None = None
    mono_depth: np.ndarray | None = None
    mono_normal: np.ndarray | None = None
    names: list = field(default_factory=list)
    sizes: np.ndarray | None = None  # [N,2] (H, W) of each view's own pixels on the canvas; None: all one size
    # [N,H,W] float32, masks made from the photos (runs without the layout's): 1 the object, 0 the background,
    # 0.5 undecided; resampled like depth, so the pixels their edges blur into read as undecided too
    object_labels: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.images.shape[0])

    @property
    def hw(self) -> tuple[int, int]:
        """The canvas' (H, W): every view's own size when :attr:`one_size`."""
        return int(self.images.shape[1]), int(self.images.shape[2])

    @property
    def one_size(self) -> bool:
        return self.sizes is None or bool((np.asarray(self.sizes) == self.hw).all())

    @property
    def view_sizes(self) -> np.ndarray:
        """[N,2] (H, W) of each view's own pixels."""
        return canvas_sizes(self.sizes, self.n, self.hw)

    def subset(self, ids, w2c_all: np.ndarray) -> "Views":
        """The views ``ids`` (rows of these), posed by ``w2c_all`` [N,4,4] (indexed like these)."""
        ids = np.asarray(ids, int)

        def pick(a):
            return None if a is None else a[ids]

        return Views(self.images[ids], self.K[ids], w2c_all[ids], pick(self.masks), pick(self.mono_depth),
                     pick(self.mono_normal), [self.names[i] for i in ids], pick(self.sizes), pick(self.object_labels))

    def resized(self, size: int) -> "Views":
        """Downscale (area filter) so the longest side is ``size``; K follows (pixel-centre
        convention: plain scaling). Normals are renormalised, masks re-thresholded at 0.5. Views of
        several sizes: each view's own pixels by the canvas' factor, to its own rounded size
        (its K by its own factors), on the canvas of those sizes."""
        import cv2

        H, W = self.hw
        if size <= 0 or max(H, W) <= size:
            return self
        s = size / max(H, W)
        if not self.one_size:
            return self._resized_each(s)
        h, w = max(int(round(H * s)), 1), max(int(round(W * s)), 1)
        sx, sy = w / W, h / H

        def rs(a, interp=cv2.INTER_AREA):
            return np.stack([cv2.resize(x, (w, h), interpolation=interp) for x in a])

        imgs = self.images
        imgs = rs(imgs.astype(np.float32) / (255.0 if imgs.dtype == np.uint8 else 1.0))
        K = np.array(self.K, dtype=np.float64)
        K[:, 0, :] *= sx
        K[:, 1, :] *= sy
        masks = None if self.masks is None else rs(self.masks.astype(np.float32)) > 0.5
        depth = None if self.mono_depth is None else rs(self.mono_depth.astype(np.float32))
        normal = None
        if self.mono_normal is not None:
            normal = rs(self.mono_normal.astype(np.float32))
            normal /= np.linalg.norm(normal, axis=-1, keepdims=True).clip(1e-8)
        labels = None if self.object_labels is None else rs(self.object_labels.astype(np.float32))
        return Views(imgs, K, np.array(self.w2c), masks, depth, normal, list(self.names), object_labels=labels)

    def _resized_each(self, s: float) -> "Views":
        """:meth:`resized` of views of several sizes, each by the factor ``s`` (module doc)."""
        import cv2

        new = np.maximum(np.round(self.view_sizes * s).astype(np.int64), 1)  # [N,2]
        K = np.array(self.K, dtype=np.float64)
        K[:, 0, :] *= (new[:, 1] / self.view_sizes[:, 1])[:, None]
        K[:, 1, :] *= (new[:, 0] / self.view_sizes[:, 0])[:, None]

        def rs(stack, scale=1.0):
            if stack is None:
                return None
            out = [cv2.resize(own(a, hw).astype(np.float32) / scale, (int(w), int(h)), interpolation=cv2.INTER_AREA)
                   for a, hw, (h, w) in zip(stack, self.view_sizes, new)]
            return on_canvas(out)[0]

        masks = None if self.masks is None else rs(self.masks) > 0.5
        normal = rs(self.mono_normal)
        if normal is not None:
            normal /= np.linalg.norm(normal, axis=-1, keepdims=True).clip(1e-8)
        return Views(rs(self.images, 255.0 if self.images.dtype == np.uint8 else 1.0), K, np.array(self.w2c), masks,
                     rs(self.mono_depth), normal, list(self.names), new, rs(self.object_labels))

    def undistorted(self, distortion: np.ndarray | None) -> "Views":
        """The views with each one's lens ``distortion`` [N,4] (OpenCV's model, see
        :mod:`manifoldneus.geometry.cameras`) removed at its own K: images and priors resampled bilinearly,
        masks by nearest pixel. Views without distortion (or ``distortion`` None) are kept as they are."""
        from manifoldneus.geometry.cameras import has_distortion, undistort_image

        if not has_distortion(distortion):
            return self

        def each(stack, nearest=False):
            if stack is None:
                return None
            return np.stack([undistort_image(a, k, d, nearest) if has_distortion(d) else a
                             for a, k, d in zip(stack, self.K, distortion)])

        return Views(each(self.images), np.array(self.K), np.array(self.w2c), each(self.masks, nearest=True),
                     each(self.mono_depth), each(self.mono_normal), list(self.names), self.sizes,
                     each(self.object_labels))

    def float_images(self) -> np.ndarray:
        im = self.images
        return im.astype(np.float32) / 255.0 if im.dtype == np.uint8 else im.astype(np.float32)
