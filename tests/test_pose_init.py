"""Pose initialisation (manifoldneus/sfm/pose_init.py) on the synthetic scene with exact ground truth.

One session fixture renders a 20-view 192 px scene and runs the project's SIFT + verified
matching on it; GT poses and depth are used only to evaluate (and, for the successor test, as
the "rendered" depth of already-placed views)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from manifoldneus.sfm import pose_init as PI
from manifoldneus.sfm import mapper as sfm
from manifoldneus.geometry.cameras import camera_centers, lift_points, look_at_w2c, project_points, rotation_angle_deg, transform_w2c
from manifoldneus.geometry.pose_metrics import evaluate_poses

N_VIEWS, RES = 20, 192


@pytest.fixture(scope="session")
def scene_matches():
    from manifoldneus.data import synthetic
    from stages.features import extract_all
    from stages.matching import exhaustive_pairs, match_pairs

    s = synthetic.make_scene(seed=0, n_views=N_VIEWS, resolution=RES)
    feats = extract_all(s.images, workers=2)
    res = match_pairs(feats, exhaustive_pairs(N_VIEWS), s.K, workers=2)
    pairs = PI.pairs_from_matches(res)
    kps = [f["keypoints"] for f in feats]
    W = PI.covisibility_from_pairs(pairs, N_VIEWS)
    return s, kps, pairs, W


@pytest.fixture(scope="session")
def init_all(scene_matches):
    s, kps, pairs, W = scene_matches
    return PI.init_from_matches(list(range(N_VIEWS)), s.K, kps, pairs, W)


def _greedy_anchors(W: np.ndarray, k: int) -> list[int]:
    """A connected, well co-visible subset (what MaVOS anchors look like): start at the largest
    c_i, add the view with the most matches to the set."""
    sel = [int(np.argmax(W.sum(1)))]
    while len(sel) < k:
        score = W[:, sel].sum(1)
        score[sel] = -1
        sel.append(int(np.argmax(score)))
    return sel


def _centre_err_frac(w2c_est, w2c_gt, valid=None):
    ev = evaluate_poses(w2c_est, w2c_gt, valid=valid)
    dist = np.linalg.norm(camera_centers(w2c_gt), axis=1).mean()  # GT camera distance to the object centre
    return ev, np.nanmean(ev["center_err"]) / dist, np.nanmax(ev["center_err"]) / dist


# --------------------------------------------------------------------------- geometry units


def test_pair_convention_matches_ground_truth(scene_matches):
    """The matching artifact's (R, t) maps camera i to camera j (x_j = R x_i + t, |t| = 1)."""
    s, kps, pairs, W = scene_matches
    p = max(pairs, key=lambda q: len(q.matches))
    R_gt = s.w2c[p.j][:3, :3] @ s.w2c[p.i][:3, :3].T
    t_gt = s.w2c[p.j][:3, 3] - R_gt @ s.w2c[p.i][:3, 3]
    # two-view rotations of these narrow-FOV cameras are off by a few degrees; the inverse would be ~30 deg off
    assert rotation_angle_deg(p.R.T @ R_gt) < 6.0
    assert np.degrees(np.arccos(np.clip(p.t @ t_gt / np.linalg.norm(t_gt), -1, 1))) < 15.0


def test_lift_points_roundtrip():
    from manifoldneus.data.synthetic import camera_poses, intrinsics

    K, w2c = intrinsics(100, 100), camera_poses(3)[1]
    X = np.array([[0.1, 0.2, 0.0], [-0.3, 0.1, 0.2]])
    Xc = X @ w2c[:3, :3].T + w2c[:3, 3]
    uv = project_points(K, Xc)
    assert np.allclose(lift_points(K, w2c, uv, Xc[:, 2]), X)
    assert np.allclose(lift_points(K, w2c, uv, np.linalg.norm(Xc, axis=1), ray_distance=True), X)
    assert np.isnan(lift_points(K, w2c, uv, np.array([np.nan, -1.0]))).all()


