"""surface: the field the mesh and the held-out renderings come from, trained on every view the rounds
posed, at the poses they ended with (held fixed), with every band of the field on from the start.

The rounds fit their field on growing subsets of the views while the poses move: what the anchors' few
views formed stays in it (docs/REFINEMENT.md). Once the poses are decided, a field trained on all views
at once (``surface.start = fresh``: a new field, its grid box fitted to every view's visual hull or
common frustum) gives the surface NeuS gives on the same poses. Without masks its frame is scaled down to
hold the object's whole extent well inside the sphere (``surface.extent_radius``), its colour turns more slowly
with the view (``surface.unmasked_dir_bands``: a membrane across a concavity, which every outline holds, shows what
lies behind it only through colour that turns quickly with the view), and it can make masks of its own from the
photos and the last round's SfM tracks (``surface.photo_masks``,
:mod:`manifoldneus.geometry.segmentation`), which the field then follows where the views agree. Writes the same
files as a round (:func:`manifoldneus.posefree.save_round`'s layout): ``poses.zarr`` (the last round's,
unchanged), ``model.pt``, ``round.json`` (this training's summary), and where it made masks ``photo_masks.zarr``
(``masks`` GrabCut's and ``voted`` the views' vote [V,H,W], of the views ``views`` [V]) with
``photo_masks.png`` (a few views, the pixels the masks decide tinted); with ``surface.iters = 0`` the last
round's field is the surface (copied).
"""
from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from manifoldneus.data import artifacts, io
from manifoldneus.geometry import cameras, object_region, segmentation
from manifoldneus import posefree
from manifoldneus.config import ParamError, param
from manifoldneus.neural.train import Trainer, TrainRun


