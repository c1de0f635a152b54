"""anchors: initial poses of the anchor views, then joint field + pose optimisation on them.

Pose initialisation (``anchors.pose_init``):
- ``matches`` (default): relative poses from the verified essential matrices along a maximum
  spanning tree of the co-visibility graph, incremental PnP, bundle adjustment, unit-sphere gauge
  (:func:`manifoldneus.pose_init.init_from_matches`);
- ``identity``: every anchor at one canonical pose looking at the origin (the paper's wording);
- ``reference``: the pycolmap reference poses (the `neus-colmap` preset), gauged the same way.
Writes ``round_0/`` (see :mod:`manifoldneus.posefree`) and the initial poses of every anchor.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from manifoldneus import io, pose_init, posefree
from manifoldneus.config import ParamError, param


@dataclass
class Params:
    """Section `anchors` of params.yaml."""

    pose_init: str = param("matches", "Initial anchor poses: matches | identity | reference (pycolmap)",
                           choices=["matches", "identity", "reference"])
    optimise_poses: bool = param(True, "Learn per-view pose corrections (False: keep the initial poses)")
    iters: int = param(1500, "Iterations of the anchor stage", lo=1)
    pose_lr: float = param(8e-3, "Peak AdamW lr of the anchors' pose corrections (supplement: 8e-3)", lo=0.0)
    pose_start_frac: float = param(0.3, "Poses stay frozen for this fraction of the iterations (the field fits first)",
                                   lo=0.0, hi=1.0)
    pose_warmup_frac: float = param(0.1, "Pose lr warm-up as a fraction of the stage (supplement: 2k iterations)",
                                    lo=0.0, hi=1.0)
    correspondence_weight: float = param(1.0, "Weight of the correspondence term (section `correspondence`) in the "
                                         "anchors' pose loss; 0 = photometric poses only (docs/REFINEMENT.md)", lo=0.0)
    reproj_px: float = param(3.0, "matches init: inlier reprojection threshold (px)", lo=0.1)
    gauge_radius: float = param(0.8, "Robust radius the anchors' points are scaled to (object in the unit sphere)",
                                lo=0.1, hi=1.0)
    identity_distance: float = param(3.0, "identity init: distance of the canonical camera from the origin", lo=0.5)
    perturb_rot_deg: list[float] = param([0.0, 0.0], "Experiments from a perturbed start (BARF): each anchor's initial "
                                         "rotation is turned by an angle drawn from [lo, hi] deg about a random axis "
                                         "(seeded by run.seed); [0, 0] = no perturbation", lo=0.0, hi=90.0)
    perturb_centre_frac: float = param(0.0, "Experiments from a perturbed start: each anchor's initial centre moves "
                                       "by this fraction of the anchors' mean distance from the origin, in a random "
                                       "direction", lo=0.0, hi=1.0)

    def __post_init__(self):
        if len(self.perturb_rot_deg) != 2 or self.perturb_rot_deg[0] > self.perturb_rot_deg[1]:
            raise ParamError(f"anchors.perturb_rot_deg: expected [lo, hi] with lo <= hi, got {self.perturb_rot_deg}")


UPSTREAM = ("ingest", "features", "matching", "covisibility", "schedule", "reference")
SECTIONS = ("anchors", "train", "field", "render", "loss", "gate", "correspondence", "run", "split")
OUTPUTS = ("round_0", "initial_poses.zarr")


def reference_poses(reference_dir, n: int, gauge_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """pycolmap's poses in the unit-sphere gauge of its own points; (w2c [N,4,4], registered [N])."""
    import pycolmap

    from manifoldneus import cameras

    ref = io.load_arrays(reference_dir / "poses.zarr")
    rec = pycolmap.Reconstruction(str(reference_dir / "sparse"))
    pts = np.array([p.xyz for p in rec.points3D.values()])
    if len(pts) < 3:
        pts = cameras.camera_centers(ref["w2c"][ref["registered"]])
    s, centre = pose_init.gauge_from_points(pts, gauge_radius)
    return cameras.transform_w2c(ref["w2c"], s, np.eye(3), -s * centre), ref["registered"].astype(bool)


