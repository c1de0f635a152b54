"""Pose conventions and Lie algebra: se(3) round trips, composition, Sim3 transforms."""
import numpy as np
import torch

from manifoldneus.geometry import cameras


def random_xi(n, scale=1.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 6, generator=g, dtype=torch.float64) - 0.5) * 2 * scale


def test_se3_exp_log_roundtrip_including_tiny_angles():
    for scale in (1e-9, 1e-4, 0.3, 1.5):
        xi = random_xi(64, scale)
        back = cameras.se3_log(cameras.se3_exp(xi))
        torch.testing.assert_close(back, xi, atol=1e-9, rtol=1e-7)


def test_se3_exp_is_a_rigid_motion_and_matches_matrix_exponential():
    xi = random_xi(16, 0.8, seed=1)
    T = cameras.se3_exp(xi)
    R = T[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(16, 3, 3))
    assert torch.allclose(torch.linalg.det(R), torch.ones(16, dtype=torch.float64))
    # against the matrix exponential of the 4x4 twist
    twist = torch.zeros(16, 4, 4, dtype=torch.float64)
    twist[:, :3, :3] = cameras.skew(xi[:, 3:])
    twist[:, :3, 3] = xi[:, :3]
    torch.testing.assert_close(torch.linalg.matrix_exp(twist)[:, :3, :4], T, atol=1e-10, rtol=1e-9)


def test_exp_gradient_at_zero_is_finite():
    xi = torch.zeros(3, 6, dtype=torch.float64, requires_grad=True)
    cameras.apply_correction(xi, torch.eye(4, dtype=torch.float64).expand(3, 4, 4)).sum().backward()
    assert torch.isfinite(xi.grad).all() and xi.grad.abs().sum() > 0


def test_compose_invert_and_correction():
    a = cameras.se3_exp(random_xi(8, 0.7, seed=2))
    b = cameras.se3_exp(random_xi(8, 0.7, seed=3))
    eye = torch.eye(4, dtype=torch.float64)[:3].expand(8, 3, 4)
    torch.testing.assert_close(cameras.compose(a, cameras.invert(a)), eye, atol=1e-12, rtol=0)
    xi = random_xi(8, 0.2, seed=4)
    torch.testing.assert_close(cameras.apply_correction(xi, b), cameras.compose(cameras.se3_exp(xi), b))


def test_numpy_inverse_centres_and_sim3_transform():
    rng = np.random.default_rng(0)
    w2c = cameras.se3_exp(random_xi(5, 1.0, seed=5)).numpy()
    c2w = cameras.invert_pose(w2c)
    np.testing.assert_allclose(cameras.invert_pose(c2w)[:, :3], w2c, atol=1e-12)
    np.testing.assert_allclose(c2w[:, :3, 3], cameras.camera_centers(w2c), atol=1e-12)
    # a similarity of the world keeps projections: x_cam_new ~ s * x_cam
    s, R, t = 2.5, cameras.se3_exp(random_xi(1, 1.0, seed=6))[0, :3, :3].numpy(), rng.normal(size=3)
    X = rng.normal(size=(10, 3))
    new = cameras.transform_w2c(w2c, s, R, t)
    Y = s * X @ R.T + t
    for k in range(5):
        xc = X @ w2c[k, :3, :3].T + w2c[k, :3, 3]
        yc = Y @ new[k, :3, :3].T + new[k, :3, 3]
        np.testing.assert_allclose(yc, s * xc, atol=1e-9)
    s2, R2, t2 = cameras.umeyama_sim3(cameras.camera_centers(w2c), cameras.camera_centers(new))
    assert abs(s2 - s) < 1e-9 and np.allclose(R2, R, atol=1e-9) and np.allclose(t2, t, atol=1e-9)