@dataclass
class Params:
    """Section `surface` of params.yaml."""

    iters: int = param(1500, "Iterations of the surface field on every posed view at its final pose (0 = none: the "
                       "last round's field is the surface)", lo=0)
    start: str = param("fresh", "fresh: a new field, its grid box fitted to all views; rounds: the last round's "
                       "field trained on (keeps what the rounds' subsets of views formed; needs frame = rounds)",
                       choices=["fresh", "rounds"])
    frame: str = param("views", "The field's normalisation: views (the object's SfM points of every posed view, "
                       "scaled and centred as the anchors' gauge does with theirs) or rounds (the anchors' gauge, "
                       "fitted to the anchors' points only)", choices=["views", "rounds"])
    axes: str = param("sfm", "The views' frame: sfm (the gauge of the matches' SfM the last round placed its views "
                      "from, sfm-all's own: where the round kept none of its views' updates, NeuS on sfm-all's poses "
                      "to the bit; the gauge refitted to the round's tracks where it placed none from the SfM) or "
                      "rounds (that refit in the anchors' SfM's axes)", choices=["sfm", "rounds"])
    photo_masks: bool = param(False, "Without the layout's masks: segment each posed view by GrabCut seeded by the "
                              "last round's SfM tracks (the object's points foreground; its support's and those "
                              "outside its region background), let the views vote on them, and train the field "
                              "towards them (loss.w_photo_mask) where a view's mask and the vote agree")
    photo_mask_band: int = param(25, "photo_masks: how far (pixels of the ingest's images) beyond the convex hull of "
                                 "the object's SfM points GrabCut may extend the object: its textureless parts that "
                                 "no point reaches", lo=1)
    photo_mask_support: float = param(0.02, "photo_masks: SfM points less than this (of the object region's radius) "
                                      "above its support plane are the support's, background seeds", lo=0.0)
    photo_mask_vote: float = param(0.9, "photo_masks: the share of the views holding a point in their frame that "
                                   "must have it inside their mask for the vote to keep it", lo=0.5, hi=1.0)
    photo_mask_fill: bool = param(False, "photo_masks: also train towards the object where a view's mask and the vote "
                                  "both hold it (params.yaml: on). Photos alone, three seeds, against no photo masks: "
                                  "Chamfer scan24 1.99 against 4.09 mm, scan24_idr 2.80 against 4.69, scan65_idr 1.49 "
                                  "against 1.55; synthetic 0.0129 against 0.0107, where both hold the torus's hole "
                                  "and the box's top behind the sphere and surface grows there; off: only the "
                                  "background they agree on is carved")
    photo_mask_fill_colour: float = param(8.0, "photo_masks with photo_mask_fill: filled pixels whose colour lies "
                                          "within this many RGB levels of one the view's carved background shows "
                                          "are left to the photos (a hole the object encloses shows the "
                                          "background; scan24: Chamfer 1.82 against 1.90 mm, three seeds); 0: none",
                                          lo=0.0)
    photo_mask_erode: int = param(4, "photo_masks: the pixels (of the ingest's images) each decided region shrinks "
                                  "by, away from the masks' edges", lo=0)
    photo_mask_sight_lines: bool = param(False, "photo_masks: keep the SfM lines of sight free of surface too "
                                         "(loss.w_free_space, as without photo masks); off, the carved background "
                                         "does their work: Chamfer scan24_idr 3.12 mm without them against 3.92 "
                                         "with them (three seeds), scan65_idr 1.56 against 1.42 (seed 0)")
    unmasked_dir_bands: int = param(0, "Without the layout's masks: the Fourier bands of the surface field's "
                                    "view-direction encoding (-1: field.dir_bands, as with masks). Fewer bands keep "
                                    "membranes off concavities, which every outline holds and which show what lies "
                                    "behind them only through colour that turns quickly with the view, but fit "
                                    "DTU's lights, which move with the camera, worse. Photos alone, Chamfer of "
                                    "seeds 0 / 1 / 2 at 0 against 4 bands: scan24 1.81 / 1.74 / 1.81 mm against "
                                    "1.82 / 2.17 / 1.99, scan65_idr 1.48 / 1.43 / 1.44 against 1.57 / 1.43 / 1.47, "
                                    "synthetic 0.0128 / 0.0118 / 0.0118 against 0.0146 / 0.0118 / 0.0122, "
                                    "scan24_idr 3.03 / 3.13 / 2.77 against 2.68 / 2.85 / 2.87", lo=-1, hi=10)
    unmasked_view_cosine: bool = param(False, "Without the layout's masks: the surface field's colour also reads the "
                                       "cosine between the view and the surface's normal (field.view_cosine), the "
                                       "shading of a light that moves with the camera, which no view-direction "
                                       "band is left to fit (unmasked_dir_bands). Photos alone, Chamfer with it "
                                       "against without, the two seeds that miss their limits with one or the "
                                       "other: scan24 seed 2 1.77 mm against 1.81, scan24_idr seed 1 2.90 against "
                                       "3.13 (the other seeds: docs/EXPERIMENTS.md)")
    extent_radius: float = param(0.6, "Without masks (frame = views), the field's frame is scaled down until the "
                                 "object's whole extent (the 99th percentile of the distances of the SfM points in "
                                 "the anchors' object region that extent_min_seen of the views see) lies within this "
                                 "radius; never up. The gauge fits the points most views see, and the parts fewer "
                                 "views see reach beyond them (scan24: 0.81 of the sphere, scan65: 0.62), where the "
                                 "background beyond the sphere explains them as well as the field and no mask "
                                 "makes the field hold them. 1 = the gauge as it is", lo=0.1, hi=1.0)
    extent_min_seen: float = param(0.2, "The fraction of the views that must see a point for it to count in the "
                                   "object's extent (extent_radius)", lo=0.0, hi=1.0)

    def __post_init__(self):
        if self.start == "rounds" and self.frame != "rounds":
            raise ParamError("surface.start = rounds trains the last round's field on: it needs surface.frame = rounds")


UPSTREAM = ("ingest", "anchors", "successors")
SECTIONS = ("surface", "train", "field", "render", "loss", "run", "anchors.gauge_radius", "anchors.gauge_percentile",
            "anchors.gauge_centre", "anchors.object_min_seen")
OUTPUTS = (artifacts.POSES, artifacts.MODEL, artifacts.ROUND_META)


