"""Pose initialisation (METHOD.md "Pose initialisation"): pure geometry, no neural code.

The method's own logic around COLMAP (:mod:`manifoldneus.sfm.mapper` does the structure from motion),
all returning world-to-camera poses in the conventions of :mod:`manifoldneus.geometry.cameras` (OpenCV
camera frame, ``w2c``, pixel centres at +0.5):

* :func:`init_from_matches` ("matches", the default for the anchors): our verified matches of the
  anchor views (and of the views that bridge them, chosen by ``stages.anchors.init_views``) go into
  a COLMAP database; COLMAP's incremental mapper and bundle adjustment pose them (intrinsics fixed
  or refined); then the gauge: a similarity that puts the middle of the points' robust box at the origin
  (or their median, :class:`GaugeOptions` ``centre``) and scales the box's half diagonal
  (:func:`manifoldneus.geometry.cameras.gauge_from_points`; the foreground points when masks exist) to
  ``radius`` (0.8), so the object sits inside the unit sphere. Views COLMAP cannot register get a
  registered neighbour's pose, and the reason.
* :func:`identity_init` ("identity", the paper's wording): every view at the same canonical pose.
* Successors: :func:`place_successor`: COLMAP's absolute pose of a view's matches to already-optimised
  views, their keypoints lifted to 3D (:func:`successor_correspondences`, with depth rendered from the
  current model or with given 3D points), else :func:`fallback_neighbour_pose` (the best-matching
  optimised neighbour's pose); it reports what happened.

Pair input (the ``matching`` stage's layout, ``stages/matching.py``): one :class:`PairMatch` per
pair ``(i, j)`` with the verified inliers as keypoint-index pairs ``[M,2]`` (index in view i,
index in view j) and the relative pose of the essential matrix, camera i -> camera j:
``x_j = R @ x_i + t`` with ``|t| = 1`` (``w2c_j = [R | t] @ w2c_i`` up to the scale of t).
:func:`pairs_from_matches` builds the list from the arrays of ``matches.zarr``
(``artifacts.load_matches``); ``manifoldneus/posefree.load_inputs`` shows the whole use.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Sequence

import numpy as np

from manifoldneus.geometry import object_region
from manifoldneus.sfm import mapper as sfm
from manifoldneus.geometry.cameras import gauge_from_points, lift_points, sim3_matrix, to_4x4, transform_w2c
from manifoldneus.scheduling.mavos import covisibility_matrix

# --------------------------------------------------------------------------- inputs


class PairMatch(NamedTuple):
    """Verified matches of one view pair (global view indices) and its relative pose.

    ``matches`` [M,2] int: (keypoint index in view i, keypoint index in view j).
    ``R`` [3,3], ``t`` [3]: camera i -> camera j, ``x_j = R @ x_i + t``, ``|t| = 1``.
    ``valid``: False when the pair has matches but no relative pose (fundamental-only)."""

    i: int
    j: int
    matches: np.ndarray
    R: np.ndarray
    t: np.ndarray
    valid: bool = True


def pairs_from_matches(arrays: dict, min_inliers: int = 1) -> list[PairMatch]:
    """``matches.zarr`` arrays (``artifacts.load_matches(path)[0]``) -> list of :class:`PairMatch`
    for the pairs with at least ``min_inliers`` verified inliers."""
    pairs = np.asarray(arrays["pairs"])
    off = np.asarray(arrays["inlier_offsets"])
    inl = np.asarray(arrays["inlier_matches"])
    valid = np.asarray(arrays.get("pose_valid", np.ones(len(pairs), bool)))
    return [PairMatch(int(pairs[p, 0]), int(pairs[p, 1]), np.asarray(inl[off[p]:off[p + 1]], np.int64),
                      np.asarray(arrays["R"][p], np.float64), np.asarray(arrays["t"][p], np.float64), bool(valid[p]))
            for p in range(len(pairs)) if off[p + 1] - off[p] >= max(min_inliers, 1)]


def covisibility_from_pairs(pairs: Sequence, n_views: int) -> np.ndarray:
    """W [N,N]: :func:`~manifoldneus.scheduling.mavos.covisibility_matrix` of the pairs' verified inlier counts."""
    return covisibility_matrix(n_views, [(p.i, p.j) for p in pairs], [len(p.matches) for p in pairs])