def test_database_round_trip(scene_matches, tmp_path):
    """Our keypoints and verified matches go into a COLMAP database and come back unchanged:
    one shared camera (one K, one size), every view's keypoints, every pair's inlier set."""
    import pycolmap

    s, kps, pairs, W = scene_matches
    names = [f"view{v}" for v in range(N_VIEWS)]
    sizes = np.tile([RES, RES], (N_VIEWS, 1))
    ids = sfm.write_database(tmp_path / "db.db", names, s.K, sizes, kps, pairs)
    db = pycolmap.Database.open(str(tmp_path / "db.db"))
    try:
        assert db.num_cameras() == 1 and db.num_images() == N_VIEWS
        cam = db.read_all_cameras()[0]
        assert np.allclose(sfm.K_of_camera(cam)[0], s.K[0]) and (cam.width, cam.height) == (RES, RES)
        for v in range(N_VIEWS):
            assert db.read_image(ids[v]).name == names[v]
            assert np.array_equal(db.read_keypoints(ids[v])[:, :2], np.asarray(kps[v], np.float32))
        assert db.num_verified_image_pairs() == len(pairs)
        for p in pairs:
            back = db.read_two_view_geometry(ids[p.i], ids[p.j]).inlier_matches
            assert np.array_equal(back, p.matches)
    finally:
        db.close()


def test_identity_init_looks_at_origin():
    w2c = PI.identity_init(5, distance=3.0)
    assert w2c.shape == (5, 4, 4)
    assert np.allclose(w2c, w2c[0])
    C = camera_centers(w2c)
    assert np.allclose(C, [0, 0, -3.0])
    # optical axis (third row of R, OpenCV +z) points from the centre to the origin; the origin projects to the centre
    axis = w2c[0, 2, :3]
    assert np.allclose(axis, -C[0] / np.linalg.norm(C[0]))
    assert np.allclose(w2c[0, :3, :3] @ np.zeros(3) + w2c[0, :3, 3], [0, 0, 3.0])
    # image up (-y of the camera) is world -y
    assert np.allclose(w2c[0, :3, :3].T @ np.array([0, -1.0, 0]), [0, -1.0, 0])


# --------------------------------------------------------------------------- anchors from matches


def test_init_from_matches_all_views(init_all, scene_matches):
    s, *_ = scene_matches
    out = init_all
    assert out.w2c.shape == (N_VIEWS, 4, 4)
    assert out.placed.all() and not out.unplaced
    ev, c_mean, c_max = _centre_err_frac(out.w2c, s.w2c)
    assert ev["summary"]["rot_err_deg"]["mean"] < 1.0, ev["summary"]["rot_err_deg"]
    assert c_mean < 0.02 and c_max < 0.05, (c_mean, c_max)
    d = out.diagnostics
    assert d["n_models"] == 1 and d["mean_reproj_px"] < 0.5
    assert np.allclose(out.K, s.K)  # intrinsics held fixed unless asked to refine
    json.dumps(out.diagnostics)  # goes into a manifest as is


def test_unit_sphere_gauge(init_all):
    out = init_all
    assert len(out.points) > 200
    # no masks: the gauge's points are those half the views see in their frame; their box between the 1st and
    # the 99th percentiles is centred at the origin, its half diagonal at 0.8
    assert out.diagnostics["gauge_points"] == "common frustum"
    P = out.points[out.point_in_mask]
    assert 0.5 * len(out.points) < len(P) < len(out.points)
    lo, hi = np.percentile(P, [1, 99], axis=0)
    assert np.linalg.norm(lo + hi) < 1e-9
    assert abs(0.5 * np.linalg.norm(hi - lo) - 0.8) < 1e-6
    # cameras are outside the unit sphere and look at the object
    C = camera_centers(out.w2c)
    assert (np.linalg.norm(C, axis=1) > 1.5).all()
    z_centre = out.w2c[:, 2, :3] @ np.zeros(3) + out.w2c[:, 2, 3]
    assert (z_centre > 0).all()
    # the gauge matrix maps reconstruction-frame poses to the returned ones (pure scale + shift)
    G = out.gauge
    assert np.allclose(G[:3, :3], G[0, 0] * np.eye(3))


def test_init_from_matches_anchor_subset(scene_matches):
    s, kps, pairs, W = scene_matches
    anchors = _greedy_anchors(W, 7)
    out = PI.init_from_matches(anchors, s.K, kps, pairs, W)
    assert out.placed.all()
    ev, c_mean, _ = _centre_err_frac(out.w2c, s.w2c[anchors])
    assert ev["summary"]["rot_err_deg"]["mean"] < 1.0
    assert c_mean < 0.02


