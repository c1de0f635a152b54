"""The correspondence term and guard of the joint rounds, on exact synthetic correspondences."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from manifoldneus.geometry import cameras
from manifoldneus.sfm import correspondence
from manifoldneus.data import synthetic
from manifoldneus.sfm.pose_init import PairMatch
from manifoldneus.geometry.pose_metrics import evaluate_poses


@pytest.fixture(scope="module")
def scene():
    """12 DTU-like views of 300 points in the unit ball; every view sees every point (keypoint k =
    point k), each view matched with its 3 next neighbours."""
    rng = np.random.default_rng(0)
    w2c = synthetic.camera_poses(12)
    K = np.tile(np.array([[300.0, 0, 128], [0, 300.0, 128], [0, 0, 1]]), (12, 1, 1))
    X = rng.uniform(-0.5, 0.5, (300, 3))
    kps = []
    for i in range(12):
        Xc = X @ w2c[i, :3, :3].T + w2c[i, :3, 3]
        kps.append((Xc[:, :2] / Xc[:, 2:]) @ K[i, :2, :2].T + K[i, :2, 2])
    idx = np.arange(300)
    pairs = [PairMatch(i, j, np.stack([idx, idx], 1), np.eye(3), np.array([1.0, 0, 0]))
             for i in range(12) for j in range(i + 1, min(i + 4, 12))]
    obs_view = np.repeat(np.arange(12), 300)
    obs_point = np.tile(idx, 12)
    obs_uv = np.concatenate(kps)
    return {"w2c": w2c, "K": K, "kps": kps, "pairs": pairs, "tracks": (obs_view, obs_point, obs_uv)}


def perturb(w2c, rot_deg, seed=1):
    rng = np.random.default_rng(seed)
    xi = np.zeros((len(w2c), 6))
    axis = rng.normal(size=(len(w2c), 3))
    xi[:, 3:] = axis / np.linalg.norm(axis, axis=1, keepdims=True) * np.radians(rot_deg)
    xi[:, :3] = rng.normal(scale=0.01 * rot_deg, size=(len(w2c), 3))
    return cameras.apply_correction(torch.tensor(xi), torch.tensor(w2c)).float()


def losses(scene, kind, holdout=0.2):
    p = correspondence.CorrespondenceParams(kind=kind, holdout_frac=holdout, batch=100000)
    ids = np.arange(12)
    if kind == "sampson":
        ms = correspondence.MatchSet(ids, scene["K"], scene["kps"], scene["pairs"], p.holdout_frac, p.seed)
        return correspondence.CorrespondenceLoss(ms, p, 1.0), p
    tracks = correspondence.TrackSet(ids, scene["K"], *scene["tracks"])
    return correspondence.ReprojectionLoss(tracks, p, 1.0), p


@pytest.mark.parametrize("kind", ["sampson", "reprojection"])
def test_error_is_zero_at_the_truth_and_grows_with_a_perturbation(scene, kind):
    loss, _ = losses(scene, kind)
    truth = torch.tensor(scene["w2c"][:, :3, :4]).float()
    assert loss.median_px(truth) < 0.01 and loss.median_px(truth, held_out=False) < 0.01
    assert loss.median_px(perturb(scene["w2c"], 0.5)) > 0.3  # 0.5 deg at f = 300 px is ~2.6 px
    assert loss.n_held_out > 0


def test_sampson_ignores_the_baseline_length(scene):
    """The epipolar error sees rotations and translation directions, not the scale of the scene."""
    loss, _ = losses(scene, "sampson")
    w = torch.tensor(scene["w2c"][:, :3, :4]).float()
    scaled = torch.cat([w[:, :, :3], 3.0 * w[:, :, 3:]], -1)
    assert loss.median_px(scaled) < 0.01


@pytest.mark.parametrize("kind", ["sampson", "reprojection"])
def test_term_alone_pulls_perturbed_poses_back(scene, kind):
    """Adam on the correspondence term only (view 0 fixed: the gauge) takes 1-deg perturbations most
    of the way back to the truth."""
    loss, _ = losses(scene, kind)
    start = perturb(scene["w2c"], 1.0)
    start[0] = torch.tensor(scene["w2c"][0, :3, :4]).float()
    xi = torch.zeros(12, 6, requires_grad=True)
    opt = torch.optim.Adam([xi], lr=2e-3)
    rng = torch.Generator().manual_seed(0)
    mask = torch.ones(12, 1)
    mask[0] = 0
    for step in range(300):
        opt.zero_grad()
        loss(cameras.apply_correction(xi * mask, start), rng, step).backward()
        opt.step()
    with torch.no_grad():
        end = cameras.apply_correction(xi * mask, start)

    def err(w):
        full = np.tile(np.eye(4), (12, 1, 1))
        full[:, :3, :4] = w.double().numpy()
        return evaluate_poses(full, scene["w2c"])["summary"]["rot_err_deg"]["mean"]

    assert err(start) > 0.8
    assert err(end) < 0.3 * err(start)


@pytest.mark.parametrize("kind", ["sampson", "reprojection"])
def test_a_view_keeps_its_update_only_where_its_held_out_tracks_improve(scene, kind):
    """Half the views brought from a small error to the truth keep their update; a worse update is
    kept by no view; with the rule off every view keeps its update."""
    loss, p = losses(scene, kind)
    start = perturb(scene["w2c"], 0.1, seed=3)  # real data is never exact: a small error to start from
    truth = torch.tensor(scene["w2c"][:, :3, :4]).float()
    better = start.clone()
    better[:6] = truth[:6]
    out = correspondence.accept_per_view(loss, start, better, p)
    assert out["checked"] and all(out["keep"][:6])  # the other six did not move: keeping them changes nothing
    assert out["error_kept"] < out["error_start"] and all(z < -out["z_limit"] for z in out["z"][:6])
    assert out["z_limit"] > 2.5  # 5 % over the views tested, not per view
    worse = perturb(scene["w2c"], 0.3)
    out = correspondence.accept_per_view(loss, start, worse, p)
    assert out["kept"] == 0 and out["kept_median_px"] == pytest.approx(out["start_median_px"])
    assert out["error_end"] > out["error_start"]
    off = correspondence.accept_per_view(loss, start, worse, dataclasses.replace(p, guard=False))
    assert off["keep"] == [True] * 12
    # too little evidence per view: nobody keeps an update, however good
    strict = correspondence.accept_per_view(loss, start, better, dataclasses.replace(p, accept_min_obs=10**6))
    assert strict["kept"] == 0


def test_held_out_draw_is_fixed_by_the_seed(scene):
    a, _ = losses(scene, "sampson")
    b, _ = losses(scene, "sampson")
    assert torch.equal(a.ms.held_index, b.ms.held_index)
    assert 0.1 < a.n_held_out / len(a.ms) < 0.3  # holdout_frac 0.2


def test_multiview_dlt_recovers_exact_points():
    """The tracks' batched DLT (TrackSet.triangulate's solver) is exact on noise-free observations."""
    rng = np.random.default_rng(0)
    w2c = synthetic.camera_poses(8)
    K = np.broadcast_to(synthetic.intrinsics(200, 200), (8, 3, 3))
    X = rng.uniform(-0.5, 0.5, (300, 3))
    cam, pt = np.repeat(np.arange(8), 300), np.tile(np.arange(300), 8)
    Xc = np.einsum("oij,oj->oi", w2c[cam, :3, :3], X[pt]) + w2c[cam, :3, 3]
    xn = cameras.pixels_to_normalised(K[cam], cameras.project_points(K[cam], Xc))
    Xt = correspondence.triangulate_multiview(w2c[cam, :3, :3], w2c[cam, :3, 3], xn, correspondence._padded(pt, 300))
    assert np.abs(Xt - X).max() < 1e-8


def test_views_whose_updates_pass_alone_but_raise_the_error_together_keep_their_start():
    """View 0's update lowers its held-out error only with view 1's, which fails its own test: kept alone,
    it would raise every error, so no view keeps its update."""

    class TwoViews(correspondence.ReprojectionLoss):
        def __init__(self, start):
            rng = np.random.default_rng(0)
            self.view = torch.arange(2).repeat_interleave(40)  # [80]: 40 held-out observations per view
            self.held_index = torch.arange(80)
            self.noise = torch.as_tensor(rng.normal(0, 0.02, 80), dtype=torch.float32)
            self.start = start

        def held_out_px(self, w2c):
            moved = [not torch.equal(w2c[v], self.start[v]) for v in (0, 1)]
            if moved == [True, True]:  # view 0 better, view 1 as it was
                base = torch.where(self.view == 0, 0.5, 1.0)
            else:
                base = torch.full((80,), 1.5 if moved[0] else 1.0)
            return base + self.noise

    start = torch.zeros(2, 3, 4)
    end = start + 0.01
    p = correspondence.CorrespondenceParams()
    out = correspondence.accept_per_view(TwoViews(start), start, end, p)
    assert out["z"][0] < -out["z_limit"] and out["together_worse"] and out["kept"] == 0
    assert out["error_kept"] == out["error_start"]
