"""surface: the field the mesh and the held-out renderings come from, trained on every view the rounds
posed, at the poses they ended with (held fixed), with every band of the field on from the start.

The rounds fit their field on growing subsets of the views while the poses move: what the anchors' few
views formed stays in it (docs/REFINEMENT.md). Once the poses are decided, a field trained on all views
at once (``surface.start = fresh``: a new field, its grid box fitted to every view's visual hull or
common frustum) gives the surface NeuS gives on the same poses. Writes the same files as a round
(:func:`manifoldneus.posefree.save_round`'s layout): ``poses.zarr`` (the last round's, unchanged),
``model.pt``, ``round.json`` (this training's summary); with ``surface.iters = 0`` the last round's
field is the surface (copied).
"""
from __future__ import annotations

import shutil
import time
from dataclasses import dataclass

import numpy as np
import torch

from manifoldneus import artifacts, io, posefree
from manifoldneus.config import param
from manifoldneus.train import Trainer, TrainRun


@dataclass
class Params:
    """Section `surface` of params.yaml."""

    iters: int = param(1500, "Iterations of the surface field on every posed view at its final pose (0 = none: the "
                       "last round's field is the surface)", lo=0)
    start: str = param("fresh", "fresh: a new field, its grid box fitted to all views; rounds: the last round's "
                       "field trained on (keeps what the rounds' subsets of views formed)",
                       choices=["fresh", "rounds"])


UPSTREAM = ("ingest", "anchors", "successors")
SECTIONS = ("surface", "train", "field", "render", "loss", "run")
OUTPUTS = (artifacts.POSES, artifacts.MODEL, artifacts.ROUND_META)


def run(ctx) -> None:
    p: Params = ctx.params
    final = ctx.input("successors") / artifacts.FINAL_ROUND
    shutil.copytree(final / artifacts.POSES, ctx.out / artifacts.POSES)  # the poses are decided: the surface keeps them
    if p.iters == 0:
        shutil.copy2(final / artifacts.MODEL, ctx.out / artifacts.MODEL)
        io.save_json(ctx.out / artifacts.ROUND_META, {"surface": "the last round's field", "iters": 0})
        return
    result = artifacts.load_round(final)
    w2c = result["w2c"]
    views = artifacts.load_views(ctx.input("ingest"), w2c, result["K"], result.get("distortion"))
    ids = np.flatnonzero(result["optimised"].astype(bool))
    run_p = ctx.section("run")
    trun = TrainRun(iters=p.iters, seed=run_p.seed, threads=run_p.threads, device=run_p.device)
    ctx.checkpoint_dir.mkdir(parents=True, exist_ok=True)
    ckpt = ctx.checkpoint_dir / artifacts.MODEL
    lp = ctx.section("loss")
    trainer = Trainer(posefree.subset_views(views, ids, w2c), ctx.section("field"), ctx.section("render"), lp,
                      ctx.section("train"), run=trun, checkpoint_path=ckpt)
    if lp.w_free_space > 0 and views.masks is None:  # without masks: no surface along the SfM lines of sight
        sfm_points = artifacts.load_initial_poses(ctx.input("anchors"), list(posefree.SFM_POINTS))
        trainer.free_space = posefree.free_space_term(lp, sfm_points, trainer.rp.radius, trainer.device)
    if p.start == "rounds":
        carried = torch.load(final / artifacts.MODEL, map_location=trainer.device, weights_only=False)
        trainer.field.load_state_dict(carried["field"])
        trainer.background.load_state_dict(carried["background"])
        if trainer.cache is not None and carried.get("cache") is not None:
            trainer.cache.load_state_dict(carried["cache"])
    if trainer.resume(ckpt):
        ctx.log.info("resumed from its checkpoint at step %d", trainer.step)
    bar = ctx.progress(total=trun.iters, desc="surface", initial=trainer.step)
    started = time.time()
    summary = trainer.train(callback=lambda t, info: bar.set_postfix(loss=f"{info['loss']:.4f}"),
                            on_step=lambda step: bar.update(step - bar.n))
    bar.close()
    seconds = time.time() - started
    trainer.save(ctx.out / artifacts.MODEL)
    io.save_json(ctx.out / artifacts.ROUND_META, io.without_keys(
        {"surface": f"{p.start} field on {len(ids)} views at their final poses", "iters": p.iters,
         "views": [int(v) for v in ids], "train": summary, "history": trainer.history}, posefree.RUN_FACTS))
    ctx.metrics.update(views=int(len(ids)), iters=p.iters, train_seconds=round(seconds, 1),
                       final_loss=summary["final_loss"])