# --------------------------------------------------------------------------- anchors


@dataclass
class InitResult:
    """Output of :func:`init_from_matches`. Arrays follow ``view_ids`` order."""

    view_ids: list[int]
    w2c: np.ndarray  # [V,4,4] in the gauge frame (every view has a pose; see `placed`/`method`)
    placed: np.ndarray  # bool [V]: pose from the reconstruction (False: fallback pose, see method)
    method: list[str]  # per view: mapped | fallback:<view id> | identity
    points: np.ndarray  # [P,3] the reconstruction's 3D points (gauge frame)
    point_in_mask: np.ndarray  # bool [P]: the gauge's points (observed mostly in the masks, or in the common frustum)
    gauge: np.ndarray  # [4,4] similarity reconstruction frame -> gauge frame (y = s x + t)
    K: np.ndarray  # [V,3,3] the intrinsics after bundle adjustment (the input K where held fixed)
    unplaced: list[int]  # global ids of the views the reconstruction could not place
    why_unplaced: dict = field(default_factory=dict)  # global id -> reason
    diagnostics: dict = field(default_factory=dict)  # JSON-able numbers (registration, timings, K, ...)
    # the observations of `points`: view (global id), point index, pixel [O,2]
    obs_view: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    obs_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    obs_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    # [V,4] OpenCV lens distortion after bundle adjustment (zeros unless a radial term was refined and freed)
    distortion: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))


def _foreground_points(obs: dict, masks: Sequence[np.ndarray], n_points: int) -> np.ndarray:
    """bool [P]: points whose observations fall mostly inside the masks (obs_view indexes masks)."""
    fg = np.ones(len(obs["obs_view"]), bool)
    for v, m in enumerate(masks):
        sel = obs["obs_view"] == v
        if m is None or not sel.any():
            continue
        m = np.asarray(m, bool)
        uv = obs["obs_uv"][sel]
        col = np.clip(np.floor(uv[:, 0]).astype(int), 0, m.shape[1] - 1)
        row = np.clip(np.floor(uv[:, 1]).astype(int), 0, m.shape[0] - 1)
        fg[sel] = m[row, col]
    n_obs = np.bincount(obs["obs_point"], minlength=n_points)
    n_fg = np.bincount(obs["obs_point"], weights=fg, minlength=n_points)
    return n_fg > 0.5 * np.maximum(n_obs, 1)


@dataclass(frozen=True)
class MapperOptions:
    """How COLMAP's mapper and the last bundle adjustment run (:func:`manifoldneus.sfm.mapper.map_views`)."""

    refine: tuple[str, ...] = ()  # intrinsics bundle adjustment may change (``sfm.REFINABLE``)
    prior_focal: bool = True  # K's focal length is known (EXIF or calibration), not a guess
    reproj_px: float = 3.0
    min_angle_deg: float = 1.5
    min_num_matches: int = 15
    seed: int = 0
    final_ba_loss: str = "cauchy"  # the robust loss of a last adjustment after COLMAP's plain least squares
    final_ba_scale_px: float = 0.5
    principal_point_p: float | None = None  # the likelihood-ratio tests of map_views
    radial_p: float | None = None


@dataclass(frozen=True)
class GaugeOptions:
    """The unit-sphere gauge of the mapper's points (:func:`manifoldneus.geometry.cameras.gauge_from_points`)."""

    radius: float = 0.8
    percentile: float = 99.0
    centre: str = "box"  # box | median
    object_min_seen: float = 0.5  # without masks: the points at least this fraction of the views see


