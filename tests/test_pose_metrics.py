"""Pose metrics on synthetic camera rigs with known errors."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from manifoldneus.geometry.cameras import camera_centers, look_at_w2c, sim3_matrix, transform_w2c
from manifoldneus.geometry.pose_metrics import evaluate_poses, json_summary, plot_cameras, relative_pose_errors


def ring_rig(n=12, radius=3.0, seed=0):
    rng = np.random.default_rng(seed)
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), 0.5 + 0.8 * rng.random()])
        poses.append(look_at_w2c(eye, rng.normal(0, 0.05, 3), np.array([0, 0, 1.0])))
    return np.stack(poses)


def random_sim3(seed=1):
    rng = np.random.default_rng(seed)
    return 0.37, Rotation.random(random_state=rng).as_matrix(), rng.normal(0, 5, 3)


def test_random_sim3_of_gt_has_zero_error():
    gt = ring_rig()
    s, R, t = random_sim3()
    est = transform_w2c(gt, s, R, t)  # same cameras, another world frame
    res = evaluate_poses(est, gt, units_scale=200.0)
    summ = res["summary"]
    # arccos-based angles resolve ~1e-6 degrees near zero
    assert summ["rot_err_deg"]["max"] < 1e-5
    assert summ["center_err"]["max"] < 1e-9
    assert summ["pre_r_deg"]["max"] < 1e-5 and summ["pre_t_deg"]["max"] < 1e-5
    # the returned alignment inverts the random similarity
    al = res["alignment"]
    M = sim3_matrix(al["s"], al["R"], al["t"]) @ sim3_matrix(s, R, t)
    assert np.allclose(M, np.eye(4), atol=1e-9)
    assert np.allclose(res["w2c_aligned"], gt, atol=1e-9)
    assert res["n_valid"] == 12 and res["n_missing"] == 0


def test_known_rotation_perturbation_of_one_view():
    gt = ring_rig()
    est = gt.copy()
    angle = 3.0
    dR = Rotation.from_rotvec(np.radians(angle) * np.array([0.0, 1.0, 0.0])).as_matrix()
    # rotate camera 4 about its own centre: centre unchanged, orientation off by `angle`
    C = camera_centers(gt[4])
    est[4, :3, :3] = dR @ gt[4, :3, :3]
    est[4, :3, 3] = -est[4, :3, :3] @ C
    s, R, t = random_sim3(3)
    res = evaluate_poses(transform_w2c(est, s, R, t), gt)
    rot = res["rot_err_deg"]
    assert rot[4] == pytest.approx(angle, abs=1e-6)
    assert np.all(np.delete(rot, 4) < 1e-5)
    assert res["summary"]["center_err"]["max"] < 1e-9
    assert res["summary"]["rot_err_deg"]["mean"] == pytest.approx(angle / 12, abs=1e-6)
    # PRE_r: exactly the pairs with view 4 are off by `angle`
    pairs, pre_r = res["pairs"], res["pre_r_deg"]
    with4 = (pairs == 4).any(1)
    assert np.allclose(pre_r[with4], angle, atol=1e-6)
    assert np.all(pre_r[~with4] < 1e-5)
    assert len(pairs) == 66


def test_pre_t_known_direction_error():
    # two cameras with identity rotation: t_ij is along the baseline
    gt = np.stack([np.eye(4)] * 3)
    gt[1, :3, 3] = [-1.0, 0, 0]  # C1 = (1,0,0)
    gt[2, :3, 3] = [0, -1.0, 0]  # C2 = (0,1,0)
    est = gt.copy()
    est[1, :3, 3] = [-1.0, -1.0, 0]  # C1 = (1,1,0): baseline 0->1 rotated by 45 degrees
    pairs, pre_r, pre_t = relative_pose_errors(est, gt)
    assert pairs.tolist() == [[0, 1], [0, 2], [1, 2]]
    assert np.allclose(pre_r, 0)
    assert pre_t[0] == pytest.approx(45.0)
    assert pre_t[1] == pytest.approx(0.0)
    # pair (1, 2): gt direction C1 - C2 = (1,-1,0), est (1,0,0): 45 degrees
    assert pre_t[2] == pytest.approx(45.0)
    # the error is scale-invariant
    est2 = est.copy()
    est2[:, :3, 3] *= 7.0
    assert np.allclose(relative_pose_errors(est2, gt)[2], pre_t)


def test_centre_error_units_and_percent():
    gt = ring_rig(n=8, radius=2.0)
    est = gt.copy()
    C = camera_centers(gt)
    # shift every centre by +-d alternately along z; the Sim3 cannot absorb an alternating pattern
    d = 0.01
    signs = np.array([1, -1] * 4, float)
    Cn = C + np.outer(signs, [0, 0, d])
    est[:, :3, 3] = -np.einsum("nij,nj->ni", est[:, :3, :3], Cn)
    res = evaluate_poses(est, gt, units_scale=100.0)
    ce = res["center_err"]
    assert np.allclose(ce, d, rtol=0.05)  # the Sim3 cannot absorb an alternating pattern
    assert np.allclose(res["center_err_units"], ce * 100)
    mean_dist = np.linalg.norm(C - C.mean(0), axis=1).mean()
    assert np.allclose(res["center_err_pct"], ce / mean_dist * 100)


def test_missing_views_excluded_and_counted(tmp_path):
    gt = ring_rig()
    s, R, t = random_sim3(5)
    est = transform_w2c(gt, s, R, t)
    est[2] = np.nan  # unregistered, stored as NaN
    est[7, :3, 3] += 50.0  # garbage pose, flagged unregistered
    valid = np.ones(12, bool)
    valid[7] = False
    res = evaluate_poses(est, gt, valid=valid)
    assert res["n_missing"] == 2 and res["missing"] == [2, 7]
    assert res["summary"]["center_err"]["max"] < 1e-9
    assert np.isnan(res["rot_err_deg"][2]) and np.isnan(res["center_err"][7])
    assert len(res["pairs"]) == 45
    js = json_summary(res)
    import json

    json.dumps(js, allow_nan=False)
    assert js["per_view"][2]["rot_err_deg"] is None and js["per_view"][7]["valid"] is False
    plot_cameras(res["w2c_aligned"], gt, tmp_path / "cams.png", valid=res["valid"], title="test")
    assert (tmp_path / "cams.png").stat().st_size > 1000


def test_too_few_views():
    gt = ring_rig(n=4)
    with pytest.raises(ValueError, match="at least 3"):
        evaluate_poses(gt, gt, valid=[True, True, False, False])
    with pytest.raises(ValueError, match="must both be"):
        evaluate_poses(gt[:3], gt)


def test_reference_with_too_few_registered_views_is_reported_not_fatal(tmp_path):
    from manifoldneus.data import io
    from stages.evaluate_poses import evaluate_pose_artifact

    gt_dir, est_dir = tmp_path / "gt", tmp_path / "est"
    gt_dir.mkdir()
    est_dir.mkdir()
    io.save_arrays(gt_dir / "poses.zarr", {"w2c": np.tile(np.eye(4), (5, 1, 1)), "normalization": np.eye(4)},
                   chunk_first=False)
    io.save_json(gt_dir / "gt.json", {"has_poses": True, "units": "unit", "units_per_scene_unit": 1.0})
    registered = np.array([True, True, False, False, False])
    io.save_arrays(est_dir / "poses.zarr", {"w2c": np.tile(np.eye(4), (5, 1, 1)), "registered": registered},
                   chunk_first=False)
    out = evaluate_pose_artifact(est_dir, gt_dir, tmp_path, "reference")
    assert out["evaluated"] is False and "only 2 registered" in out["reason"]
