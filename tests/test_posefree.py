"""Joint field + pose optimisation repairs deliberately perturbed poses (synthetic scene, CPU)."""
from __future__ import annotations

import numpy as np
import torch

from manifoldneus.geometry import cameras
from manifoldneus.data import synthetic
from manifoldneus.neural.field import FieldParams
from manifoldneus.neural.losses import LossParams
from manifoldneus.geometry.pose_metrics import evaluate_poses
from manifoldneus.neural.render import RenderParams
from manifoldneus.neural.train import TrainParams, Trainer, TrainRun, Views


def perturbed(w2c: np.ndarray, rot_deg: float, trans_sigma: float, seed: int = 0) -> np.ndarray:
    """Every view but the first moved by a random rotation of exactly ``rot_deg`` and a random
    translation (N(0, trans_sigma) per axis), as a left se(3) correction of the world-to-camera pose."""
    rng = np.random.default_rng(seed)
    n = len(w2c)
    xi = np.zeros((n, 6))
    axis = rng.normal(size=(n - 1, 3))
    xi[1:, 3:] = axis / np.linalg.norm(axis, axis=1, keepdims=True) * np.radians(rot_deg)
    xi[1:, :3] = rng.normal(scale=trans_sigma, size=(n - 1, 3))
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :4] = cameras.apply_correction(torch.tensor(xi), torch.tensor(w2c)).numpy()
    return out


def test_short_joint_run_reduces_rotation_error_of_perturbed_poses():
    scene = synthetic.make_scene(seed=1, n_views=8, resolution=48)
    w2c0 = perturbed(scene.w2c, rot_deg=3.0, trans_sigma=0.02)
    before = evaluate_poses(w2c0, scene.w2c)["summary"]
    views = Views(scene.images, scene.K, w2c0, scene.masks, None, None, scene.names)
    fp = FieldParams(kind="grid", grid_levels=4, grid_min_res=8, grid_max_res=48, decoder_width=32, dir_bands=2)
    rp = RenderParams(n_uniform=8, n_importance=16, n_coarse=32, cache_res=32, cache_every=20,
                      eikonal_samples=128, eikonal_uniform=32)
    tp = TrainParams(batch_rays=256, image_size=0, warmup=20, log_every=50)
    run = TrainRun(iters=200, threads=2, learn_poses=True, pose_lr=3e-3, pose_warmup=20)
    trainer = Trainer(views, fp, rp, LossParams(), tp, run=run, pose_views=np.arange(1, len(views.names)))  # view 0 fixes the gauge
    ticks = []
    trainer.train(on_step=ticks.append)  # a progress bar's tick every iteration, not every log_every
    assert ticks[-1] == trainer.step == 200 and len(ticks) >= 200
    after = evaluate_poses(trainer.poses_numpy(), scene.w2c)["summary"]
    assert before["rot_err_deg"]["mean"] > 2.5
    # measured: 2.7 -> 0.8-1.0 deg after 150-300 iterations
    assert after["rot_err_deg"]["mean"] < 0.5 * before["rot_err_deg"]["mean"]
    # the centres, weakly constrained by 8 views at 48 px, must at least not run away
    assert after["center_err_pct"]["mean"] < 3.0
