"""successors: the MaVOS successor rounds. Each round places its new views by PnP against depth
rendered from the current model (fallback: the best-matching optimised neighbour's pose), then
optimises all views scheduled so far jointly. One sub-artifact per round (``round_<r>/``); each
round is also checkpointed, so an interrupted run resumes at the round (and iteration) it reached.
"""
from __future__ import annotations

import dataclasses
import os
import shutil
from dataclasses import dataclass

import numpy as np
import torch

from manifoldneus.data import artifacts, io
from manifoldneus.sfm import pose_init
from manifoldneus import posefree
from manifoldneus.config import param
from stages import anchors  # COLMAP's mapper and gauge as the anchors run them


@dataclass
class Params:
    """Section `successors` of params.yaml."""

    iters: int = param(1000, "Iterations of each successor round", lo=1)
    final_iters: int = param(0, "Iterations of the last round run (0 = `iters`): the round that fits the field and "
                             "poses of every view, whose result is final", lo=0)
    pose_lr: float = param(5e-3, "Peak AdamW lr of the pose corrections (supplement: 5e-3)", lo=0.0)
    pose_start_frac: float = param(0.2, "Poses stay frozen for this fraction of the iterations (the field fits first)",
                                   lo=0.0, hi=1.0)
    pose_warmup_frac: float = param(0.1, "Pose lr warm-up as a fraction of a round", lo=0.0, hi=1.0)
    optimise_poses: bool = param(True, "Learn per-view pose corrections")
    final_translation: bool = param(True, "The last round learns translations too (False: rotations only; its camera "
                                    "centres stay where the round starts them: with sfm_restart last, sfm-all's)")
    refine_placed: bool = param(True, "A round also refines the poses of the views earlier rounds placed (False: only "
                                "its new views' poses learn; the earlier ones stay where their round left them)")
    correspondence_weight: float = param(0.01, "Weight of the correspondence term in a successor round's pose loss "
                                         "(smaller than the anchors': with many views the matches' own optimum is "
                                         "further from the truth than the images', docs/REFINEMENT.md)", lo=0.0)
    placement: str = param("depth", "Initial pose of a new view: 'depth' (PnP on matches lifted with depth rendered "
                           "from the model, METHOD.md) or 'matches' (incremental SfM on the verified matches of all "
                           "views so far, Sim3-aligned to the optimised poses)", choices=["depth", "matches"])
    sfm_restart: str = param("none", "Rounds whose placed views also restart from the matches' SfM (COLMAP's mapper "
                             "over every view placed so far and the round's new ones, Sim3-aligned to the optimised "
                             "poses), as the new views start: none, last (the final round, when every view joins) "
                             "or every round. The field keeps what it learnt; with refine_placed false the restarted poses are "
                             "then held (docs/REFINEMENT.md)",
                             choices=["none", "last", "every"])
    final_image_size: int = param(-1, "Longest side (px) the last round trains at: -1 = train.image_size like the "
                                  "other rounds, 0 = the images' own size (coarse-to-fine over image resolution: "
                                  "the earlier rounds fit the field at train.image_size, the last one sharpens it "
                                  "and the poses on the full images; a step costs the same at any size)", lo=-1)
    regate_kept: float = param(0.0, "Fraction of the field's bands (the coarsest) that the views earlier rounds "
                               "optimised keep from a round's start; their finer bands, and every band of the "
                               "round's new views, go through the coarse-to-fine gate again: 0 = every view "
                               "restarts coarse-to-fine (the gate read per round), 1 = only the new views do",
                               lo=0.0, hi=1.0)
    polish_steps: int = param(0, "Poses-only polish closing a round: Adam steps of every round view's pose against "
                              "the field the round trained, the field held (0 = off; docs/REFINEMENT.md)", lo=0)
    polish_rays: int = param(4096, "Pose polish: rays per step over the round's views", lo=16)
    polish_lr: float = param(1e-3, "Pose polish: peak lr of the se(3) corrections (cosine to a tenth)", lo=0.0)
    polish_translation: bool = param(True, "Pose polish: learn translations too (False: rotations only, which keeps "
                                     "every camera centre where the round left it)")
    polish_rounds: str = param("last", "Which rounds the polish closes: the last or every one",
                               choices=["last", "every"])
    pnp_reproj_px: float = param(3.0, "PnP-RANSAC inlier threshold (px)", lo=0.1)
    max_rounds: int = param(0, "Stop after this many successor rounds (0 = all); later rounds' views stay unplaced "
                            "(the sweeps of bench/sweep.py only read round 1)", lo=0)
    pnp_min_inliers: int = param(12, "Fewer PnP inliers -> fallback to the best-matching optimised neighbour", lo=4)


