"""Tests of the synthetic scene generator (manifoldneus.data.synthetic)."""
import cv2
import numpy as np
import pytest

from manifoldneus.data import synthetic as syn
from manifoldneus.geometry.cameras import camera_centers, look_at_w2c


@pytest.fixture(scope="module")
def scene():
    return syn.make_scene(seed=0, n_views=8, resolution=96)


def test_scene_arrays(scene):
    N, H, W = 8, 96, 96
    assert scene.images.shape == (N, H, W, 3) and scene.images.dtype == np.uint8
    assert scene.masks.shape == (N, H, W) and scene.masks.dtype == bool
    assert scene.K.shape == (N, 3, 3) and scene.K.dtype == np.float64
    assert scene.w2c.shape == (N, 4, 4) and scene.w2c.dtype == np.float64
    assert scene.depth.shape == (N, H, W) and scene.depth.dtype == np.float32
    assert scene.normals.shape == (N, H, W, 3) and scene.normals.dtype == np.float32
    assert scene.names == [f"view_{i:03d}" for i in range(N)]
    np.testing.assert_allclose(scene.K[:, 0, 0], 2.4 * W)
    np.testing.assert_allclose(scene.K[:, :2, 2], np.full((N, 2), W / 2))
    assert 0.2 < scene.masks.mean() < 0.7
    # background untouched, foreground consistent
    assert np.all(scene.depth[~scene.masks] == 0) and np.all(scene.normals[~scene.masks] == 0)
    assert np.all(scene.depth[scene.masks] > 2.0)
    np.testing.assert_allclose(np.linalg.norm(scene.normals[scene.masks], axis=-1), 1.0, atol=1e-4)
    # whole object in view: nothing on the image border
    m = scene.masks
    assert not (m[:, 0].any() or m[:, -1].any() or m[:, :, 0].any() or m[:, :, -1].any())


def test_sample_surface_exact():
    p = syn.sample_surface(20000, seed=1)
    assert p.shape == (20000, 3)
    assert np.abs(syn.sdf(p)).max() < 1e-6
    lo, hi = syn.bounding_box()
    assert np.all(p >= lo - 1e-9) and np.all(p <= hi + 1e-9)
    assert np.all(p.min(0) - lo < 0.02) and np.all(hi - p.max(0) < 0.02)  # box is tight
    assert np.linalg.norm(p, axis=1).max() < 0.75
    # uniform by area: the (fully exposed) bottom face has twice the area of the front face
    a = syn.BOX_HALF - syn.BOX_ROUND
    c = syn.BOX_CENTER
    bottom = (np.abs(p[:, 2] - (c[2] - syn.BOX_HALF[2])) < 1e-9) & np.all(np.abs(p[:, :2] - c[:2]) <= a[:2], 1)
    front = (np.abs(p[:, 1] - (c[1] - syn.BOX_HALF[1])) < 1e-9) & np.all(np.abs(p[:, [0, 2]] - c[[0, 2]]) <= a[[0, 2]], 1)
    ratio = bottom.sum() / front.sum()
    assert abs(ratio - (a[0] * a[1]) / (a[0] * a[2])) < 0.3
    # sdf sign: outside positive, inside negative; exact outside (distance to a sphere point)
    assert syn.sdf(np.array([[0.0, 0.0, 2.0]]))[0] > 0 and syn.sdf(np.array([[0.0, 0.0, -0.17]]))[0] < 0
    top = syn.SPHERE_CENTER + np.array([0, 0, syn.SPHERE_RADIUS + 0.3])
    assert syn.sdf(top[None])[0] == pytest.approx(0.3, abs=1e-12)
    # deterministic
    np.testing.assert_array_equal(p, syn.sample_surface(20000, seed=1))


def test_mask_is_traced_hit(scene):
    H = W = 96
    for i in (0, 5):
        o, d, dz = syn.pixel_rays(scene.K[i], scene.w2c[i], H, W)
        t = syn.trace(o[0], d[0])
        hit = np.isfinite(t).reshape(H, W)
        np.testing.assert_array_equal(scene.masks[i], hit)
        np.testing.assert_allclose(scene.depth[i][hit], (t * dz[0]).reshape(H, W)[hit], rtol=1e-6)