def init_from_matches(view_ids: Sequence[int], K: np.ndarray, keypoints: Sequence[np.ndarray], pairs: Sequence,
                      W: np.ndarray | None = None, *, sizes: np.ndarray | None = None,
                      mapper: MapperOptions = MapperOptions(), gauge: GaugeOptions = GaugeOptions(),
                      masks: Sequence[np.ndarray] | None = None, log: Callable[[str], None] | None = None,
                      ) -> InitResult:
    """Initial poses of the views ``view_ids`` (the anchors) from our verified matches, by
    COLMAP's incremental mapper (:func:`manifoldneus.sfm.mapper.map_views`: initial pair, registration,
    triangulation, bundle adjustment, as ``mapper`` says), then our gauge.

    K [N,3,3], keypoints (length N, [K_v,2] pixels), pairs (:class:`PairMatch`) and W [N,N] are
    indexed by **global** view id; only pairs with both views in ``view_ids`` are used. sizes [N,2]
    (H, W) default to twice the principal point. masks (optional, one [H,W] bool per entry of
    ``view_ids``): the gauge's robust extent is then measured on the points seen mostly inside the
    foreground (when there are >= 20 of them); without masks, on the points at least
    ``gauge.object_min_seen`` of the registered views see (:mod:`manifoldneus.geometry.object_region`), whose
    region (ball and support plane, gauge frame) the diagnostics carry as ``object_region``.

    Gauge (:func:`manifoldneus.geometry.cameras.gauge_from_points`): y = s (x - c), s maps the half diagonal of the
    points' box between their ``100 - gauge.percentile``-th and ``gauge.percentile``-th percentiles per axis to
    gauge.radius, c the box's middle or (``gauge.centre="median"``) the points' median, pulled towards the box's
    middle as far as keeps the box in the unit sphere: the object sits inside the unit sphere. Views COLMAP does
    not register (outside its largest model) keep the pose of their best-matching registered neighbour (method ``fallback:<id>``) and are listed
    in ``unplaced`` with the reason in ``why_unplaced``.
    """
    say = log or (lambda s: None)
    view_ids = [int(v) for v in view_ids]
    V = len(view_ids)
    if V == 0:
        raise ValueError("init_from_matches: no views")
    if len(set(view_ids)) != V:
        raise ValueError("init_from_matches: duplicate view ids")
    K = np.asarray(K, np.float64)
    loc = {g: a for a, g in enumerate(view_ids)}
    pairs = [p for p in pairs if p.i in loc and p.j in loc and p.i != p.j]
    if W is None:
        W = covisibility_from_pairs(pairs, int(max(max(view_ids) + 1, len(K))))
    Wsub = np.asarray(W, np.float64)[np.ix_(view_ids, view_ids)].copy()
    np.fill_diagonal(Wsub, 0.0)
    Kl = K[view_ids]
    sizes_l = (np.round(2 * Kl[:, [1, 0], 2]).astype(int) if sizes is None
               else np.asarray(sizes, int).reshape(-1, 2)[view_ids])
    local_pairs = [p._replace(i=loc[p.i], j=loc[p.j]) for p in pairs]
    names = [f"{g:06d}" for g in view_ids]
    m = mapper
    rec = sfm.map_views(names, Kl, sizes_l, [keypoints[g] for g in view_ids], local_pairs, refine=m.refine,
                        prior_focal=m.prior_focal, seed=m.seed, min_num_matches=m.min_num_matches,
                        reproj_px=m.reproj_px, min_tri_angle_deg=m.min_angle_deg, final_ba_loss=m.final_ba_loss,
                        final_ba_scale_px=m.final_ba_scale_px, principal_point_p=m.principal_point_p,
                        radial_p=m.radial_p, log=say)
    placed = rec["registered"]
    pts = rec["points"]

    w2c = np.array(rec["w2c"])
    reg = np.flatnonzero(placed)
    in_mask = np.ones(len(pts), bool)
    if masks is not None and len(pts):
        in_mask = _foreground_points(rec, masks, len(pts))
    elif len(pts) and len(reg):  # no masks: the points in the registered views' common frustum
        in_mask = object_region.seen_fraction(pts, rec["K"][reg], w2c[reg], sizes_l[reg]) >= gauge.object_min_seen
    gpts = pts[in_mask] if in_mask.sum() >= 20 else pts
    if len(gpts) >= 3:
        s, centre = gauge_from_points(gpts, gauge.radius, gauge.percentile, gauge.centre)
    else:  # no structure: the views look at the origin from identity_init's distance
        s, centre = 1.0, np.zeros(3)
        w2c[:] = identity_init(V)
        placed = np.zeros(V, bool)
    G = sim3_matrix(s, np.eye(3), -s * centre)
    w2c = transform_w2c(w2c, s, np.eye(3), -s * centre)
    region = None
    if len(pts) and len(reg):
        region, _ = object_region.locate(s * (pts - centre), rec["K"][reg], w2c[reg], sizes_l[reg], gauge.object_min_seen,
                                         seen=None if masks is not None else in_mask)

    method = ["mapped" if placed[a] else "" for a in range(V)]
    unplaced, why = [], {}
    for a in np.flatnonzero(~placed):
        g = view_ids[a]
        unplaced.append(g)
        linked = [n for n in np.argsort(-Wsub[a]) if Wsub[a, n] > 0]
        nb = [n for n in linked if placed[n]]
        why[g] = ("no verified matches to the other views" if not linked else
                  "its matches link it only to views COLMAP did not register" if not nb else
                  f"COLMAP could not register it ({int(Wsub[a, nb[0]])} verified matches to its best registered "
                  f"neighbour {view_ids[nb[0]]}; fewer than {m.min_num_matches} or a failed pose)")
        w2c[a] = w2c[nb[0]] if nb else w2c[a]
        method[a] = f"fallback:{view_ids[nb[0]]}" if nb else "identity"
    for g in unplaced:
        say(f"  view {g} not registered: {why[g]}")

    refined_K = rec["K"]
    diag = {
        "n_views": V,
        "n_placed": int(placed.sum()),
        "n_pairs": len(pairs),
        "n_models": int(rec["n_models"]),
        "n_points": int(len(pts)),
        "n_points_in_mask": int(in_mask.sum()),
        "n_observations": int(len(rec["obs_view"])),
        "mean_reproj_px": rec["mean_reproj_px"],
        "refine_intrinsics": list(m.refine),
        "principal_point_test": rec["principal_point_test"],
        "radial_test": rec["radial_test"],
        "K": refined_K[np.flatnonzero(placed)[0]].tolist() if placed.any() else Kl[0].tolist(),
        "gauge_scale": float(s),
        "gauge_centre": centre.tolist(),
        "gauge_points": ("all" if in_mask.sum() < 20 else "foreground" if masks is not None else "common frustum"),
        "object_region": None if region is None else region.to_json(),
        "methods": {k: [m.split(":")[0] for m in method].count(k) for k in {m.split(":")[0] for m in method}},
        "seconds_total": rec["seconds"],
    }
    return InitResult(
        view_ids=view_ids, w2c=w2c, placed=placed.copy(), method=method, points=s * (pts - centre),
        point_in_mask=in_mask, gauge=G, K=refined_K, unplaced=unplaced, why_unplaced=why, diagnostics=diag,
        obs_view=np.asarray(view_ids, np.int64)[rec["obs_view"]], obs_point=rec["obs_point"], obs_uv=rec["obs_uv"],
        distortion=sfm.opencv_distortion(rec["extra"]),
    )