UPSTREAM = ("ingest", "features", "matching", "covisibility", "schedule", "anchors")
SECTIONS = ("successors", "train", "field", "render", "loss", "gate", "correspondence", "run", "anchors.reproj_px",
            "anchors.ba_loss", "anchors.ba_loss_px", "anchors.principal_point_p", "anchors.radial_p",
            "anchors.gauge_radius", "anchors.gauge_percentile", "anchors.gauge_centre", "anchors.object_min_seen")
OUTPUTS = (artifacts.FINAL_ROUND,)


def matches_placement(inputs, placed_ids, new_ids, w2c: np.ndarray, mapper: pose_init.MapperOptions,
                      gauge: pose_init.GaugeOptions) -> tuple[dict, np.ndarray | None]:
    """Poses of placed + new views from an incremental SfM over them (verified matches only; COLMAP's
    mapper as the anchors run it, K held, in the anchors' gauge of its points: over every view it is
    `sfm-all`'s SfM, to the bit), brought into the model's frame by the Sim3 that maps its placed views
    onto their optimised poses; views the SfM did not register are left out. Returns the poses by view and
    that Sim3 as a 4x4 (the SfM's gauge frame -> the model's; None where fewer than 3 placed views
    registered)."""
    from manifoldneus.geometry import cameras

    ids = sorted(set(map(int, placed_ids)) | set(map(int, new_ids)))
    masks = None if inputs.views.masks is None else [inputs.views.masks[v] for v in ids]
    res = pose_init.init_from_matches(ids, inputs.views.K, inputs.keypoints, inputs.pairs, inputs.W, sizes=inputs.sizes,
                                      mapper=mapper, gauge=gauge, masks=masks)
    row = {v: k for k, v in enumerate(ids)}
    ok = [v for v in placed_ids if res.placed[row[v]]]
    if len(ok) < 3:
        return {}, None
    s, R, t = cameras.umeyama_sim3(cameras.camera_centers(res.w2c[[row[v] for v in ok]]), cameras.camera_centers(w2c[ok]))
    moved = cameras.transform_w2c(res.w2c, s, R, t)
    return {v: moved[row[v]] for v in ids if res.placed[row[v]]}, cameras.sim3_matrix(s, R, t)