def test_visible_surface_points_project_into_mask(scene):
    pts = syn.sample_surface(4000, seed=2)
    H = W = 96
    for i in range(len(scene.w2c)):
        K, T = scene.K[i], scene.w2c[i]
        vis = syn.points_visible(pts, K, T[None], H, W)
        assert vis.sum() > 500
        xc = pts[vis] @ T[:3, :3].T + T[:3, 3]
        uv = xc @ K.T
        u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
        col, row = np.floor(u).astype(int), np.floor(v).astype(int)
        inside = scene.masks[i][row, col]
        assert inside.mean() > 0.95, (i, inside.mean())  # misses: silhouette pixels only
        dil = cv2.dilate(scene.masks[i].astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        assert dil[row, col].all()
        # their depth agrees with the depth map (up to the depth variation within a pixel)
        err = np.abs(xc[:, 2] - scene.depth[i][row, col])[inside]
        assert np.median(err) < 0.01 and (err < 0.05).mean() > 0.95
    # the bottom of the box is never seen
    bottom = pts[np.abs(pts[:, 2] - (syn.BOX_CENTER[2] - syn.BOX_HALF[2])) < 1e-9]
    assert len(bottom) and not syn.points_visible(bottom, scene.K, scene.w2c, H, W).any()


def test_centre_pixel_depth_by_hand():
    """Odd resolution: the centre pixel's ray is the optical axis, hit computed by hand."""
    S = 33
    K = syn.intrinsics(S, S)
    assert K[0, 2] == S / 2 == 16.5  # centre of pixel 16
    # 1) frontal camera at distance D facing the flat front face of the box (y = -0.3)
    D = 2.8
    target = np.array([0.0, 0.0, syn.BOX_CENTER[2]])
    w2c = look_at_w2c(target + np.array([0.0, -D, 0.0]), target, np.array([0.0, 0.0, 1.0]))
    _, mask, depth, normals = syn.render_view(K, w2c, S, S)
    assert mask[16, 16]
    assert depth[16, 16] == pytest.approx(D - syn.BOX_HALF[1], abs=1e-5)
    np.testing.assert_allclose(normals[16, 16], [0, 0, -1], atol=1e-4)
    # 2) camera looking at the sphere centre from the front-top: depth = D - radius
    direction = np.array([0.0, -0.6, 0.8])
    c = syn.SPHERE_CENTER
    w2c = look_at_w2c(c + D * direction, c, np.array([0.0, 0.0, 1.0]))
    _, mask, depth, _ = syn.render_view(K, w2c, S, S)
    assert depth[16, 16] == pytest.approx(D - syn.SPHERE_RADIUS, abs=1e-5)
    # 3) a scene camera: the centre ray runs to the origin along -C / |C|; first hit by bisection
    #    of the sdf sign along the axis is the same as the traced depth
    T = syn.camera_poses(49)[20]
    C = camera_centers(T[None])[0]
    assert np.linalg.norm(C) == pytest.approx(syn.DISTANCE)
    _, mask, depth, _ = syn.render_view(K, T, S, S)
    ts = np.linspace(0, syn.DISTANCE, 300001)
    f = syn.sdf(C - ts[:, None] * C / np.linalg.norm(C))
    first = ts[np.argmax(f < 0)]
    assert depth[16, 16] == pytest.approx(first, abs=2e-5)


def test_cameras_layout():
    T = syn.camera_poses(49)
    C = camera_centers(T)
    np.testing.assert_allclose(np.linalg.norm(C, axis=1), syn.DISTANCE)
    assert np.all(C[:, 2] > 0.9)  # upper hemisphere (elevation >= 20 deg)
    assert np.all(C[:, 1] < 0)  # in front of the object
    steps = np.linalg.norm(np.diff(C, axis=0), axis=1)
    assert np.median(steps) < 0.35 and steps.max() < 1.3  # serpentine: neighbours (25 deg max at arc changes)
    # optical axis through the origin, world +z up in the image
    K = syn.intrinsics(192, 192)
    for w in T:
        for p, check in ((np.zeros(3), None), (np.array([0.0, 0.0, 0.3]), "up")):
            x = K @ (w[:3, :3] @ p + w[:3, 3])
            u, v = x[:2] / x[2]
            if check is None:
                assert u == pytest.approx(96) and v == pytest.approx(96)
            else:
                assert v < 96 - 5
    assert len(syn.camera_poses(8)) == 8 and len(syn.camera_poses(1)) == 1
    np.testing.assert_allclose([np.linalg.det(w[:3, :3]) for w in T], 1.0)


def _sift(image):
    sift = cv2.SIFT_create()
    return sift.detectAndCompute(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), None)


