"""Where the object is, from the cameras and the SfM points alone (no masks, no segmentation weights).

People photograph an object by walking around it with the camera pointed at it, so:

* the point nearest to every optical axis (least squares) is where the views aim (:func:`aim_point`);
* the object's SfM points are those most of the views see inside their frame, the views' common
  frustum (:func:`seen_fraction`); background behind the object and clutter at the edges of the frame
  are seen by few views;
* the object stands on a support (a table, a turntable) that is the dominant plane among the points
  near it, with every camera on one side (:func:`support_plane`); the surface below it is not the object.

:class:`ObjectRegion` holds the result in the normalised frame of the pose-free rounds (the anchors'
gauge); the anchors stage saves it and the mesh stage crops the surface to it.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .cameras import camera_centers


def aim_point(w2c: np.ndarray) -> np.ndarray:
    """The point [3] nearest, in least squares, to the optical axes of the views w2c [N,4,4]."""
    centres = camera_centers(w2c)  # [N,3]
    axes = np.asarray(w2c)[:, 2, :3]  # [N,3] the cameras' +z in the world frame
    P = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # [N,3,3] projectors orthogonal to each axis
    return np.linalg.lstsq(P.sum(0), np.einsum("nij,nj->i", P, centres), rcond=None)[0]


def seen_fraction(points: np.ndarray, K: np.ndarray, w2c: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Fraction [P] of the views (K [N,3,3], w2c [N,4,4], sizes [N,2] as (H, W)) whose frame holds each
    of the points [P,3], in front of the camera."""
    Xc = np.einsum("nij,pj->npi", w2c[:, :3, :3], points) + w2c[:, None, :3, 3]  # [N,P,3]
    uvw = np.einsum("nij,npj->npi", K, Xc)  # [N,P,3]
    z = uvw[..., 2]
    uv = uvw[..., :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[..., None]
    H, W = np.asarray(sizes, float)[:, 0, None], np.asarray(sizes, float)[:, 1, None]  # [N,1]
    inside = (Xc[..., 2] > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < W) & (uv[..., 1] >= 0) & (uv[..., 1] < H)
    return inside.mean(0)


def support_plane(points: np.ndarray, w2c: np.ndarray, tol: float, min_share: float = 0.1, min_above: float = 0.99,
                  confidence: float = 0.999, seed: int = 0, batch: int = 256) -> tuple[np.ndarray, float] | None:
    """The plane n.x + d = 0 (n [3] unit, pointing to the cameras) holding the most points [P,3] within
    ``tol`` (RANSAC), when it holds at least ``min_share`` of them, every camera centre lies above it and
    ``min_above`` of the points lie above it or on it; else None (no support in view: e.g. an object held in
    the air). No view sees through a support, so nothing but mismatches lies below one: a face of the object
    has the object beyond it (scan24's photos alone: a plane of the object's own points, 4.7 % of the points
    more than 2 % of the radius below it; scan65's table: none below). As many hypotheses as find a plane holding
    ``min_share`` with probability ``confidence`` (6905 at 0.1): 500 missed scan65's table, 22 % of its points."""
    points = np.asarray(points, np.float64)
    if len(points) < 3:
        return None
    iterations = int(np.ceil(np.log(1 - confidence) / np.log(1 - min_share**3)))
    rng = np.random.default_rng(seed)
    centres = camera_centers(w2c)  # [C,3]
    best, best_count = None, 0
    for start in range(0, iterations, batch):
        a, b, c = np.moveaxis(points[rng.choice(len(points), (min(batch, iterations - start), 3))], 1, 0)  # [B,3] each
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        ok = norm > 1e-12
        n, a = n[ok] / norm[ok, None], a[ok]
        d = -np.einsum("bi,bi->b", n, a)
        side = centres @ n.T + d  # [C,B]
        # cameras on both sides: a wall between them, or the object's own face
        ok = np.all(side > tol, 0) | np.all(side < -tol, 0)
        n, d = n[ok] * np.sign(side[0, ok])[:, None], d[ok] * np.sign(side[0, ok])  # oriented to the cameras
        dist = points @ n.T + d  # [P,B] > 0 on the cameras' side
        count = (np.abs(dist) < tol).sum(0)
        count[(dist > -tol).mean(0) < min_above] = 0  # a support, not a face with more beyond it
        if len(count) and count.max() > best_count:
            i = int(count.argmax())
            best, best_count = (n[i], float(d[i])), int(count[i])
    if best is None or best_count < min_share * len(points):
        return None
    n, d = best
    on = np.abs(points @ n + d) < tol  # refit to the inliers (least squares), keeping the orientation
    centroid = points[on].mean(0)
    n_fit = np.linalg.svd(points[on] - centroid)[2][-1]
    n_fit = n_fit if n_fit @ n > 0 else -n_fit
    return n_fit, -float(n_fit @ centroid)


@dataclass
class ObjectRegion:
    """The object's region in the normalised frame: a ball (centre [3], radius) and, when the object stands
    on one, the support plane n.x + d = 0 with the object on the positive side (``plane`` = n + [d], or None)."""

    centre: list
    radius: float
    plane: list | None = None
    n_points: int = 0
    source: str = "points"

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> "ObjectRegion":
        return cls(**d)

    def transformed(self, M: np.ndarray) -> "ObjectRegion":
        """The region in the frame y = M x = s R x + t of a 4x4 similarity M: the ball mapped, the plane's
        normal turned (n' = R n) and its offset d' = s d - n'.t."""
        from .cameras import sim3_from_matrix, transform_points

        s, R, t = sim3_from_matrix(M)
        plane = None
        if self.plane is not None:
            n = R @ np.asarray(self.plane[:3], np.float64)
            plane = [*n.tolist(), s * self.plane[3] - float(n @ t)]
        centre = transform_points(M, np.asarray(self.centre, np.float64)[None])[0]
        return ObjectRegion(centre.tolist(), s * self.radius, plane, self.n_points, self.source)

    def contains(self, x: np.ndarray, plane_margin: float | None = 0.0) -> np.ndarray:
        """bool [P]: points x [P,3] inside the ball and above the support plane by ``plane_margin`` (None: the
        ball alone, the support kept)."""
        inside = np.linalg.norm(np.asarray(x) - np.asarray(self.centre), axis=1) <= self.radius
        if self.plane is not None and plane_margin is not None:
            inside &= np.asarray(x) @ np.asarray(self.plane[:3]) + self.plane[3] > plane_margin
        return inside


def locate(points: np.ndarray, K: np.ndarray, w2c: np.ndarray, sizes: np.ndarray, min_seen: float = 0.5,
           radius_percentile: float = 99.0, radius_margin: float = 0.15, plane_tol: float = 0.02,
           find_plane: bool = True, seen: np.ndarray | None = None) -> tuple[ObjectRegion, np.ndarray]:
    """The object's region from SfM points [P,3] and the views that made them (K, w2c, sizes as in
    :func:`seen_fraction`), in their frame; and the bool [P] of the object's points: those at least
    ``min_seen`` of the views see (``seen``, when the caller has it already: the fraction does not change
    under a similarity). Radius: the ``radius_percentile``-th distance of those points from their
    median, plus ``radius_margin`` of it; support plane within ``plane_tol`` of that radius."""
    points = np.asarray(points, np.float64)
    if seen is None:
        seen = seen_fraction(points, K, w2c, sizes) >= min_seen if len(points) else np.zeros(0, bool)
    source = "common frustum"
    if seen.sum() < 20:  # too few points in every view's frame: use all of them
        seen, source = np.ones(len(points), bool), "all points"
    obj = points[seen]
    if len(obj) == 0:
        c = aim_point(w2c)
        return ObjectRegion(c.tolist(), float(np.median(np.linalg.norm(camera_centers(w2c) - c, axis=1))) / 2,
                            None, 0, "aim point"), seen
    centre = np.median(obj, 0)
    radius = float(np.percentile(np.linalg.norm(obj - centre, axis=1), radius_percentile)) * (1 + radius_margin)
    plane = None
    if find_plane:
        near = points[np.linalg.norm(points - centre, axis=1) <= radius]
        found = support_plane(near, w2c, plane_tol * radius)
        if found is not None:
            plane = [*found[0].tolist(), found[1]]
    return ObjectRegion(centre.tolist(), radius, plane, int(seen.sum()), source), seen