def run(ctx) -> None:
    p: Params = ctx.params
    cfg = posefree.RoundConfig.from_sections(ctx.section, ctx.log_path)
    inputs = posefree.load_inputs(**{s: ctx.input(s) for s in posefree.INPUT_STAGES})
    rounds = inputs.schedule["round"]
    n_rounds = int(rounds.max()) if (rounds >= 0).any() else 0
    if p.max_rounds and n_rounds > p.max_rounds:
        ctx.log.info("successors.max_rounds = %d: rounds %d..%d are not run", p.max_rounds, p.max_rounds + 1, n_rounds)
        n_rounds = p.max_rounds
    prev_dir = ctx.input("anchors") / artifacts.ANCHOR_ROUND
    prev = artifacts.load_round(prev_dir)
    inputs = posefree.with_intrinsics(inputs, prev["K"], prev.get("distortion"))  # the anchors' (refined, if they were)
    anchors_p = ctx.section("anchors")  # the SfM a round restarts from is sfm-all's of the same seed, K held
    sfm = (anchors.mapper_options(inputs, anchors_p, cfg.run.seed), anchors.gauge_options(anchors_p))
    carry = {k: v for k, v in torch.load(prev_dir / artifacts.MODEL, map_location="cpu", weights_only=False).items()
             if k in ("field", "background", "cache")}
    w2c, placed = prev["w2c"], prev["placed"].astype(bool)
    ctx.checkpoint_dir.mkdir(parents=True, exist_ok=True)
    ctx.metrics["rounds"] = []
    left_out: list[int] = []  # views an earlier round could not place: retried once more views are placed
    sfm_points = artifacts.load_initial_poses(ctx.input("anchors"), list(posefree.SFM_POINTS))
    for r in range(1, n_rounds + 1):
        new = [*left_out, *(int(v) for v in np.flatnonzero((rounds == r) & inputs.train_mask))]
        left_out = []
        from_matches, round_from_sfm = None, None
        before = np.flatnonzero(placed)  # the views whose poses the round inherits: the SfM's Sim3 is fitted on them
        restart = p.sfm_restart == "every" or (p.sfm_restart == "last" and r == n_rounds)
        if restart and len(before):  # first, so that depth PnP places the new views against the restarted poses
            with io.native_output_to(ctx.log_path):
                from_matches, round_from_sfm = matches_placement(inputs, before, new, w2c, *sfm)
            moved = [int(v) for v in before if v in from_matches]
            for v in moved:
                w2c[v] = from_matches[v]
            ctx.log.info("round %d: %d of %d placed views restart from the matches' SfM (successors.sfm_restart = %s)",
                         r, len(moved), len(before), p.sfm_restart)
        # initial poses of the new views (depth PnP against the previous round's model, or the matches)
        if p.placement == "depth":
            probe = posefree.Round(cfg, inputs, before, w2c, np.ones(len(w2c)), iters=1, carry=carry)
            depth_at = posefree.depth_at_fn(probe)
        placed_poses = {int(v): w2c[v] for v in before}
        init = {}
        for v in ctx.progress(new, desc=f"round {r}: placing"):
            pose, info = None, {"method": "unplaced"}
            if p.placement == "depth":
                pose, info = pose_init.place_successor(v, inputs.views.K, inputs.keypoints, inputs.pairs,
                                                       placed_poses, inputs.W, depth_at=depth_at, ray_distance=True,
                                                       reproj_px=p.pnp_reproj_px, min_inliers=p.pnp_min_inliers)
            if p.placement == "matches" or info["method"] != "pnp":
                if from_matches is None:
                    with io.native_output_to(ctx.log_path):  # COLMAP's own log goes to log.txt
                        from_matches, round_from_sfm = matches_placement(inputs, before, new, w2c, *sfm)
                if from_matches.get(v) is not None:
                    pose, info = from_matches[v], {"method": "matches", "after": info["method"] if p.placement == "depth" else None}
            init[inputs.names[v]] = info
            if pose is None:
                why = ("COLMAP did not register it with the placed views' matches" if p.placement == "matches"
                       else "it has no verified matches to a placed view")
                ctx.log.warning("round %d: view %s cannot be placed (%s); left out of the round%s", r, inputs.names[v],
                                why, ", retried in the next" if r < n_rounds else "")
                left_out.append(v)
                continue
            if info["method"] == "fallback":
                ctx.log.warning("round %d: PnP failed for %s (%d inliers); starting from neighbour %s's pose", r,
                                inputs.names[v], info["n_inliers"], inputs.names[info["neighbour"]])
            elif info["method"] == "matches" and info.get("after"):
                ctx.log.info("round %d: depth PnP gave %s for %s; placed from the matches instead", r, info["after"],
                             inputs.names[v])
            w2c[v] = pose
            placed[v] = True
        ids = np.flatnonzero(placed)
        last = r == n_rounds
        iters = p.final_iters if last and p.final_iters else p.iters
        poses = dataclasses.replace(posefree.PoseLearning.of(p), translation=p.final_translation or not last)
        rnd = posefree.Round(cfg, inputs, ids, w2c, inputs.schedule["s_tilde_rounds"][r], iters=iters, poses=poses,
                             carry=carry, pose_ids=None if p.refine_placed else new, sfm_points=sfm_points,
                             image_size=p.final_image_size if last and p.final_image_size >= 0 else None,
                             kept_ids=np.setdiff1d(ids, new), kept_frac=p.regate_kept,
                             polish=posefree.Polish(p.polish_steps, p.polish_rays, p.polish_lr, p.polish_translation)
                             if last or p.polish_rounds == "every" else None)
        summary = rnd.run(f"round {r}", ctx.checkpoint_dir / f"{artifacts.round_folder(r)}.pt", log=ctx.log, progress=ctx.progress)
        posefree.save_round(ctx.out / artifacts.round_folder(r), rnd, placed.copy(), {
            "round": r, "views": [int(v) for v in ids], "new_views": new, "init": init, "train": summary,
            "history": rnd.trainer.history,
            **({} if round_from_sfm is None else {"round_from_sfm": round_from_sfm.tolist()})})
        w2c = rnd.poses_all()
        carry = rnd.carry()
        methods = [i["method"] for i in init.values()]
        ctx.metrics["rounds"].append({"round": r, "n_views": int(len(ids)), "new": len(new),
                                      "pnp": methods.count("pnp"), "matches": methods.count("matches"),
                                      "fallback": methods.count("fallback"),
                                      "unplaced": methods.count("unplaced"), "seconds": summary["seconds"],
                                      "final_loss": summary["final_loss"], "rollbacks": summary["rollbacks"]})
    if n_rounds:
        os.symlink(artifacts.round_folder(n_rounds), ctx.out / artifacts.FINAL_ROUND)  # relative: survives the version's rename
    else:  # no successor rounds (e.g. the uniform schedule): the anchors' result is final
        shutil.copytree(prev_dir, ctx.out / artifacts.FINAL_ROUND)
    ctx.metrics["n_rounds"] = n_rounds
