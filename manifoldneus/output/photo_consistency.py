"""Photo-consistency of a surface: how much the images disagree about the grey level of its points.

A surface in the right place shows every view that sees it the same texture; one a few millimetres
off reads a different pixel in each view. The colour spread is the standard deviation of the grey level
over the views that see a point (facing it, inside the frame, not hidden by the surface itself), its
median taken over points sampled on the surface. It is read at the images' own resolution under the
ground-truth cameras, so it needs neither masks nor a reference surface: on DTU, where Chamfer is
measured against a NeuS trained with the masks (``reference_surface``), it also scores that reference.
A textureless surface gives the same grey at any depth, so it cannot see errors there (a table kept
around the object scores well): it stands beside Chamfer, never in its place.

Visibility comes from a z-buffer of dense surface samples splatted into each view: no ray caster.
Frames: ``K`` [N,3,3] and ``w2c`` [N,4,4] OpenCV world-to-camera (:mod:`manifoldneus.geometry.cameras`),
the mesh in the same world frame.
"""
from __future__ import annotations

import numpy as np

from manifoldneus.geometry import cameras
from manifoldneus.output.meshing import splat_depth


def _depth_buffer(points: np.ndarray, K: np.ndarray, w2c: np.ndarray, hw) -> np.ndarray:
    """[H,W] nearest camera depth of ``points`` [P,3] splatted one pixel each; a pixel no point lands on
    takes the nearest depth of its 3x3 neighbourhood (inf where none lands there either)."""
    import cv2

    cam = cameras.transform_points(w2c, points)  # [P,3]
    cam = cam[cam[:, 2] > 1e-9]
    buffer = splat_depth(cameras.project_points(K, cam), cam[:, 2].astype(np.float32), hw)
    return np.where(np.isinf(buffer), cv2.erode(buffer, np.ones((3, 3), np.uint8)), buffer)


def colour_spread(mesh, images, K: np.ndarray, w2c: np.ndarray, *, depth_tolerance: float, n_points: int = 50000,
                  splat_points: int = 2_000_000, splats_per_pixel: float = 16, min_views: int = 4,
                  min_facing: float = 0.5, seed: int = 0) -> dict:
    """The colour spread of ``mesh`` (a trimesh) seen by the views ``images`` (N grey images [H,W] in
    [0,1], sizes may differ), ``K`` [N,3,3] and ``w2c`` [N,4,4]. A point is seen by a view that it faces
    (cosine above ``min_facing``), whose frame holds it and whose depth buffer it is within
    ``depth_tolerance`` (scene units) plus two pixels' width of; points seen by fewer than ``min_views``
    views are left out.
    Returns ``median`` and ``mean`` spread, ``p90``, and ``share_scored`` (the share of the points
    kept); None where the mesh is empty or no point is seen often enough.
    The z-buffers splat ``splats_per_pixel`` surface samples per pixel of the largest image, at most
    ``splat_points``: enough that every pixel the surface covers receives one (DTU's images reach the
    cap; a 192-px synthetic view needs under a third of it)."""
    import trimesh
    from scipy.ndimage import map_coordinates

    if mesh is None or len(mesh.faces) == 0:
        return None
    n_splats = min(splat_points, int(splats_per_pixel * max(image.shape[0] * image.shape[1] for image in images)))
    dense = np.asarray(trimesh.sample.sample_surface(mesh, n_splats, seed=seed + 1)[0])  # [D,3] the z-buffers'
    points, faces = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    points, normals = np.asarray(points), np.asarray(mesh.face_normals[faces])  # [P,3] each
    grey = np.full((len(images), len(points)), np.nan, np.float32)  # [N,P]
    for i, image in enumerate(images):
        H, W = image.shape[:2]
        buffer = _depth_buffer(dense, K[i], w2c[i], (H, W))
        cam = cameras.transform_points(w2c[i], points)  # [P,3]
        to_camera = cameras.camera_centers(w2c[i]) - points
        facing = np.einsum("pi,pi->p", normals, to_camera) > min_facing * np.linalg.norm(to_camera, axis=1)
        idx = np.flatnonzero(facing & (cam[:, 2] > 1e-9))
        uv = cameras.project_points(K[i], cam[idx])  # [S,2]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] < H - 1)
        idx, uv, z = idx[inside], uv[inside], cam[idx[inside], 2]
        footprint = z / K[i][0, 0]  # [S] a pixel's width at the point: the buffer's own resolution
        seen = z <= buffer[uv[:, 1].astype(int), uv[:, 0].astype(int)] + depth_tolerance + 2 * footprint
        # bilinear, pixel centres at integers
        grey[i, idx[seen]] = map_coordinates(np.asarray(image, np.float32), uv[seen, ::-1].T, order=1)
    scored = np.isfinite(grey).sum(0) >= min_views
    if not scored.any():
        return None
    spread = np.nanstd(grey[:, scored], axis=0)  # [S]
    return {"median": float(np.median(spread)), "mean": float(spread.mean()), "p90": float(np.percentile(spread, 90)),
            "share_scored": float(scored.mean())}


def grey_levels(images: np.ndarray) -> np.ndarray:
    """Grey levels [...] in [0,1] of RGB pixels [...,3] (uint8, or float in [0,1]), ITU-R 601 weights."""
    rgb = np.asarray(images, np.float32)
    if np.asarray(images).dtype == np.uint8:
        rgb = rgb / 255.0
    return rgb @ np.array([0.299, 0.587, 0.114], np.float32)
