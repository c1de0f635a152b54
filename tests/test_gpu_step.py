"""The step for a GPU: the `gpu` profile's size, the deferred checks (train.check_every) and the compiled step
(train.compile), measured on the CPU (docs/PERFORMANCE.md, "A step for the GPU")."""
from __future__ import annotations

import dataclasses
import logging

import pytest
import torch

import runner
from bench.profile_step import counting_host_reads
from manifoldneus.neural.losses import LossParams
from manifoldneus.neural.train import Trainer, compile_unavailable
from test_neural import synthetic_views, tiny_params

PAPER_SAMPLES = 512 * (64 + 64)  # the paper profile's step: 512 rays of 64 + 64 network samples


def static_tiny(iters, **train):
    """tiny_params with the static shapes a compiled step needs (no compaction of samples)."""
    fp, rp, tp, run = tiny_params(iters)
    rp = dataclasses.replace(rp, skip_empty=False, colour_min_weight=0.0)
    return fp, rp, dataclasses.replace(tp, **train), run


def test_the_gpu_profile_sizes_the_step_for_a_device_and_fast_keeps_the_eager_step():
    stages = runner.load_stages()
    gpu = runner.resolve_params(stages, profile="gpu", overrides=["run.device=cuda"])
    tp, rp, fp = gpu["train"], gpu["render"], gpu["field"]
    assert tp.image_size == 0 and tp.batch_rays >= 1000
    assert tp.batch_rays * (rp.n_uniform + rp.n_importance) >= 8 * PAPER_SAMPLES
    assert (fp.kind, rp.sampler) == ("grid", "cache") and fp.grid_max_res >= 2048 and 19 <= fp.grid_hash_log2 <= 21
    assert not rp.skip_empty and rp.colour_min_weight == 0  # static shapes
    assert tp.compile != "off" and tp.check_every > 1 and tp.ckpt_every % tp.check_every == 0
    for name in ("fast", "quick", "paper"):
        other = runner.resolve_params(stages, profile=name)["train"]
        assert (other.compile, other.check_every) == ("off", 1), name


def test_between_checks_a_step_reads_nothing_from_the_device_and_a_nan_still_rolls_back():
    views = synthetic_views(n=4, size=16)
    fp, rp, tp, run = static_tiny(40, check_every=5)
    tr = Trainer(views, fp, rp, LossParams(), tp, run=run)
    for _ in range(11):
        tr.train_step()
    with counting_host_reads() as reads:
        results = [tr.train_step() for _ in range(3)]  # steps 12, 13, 14: no check
    assert sum(reads.values()) == 0, dict(reads)
    assert all(r["loss"] is None for r in results) and tr.step == 14
    eager = Trainer(views, fp, rp, LossParams(), dataclasses.replace(tp, check_every=1), run=run)
    with counting_host_reads() as reads:
        eager.train_step()
    assert sum(reads.values()) > 0  # the per-step check reads the loss and the gradients' finiteness

    r = tr.train_step(inject_nan=True)  # step 15 is a check: the NaN is found there
    assert r.get("rollback") and tr.step == 10 and tr.rollbacks == 1
    assert tr.lr_scale == pytest.approx(0.5) and "non-finite loss" in tr.events[-1]["reason"]
    for p in tr.field.parameters():
        assert torch.isfinite(p).all()
    # a NaN found a few steps later, the parameters it reached rolled back too
    for _ in range(2):
        tr.train_step()
    tr.train_step(inject_nan=True)
    results = [tr.train_step() for _ in range(2)]
    assert results[-1].get("rollback") and tr.step == 10 and tr.rollbacks == 2
    summary = tr.train(iters=20)
    assert tr.step == 20 and isinstance(summary["final_loss"], float) and tr.history[-1]["step"] == 20


def test_a_run_with_deferred_checks_resumes_as_it_runs(tmp_path):
    """The ray indices of a check window are drawn at once: a run resumed at a checkpoint draws what the
    uninterrupted run drew (ckpt_every a multiple of check_every)."""
    views = synthetic_views(n=4, size=16)
    fp, rp, tp, run = static_tiny(25, check_every=5)
    whole = Trainer(views, fp, rp, LossParams(), tp, run=run)
    whole.train()
    ck = tmp_path / "ck.pt"
    Trainer(views, fp, rp, LossParams(), tp, run=run, checkpoint_path=ck).train(iters=17)  # the file holds step 10
    resumed = Trainer(views, fp, rp, LossParams(), tp, run=run)
    resumed.load(ck)
    resumed.train()
    for a, b in zip(whole.field.parameters(), resumed.field.parameters()):
        assert torch.equal(a, b)
    assert whole.history[-1] == resumed.history[-1]


@pytest.mark.skipif(compile_unavailable(torch.device("cpu")) is not None, reason="no C++ compiler for inductor")
def test_the_compiled_step_computes_the_eager_steps_losses():
    """train.compile builds the same step (inductor's C++ kernels on the CPU, the grids' torch kernel): the same
    losses to float tolerance at one seed, random draws included (inductor's fallback_random)."""
    views = synthetic_views(n=4, size=16)
    fp, rp, tp, run = static_tiny(10, check_every=5, log_every=5, ckpt_every=5)
    fp = dataclasses.replace(fp, grid_levels=2, grid_kernel="torch")
    rp = dataclasses.replace(rp, eikonal_uniform=0)
    losses = {}
    for mode in ("off", "default"):
        tr = Trainer(views, fp, rp, LossParams(), dataclasses.replace(tp, compile=mode), run=run)
        tr.train()
        losses[mode] = [h["loss"] for h in tr.history]
    assert len(losses["off"]) == 2
    assert losses["default"] == pytest.approx(losses["off"], rel=1e-4)


def test_a_compiler_that_is_missing_is_named_and_the_step_runs_eagerly(monkeypatch, caplog):
    import manifoldneus.neural.train as train

    monkeypatch.setattr(train, "compile_unavailable", lambda device: "no C++ compiler (a test's)")
    views = synthetic_views(n=4, size=16)
    fp, rp, tp, run = static_tiny(4, compile="default")
    with caplog.at_level(logging.WARNING, logger="manifoldneus.train"):
        tr = Trainer(views, fp, rp, LossParams(), tp, run=run)
    assert "no C++ compiler (a test's); the training step runs eagerly" in caplog.text
    assert tr._loss_fn == tr._render_losses
    tr.train()
    assert tr.step == 4
