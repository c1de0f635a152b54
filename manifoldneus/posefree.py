"""The pose-free rounds (METHOD.md stages 7-8): what the `anchors` and `successors` stages share.

A round trains the field jointly with per-view se(3) corrections on a subset of views (the
anchors, then everything scheduled so far), gated per view by the MaVOS coarse-to-fine gate.
Each round carries the field (and background, SDF cache) over from the previous one and starts
its pose corrections at zero on top of the poses the previous round ended with.

A round's artifact (`save_round`): ``poses.zarr`` (``w2c`` [N,4,4] for all views, identity where
``placed`` is False; ``w2c_init`` the poses the round started from; ``K`` [N,3,3] the intrinsics
they belong to; ``pose_trace`` [T,N,4,4] and
``pose_grad_norm`` [T,N] sampled every ``log_every`` iterations, for the easy-view-bias analysis; with
the `reprojection` correspondence term, ``track_points`` [T,3]: its tracks over the round's views triangulated
under the poses the round ended with, and their observations ``track_obs_view`` [O] (global view ids),
``track_obs_point`` [O] (rows of track_points), ``track_obs_uv`` [O,2] px), ``model.pt`` (the trainer state), ``round.json`` (views, initial-pose methods, losses, timings).
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from manifoldneus.data import artifacts, io
from manifoldneus.sfm import correspondence
from manifoldneus.neural import gate
from manifoldneus.config import RunParams
from manifoldneus.sfm.correspondence import CorrespondenceParams
from manifoldneus.neural.field import FieldParams
from manifoldneus.neural.gate import GateParams
from manifoldneus.neural.losses import LossParams
from manifoldneus.neural.render import RenderParams
from manifoldneus.neural.train import Trainer, TrainParams, TrainRun, Views

INPUT_STAGES = ("ingest", "features", "matching", "covisibility", "schedule")  # what load_inputs reads
ROUND_SECTIONS = ("field", "render", "loss", "train", "gate", "correspondence", "run")  # what a Round reads


@dataclasses.dataclass
class RoundConfig:
    """The parameter sections a round reads (each the stage's resolved section)."""

    field: FieldParams
    render: RenderParams
    loss: LossParams
    train: TrainParams
    gate: GateParams
    correspondence: CorrespondenceParams
    run: RunParams
    log_path: Path | None = None  # where COLMAP's own output goes (None: the console)

    @classmethod
    def from_sections(cls, section: Callable[[str], object], log_path: Path | None = None) -> "RoundConfig":
        """From a lookup of sections by name (a stage's ``ctx.section``)."""
        return cls(**{name: section(name) for name in ROUND_SECTIONS}, log_path=log_path)


@dataclasses.dataclass
class SceneInputs:
    """Everything a pose-free round reads (no ground truth)."""

    views: Views  # all N views, w2c = identity placeholders
    names: list
    keypoints: list  # per view [K_v, 2] pixels
    pairs: list  # pose_init.PairMatch, global ids
    W: np.ndarray  # [N,N] co-visibility
    schedule: dict  # arrays of the schedule stage + 'meta'
    train_mask: np.ndarray  # bool [N]: scheduled and not held out
    intrinsics_source: str = "calibrated"  # views.json's: calibrated | given | exif | default
    distortion: np.ndarray | None = None  # [N,4] the lens distortion removed from views and keypoints (None: none)

    @property
    def sizes(self) -> np.ndarray:
        """[N,2] (H, W) of every view."""
        return self.views.view_sizes


def with_intrinsics(inputs: SceneInputs, K: np.ndarray, distortion: np.ndarray | None = None) -> SceneInputs:
    """The inputs with the intrinsics [N,3,3] the poses belong to (the anchors' initialisation may
    refine the ingest's; every later round reads them from the previous round's ``poses.zarr``) and,
    where the self-calibration found one, the lens ``distortion`` [N,4] removed from the images, masks
    and keypoints (once: inputs already undistorted must be given the same distortion or none)."""
    from manifoldneus.geometry.cameras import has_distortion, undistort_points

    K = np.asarray(K, np.float64)
    views = dataclasses.replace(inputs.views, K=K)
    if not has_distortion(distortion) or (inputs.distortion is not None
                                          and np.array_equal(inputs.distortion, distortion)):
        return dataclasses.replace(inputs, views=views)
    if has_distortion(inputs.distortion):
        raise ValueError("with_intrinsics: the inputs are already undistorted with another distortion")
    keypoints = [undistort_points(kp, K[v], distortion[v]) if has_distortion(distortion[v]) else kp
                 for v, kp in enumerate(inputs.keypoints)]
    return dataclasses.replace(inputs, views=views.undistorted(distortion), keypoints=keypoints,
                               distortion=np.asarray(distortion, np.float64))


def load_inputs(ingest: Path, features: Path, matching: Path, covisibility: Path, schedule: Path) -> SceneInputs:
    """The inputs of the rounds from the version folders of the stages :data:`INPUT_STAGES` names."""
    from manifoldneus.sfm.pose_init import pairs_from_matches

    views = artifacts.load_views(ingest)  # identity placeholders for the poses
    meta = artifacts.load_views_meta(ingest)
    n = views.n
    feats, _ = artifacts.load_features(features)
    matches, _ = artifacts.load_matches(matching)
    W = artifacts.load_covisibility(covisibility, ["W"])["W"].astype(np.float64)
    schedule = artifacts.load_schedule(schedule)
    held_out = np.isin(np.arange(n), schedule["meta"]["held_out_views"])  # the schedule decided them
    train_mask = (schedule["round"] >= 0) & ~held_out
    return SceneInputs(views, meta["names"], [f["keypoints"] for f in feats], pairs_from_matches(matches), W,
                       schedule, train_mask, meta.get("intrinsics_source", "calibrated"))


@dataclasses.dataclass(frozen=True)
class PoseLearning:
    """How a round learns its views' poses: the keys of the stage's section that say it (`anchors`,
    `successors`: :meth:`of`)."""

    learn: bool = False
    lr: float = 0.0
    warmup_frac: float = 0.0  # the pose lr's warm-up, as a fraction of the round
    start_frac: float = 0.0  # poses frozen for this fraction of the round (the field fits first)
    correspondence_weight: float = 0.0  # of the correspondence term in the pose loss
    translation: bool = True  # False: rotations only (every camera centre stays at its start)

    @classmethod
    def of(cls, p) -> "PoseLearning":
        """From a stage's Params (``optimise_poses``, ``pose_lr``, ``pose_warmup_frac``, ``pose_start_frac``,
        ``correspondence_weight``)."""
        return cls(p.optimise_poses, p.pose_lr, p.pose_warmup_frac, p.pose_start_frac, p.correspondence_weight)


def train_run(run: RunParams, iters: int, poses: PoseLearning) -> TrainRun:
    """One round's run: its length and pose optimiser, the run's device."""
    return TrainRun(iters=iters, learn_poses=poses.learn, pose_lr=poses.lr, learn_translation=poses.translation,
                    pose_warmup=int(round(poses.warmup_frac * iters)), seed=run.seed, threads=run.threads,
                    device=run.device)


@dataclasses.dataclass(frozen=True)
class Polish:
    """The poses-only polish that closes a round (:func:`manifoldneus.neural.pose_alignment.align_poses`): the
    round's pose views refined against the field it trained, the field held."""

    steps: int
    rays: int
    lr: float
    translation: bool = True


SFM_POINTS = ("object_points", "sight_lines")  # the anchors' SfM points, in initial_poses.zarr


def free_space_term(lp, sfm_points: dict, radius: float, device):
    """The loss section's free-space prior along the anchors' lines of sight (``sfm_points``, see
    :data:`SFM_POINTS`), or None when there are too few to say where space is free."""
    from manifoldneus.neural.losses import SightLines

    lines = sfm_points.get("sight_lines")
    return None if lines is None or len(lines) < 20 else SightLines(lines, lp.sight_stop, radius, device=device)


class Round:
    """One optimisation round over ``ids`` (global view ids) starting from poses ``w2c_all``."""

    def __init__(self, cfg: RoundConfig, inputs: SceneInputs, ids, w2c_all: np.ndarray, s_tilde_all: np.ndarray, *,
                 iters: int, poses: PoseLearning = PoseLearning(), carry: dict | None = None, pose_ids=None,
                 sfm_points: dict | None = None, image_size: int | None = None, kept_ids=None,
                 kept_frac: float = 0.0, polish: Polish | None = None):
        """poses: how the round learns them (default: held). pose_ids: the views (global ids) whose poses
        learn (None: all of the round's). image_size: longest side the round trains at (None:
        ``train.image_size``; 0: the images' own). kept_ids, kept_frac: the views (global ids) whose rays keep
        the coarsest ``kept_frac`` of the field's bands from the round's start (the gate's progress starts there
        for them, at 0 for the others); 1 = they see every band. polish: the poses-only polish after the
        training (None: none)."""
        learn_poses, correspondence_weight = poses.learn, poses.correspondence_weight
        self.ids = np.asarray(ids, int)
        self.iters = iters
        self.K_all = inputs.views.K  # [N,3,3]: saved with the poses, which belong to it
        self.distortion_all = inputs.distortion  # [N,4] or None: the lens distortion removed from the views
        self.full_K = self.K_all[self.ids]
        run = train_run(cfg.run, iters, poses)
        gate_p = cfg.gate
        device = cfg.run.device
        # on the run's device once: the gate reads it every step (a copy a step is a synchronisation on a GPU)
        s_sub = torch.as_tensor(np.asarray(s_tilde_all, np.float32)[self.ids], device=device)
        self.corr_p = cfg.correspondence
        self.corr = None
        if learn_poses and self.corr_p.kind == "reprojection":
            from manifoldneus.sfm.pose_init import MapperOptions, init_from_matches

            # the tracks (not the poses) of COLMAP's reconstruction of this round's views' matches
            with io.native_output_to(cfg.log_path) if cfg.log_path else contextlib.nullcontext():  # COLMAP's own log goes to log.txt
                ba = init_from_matches(self.ids, inputs.views.K, inputs.keypoints, inputs.pairs, inputs.W,
                                       sizes=inputs.sizes, mapper=MapperOptions(seed=cfg.run.seed))
            self.corr = correspondence.ReprojectionLoss(
                correspondence.TrackSet(self.ids, inputs.views.K, ba.obs_view, ba.obs_point, ba.obs_uv), self.corr_p,
                correspondence_weight, device)
        elif learn_poses:
            ms = correspondence.MatchSet(self.ids, inputs.views.K, inputs.keypoints, inputs.pairs,
                                         self.corr_p.holdout_frac, self.corr_p.seed)
            self.corr = correspondence.CorrespondenceLoss(ms.to(device), self.corr_p, correspondence_weight)
        train_p = cfg.train
        if image_size is not None:
            train_p = dataclasses.replace(train_p, image_size=int(image_size))
        # Poses stay frozen until the field has had `pose_start` iterations to fit them: a
        # correction driven by an unfitted field only moves good initial poses away.
        self.pose_start = int(round(poses.start_frac * iters))
        self.trainer = Trainer(
            inputs.views.subset(self.ids, w2c_all), cfg.field, cfg.render, cfg.loss, train_p, run=run,
            band_weight_fn=lambda view, step: gate.band_weights(view, step, iters, s_sub, self.trainer.field.n_bands,
                                                                gate_p, gate_start),
            pose_start=self.pose_start, pose_loss=self.corr,
            # the views whose poses learn (default all of the round's): local indices into ids
            pose_views=None if pose_ids is None else np.flatnonzero(np.isin(self.ids, np.asarray(pose_ids, int))),
        )
        # the gate's starting progress per view, in bands: the kept views' share of the field's bands
        gate_start = None if kept_ids is None or kept_frac <= 0 else torch.as_tensor(
            np.isin(self.ids, np.asarray(kept_ids, int)) * (kept_frac * self.trainer.field.n_bands),
            dtype=torch.float32, device=self.trainer.device)  # [n]
        lp = cfg.loss
        if lp.w_free_space > 0 and inputs.views.masks is None and sfm_points is not None:
            self.trainer.free_space = free_space_term(lp, sfm_points, self.trainer.rp.radius, self.trainer.device)
        if carry is not None:  # the field learned so far; poses restart at zero correction
            load_carry(self.trainer, carry)
        self.w2c_init = np.array(w2c_all)
        self.start_poses = self.trainer.w2c_init.clone()  # [n,3,4] what a view's update is tested against
        self.polish = polish
        self.pose_local = np.arange(len(self.ids)) if pose_ids is None else np.flatnonzero(
            np.isin(self.ids, np.asarray(pose_ids, int)))  # the views whose poses move (local indices)
        # sampled every log_every steps; kept in the trainer's checkpoint so a resumed round has them all
        self.trainer.extra_state = {"pose_trace": [], "grad_trace": []}
        self.trainer.recorder = self._record
        self.guard: dict = {}

    @property
    def pose_trace(self) -> list:
        return self.trainer.extra_state["pose_trace"]

    @property
    def grad_trace(self) -> list:
        return self.trainer.extra_state["grad_trace"]

    def _record(self, trainer: Trainer, info: dict) -> None:
        self.grad_trace.append(trainer.cams.grad_norms())
        self.pose_trace.append(trainer.poses_numpy())

    def _guard(self, log: logging.Logger, desc: str) -> dict:
        """The per-view acceptance of :mod:`manifoldneus.sfm.correspondence`: a view keeps the round's pose
        update only where its held-out tracks say it is better; the others get their start pose back."""
        t = self.trainer
        if self.corr is None:
            return {"checked": False, "why": "poses not learned"}
        out = correspondence.accept_per_view(self.corr, self.start_poses, t.poses().detach(), self.corr_p)
        keep = torch.as_tensor(out["keep"], device=t.device)
        t.set_poses(torch.where(keep[:, None, None], t.poses().detach(), self.start_poses))
        out["kept_views"] = [int(v) for v in self.ids[np.asarray(out["keep"], bool)]]
        if out["checked"]:
            log.info("%s: %d of %d views keep their pose update (held-out %s error better by more than %.2f standard "
                     "errors%s); the others keep their start. Held-out robust error %.4g -> %.4g (all updated) / %.4g "
                     "(kept); median %.3f -> %.3f / %.3f px", desc, out["kept"], out["n_views"], self.corr_p.kind,
                     out["z_limit"], "; the views that passed raised it together, so none keeps its update"
                     if out["together_worse"] else "", out["error_start"], out["error_end"], out["error_kept"],
                     out["start_median_px"], out["end_median_px"], out["kept_median_px"])
        else:
            log.warning("%s: %s: %s", desc, out["why"], "every view keeps its start pose" if self.corr_p.guard else
                        "every view keeps its update (correspondence.guard is off)")
        return out

    def run(self, desc: str, checkpoint: Path | None = None, *, log: logging.Logger,
            progress: Callable[..., object]) -> dict:
        """Train the round (resuming from ``checkpoint`` when it holds this round's state); ``progress``
        makes a tqdm-like bar (total=, desc=, initial=)."""
        t = self.trainer
        t.checkpoint_path = checkpoint
        resumed_from = None
        if checkpoint is not None and t.resume(checkpoint):
            resumed_from = t.step
            log.info("%s: resumed from %s at step %d", desc, checkpoint.name, t.step)
        bar = progress(total=self.iters, desc=desc, initial=t.step)

        def callback(trainer, info):
            bar.set_postfix(loss=f"{info['loss']:.4f}")

        started = time.time()
        summary = t.train(callback=callback, on_step=lambda step: bar.update(step - bar.n))  # the bar moves every step
        bar.close()
        if self.polish is not None and self.polish.steps > 0:
            summary["polish"] = self._polish(log, desc, progress)
        summary["seconds"] = time.time() - started
        summary["resumed_from_step"] = resumed_from  # None: ran from step 0 (the history covers every step either way)
        summary["guard"] = self.guard = self._guard(log, desc)
        return summary

    def _polish(self, log: logging.Logger, desc: str, progress) -> dict:
        """Every pose view refined against the trained field, held fixed; how far each moved."""
        from manifoldneus.geometry.cameras import camera_centers, rotation_angle_deg
        from manifoldneus.neural.pose_alignment import align_poses

        t, pp, v = self.trainer, self.polish, torch.as_tensor(self.pose_local, device=self.trainer.device)
        before = t.poses().detach().clone()  # [n,3,4]
        after = before.clone()
        after[v] = align_poses(t, before[v], t.images[v], None if t.masks is None else t.masks[v], t.K[v],
                               steps=pp.steps, rays=pp.rays, lr=pp.lr, seed=t.run.seed, translation=pp.translation,
                               progress=progress, sizes=None if t.sizes is None else t.sizes[v.cpu()])
        t.set_poses(after)
        b, a = before[v].double().cpu().numpy(), after[v].double().cpu().numpy()  # [m,3,4]
        turn = rotation_angle_deg(a[:, :, :3] @ b[:, :, :3].transpose(0, 2, 1))  # [m]
        shift = np.linalg.norm(camera_centers(a) - camera_centers(b), axis=-1)  # [m]
        log.info("%s: pose polish (%d steps of %d rays, field held) turned the %d views by %.4f deg, moved their "
                 "centres by %.2e (means)", desc, pp.steps, pp.rays, len(v), turn.mean(), shift.mean())
        return {"steps": pp.steps, "rays": pp.rays, "lr": pp.lr, "translation": pp.translation,
                "turn_deg_mean": float(turn.mean()), "shift_mean": float(shift.mean())}

    def poses_all(self) -> np.ndarray:
        out = np.array(self.w2c_init)
        learnt = self.trainer.cams.learning or (self.polish is not None and self.polish.steps > 0)
        moved = np.asarray(self.guard.get("keep", np.full(len(self.ids), learnt)), bool)  # [n]
        out[self.ids[moved]] = self.trainer.poses_numpy()[moved]  # the others stay at their start, to the last bit
        return out

    def carry(self) -> dict:
        s = self.trainer.state_dict()
        return {k: s[k] for k in ("field", "background", "cache")}


def load_carry(trainer: Trainer, carry: dict) -> None:
    """A field carried from another trainer (:meth:`Round.carry`, or a round's ``model.pt``): field,
    background and, where both have one, the SDF cache."""
    trainer.field.load_state_dict(carry["field"])
    trainer.background.load_state_dict(carry["background"])
    if trainer.cache is not None and carry.get("cache") is not None:
        trainer.cache.load_state_dict(carry["cache"])


def depth_at_fn(rnd: Round):
    """depth_at(view, uv [P,2]) -> distance along the ray [P] (NaN where the ray hits nothing),
    rendered from the round's current field and poses; for PnP placement of successors."""
    from manifoldneus.geometry.rays import camera_rays
    from manifoldneus.neural.render import render_rays

    t = rnd.trainer
    local = {int(g): i for i, g in enumerate(rnd.ids)}
    poses = t.poses().detach()

    def depth_at(view: int, uv: np.ndarray) -> np.ndarray:
        i = local[int(view)]
        uv_t = torch.as_tensor(np.asarray(uv, np.float32), device=t.device)
        # the trainer's K is at its training resolution; keypoints are in full-resolution pixels
        K_full = torch.as_tensor(rnd.full_K[i], dtype=torch.float32, device=t.device)
        cols, rows = torch.floor(uv_t[:, 0]), torch.floor(uv_t[:, 1])
        o, d = camera_rays(cols, rows, K_full, poses[i], jitter=uv_t - torch.stack([cols, rows], -1))
        depths = []
        with torch.no_grad():
            for a in range(0, len(o), 4096):
                out = render_rays(t.field, o[a:a + 4096], d[a:a + 4096], t.rp, cache=t.cache, background=t.background,
                                  want_normals=False)
                op = out["opacity"]
                dep = out["depth"] / op.clamp_min(1e-4)
                depths.append(torch.where(op > 0.5, dep, torch.full_like(dep, float("nan"))))
        return torch.cat(depths).cpu().numpy() if depths else np.zeros(0)

    return depth_at


RUN_FACTS = ("seconds", "seconds_total", "resumed_from_step")  # of one run, not of its result (the manifest has times)


def save_round(out_dir: Path, rnd: Round, placed: np.ndarray, info: dict) -> None:
    """The round's artifact (module doc); ``info`` goes to round.json without its :data:`RUN_FACTS`, so that
    two runs, or a run resumed from a checkpoint, write the same bytes and later stages reuse theirs."""
    out_dir.mkdir(parents=True, exist_ok=True)
    info = io.without_keys(info, RUN_FACTS)
    n_views = len(placed)
    w2c = rnd.poses_all()
    w2c[~placed] = np.eye(4)
    trace = np.tile(np.eye(4), (len(rnd.pose_trace), n_views, 1, 1))
    grads = np.zeros((len(rnd.grad_trace), n_views))
    for k, (P, g) in enumerate(zip(rnd.pose_trace, rnd.grad_trace)):
        trace[k, rnd.ids] = P
        grads[k, rnd.ids] = g
    extra = {} if rnd.distortion_all is None else {"distortion": rnd.distortion_all}
    if isinstance(rnd.corr, correspondence.ReprojectionLoss):  # the structure of every view of the round, for the mesh's crop
        tr = rnd.corr.tr
        X = tr.triangulate(w2c[rnd.ids])  # [T,3]
        finite = np.isfinite(X).all(1)
        extra["track_points"] = X[finite]
        # the observations of those points (the exported COLMAP model's tracks): global view, point, pixel
        seen = finite[tr.track]
        extra.update(track_obs_view=rnd.ids[tr.view[seen]], track_obs_point=(np.cumsum(finite) - 1)[tr.track[seen]],
                     track_obs_uv=tr.uv[seen])
    io.save_arrays(out_dir / artifacts.POSES, {"w2c": w2c, "w2c_init": rnd.w2c_init, "placed": placed, "K": rnd.K_all,
                                     "optimised": np.isin(np.arange(n_views), rnd.ids),
                                     "pose_trace": trace, "pose_grad_norm": grads, **extra}, chunk_first=False)
    rnd.trainer.save(out_dir / artifacts.MODEL)
    io.save_json(out_dir / artifacts.ROUND_META, info)
