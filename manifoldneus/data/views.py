"""The trainer's plain-array input (:class:`Views`), apart from the trainer so that the artifacts'
readers (:mod:`manifoldneus.data.artifacts`) import neither torch nor the field: a stage's fingerprint
hashes every module it can import, and the front-end stages that write artifacts would otherwise
rerun for every change to the training code.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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

    @property
    def n(self) -> int:
        return int(self.images.shape[0])

    @property
    def hw(self) -> tuple[int, int]:
        return int(self.images.shape[1]), int(self.images.shape[2])

    def subset(self, ids, w2c_all: np.ndarray) -> "Views":
        """The views ``ids`` (rows of these), posed by ``w2c_all`` [N,4,4] (indexed like these)."""
        ids = np.asarray(ids, int)

        def pick(a):
            return None if a is None else a[ids]

        return Views(self.images[ids], self.K[ids], w2c_all[ids], pick(self.masks), pick(self.mono_depth),
                     pick(self.mono_normal), [self.names[i] for i in ids])

    def resized(self, size: int) -> "Views":
        """Downscale (area filter) so the longest side is ``size``; K follows (pixel-centre
        convention: plain scaling). Normals are renormalised, masks re-thresholded at 0.5."""
        import cv2

        H, W = self.hw
        if size <= 0 or max(H, W) <= size:
            return self
        s = size / max(H, W)
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
        return Views(imgs, K, np.array(self.w2c), masks, depth, normal, list(self.names))

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
                     each(self.mono_depth), each(self.mono_normal), list(self.names))

    def float_images(self) -> np.ndarray:
        im = self.images
        return im.astype(np.float32) / 255.0 if im.dtype == np.uint8 else im.astype(np.float32)