def test_sift_features_and_matches():
    H = W = 192
    K = syn.intrinsics(H, W)
    T = syn.camera_poses(49)
    (k1, d1), (k2, d2) = (_sift(syn.render_view(K, T[i], H, W, seed=0)[0]) for i in (10, 11))
    assert len(k1) > 200 and len(k2) > 200
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m for m, n in knn if m.distance < 0.8 * n.distance]
    assert len(good) > 50
    p1 = np.float64([k1[m.queryIdx].pt for m in good])
    p2 = np.float64([k2[m.trainIdx].pt for m in good])
    E, inl = cv2.findEssentialMat(p1, p2, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
    assert inl.sum() > 0.8 * len(good)
    # the matches obey the epipolar geometry of the true poses (images and poses agree)
    R = T[11][:3, :3] @ T[10][:3, :3].T
    t = T[11][:3, 3] - R @ T[10][:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Kinv = np.linalg.inv(K)
    F = Kinv.T @ tx @ R @ Kinv
    h1, h2 = np.c_[p1, np.ones(len(p1))], np.c_[p2, np.ones(len(p2))]
    lines = h1 @ F.T
    err = np.abs((h2 * lines).sum(1)) / np.linalg.norm(lines[:, :2], axis=1)
    assert np.median(err) < 0.3 and (err < 1.0).mean() > 0.9


def test_seeds_change_texture_only():
    T = syn.camera_poses(49)[12]
    K = syn.intrinsics(64, 64)
    im0, m0, d0, n0 = syn.render_view(K, T, 64, 64, seed=0)
    im1, m1, d1, n1 = syn.render_view(K, T, 64, 64, seed=1)
    np.testing.assert_array_equal(m0, m1)
    np.testing.assert_array_equal(d0, d1)
    diff = np.abs(im0.astype(int) - im1.astype(int))[m0].mean()
    assert diff > 20
    p = syn.sample_surface(1000)
    assert np.abs(syn.albedo(p, 0) - syn.albedo(p, 1)).mean() > 0.1


def test_deterministic():
    a = syn.make_scene(seed=3, n_views=2, resolution=48)
    syn._rendered.cache_clear()  # rendered again, not the process's kept copy
    b = syn.make_scene(seed=3, n_views=2, resolution=48)
    for name in ("images", "masks", "K", "w2c", "depth", "normals"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.names == b.names


def test_a_scene_is_rendered_once_per_process_and_each_caller_owns_its_copy(monkeypatch):
    syn._rendered.cache_clear()
    calls = []
    render = syn.render_view
    monkeypatch.setattr(syn, "render_view", lambda *a, **k: calls.append(1) or render(*a, **k))
    a = syn.make_scene(seed=5, n_views=2, resolution=32)
    a.images[:] = 0
    a.names.append("changed")
    b = syn.make_scene(seed=5, n_views=2, resolution=32)
    assert len(calls) == 2 and b.images.max() > 0 and b.names == ["view_000", "view_001"]
    syn.make_scene(seed=5, n_views=2, resolution=32, k1=-0.1)  # another lens: another rendering
    assert len(calls) == 4


def test_look_at_shows_world_up_at_the_image_top():
    from manifoldneus.geometry.cameras import look_at_w2c

    w2c = look_at_w2c(np.array([0.0, -3.0, 0.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    # camera y (image down) points to world -z; camera x (image right) to world +x
    np.testing.assert_allclose(w2c[1, :3], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(w2c[0, :3], [1, 0, 0], atol=1e-12)