def test_unplaceable_anchor_is_reported(scene_matches):
    s, kps, pairs, W = scene_matches
    anchors = _greedy_anchors(W, 6)
    lone = next(v for v in range(N_VIEWS) if v not in anchors and W[v, anchors].max() > 0)
    # the lone view keeps only 4 matches to its best anchor (and none to the others): it cannot be placed
    nb = anchors[int(np.argmax(W[lone, anchors]))]
    kept = []
    for p in pairs:
        if lone in (p.i, p.j):
            if {p.i, p.j} == {lone, nb}:
                kept.append(p._replace(matches=p.matches[:4]))
            continue
        kept.append(p)
    out = PI.init_from_matches(anchors + [lone], s.K, kps, kept)
    assert out.unplaced == [lone]
    assert not out.placed[-1] and out.placed[:-1].all()
    assert out.method[-1] == f"fallback:{nb}"
    assert "4 verified matches" in out.why_unplaced[lone]
    assert np.allclose(out.w2c[-1], out.w2c[anchors.index(nb)])


# --------------------------------------------------------------------------- successors


def _depth_sampler(depth_maps):
    """depth_at(view, uv): bilinear GT z-depth (NaN where a neighbour pixel is background)."""

    def depth_at(v, uv):
        D = depth_maps[v]
        x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5  # pixel centres at +0.5
        x0 = np.clip(np.floor(x).astype(int), 0, D.shape[1] - 2)
        y0 = np.clip(np.floor(y).astype(int), 0, D.shape[0] - 2)
        fx, fy = x - x0, y - y0
        d = np.stack([D[y0, x0], D[y0, x0 + 1], D[y0 + 1, x0], D[y0 + 1, x0 + 1]], 1).astype(np.float64)
        w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
        out = (d * w).sum(1)
        out[(d <= 0).any(1)] = np.nan
        return out

    return depth_at


def test_place_successor_pnp_with_depth(scene_matches):
    s, kps, pairs, W = scene_matches
    held = 13
    placed = {v: s.w2c[v] for v in range(N_VIEWS) if v != held}
    w2c, info = PI.place_successor(held, s.K, kps, pairs, placed, W, depth_at=_depth_sampler(s.depth))
    assert info["method"] == "pnp", info
    assert info["n_inliers"] >= 50
    assert rotation_angle_deg(w2c[:3, :3] @ s.w2c[held][:3, :3].T) < 1.0
    C, Cg = camera_centers(w2c[None])[0], camera_centers(s.w2c[held][None])[0]
    assert np.linalg.norm(C - Cg) < 0.02 * np.linalg.norm(Cg)

    # the same in a similarity-transformed world (what the current model's frame looks like)
    sc, tg = 0.37, np.array([0.1, -0.2, 0.3])
    Rg = look_at_w2c(np.array([1.0, 2.0, 0.5]), np.zeros(3), np.array([0, 0, 1.0]))[:3, :3]
    placed2 = {v: transform_w2c(p[None], sc, Rg, tg)[0] for v, p in placed.items()}
    depth_scaled = [d * sc for d in s.depth]
    w2c2, info2 = PI.place_successor(held, s.K, kps, pairs, placed2, W, depth_at=_depth_sampler(depth_scaled))
    expect = transform_w2c(s.w2c[held][None], sc, Rg, tg)[0]
    assert info2["method"] == "pnp"
    assert rotation_angle_deg(w2c2[:3, :3] @ expect[:3, :3].T) < 1.0


def test_absolute_pose_with_points_and_too_few(scene_matches):
    s, kps, pairs, W = scene_matches
    held = 5
    placed = {v: s.w2c[v] for v in range(N_VIEWS) if v != held}
    uv, X, src = PI.successor_correspondences(held, kps, pairs, placed, s.K, depth_at=_depth_sampler(s.depth))
    assert len(uv) > 100 and set(np.unique(src)) <= set(placed)
    w2c, n = sfm.absolute_pose(s.K[held], uv, X)
    assert w2c is not None and n > 50
    assert rotation_angle_deg(w2c[:3, :3] @ s.w2c[held][:3, :3].T) < 1.0
    # precomputed 3D points (per placed view and keypoint) instead of a depth callable
    depth_at = _depth_sampler(s.depth)
    pts3d = {}
    for v in placed:
        uv_v = np.asarray(kps[v], float)
        pts3d[v] = lift_points(s.K[v], s.w2c[v], uv_v, depth_at(v, uv_v))
    w2c_b, info_b = PI.place_successor(held, s.K, kps, pairs, placed, W, points3d=pts3d)
    assert info_b["method"] == "pnp" and rotation_angle_deg(w2c_b[:3, :3] @ s.w2c[held][:3, :3].T) < 1.0
    # too few correspondences: None, no crash
    w2c_none, n_none = sfm.absolute_pose(s.K[held], uv[:6], X[:6])
    assert w2c_none is None and n_none <= 6