def field_frame(result: dict, views, ids: np.ndarray, anchors_p, axes: str = "sfm") -> np.ndarray:
    """4x4 similarity from the rounds' frame to the field's. ``axes = sfm`` where the last round placed its
    views from the matches' SfM over them: that SfM's own gauge (the anchors' gauge fitted to its points,
    the round's ``round_from_sfm`` undone), the frame of NeuS on `sfm-all`'s poses: over every view it is
    sfm-all's SfM, so where the round kept none of its views' updates the field trains on sfm-all's poses
    to the bit. Otherwise (or ``axes = rounds``) the same gauge y = s (x - c)
    (:func:`manifoldneus.geometry.cameras.gauge_from_points`) fitted to the last round's tracks over every posed
    view in the rounds' axes, on the points the anchors would pick: with masks those most of whose observations
    fall inside the masks (those most views holding them see inside their masks also keep what lies behind
    the object, e.g. the table: scan65's object shrank 0.77x), without masks those in the views' common
    frustum; identity where the round kept too few tracks. Turned onto the points' principal axes instead
    (the tightest box), scan65_idr's surface lost 0.3 dB."""
    round_from_sfm = result["info"].get("round_from_sfm") if axes == "sfm" else None
    if round_from_sfm is not None:
        return np.linalg.inv(np.asarray(round_from_sfm, np.float64))
    points = result.get("track_points")
    if points is None or len(points) < 20:
        return np.eye(4)
    K, w2c = views.K[ids], result["w2c"][ids]
    if views.masks is not None:
        view, point, uv = result["track_obs_view"], result["track_obs_point"], result["track_obs_uv"]
        H, W = views.masks.shape[1:3]
        inside = views.masks[view, np.clip(uv[:, 1].astype(int), 0, H - 1), np.clip(uv[:, 0].astype(int), 0, W - 1)]
        obj = np.bincount(point, inside, len(points)) > 0.5 * np.maximum(np.bincount(point, minlength=len(points)), 1)
    else:
        sizes = views.view_sizes[ids]
        obj = object_region.seen_fraction(points, K, w2c, sizes) >= anchors_p.object_min_seen
    fitted = points[obj] if obj.sum() >= 20 else points  # [P,3]
    s, c = cameras.gauge_from_points(fitted, anchors_p.gauge_radius, anchors_p.gauge_percentile, anchors_p.gauge_centre)
    return cameras.sim3_matrix(s, np.eye(3), -s * c)


def extent_scale(points: np.ndarray, seen: np.ndarray, region: object_region.ObjectRegion | None,
                 radius: float, min_seen: float) -> float:
    """The scale (<= 1) that brings the object's extent within ``radius`` of the origin: the 99th percentile of
    the distances of the points [P,3] (the field's frame) inside ``region`` that at least ``min_seen`` of the
    views see (``seen`` [P], fractions). 1 when fewer than 20 points qualify."""
    keep = seen >= min_seen
    if region is not None:
        keep &= region.contains(points)
    if keep.sum() < 20:
        return 1.0
    return min(1.0, radius / float(np.percentile(np.linalg.norm(points[keep], axis=1), 99)))


def photo_labels(ctx, views, result: dict, ids: np.ndarray) -> np.ndarray:
    """[N,H,W] float32 object labels of every view (0.5 where undecided, and in the views ``ids`` leaves out) from
    masks made from the photos (module doc); saves them and their picture."""
    p: Params = ctx.params
    min_seen = ctx.section("anchors").object_min_seen
    w2c, sizes = result["w2c"], views.view_sizes
    # the region and its support refitted to the final round's tracks over every posed view: the anchors' plane,
    # fitted to their few views' points, can lie a few % of the radius off them
    region, obj = object_region.locate(result["track_points"], views.K[ids], w2c[ids], sizes[ids], min_seen)
    masks = segmentation.object_masks(views.images, sizes, views.K, w2c, ids, result, region, min_seen,
                                      p.photo_mask_support, p.photo_mask_band,
                                      progress=lambda it: ctx.progress(it, desc="masks from the photos"))  # [V,H,W]
    voted = segmentation.vote_masks(masks, views.K[ids], w2c[ids], sizes[ids], result["track_points"][obj],
                                    agree=p.photo_mask_vote)
    io.save_arrays(ctx.out / artifacts.PHOTO_MASKS, {"masks": masks, "voted": voted, "views": ids})
    labels = np.full((views.n, *masks.shape[1:]), 0.5, np.float32)
    labels[ids] = segmentation.object_labels(masks, voted, p.photo_mask_erode, p.photo_mask_fill)
    if p.photo_mask_fill and p.photo_mask_fill_colour > 0:
        labels[ids] = segmentation.unfill_background_colours(labels[ids], views.images[ids], sizes[ids],
                                                             p.photo_mask_fill_colour)
    io.save_png(ctx.out / artifacts.PHOTO_MASKS_PLOT, segmentation.labels_picture(views.images[ids], labels[ids]))
    disputed = 1 - (masks == voted).mean()
    ctx.log.info("masks from the photos: %.1f %% of the posed views' pixels the object's, %.1f %% the background's, "
                 "%.1f %% disputed by the vote (support %s)", 100 * (labels[ids] == 1).mean(),
                 100 * (labels[ids] == 0).mean(), 100 * disputed, "found" if region.plane is not None else "none found")
    ctx.metrics.update(photo_mask_background=round(float((labels[ids] == 0).mean()), 4),
                       photo_mask_object=round(float((labels[ids] == 1).mean()), 4),
                       photo_mask_disputed=round(float(disputed), 4))
    return labels