def test_decompose_projection_roundtrip():
    K = np.array([[900.0, 0, 190], [0, 905, 200], [0, 0, 1]])
    w2c = cameras.to_4x4(cameras.se3_exp(random_xi(1, 1.0, seed=7)).numpy()[0])
    K2, w2c2 = cameras.decompose_projection(K @ w2c[:3])
    np.testing.assert_allclose(K2, K, atol=1e-8)
    np.testing.assert_allclose(w2c2, w2c, atol=1e-9)


def test_sim3_inverse_undoes_the_similarity():
    rng = np.random.default_rng(0)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    s, t = 2.5, rng.normal(size=3)
    x = rng.normal(size=(5, 3))
    y = s * x @ R.T + t
    si, Ri, ti = cameras.sim3_inverse(s, R, t)
    assert np.allclose(si * y @ Ri.T + ti, x)


def test_perturbed_poses_turn_and_move_by_the_asked_amounts():
    rng = np.random.default_rng(0)
    eyes = rng.normal(size=(20, 3)) * 3
    w2c = np.stack([cameras.look_at_w2c(e, np.zeros(3), np.array([0.0, 0.0, 1.0])) for e in eyes])
    out = cameras.perturb_w2c(w2c, (3.0, 5.0), 0.15, np.random.default_rng(1))
    turn = cameras.rotation_angle_deg(out[:, :3, :3] @ np.swapaxes(w2c[:, :3, :3], 1, 2))
    assert np.all((turn >= 3.0 - 1e-9) & (turn <= 5.0 + 1e-9)) and turn.std() > 0.1
    shift = np.linalg.norm(cameras.camera_centers(out) - eyes, axis=1)
    np.testing.assert_allclose(shift, 0.15, atol=1e-9)
    np.testing.assert_allclose(out[:, :3, :3] @ np.swapaxes(out[:, :3, :3], 1, 2), np.tile(np.eye(3), (20, 1, 1)),
                               atol=1e-12)


def test_projection_and_normalised_coordinates_are_inverse():
    rng = np.random.default_rng(0)
    K = np.array([[900.0, 2.5, 190.3], [0, 905.0, 200.7], [0, 0, 1]])  # with skew
    Xc = np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 5, 50)]
    uv = cameras.project_points(K, Xc)
    h = Xc @ K.T
    np.testing.assert_allclose(uv, h[:, :2] / h[:, 2:], rtol=1e-12)
    np.testing.assert_allclose(cameras.pixels_to_normalised(K, uv), Xc[:, :2] / Xc[:, 2:], atol=1e-12)
    Ks = K * rng.uniform(0.5, 2.0, (50, 1, 1))  # one K per point
    Ks[:, 2, 2] = 1.0
    uv = cameras.project_points(Ks, Xc)
    np.testing.assert_allclose(cameras.pixels_to_normalised(Ks, uv), Xc[:, :2] / Xc[:, 2:], atol=1e-12)
    h = np.linalg.solve(Ks, np.c_[uv, np.ones(50)][..., None])[..., 0]  # K^-1 [u, v, 1]
    np.testing.assert_allclose(cameras.pixels_to_normalised(Ks, uv), h[:, :2], atol=1e-12)


def test_skew_and_rotvec_numpy_and_torch():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(7, 3)), rng.normal(size=(7, 3))
    np.testing.assert_allclose(cameras.skew(a) @ b[..., None], np.cross(a, b)[..., None], atol=1e-12)
    np.testing.assert_array_equal(cameras.skew(torch.from_numpy(a)).numpy(), cameras.skew(a))
    w = rng.normal(size=(7, 3))
    R = cameras.rotvec_to_matrix(w)
    assert R.shape == (7, 3, 3)
    np.testing.assert_allclose(R, torch.linalg.matrix_exp(torch.from_numpy(cameras.skew(w))).numpy(), atol=1e-12)
    np.testing.assert_allclose(cameras.rotvec_to_matrix(np.array([0.0, 0.0, np.pi / 2]))[0] @ [1.0, 0, 0], [0, 1.0, 0],
                               atol=1e-15)