def test_fallback_neighbour_pose(scene_matches):
    s, kps, pairs, W = scene_matches
    view = 9
    neighbours = [j for j in np.argsort(-W[view]) if W[view, j] > 0]
    best, second = int(neighbours[0]), int(neighbours[1])
    # the view keeps only 5 matches with each of two placed views: PnP fails, the best-matching one is used
    few = [p._replace(matches=p.matches[:5]) for p in pairs if {p.i, p.j} in ({view, best}, {view, second})]
    placed = {best: s.w2c[best], second: s.w2c[second]}
    w2c, info = PI.place_successor(view, s.K, kps, few, placed, W, depth_at=_depth_sampler(s.depth))
    assert info["method"] == "fallback" and info["neighbour"] == best
    assert np.allclose(w2c, s.w2c[best])
    nb_pose, nb = PI.fallback_neighbour_pose(view, placed, W)
    assert nb == best and np.allclose(nb_pose, s.w2c[best])
    # no placed neighbour at all: reported as unplaced, no crash
    far = {v: s.w2c[v] for v in range(N_VIEWS) if W[view, v] == 0 and v != view}
    w2c_u, info_u = PI.place_successor(view, s.K, kps, pairs, far, W, depth_at=_depth_sampler(s.depth))
    assert w2c_u is None and info_u["method"] == "unplaced"


def test_weakly_linked_anchors_are_initialised_with_the_views_that_bridge_them():
    from stages.anchors import init_views

    # anchors {0, 1} and {4, 5}: no edge between the two pairs; views 2-3 bridge them strongly,
    # view 6 hangs off view 2 (on the spanning tree but on no anchor-to-anchor path), 7 is held out
    W = np.zeros((8, 8))
    for a, b, w in ((0, 1, 300), (4, 5, 300), (1, 2, 200), (2, 3, 200), (3, 4, 200), (2, 6, 250), (0, 7, 400),
                    (7, 5, 400)):
        W[a, b] = W[b, a] = w
    trainable = [0, 1, 2, 3, 4, 5, 6]
    assert init_views([0, 1, 4, 5], W, trainable, min_matches=50) == [0, 1, 2, 3, 4, 5]
    assert init_views([0, 1, 4, 5], W, trainable, min_matches=0) == [0, 1, 4, 5]  # off
    W[1, 4] = W[4, 1] = 20  # linked now, but by 20 matches: still bridged by the strong path
    assert init_views([0, 1, 4, 5], W, trainable, min_matches=50) == [0, 1, 2, 3, 4, 5]
    assert init_views([0, 1, 4, 5], W, trainable, min_matches=10) == [0, 1, 4, 5]  # strong enough