def initial_poses(ctx, inputs: posefree.SceneInputs, anchors: list[int], p: Params) -> tuple[np.ndarray, dict]:
    n = len(inputs.names)
    w2c = np.tile(np.eye(4), (n, 1, 1))
    if p.pose_init == "identity":
        w2c[anchors] = pose_init.identity_init(len(anchors), p.identity_distance)
        return w2c, {"method": "identity"}
    if p.pose_init == "reference":
        ref, registered = reference_poses(ctx.input("reference"), n, p.gauge_radius)
        missing = [inputs.names[a] for a in anchors if not registered[a]]
        if missing:
            ctx.log.warning("pycolmap did not register anchors %s; they start at a registered neighbour's pose", missing)
        w2c[anchors] = ref[anchors]
        for a in anchors:
            if not registered[a]:
                nb = [j for j in np.argsort(-inputs.W[a]) if registered[j]]
                w2c[a] = ref[nb[0]] if nb else np.eye(4)
        return w2c, {"method": "reference", "unregistered": missing}
    masks = None if inputs.views.masks is None else [inputs.views.masks[a] for a in anchors]
    res = pose_init.init_from_matches(anchors, inputs.views.K, inputs.keypoints, inputs.pairs, inputs.W,
                                      reproj_px=p.reproj_px, gauge_radius=p.gauge_radius, masks=masks,
                                      log=ctx.log.info)
    if res.unplaced:
        ctx.log.warning("initialisation could not place anchors %s; they start at a neighbour's pose",
                        [inputs.names[v] for v in res.unplaced])
    w2c[anchors] = res.w2c
    return w2c, {"method": "matches", "per_view": dict(zip(map(int, anchors), res.method)),
                 "unplaced": [inputs.names[v] for v in res.unplaced], **res.diagnostics}


def perturbed(w2c: np.ndarray, p: Params, seed: int) -> np.ndarray:
    from manifoldneus import cameras

    distance = float(np.linalg.norm(cameras.camera_centers(w2c), axis=1).mean())
    return cameras.perturb_w2c(w2c, tuple(p.perturb_rot_deg), p.perturb_centre_frac * distance,
                               np.random.default_rng(seed))


def run(ctx) -> None:
    p: Params = ctx.params
    inputs = posefree.load_inputs(ctx)
    rounds = inputs.schedule["round"]
    anchors = [int(v) for v in np.flatnonzero((rounds == 0) & inputs.train_mask)]
    if len(anchors) < 2:
        raise RuntimeError(f"only {len(anchors)} trainable anchor view(s); check schedule.anchor_percent and "
                           f"split.holdout_every")
    n = len(inputs.names)
    w2c0, init_info = initial_poses(ctx, inputs, anchors, p)
    if max(p.perturb_rot_deg, default=0.0) > 0 or p.perturb_centre_frac > 0:
        w2c0[anchors] = perturbed(w2c0[anchors], p, ctx.section("run").seed)
        init_info["perturbed"] = {"rot_deg": list(p.perturb_rot_deg), "centre_frac": p.perturb_centre_frac}
        ctx.log.info("anchors: initial poses perturbed by %s deg and %g of their distance (anchors.perturb_*)",
                     p.perturb_rot_deg, p.perturb_centre_frac)
    placed = np.zeros(n, bool)
    placed[anchors] = True
    io.save_arrays(ctx.out / "initial_poses.zarr", {"w2c": w2c0, "placed": placed}, chunk_first=False)
    ctx.log.info("anchors %s initialised by %s", [inputs.names[a] for a in anchors], init_info["method"])

    s_tilde = inputs.schedule["s_tilde_rounds"][0]
    ctx.checkpoint_dir.mkdir(parents=True, exist_ok=True)
    rnd = posefree.Round(ctx, inputs, anchors, w2c0, s_tilde, iters=p.iters, pose_lr=p.pose_lr,
                         pose_warmup_frac=p.pose_warmup_frac, learn_poses=p.optimise_poses,
                         pose_start_frac=p.pose_start_frac, correspondence_weight=p.correspondence_weight)
    summary = rnd.run(ctx, "anchors", ctx.checkpoint_dir / "round_0.pt")
    posefree.save_round(ctx.out / "round_0", rnd, placed, {
        "round": 0, "views": anchors, "names": [inputs.names[a] for a in anchors], "init": init_info,
        "train": summary, "history": rnd.trainer.history})
    ctx.metrics.update(n_anchors=len(anchors), init=init_info["method"], seconds=summary["seconds"],
                       final_loss=summary["final_loss"], rollbacks=summary["rollbacks"],
                       losses_on=sorted(k for k, v in summary["loss_status"].items() if v == "on"))