def test_undistortion_inverts_the_lens():
    """OpenCV's lens model both ways: undistort_points takes cv2.projectPoints' distorted pixels back to the
    pinhole ones, and a synthetic view rendered through a lens (k1 = -1), undistorted with that lens, is the
    pinhole render of the view (away from the border the lens leaves uncovered; within the resampling's blur)."""
    import cv2

    from manifoldneus.data import synthetic

    K = synthetic.intrinsics(128, 128)
    lens = np.array([-1.0, 0.0, 0.002, 0.0])
    X = np.random.default_rng(0).uniform([-0.2, -0.2, 2.0], [0.2, 0.2, 4.0], (200, 3))  # [M,3] camera frame
    distorted = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, lens)[0].reshape(-1, 2)
    assert np.abs(cameras.undistort_points(distorted, K, lens) - cameras.project_points(K, X)).max() < 1e-6

    res = 256  # at 128 px the texture's finest scale is the pixel: resampling blurs it as much as the lens moves it
    K = synthetic.intrinsics(res, res)
    w2c = synthetic.camera_poses(6)[2]
    through_lens, mask = synthetic.render_view(K, w2c, res, res, k1=-1.0)[:2]
    pinhole = synthetic.render_view(K, w2c, res, res)[0]

    def blurred(image):  # the lens's compression of the periphery loses the finest texture for good
        return cv2.GaussianBlur(image.astype(np.float32), (0, 0), 3.0)

    inner = np.zeros_like(mask)
    inner[48:-48, 48:-48] = True
    after = np.abs(blurred(cameras.undistort_image(through_lens, K, [-1.0, 0, 0, 0])) - blurred(pinhole))[inner].mean()
    before = np.abs(blurred(through_lens) - blurred(pinhole))[inner].mean()
    assert after < 0.25 * before, (after, before)
    assert cameras.undistort_image(mask, K, [-1.0, 0, 0, 0], nearest=True).dtype == bool


def test_the_gauge_puts_a_lopsided_objects_whole_box_in_its_sphere():
    """Views see some parts of an object more than others (the synthetic scene's textured top, its base
    barely): the gauge scales the box of the points, not a median distance, so the parts the points cover
    thinly fit the sphere too. Its centre is the box's middle, or (centre="median") the median where the box
    fits the unit sphere from there, moved towards the box's middle where it does not; a few far outliers
    (mismatches) move neither its centre nor its scale much."""
    from manifoldneus.data import synthetic

    rng = np.random.default_rng(0)
    surface = synthetic.sample_surface(20000)  # [P,3], radius <= 0.6 about the origin
    seen_most = surface[surface[:, 2] > 0.1]
    points = np.concatenate([surface[rng.random(len(surface)) < 0.1], np.repeat(seen_most, 5, 0)])  # [Q,3]
    s_box, middle = cameras.gauge_from_points(points, radius=0.8)
    assert np.linalg.norm(s_box * (surface - middle), axis=1).max() < 0.82  # the whole object, thin parts too
    s, centre = cameras.gauge_from_points(points, radius=0.8, centre="median")
    median = np.median(points, 0)
    assert s == s_box
    lo, hi = np.percentile(points, [1, 99], axis=0)
    corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), -1).reshape(-1, 3)  # [8,3]
    assert 0.999 < np.linalg.norm(s * (corners - centre), axis=1).max() < 1 + 1e-9  # the box touches the sphere
    assert np.linalg.norm(centre - median) < 0.5 * np.linalg.norm(middle - median)  # pulled only part of the way
    # a smaller box fits the unit sphere from the median itself
    s_fit, centre_fit = cameras.gauge_from_points(points, radius=0.6, centre="median")
    assert np.allclose(centre_fit, median)
    outliers = rng.normal(size=(len(points) // 200, 3)) * 10.0  # 0.5 % of the points, far away
    s2, centre2 = cameras.gauge_from_points(np.concatenate([points, outliers]), radius=0.8, centre="median")
    assert abs(s2 / s - 1) < 0.05 and np.linalg.norm(centre2 - centre) * s < 0.05