def run(ctx) -> None:
    p: Params = ctx.params
    final = ctx.input("successors") / artifacts.FINAL_ROUND
    shutil.copytree(final / artifacts.POSES, ctx.out / artifacts.POSES)  # the poses are decided: the surface keeps them
    if p.iters == 0:
        shutil.copy2(final / artifacts.MODEL, ctx.out / artifacts.MODEL)
        io.save_json(ctx.out / artifacts.ROUND_META, {"surface": "the last round's field", "iters": 0,
                                                      artifacts.FIELD_FROM_MODEL: np.eye(4).tolist()})
        return
    result = artifacts.load_round(final)
    views = artifacts.load_views(ctx.input("ingest"), None, result["K"], result.get("distortion"))
    ids = np.flatnonzero(result["optimised"].astype(bool))
    if p.photo_masks and views.masks is None and result.get("track_points") is not None:
        views.object_labels = photo_labels(ctx, views, result, ids)
    G = np.eye(4) if p.frame == "rounds" else field_frame(result, views, ids, ctx.section("anchors"), p.axes)
    if p.frame == "views" and views.masks is None and result.get("track_points") is not None:
        found = io.load_json(ctx.input("anchors") / artifacts.ANCHOR_ROUND / artifacts.ROUND_META)["init"].get(
            "object_region")  # as the mesh stage reads it
        region = None if found is None else object_region.ObjectRegion.from_json(found).transformed(G)
        points = result["track_points"]  # [T,3] the rounds' frame
        seen = object_region.seen_fraction(points, views.K[ids], result["w2c"][ids], views.view_sizes[ids])
        scale = extent_scale(cameras.transform_points(G, points), seen, region, p.extent_radius, p.extent_min_seen)
        G = cameras.sim3_matrix(scale, np.eye(3), np.zeros(3)) @ G
        ctx.log.info("without masks: the field's frame scaled by %.3f to hold the object's extent within %.2f",
                     scale, p.extent_radius)
    w2c = cameras.transform_w2c(result["w2c"], *cameras.sim3_from_matrix(G))  # [N,4,4] in the field's frame
    ctx.log.info("the field's frame: %s, %s axes (scale %.4g of the rounds')", p.frame, p.axes,
                 cameras.sim3_from_matrix(G)[0])
    run_p = ctx.section("run")
    trun = TrainRun(iters=p.iters, seed=run_p.seed, threads=run_p.threads, device=run_p.device)
    ctx.checkpoint_dir.mkdir(parents=True, exist_ok=True)
    ckpt = ctx.checkpoint_dir / artifacts.MODEL
    lp = ctx.section("loss")
    field_p = ctx.section("field")
    if views.masks is None and p.unmasked_dir_bands >= 0:
        field_p = replace(field_p, dir_bands=p.unmasked_dir_bands)
    if views.masks is None and p.unmasked_view_cosine:
        field_p = replace(field_p, view_cosine=True)
    trainer = Trainer(views.subset(ids, w2c), field_p, ctx.section("render"), lp,
                      ctx.section("train"), run=trun, checkpoint_path=ckpt)
    sight_lines = views.object_labels is None or p.photo_mask_sight_lines
    if lp.w_free_space > 0 and views.masks is None and sight_lines:  # no surface along the SfM lines of sight
        sfm_points = artifacts.load_initial_poses(ctx.input("anchors"), list(posefree.SFM_POINTS))
        lines = sfm_points["sight_lines"]  # [O,2,3]
        sfm_points["sight_lines"] = cameras.transform_points(G, lines.reshape(-1, 3)).reshape(lines.shape)
        trainer.free_space = posefree.free_space_term(lp, sfm_points, trainer.rp.radius, trainer.device)
    if p.start == "rounds":
        posefree.load_carry(trainer, torch.load(final / artifacts.MODEL, map_location=trainer.device, weights_only=False))
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
         "views": [int(v) for v in ids], artifacts.FIELD_FROM_MODEL: G.tolist(), "train": summary,
         "history": trainer.history}, posefree.RUN_FACTS))
    ctx.metrics.update(views=int(len(ids)), iters=p.iters, train_seconds=round(seconds, 1),
                       final_loss=summary["final_loss"])