def test_principal_point_off_the_centre_is_refined():
    """Photos whose principal point is not the image centre (DTU's is 12 px off), started at the centre: with
    the principal point refined it is found and the rotations are as good as with the true K; with the focal
    length alone refined, the offset turns every camera by ~1 deg."""
    from manifoldneus.data import synthetic
    from stages.features import extract_all
    from stages.matching import exhaustive_pairs, match_pairs

    n, res = 10, 384
    s = synthetic.make_scene(seed=0, n_views=n, resolution=res)
    K = s.K.copy()
    K[:, 0, 2] += 0.05 * res  # [N,3,3] the camera that took the photos
    K[:, 1, 2] -= 0.03 * res
    images = np.stack([synthetic.render_view(K[i], s.w2c[i], res, res)[0] for i in range(n)])
    feats = extract_all(images, workers=2)
    pairs = PI.pairs_from_matches(match_pairs(feats, exhaustive_pairs(n), K, workers=2))
    kps = [f["keypoints"] for f in feats]

    def rot(out):
        return evaluate_poses(out.w2c, s.w2c)["summary"]["rot_err_deg"]["mean"]

    both = PI.init_from_matches(list(range(n)), s.K, kps, pairs, mapper=PI.MapperOptions(
        refine=("focal", "principal_point"), prior_focal=False, principal_point_p=1e-3))
    assert both.diagnostics["principal_point_test"]["freed"], both.diagnostics["principal_point_test"]
    focal_only = PI.init_from_matches(list(range(n)), s.K, kps, pairs,
                                      mapper=PI.MapperOptions(refine=("focal",), prior_focal=False))
    true_K = PI.init_from_matches(list(range(n)), K, kps, pairs)
    assert both.placed.all() and focal_only.placed.all()
    assert np.abs(both.K[0, :2, 2] - K[0, :2, 2]).max() < 0.01 * res, both.K[0]
    assert np.allclose(focal_only.K[:, :2, 2], s.K[:, :2, 2])  # held at the centre
    assert rot(both) < 0.25 * rot(focal_only), (rot(both), rot(focal_only))
    assert rot(both) < 4 * rot(true_K) + 0.1, (rot(both), rot(true_K))


def test_principal_point_at_the_centre_and_no_lens_distortion_are_not_freed():
    """The same test on pinhole photos whose principal point is the centre: freeing either the radial
    distortion or the principal point does not lower the reprojection error significantly, so both stay
    where they started (and the images would not be resampled)."""
    from manifoldneus.data import synthetic
    from stages.features import extract_all
    from stages.matching import exhaustive_pairs, match_pairs

    n = 10
    s = synthetic.make_scene(seed=0, n_views=n, resolution=384)
    feats = extract_all(s.images, workers=2)
    pairs = PI.pairs_from_matches(match_pairs(feats, exhaustive_pairs(n), s.K, workers=2))
    out = PI.init_from_matches(list(range(n)), s.K, [f["keypoints"] for f in feats], pairs,
                               mapper=PI.MapperOptions(refine=("focal", "principal_point", "radial"),
                                                       prior_focal=False, principal_point_p=1e-3, radial_p=1e-3))
    for test in (out.diagnostics["principal_point_test"], out.diagnostics["radial_test"]):
        assert not test["freed"] and test["chi2"] < test["threshold"], test
    assert np.allclose(out.K[:, :2, 2], s.K[:, :2, 2])
    assert not out.distortion.any()


def test_focal_length_is_refined_from_a_wrong_guess():
    """One shared camera whose focal length starts 30 % off: COLMAP's bundle adjustment brings it
    back within 2 % and the poses stay within 2x those of the calibrated initialisation. (At 384 px:
    at 192 px SIFT's keypoints on this narrow-angle scene leave the focal length 2.3 % short.)"""
    from manifoldneus.data import synthetic
    from stages.features import extract_all
    from stages.matching import exhaustive_pairs, match_pairs

    n = 10
    s = synthetic.make_scene(seed=0, n_views=n, resolution=384)
    feats = extract_all(s.images, workers=2)
    pairs = PI.pairs_from_matches(match_pairs(feats, exhaustive_pairs(n), s.K, workers=2))
    kps = [f["keypoints"] for f in feats]
    K0 = s.K.copy()
    K0[:, :2, :2] *= 1.3
    out = PI.init_from_matches(list(range(n)), K0, kps, pairs, mapper=PI.MapperOptions(refine=("focal",), prior_focal=False))
    assert out.placed.all()
    assert abs(out.K[0, 0, 0] / s.K[0, 0, 0] - 1) < 0.02, out.K[0]
    assert np.allclose(out.K[:, 0, 0], out.K[0, 0, 0]) and np.allclose(out.K[:, 1, 1], out.K[0, 0, 0])  # one camera
    rot = evaluate_poses(out.w2c, s.w2c)["summary"]["rot_err_deg"]["mean"]
    calibrated = PI.init_from_matches(list(range(n)), s.K, kps, pairs)
    rot_calibrated = evaluate_poses(calibrated.w2c, s.w2c)["summary"]["rot_err_deg"]["mean"]
    assert rot < 2 * rot_calibrated + 0.05, (rot, rot_calibrated)
    # held fixed, the wrong focal length stays
    assert np.allclose(PI.init_from_matches(list(range(n)), K0, kps, pairs).K, K0)
