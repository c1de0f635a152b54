"""reference_surface: REFERENCE, NOT THE METHOD. The neural surface trained with ground-truth
poses, and the layout's own intrinsics and masks (a GT reader by design). It gives the upper bound the pose-free rounds are compared to,
and, on DTU (whose official point clouds are not here), the mesh that Chamfer is measured
against, labelled as such. Held-out views (split.holdout_every) are scored for novel-view
synthesis at the training resolution.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from manifoldneus.data import artifacts, io
from manifoldneus.output import evaluation, metrics
from manifoldneus.config import holdout_mask, param
from manifoldneus.neural.train import Trainer, TrainRun
from manifoldneus.data.views import Views


@dataclass
class Params:
    """Section `reference_surface` of params.yaml."""

    enabled: bool = param(True, "Train the GT-pose reference (False: write a note and skip)")
    iters: int = param(1500, "Training iterations; bench/bench_refine.py sets the pose-free rounds' total, for a "
                       "comparison at equal iterations", lo=1)
    seed: int = param(0, "Random seed of its training: fixed, not run.seed, so that runs of several seeds are "
                      "measured against one reference (and share it)", lo=0)


UPSTREAM = ("ingest", "ground_truth")
# meshing: the keys of a mesh without an object crop (the crop needs the method's SfM region)
SECTIONS = ("reference_surface", "train", "field", "render", "loss", "run.threads", "run.device", "split", "novel_views",
            *(f"meshing.{k}" for k in ("resolution", "coarse_step", "band", "keep_components", "drop_sphere_closure",
                                       "cull_by_masks", "cull_dilation", "cull_unseen", "visibility_size", "preview_size")))
OUTPUTS = (artifacts.REFERENCE_SURFACE_META,)
# of the method's ingest only the pixels (and monocular priors): cameras, masks and names come from the layout
# (ground_truth), so a run on the layout's photos alone shares this version with the calibrated, masked run
READS = {"ingest": tuple(f"{artifacts.VIEWS}/{a}" for a in artifacts.VIEW_PIXELS)}


def input_signature(scene, p) -> str:
    """LPIPS's weights (named by an environment variable) change the scores: their content counts."""
    return metrics.lpips_signature()


def run(ctx) -> None:
    gt_meta = artifacts.load_gt_meta(ctx.input("ground_truth"))
    if not ctx.params.enabled or not gt_meta["has_poses"]:
        why = "disabled" if not ctx.params.enabled else "the scene has no ground-truth poses"
        ctx.log.info("no reference surface: %s", why)
        io.save_json(ctx.out / artifacts.REFERENCE_SURFACE_META, {"trained": False, "why": why})
        return
    # ground truth through and through: the layout's poses, calibration and masks (when the method runs without)
    gt = artifacts.load_ground_truth_poses(ctx.input("ground_truth"))
    w2c = gt["w2c"]
    pixels = artifacts.load_view_pixels(ctx.input("ingest"))
    views = Views(pixels["images"], gt["K"], w2c, gt.get("masks"), pixels.get("mono_depth"), pixels.get("mono_normal"),
                  gt_meta["names"], pixels["sizes"])
    held = holdout_mask(len(views.names), ctx.section("split"))
    run_p = ctx.section("run")
    tp = ctx.section("train")
    run = TrainRun(iters=ctx.params.iters, seed=ctx.params.seed, threads=run_p.threads, device=run_p.device)
    ctx.checkpoint_dir.mkdir(parents=True, exist_ok=True)
    ckpt = ctx.checkpoint_dir / artifacts.MODEL
    trainer = Trainer(views, ctx.section("field"), ctx.section("render"), ctx.section("loss"), tp, run=run,
                      train_views=np.flatnonzero(~held), checkpoint_path=ckpt)
    if trainer.resume(ckpt):
        ctx.log.info("resumed from its checkpoint at step %d", trainer.step)
    bar = ctx.progress(total=run.iters, desc="reference_surface", initial=trainer.step)
    started = time.time()
    summary = trainer.train(callback=lambda t, info: (bar.update(info["step"] - bar.n),
                                                      bar.set_postfix(loss=f"{info['loss']:.4f}"))[-1])
    bar.close()
    seconds = time.time() - started
    trainer.save(ctx.out / artifacts.MODEL)
    mp = ctx.section("meshing")
    train_ids = np.flatnonzero(~held)
    masks = None if views.masks is None else views.masks[train_ids]
    mesh = evaluation.make_mesh(trainer, mp, views.K[train_ids], w2c[train_ids], masks, views.images.shape[1:3],
                                sizes=views.view_sizes[train_ids])
    evaluation.save_mesh_with_preview(mesh, ctx.out, mp, w2c=w2c[train_ids])
    nvs = evaluation.novel_views(trainer, views, np.flatnonzero(held), w2c, ctx.out / "novel_views", ctx.progress,
                                 align=ctx.section("novel_views"))
    rays = summary["steps"] * tp.batch_rays
    io.save_json(ctx.out / artifacts.REFERENCE_SURFACE_META, {
        "trained": True, "label": "reference: trained with GROUND-TRUTH poses", "train": summary,
        "history": trainer.history, "novel_views": nvs, "train_seconds": seconds,
        "rays_per_second": rays / max(seconds, 1e-9), "mesh_faces": int(len(mesh.faces))})
    ctx.metrics.update(label="GT-pose reference", train_seconds=round(seconds, 1),
                       rays_per_second=round(rays / max(seconds, 1e-9)), steps=summary["steps"],
                       losses_on=sorted(k for k, v in summary["loss_status"].items() if v == "on"),
                       **{f"nvs_{k}": v for k, v in nvs["summary"].items() if isinstance(v, float)})