# --------------------------------------------------------------------------- identity


def identity_init(n: int, distance: float = 3.0) -> np.ndarray:
    """The paper's "identity" initialisation: n copies of one canonical pose, [n,4,4].

    Rotation = identity (camera axes = world axes: x right, y down, the camera looks along +z),
    camera centre at (0, 0, -distance), so every camera looks at the origin (the object's centre in
    the unit-sphere frame) from ``distance`` (default 3, outside the unit sphere):
    ``w2c = [I | (0, 0, distance)]``."""
    w2c = np.tile(np.eye(4), (int(n), 1, 1))
    w2c[:, 2, 3] = float(distance)
    return w2c


# --------------------------------------------------------------------------- successors


def successor_correspondences(
    view: int,
    keypoints: Sequence[np.ndarray],
    pairs: Sequence,
    placed: dict,
    K: np.ndarray | None = None,
    depth_at: Callable[[int, np.ndarray], np.ndarray] | None = None,
    points3d: dict | None = None,
    ray_distance: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D-3D correspondences of ``view`` from its matches to the placed views.

    placed: {global view id: w2c [4,4]} of the already-optimised views. The placed view's matched
    keypoints are lifted either with ``depth_at(j, uv [M,2]) -> depth [M]`` (z-depth, e.g. rendered
    from the current SDF; NaN/<= 0 = no surface) using K[j] and placed[j], or looked up in
    ``points3d[j]`` ([n_keypoints_j, 3] world points, NaN = unknown). Returns (uv of ``view`` [M,2],
    X [M,3], source view [M]) with non-finite points removed."""
    if depth_at is None and points3d is None:
        raise ValueError("successor_correspondences: give depth_at or points3d")
    uvs, Xs, srcs = [], [], []
    kv = np.asarray(keypoints[view], np.float64)
    for p in pairs:
        if view not in (p.i, p.j) or len(p.matches) == 0:
            continue
        j = p.j if p.i == view else p.i
        if j not in placed:
            continue
        mv, mj = (p.matches[:, 0], p.matches[:, 1]) if p.i == view else (p.matches[:, 1], p.matches[:, 0])
        uv_j = np.asarray(keypoints[j], np.float64)[mj]
        if points3d is not None and j in points3d:
            X = np.asarray(points3d[j], np.float64)[mj]
        elif depth_at is not None:
            X = lift_points(K[j], placed[j], uv_j, depth_at(j, uv_j), ray_distance)
        else:
            continue
        uvs.append(kv[mv])
        Xs.append(X)
        srcs.append(np.full(len(mv), j))
    if not uvs:
        return np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, np.int64)
    uv, X, src = np.concatenate(uvs), np.concatenate(Xs), np.concatenate(srcs)
    ok = np.isfinite(X).all(1)
    return uv[ok], X[ok], src[ok]


def fallback_neighbour_pose(view: int, placed: dict, W: np.ndarray) -> tuple[np.ndarray | None, int | None]:
    """The pose of ``view``'s best-matching placed neighbour (largest W[view, j] > 0 over j in
    ``placed``, a {global id: w2c} dict). Returns (w2c copy, neighbour id) or (None, None)."""
    near = [j for j in placed if j != view and W[view, j] > 0]
    if not near:
        return None, None
    best = max(near, key=lambda j: W[view, j])
    return to_4x4(placed[best]), int(best)


def place_successor(
    view: int,
    K: np.ndarray,
    keypoints: Sequence[np.ndarray],
    pairs: Sequence,
    placed: dict,
    W: np.ndarray | None = None,
    *,
    depth_at: Callable[[int, np.ndarray], np.ndarray] | None = None,
    points3d: dict | None = None,
    ray_distance: bool = False,
    reproj_px: float = 3.0,
    min_inliers: int = 12,
) -> tuple[np.ndarray | None, dict]:
    """Initial pose of a successor view: COLMAP's absolute pose (:func:`manifoldneus.sfm.mapper.absolute_pose`) of its matches to the placed (optimised) views
    lifted to 3D, else the best-matching placed neighbour's pose. K, keypoints, pairs and W use
    global view ids (W defaults to the pairs' inlier counts). Never raises for a view that cannot be
    placed: returns (None, info) with ``info["method"] == "unplaced"`` when it has no placed neighbour.
    info: method ("pnp" | "fallback" | "unplaced"), n_correspondences, n_inliers, neighbour."""
    uv, X, src = successor_correspondences(view, keypoints, pairs, placed, K, depth_at, points3d, ray_distance)
    w2c, n_in = sfm.absolute_pose(K[view], uv, X, reproj_px=reproj_px, min_inliers=min_inliers)
    info = {"view": int(view), "n_correspondences": int(len(uv)), "n_inliers": int(n_in), "neighbour": None}
    if w2c is not None:
        info["method"] = "pnp"
        return w2c, info
    if W is None:
        W = covisibility_from_pairs(pairs, int(max([view, *placed, len(K) - 1]) + 1))
    w2c, nb = fallback_neighbour_pose(view, placed, W)
    info["neighbour"] = nb
    info["method"] = "fallback" if w2c is not None else "unplaced"
    return w2c, info
