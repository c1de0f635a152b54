"""Trainer of the neural surface: random ray batches over training views, Adam with linear
warm-up then cosine decay, optional learnable per-view se(3) pose corrections (AdamW),
checkpoint save / resume, and rollback to the last good state (NaN, loss divergence, a learned
pose that jumps) with a lowered learning rate.

Input is plain arrays (:class:`Views`): images [N,H,W,3], K [N,3,3], w2c [N,4,4] and optional
masks [N,H,W], mono_depth [N,H,W], mono_normal [N,H,W,3] (unit, OpenCV camera frame).

Hooks for the pose-free method:
* ``band_weight_fn(view_ids [R] long, step) -> [R, L]``: per-ray gate of the field's bands/levels
  (the MaVOS-gated BARF schedule); without it a global BARF ramp over ``c2f_iters`` applies
  (0 = all bands on from the start).
* ``learn_poses``: the views ``pose_views`` (default: all training views) learn se(3) corrections
  from step ``pose_start`` on (:class:`manifoldneus.neural.pose_correction.PoseCorrections`, ``self.cams``).
* ``pose_loss(w2c [N,3,4], rng, step) -> scalar | None`` with a ``weight`` attribute: a term on the poses
  alone (the verified matches' tracks or epipolar errors, :mod:`manifoldneus.sfm.correspondence`),
  added to the loss while poses are learned.

Reproducibility: one seed drives every random draw (ray batches from ``self.rng``, sample jitter
from torch's global generator); both generators' states, the loss average and the history are in
the checkpoint, so a resumed run continues exactly as an uninterrupted one would. The trainer turns
on torch's deterministic algorithms: on the CPU, the backward of an index with repeated entries (the
pose terms' ``w2c[view]``) otherwise adds with atomics across threads once a batch passes torch's grain
size, and two runs of one seed drift apart (scan24_idr's masked anchors, 2 threads: final loss 0.19973 vs
0.19930 after 600 iterations, the same code and inputs). On cuda the dense grid levels' ``grid_sample``
backward has no deterministic version (torch warns once): there one seed gives one result to float
tolerance, not bit for bit.
"""
from __future__ import annotations

import copy
import errno
import logging
import math
import os
import pickle
import shutil
import time
import types
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch.profiler import record_function

from manifoldneus.config import param
from manifoldneus.neural.field import FieldParams, make_field
from manifoldneus.neural.gate import barf_weights
from manifoldneus.neural.pose_correction import PoseCorrections
from manifoldneus.neural.losses import LossParams, compute_losses
from manifoldneus.geometry.rays import camera_rays, draw_pixels, project
from manifoldneus.neural.render import Background, RenderParams, SDFCache, render_image, render_rays, resolve_background
from manifoldneus.data.views import Views

log = logging.getLogger("manifoldneus.train")


@dataclass
class TrainParams:
    """Section `train`: how the neural surface is optimised, shared by every stage that trains one.
    What differs per run (its length, whether poses learn and how fast, the device and seed) is
    not here: see :class:`TrainRun`."""

    time_budget_s: float = param(0.0, "Stop after this many seconds of training (0 = no limit); the lr schedules "
                                 "then follow max(iteration / iters, elapsed / budget)", lo=0.0)
    batch_rays: int = param(1024, "Rays per iteration", lo=1)
    fg_ray_fraction: float = param(0.5, "With masks: fraction of rays drawn from foreground pixels (0 = uniform)", lo=0.0, hi=1.0)
    image_size: int = param(192, "Train on images downscaled so the longest side is this (0 = native)", lo=0)
    lr: float = param(0.0, "Peak learning rate of the network weights; 0 = auto: 1e-2 for the grid field's tiny "
                      "decoders (measured best on scan24), 5e-4 for the mlp field (supplement)", lo=0.0)
    grid_lr: float = param(1e-2, "Peak learning rate of grid features (grid field)", lo=0.0)
    s_lr: float = param(5e-3, "Peak learning rate of the NeuS variance parameter (inv_s = exp(10 v))", lo=0.0)
    lr_min_ratio: float = param(0.05, "Final lr as a fraction of the peak (supplement: 2.5e-5 / 5e-4)", lo=0.0, hi=1.0)
    warmup: int = param(100, "Linear lr warm-up iterations (supplement: 5k of the paper's run; scale with iters)", lo=0)
    c2f_iters: int = param(0, "Global coarse-to-fine: BARF ramp of the bands over this many iterations (0 = off); "
                           "ignored when a per-view band_weight_fn is given", lo=0)
    auto_aabb: bool = param(True, "grid: fit the grid box to the masks' visual hull (or the views' common frustum)")
    pose_lr_min_ratio: float = param(0.1, "Final pose lr as a fraction of its peak", lo=0.0, hi=1.0)
    pose_weight_decay: float = param(0.0, "AdamW weight decay of the pose corrections", lo=0.0)
    ckpt_every: int = param(200, "Keep a rollback state (and write the checkpoint file, if any) every N iterations", lo=1)
    rollback_lr_factor: float = param(0.5, "Multiply the lr by this after a NaN/divergence rollback", lo=0.0, hi=1.0)
    max_rollbacks: int = param(5, "Give up after this many rollbacks", lo=0)
    diverge_factor: float = param(20.0, "A field loss (the pose term excluded) above this times its running mean "
                                  "counts as divergence", lo=1.0)
    pose_jump_deg: float = param(30.0, "A learned pose that turns by more than this between two rollback states (or "
                                 "becomes non-finite) counts as divergence (0 = no check)", lo=0.0)
    log_every: int = param(100, "Log every N iterations", lo=1)
    check_every: int = param(1, "Read the loss and the gradients' finiteness on the host every N iterations (1 = every "
                             "iteration). In between, the non-finite and divergence checks accumulate on the device "
                             "and the ray indices of the N iterations are drawn at once, so a GPU's step waits on no "
                             "host read; a failed check rolls back to the last good state, as the per-iteration check "
                             "does. Logged and checkpointed iterations are checked; a resumed run repeats an "
                             "uninterrupted one when ckpt_every is a multiple of N", lo=1)
    compile: str = param("off", "torch.compile of the step's rendering and losses, forward and backward: 'default' "
                         "(inductor's fused kernels: C++ on the CPU, triton on cuda), 'reduce-overhead' (the same "
                         "with CUDA graphs) or 'off' (eager). Static shapes need render.skip_empty off and "
                         "render.colour_min_weight 0 (else the graph breaks at their data-dependent sizes); the "
                         "grids and the SDF cache then use the 'torch' kernel. Where torch.compile, triton (cuda) "
                         "or a C++ compiler (CPU) is missing, a warning names it and the step runs eagerly",
                         choices=["off", "default", "reduce-overhead"])


@dataclass
class TrainRun:
    """One training run: its length, whether and how fast the poses learn, and where it runs. Not
    a params.yaml section: each stage fills it from its own section (``anchors.iters``,
    ``successors.pose_lr``, ``reference_surface.iters``) and from ``run``, so every value has one
    home and a stage's fingerprint holds only what it uses."""

    iters: int  # training iterations (with a time budget: the cap)
    learn_poses: bool = False  # learn per-view se(3) corrections of the initial poses
    pose_lr: float = 0.0  # peak AdamW lr of the corrections
    pose_warmup: int = 0  # pose lr warm-up iterations
    learn_translation: bool = True  # False: the corrections are rotations only (camera centres held)
    seed: int = 0
    threads: int = 0  # torch CPU threads (0 = leave torch's default)
    device: str = "cpu"


LOSS_NAN, DIVERGED, GRAD_NAN = 1, 2, 4  # check_every > 1: the device-side flags of a failed check


def compile_unavailable(device: torch.device) -> str | None:
    """Why ``torch.compile`` cannot build the step on ``device`` (None: it can): torch without it, cuda
    without triton, a CPU without a C++ compiler (inductor writes C++ there)."""
    if not hasattr(torch, "compile"):
        return f"torch {torch.__version__} has no torch.compile"
    if device.type == "cuda":
        try:
            from torch.utils._triton import has_triton
        except ImportError:
            return "torch.utils._triton is missing"
        return None if has_triton() else "triton is not installed (pip install triton)"
    if device.type == "cpu":
        import shutil

        cxx = os.environ.get("CXX", "")
        if not any(shutil.which(c) for c in (cxx, "g++", "c++", "clang++") if c):
            return "no C++ compiler (g++, c++ or clang++; or $CXX) for inductor's CPU kernels"
        return None
    return f"no compiled step for device type {device.type!r}"


def keep_freed_memory(threshold: int = 1 << 30) -> bool:
    """Ask glibc to keep freed blocks up to ``threshold`` bytes in the heap instead of returning them to
    the system. The grid field's gradients are tens of MB, allocated and freed every step; returned to the
    system, every step paid their page faults again (scan24 anchors' step, 2 threads: 198 -> 180 ms).
    A no-op (False) where the C library is not glibc."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"))
        m_trim_threshold, m_mmap_threshold = -1, -3  # malloc.h
        return bool(libc.mallopt(m_mmap_threshold, threshold)) and bool(libc.mallopt(m_trim_threshold, threshold))
    except (OSError, AttributeError):
        return False


class _ValuePickler(pickle.Pickler):
    """A pickler without its memo: the bytes depend on the values alone, not on which objects happen to be
    shared (a trainer resumed from a checkpoint holds equal values in other objects), so one training
    writes one file however often it was interrupted. The trainer's state has no cycles."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.fast = True


_value_pickle = types.SimpleNamespace(Pickler=_ValuePickler, Unpickler=pickle.Unpickler, load=pickle.load,
                                      __name__="pickle")


def lr_factor(step: int, total: int, warmup: int, min_ratio: float) -> float:
    """Linear warm-up 0 -> 1 over ``warmup`` steps, then cosine decay to ``min_ratio`` at ``total``."""
    if warmup > 0 and step < warmup:
        return (step + 1) / warmup
    if total <= warmup:
        return 1.0
    prog = min(max((step - warmup) / (total - warmup), 0.0), 1.0)
    return min_ratio + (1.0 - min_ratio) * 0.5 * (1.0 + math.cos(math.pi * prog))


def visual_hull_aabb(views: Views, res: int = 48, radius: float = 1.0, margin: float = 0.05,
                     min_seen_frac: float = 0.5, mask_agree: float = 0.9):
    """Box of the region the views constrain: points inside the sphere seen by at least
    ``min_seen_frac`` of the views and, with masks, inside the mask of at least ``mask_agree`` of
    the views that see them (a visual hull tolerant to mask errors). Padded by ``margin`` of its
    extent plus two cells. Returns (lo [3], hi [3]) numpy (the sphere's cube if nothing fits)."""
    lin = np.linspace(-radius, radius, res)
    P = np.stack(np.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3)
    P = P[np.linalg.norm(P, axis=1) <= radius]
    Pt = torch.as_tensor(P, dtype=torch.float64)
    seen = np.zeros(len(P), int)
    in_mask = np.zeros(len(P), int)
    for i, (H, W) in enumerate(views.view_sizes):  # each view's own frame
        uv, z = project(Pt, torch.as_tensor(views.K[i]), torch.as_tensor(views.w2c[i]))
        uv, z = uv.numpy(), z.numpy()
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        seen += inside
        if views.masks is not None:
            c = np.clip(uv[:, 0].astype(int), 0, W - 1)
            r = np.clip(uv[:, 1].astype(int), 0, H - 1)
            in_mask += inside & views.masks[i][r, c]
    keep = seen >= max(1, int(np.ceil(min_seen_frac * views.n)))
    if views.masks is not None:
        keep &= in_mask >= mask_agree * seen
    if keep.sum() < 8:
        return np.full(3, -radius), np.full(3, radius)
    cell = 2 * radius / (res - 1)
    lo = P[keep].min(0) - 2 * cell
    hi = P[keep].max(0) + 2 * cell
    ext = hi - lo
    lo, hi = lo - margin * ext, hi + margin * ext
    return np.clip(lo, -radius, radius), np.clip(hi, -radius, radius)


class Trainer:
    """Owns the field, background, SDF cache, optimisers and (optionally) pose corrections.

    Parameters: ``views`` (:class:`Views`, full resolution; resized to ``train_p.image_size``),
    ``train_views`` (indices used for training; default all), ``pose_views`` (indices whose poses
    are learned when ``run.learn_poses``; default ``train_views``), ``band_weight_fn`` (see module
    doc), ``progress`` (callable(step, info dict) called every ``log_every`` iterations).
    """

    def __init__(self, views: Views, field_p: FieldParams | None = None, render_p: RenderParams | None = None,
                 loss_p: LossParams | None = None, train_p: TrainParams | None = None, *, run: TrainRun,
                 train_views=None, pose_views=None, band_weight_fn=None, progress=None, checkpoint_path=None,
                 pose_start: int = 0, pose_loss=None):
        self.fp = field_p or FieldParams()
        self.rp = render_p or RenderParams()
        self.lp = loss_p or LossParams()
        self.tp = train_p or TrainParams()
        self.run = run
        # a warm-up longer than a quarter of a (short) run would leave it no time at the peak lr
        self.warmup = min(self.tp.warmup, run.iters // 4)
        self.device = torch.device(run.device)
        if run.threads > 0:
            torch.set_num_threads(run.threads)
        if self.device.type == "cpu":
            keep_freed_memory()
        if self.device.type == "cuda":
            os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")  # cuBLAS's condition for determinism
        torch.use_deterministic_algorithms(True, warn_only=True)  # one seed, one result (module doc)
        torch.manual_seed(run.seed)
        self.rng = torch.Generator(device="cpu").manual_seed(run.seed)
        self.views = views.resized(self.tp.image_size)
        self.train_views = np.arange(self.views.n) if train_views is None else np.asarray(train_views, int)
        self.band_weight_fn = band_weight_fn
        self.pose_loss = pose_loss
        self.progress = progress
        self.checkpoint_path = checkpoint_path
        dev = self.device
        v = self.views
        H, W = v.hw
        self.H, self.W = H, W
        # views of several sizes: each one's own part of the canvas [N,2] on the CPU, as the ray draw; None: one size
        self.sizes = None if v.one_size else torch.as_tensor(v.view_sizes, dtype=torch.long)
        self.images = torch.as_tensor(v.float_images().reshape(v.n, H * W, 3), device=dev)
        self.K = torch.as_tensor(v.K, dtype=torch.float32, device=dev)
        self.w2c_init = torch.as_tensor(np.asarray(v.w2c)[:, :3, :4], dtype=torch.float32, device=dev)
        self.masks = None if v.masks is None else torch.as_tensor(v.masks.reshape(v.n, H * W), device=dev)
        self.object_labels = None if v.object_labels is None else torch.as_tensor(
            v.object_labels.reshape(v.n, H * W), dtype=torch.float32, device=dev)
        self.mono_depth = None if v.mono_depth is None else torch.as_tensor(v.mono_depth.reshape(v.n, H * W), device=dev)
        self.mono_normal = None if v.mono_normal is None else torch.as_tensor(
            v.mono_normal.reshape(v.n, H * W, 3), device=dev)
        self.field = make_field(self.fp).to(dev)
        if self.fp.kind == "grid" and self.tp.auto_aabb:
            lo, hi = visual_hull_aabb(self.views, radius=self.rp.radius)
            self.field.set_aabb(lo, hi)
        self.bg_kind = resolve_background(self.rp.background, self.masks is not None, self.rp.background_unmasked)
        self.background = Background(self.bg_kind, self.rp.radius, self.rp.background_samples).to(dev)
        self.cache = SDFCache(self.rp.cache_res, self.rp.radius, device=dev) if self.rp.sampler == "cache" else None
        self.cams = PoseCorrections(
            self.w2c_init, (self.train_views if pose_views is None else pose_views) if run.learn_poses else None,
            start=pose_start, lr=run.pose_lr, weight_decay=self.tp.pose_weight_decay,
            translation=run.learn_translation)
        self._build_optimizers()
        self._loss_fn = self._render_losses if self.tp.compile == "off" else self._compiled(self._render_losses)
        self._flags = None  # check_every > 1: the failed checks since the last host read (LOSS_NAN | DIVERGED | GRAD_NAN)
        self._ema_t = None  # check_every > 1: the loss average on the device
        self._ray_queue: list = []  # check_every > 1: the window's ray indices, drawn at once
        self._last_loss = None  # check_every > 1: the last iteration's loss, unread
        self._tv = None  # (train_views, the same on the device)
        self.step = 0
        self.lr_scale = 1.0
        self.rollbacks = 0
        self.events: list[dict] = []
        self.loss_status: dict = {}
        self._good_state = None
        self._loss_ema = None
        self._budget = 0.0
        self._t_start = None
        self._target, self._t_train = run.iters, None  # set by train()
        self.clock = time.time  # budget / schedule clock (e.g. time.process_time for CPU-time budgets)
        self.history: list[dict] = []
        self.extra_state: dict = {}  # a caller's own per-run records, checkpointed with the trainer
        self.recorder = None  # callable(trainer, info) at every logged step, before that step's checkpoint
        self.free_space = None  # losses.SightLines: no surface along the SfM lines of sight (runs without masks)
        if self.masks is not None and self.tp.fg_ray_fraction > 0:
            tv = torch.as_tensor(self.train_views, dtype=torch.long, device=dev)
            fg = self.masks[tv].reshape(-1).nonzero()[:, 0]
            self._fg_flat = fg  # indices into [len(train_views) * H * W]
        else:
            self._fg_flat = None

    # ------------------------------------------------------------------ setup
    def _build_optimizers(self):
        grid_params = list(self.field.grid_parameters()) if hasattr(self.field, "grid_parameters") else []
        gid = {id(p) for p in grid_params} | {id(self.field.variance)}
        net_params = [p for p in self.field.parameters() if id(p) not in gid] + list(self.background.parameters())
        lr = self.tp.lr if self.tp.lr > 0 else (1e-2 if self.fp.kind == "grid" else 5e-4)
        groups = [{"params": net_params, "lr": lr, "base_lr": lr},
                  {"params": [self.field.variance], "lr": self.tp.s_lr, "base_lr": self.tp.s_lr}]
        if grid_params:
            groups.append({"params": grid_params, "lr": self.tp.grid_lr, "base_lr": self.tp.grid_lr,
                           "eps": 1e-15})
        fused = self.device.type in ("cpu", "cuda")
        self.opt = torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15 if grid_params else 1e-8,
                                    fused=fused)

    def _compiled(self, fn):
        """``fn`` compiled by torch.compile (``train.compile``), or ``fn`` itself with a warning that names what is
        missing; a compilation that fails at the first call warns and the step runs ``fn`` from then on."""
        why = compile_unavailable(self.device)
        if why is not None:
            log.warning("train.compile=%s: %s; the training step runs eagerly", self.tp.compile, why)
            return fn
        # the fused CPU grid kernel is a pybind call the compiler cannot see through (a graph break)
        if getattr(self.field, "grid_kernel", "torch") != "torch":
            log.warning("train.compile=%s: the grids use the 'torch' kernel (field.grid_kernel=%s is opaque to the "
                        "compiler)", self.tp.compile, self.field.grid_kernel)
            self.field.grid_kernel = "torch"
        if self.cache is not None:
            self.cache.kernel = "torch"
        import torch._inductor.config as inductor_config

        # random draws as eager's (torch's generator, not inductor's own): one seed gives the eager step's samples
        inductor_config.fallback_random = True
        import torch._dynamo.config as dynamo_config

        # each trainer (one per stage and round of a run, in one process) is a new `self` to the step's guards: a
        # recompilation each; past dynamo's limit (8) its later trainers would run eagerly without a word
        dynamo_config.recompile_limit = max(dynamo_config.recompile_limit, 64)
        compiled = torch.compile(fn, mode=self.tp.compile, dynamic=False)
        state = {"failed": False}

        def call(*args, **kwargs):
            if state["failed"]:
                return fn(*args, **kwargs)
            try:
                return compiled(*args, **kwargs)
            except torch.OutOfMemoryError:
                raise
            except Exception as e:  # a missing piece found while compiling; a real error comes back eagerly
                state["failed"] = True
                log.warning("train.compile=%s failed (%s: %s); the training step runs eagerly", self.tp.compile,
                            type(e).__name__, str(e).strip().splitlines()[0][:300] if str(e).strip() else "")
                return fn(*args, **kwargs)

        return call

    def _render_losses(self, b: dict, bw, host: bool = True):
        """(total loss, terms, status) of a batch: the part of the step ``train.compile`` compiles."""
        # normals cost 4 extra field evaluations per ray: only the normal prior reads them
        out = render_rays(self.field, b["o"], b["d"], self.rp, cache=self.cache, background=self.background,
                          band_weights=bw, perturb=True, train=True,
                          want_normals=self.mono_normal is not None and self.lp.w_normal > 0)
        return compute_losses(out, b, self.lp, host=host)

    # ------------------------------------------------------------------ poses
    def poses(self) -> torch.Tensor:
        """Current world-to-camera poses [N,3,4] (corrected when poses are learned)."""
        return self.cams.poses(self.step)

    def set_poses(self, w2c: torch.Tensor) -> None:
        """Make ``w2c`` [N,3,4] the poses the corrections apply to, every correction back to zero: a pose
        step taken outside the training loop (a round's polish) or undone (the guard's rollback)."""
        with torch.no_grad():
            self.w2c_init.copy_(w2c)  # the corrections' own reference to the same tensor
        self.cams.reset()

    def poses_numpy(self) -> np.ndarray:
        with torch.no_grad():
            P = self.poses().cpu().double().numpy()
        out = np.tile(np.eye(4), (P.shape[0], 1, 1))
        out[:, :3, :4] = P
        return out

    # ------------------------------------------------------------------ batches
    def sample_batch(self, n: int) -> dict:
        dev = self.device
        HW = self.H * self.W
        if self._tv is None or self._tv[0] is not self.train_views:  # copied to the device once, not every step
            self._tv = (self.train_views, torch.as_tensor(self.train_views, dtype=torch.long, device=dev))
        tv = self._tv[1]
        n_fg = int(round(n * self.tp.fg_ray_fraction)) if self._fg_flat is not None else 0
        ce = self.tp.check_every
        if ce > 1 and n == self.tp.batch_rays:
            # the window's indices in one copy to the device (one per step is a synchronisation each on a GPU);
            # windows start at multiples of check_every, so a run resumed at a checkpoint draws what it drew
            if not self._ray_queue:
                k = ce - self.step % ce
                flat_k = self._draw_pixels(k * (n - n_fg)).reshape(k, n - n_fg)
                pick_k = torch.randint(0, self._fg_flat.shape[0], (k, n_fg), generator=self.rng) if n_fg else None
                both = flat_k if pick_k is None else torch.cat([flat_k, pick_k], 1)
                self._ray_queue = list(both.to(dev).unbind(0))
            flat = self._ray_queue.pop(0)
            if n_fg:
                flat = torch.cat([flat[:n - n_fg], self._fg_flat[flat[n - n_fg:]]])
        else:
            flat = self._draw_pixels(n - n_fg).to(dev)
            if n_fg:
                pick = torch.randint(0, self._fg_flat.shape[0], (n_fg,), generator=self.rng).to(dev)
                flat = torch.cat([flat, self._fg_flat[pick]])
        view = tv[flat // HW]
        pix = flat % HW
        rows, cols = pix // self.W, pix % self.W
        w2c_all = self.poses()
        w2c = w2c_all[view]
        o, d = camera_rays(cols, rows, self.K[view], w2c)
        b = {"view": view, "pix": pix, "o": o, "d": d, "rgb": self.images[view, pix], "R_w2c": w2c[:, :3, :3]}
        b["mask"] = None if self.masks is None else self.masks[view, pix]
        b["object_label"] = None if self.object_labels is None else self.object_labels[view, pix]
        b["mono_depth"] = None if self.mono_depth is None else self.mono_depth[view, pix]
        b["mono_normal"] = None if self.mono_normal is None else self.mono_normal[view, pix]
        return b

    def _draw_pixels(self, m: int) -> torch.Tensor:
        """``m`` flat pixel indices [m] over the training views (on the CPU, from the run's generator)."""
        if self.sizes is None:
            return torch.randint(0, len(self.train_views) * self.H * self.W, (m,), generator=self.rng)
        return draw_pixels(m, self.sizes[self.train_views], self.H, self.W, self.rng)

    def band_weights(self, view: torch.Tensor, step: int):
        if self.band_weight_fn is not None:
            return self.band_weight_fn(view, step)
        if self.tp.c2f_iters > 0:
            L = self.field.n_bands
            a = min(step / self.tp.c2f_iters, 1.0) * L
            if a >= L:
                return None
            return barf_weights(a, L).to(self.device).expand(view.shape[0], L)
        return None

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        return {
            "step": self.step,
            "field": self.field.state_dict(),
            "background": self.background.state_dict(),
            "opt": self.opt.state_dict(),
            "cams": self.cams.state_dict(),
            "lr_scale": self.lr_scale,
            "rollbacks": self.rollbacks,
            "cache": None if self.cache is None else self.cache.state_dict(),
            "params": {"field": asdict(self.fp), "render": asdict(self.rp), "loss": asdict(self.lp),
                       "train": asdict(self.tp), "run": asdict(self.run)},
            "bg_kind": self.bg_kind,
            "rng": self.rng.get_state(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if self.device.type == "cuda" else None,
            "loss_ema": self._loss_ema,
            "loss_status": dict(self.loss_status),
            "history": list(self.history),
            "events": list(self.events),
            "extra": copy.deepcopy(self.extra_state),
        }

    def load_state_dict(self, s: dict) -> None:
        self.step = int(s["step"])
        self.field.load_state_dict(s["field"])
        self.background.load_state_dict(s["background"])
        self.opt.load_state_dict(s["opt"])
        self.cams.load_state_dict(s["cams"])
        self.lr_scale = float(s["lr_scale"])
        self.rollbacks = int(s.get("rollbacks", 0))
        if self.cache is not None and s.get("cache") is not None:
            self.cache.load_state_dict(s["cache"])
        if s.get("rng") is not None:  # generator states are CPU byte tensors; a checkpoint loaded onto cuda moved them
            self.rng.set_state(s["rng"].cpu())
            torch.set_rng_state(s["torch_rng"].cpu())
            if s.get("cuda_rng") is not None and self.device.type == "cuda":
                torch.cuda.set_rng_state_all([state.cpu() for state in s["cuda_rng"]])
        self._loss_ema = s.get("loss_ema")
        self._ema_t = None if self._loss_ema is None else torch.tensor(self._loss_ema, dtype=torch.float64,
                                                                      device=self.device)
        self._flags, self._ray_queue = None, []
        self.loss_status = dict(s.get("loss_status", {}))
        self.history = list(s.get("history", []))
        self.events = list(s.get("events", []))
        self.extra_state = copy.deepcopy(s.get("extra", {}))

    def save(self, path) -> None:
        """Write a checkpoint (torch.save) that :meth:`load` resumes from; atomically (a temporary file,
        then a rename), so a kill while writing leaves the previous checkpoint, never a truncated one."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        try:
            torch.save(self.state_dict(), str(tmp), pickle_module=_value_pickle)
        except BaseException as e:
            tmp.unlink(missing_ok=True)  # a partial checkpoint is only lost space (on a full disk, the most)
            if isinstance(e, RuntimeError) and shutil.disk_usage(tmp.parent).free < (64 << 20):
                # torch reports a full disk as "PytorchStreamWriter failed writing file ..."
                raise OSError(errno.ENOSPC, "No space left on device", str(path)) from e
            raise
        os.replace(tmp, path)

    def load(self, path) -> None:
        self.load_state_dict(torch.load(str(path), map_location=self.device, weights_only=False))

    def resume(self, path) -> bool:
        """Load the checkpoint at ``path`` if there is one; an unreadable one is discarded with a
        warning (training restarts from step 0). Returns whether it resumed."""
        path = Path(path)
        if not path.exists():
            return False
        try:
            self.load(path)
        except Exception as e:  # truncated or foreign file: its content is lost either way
            log.warning("checkpoint %s is unreadable (%s: %s); discarded, training starts afresh", path,
                        type(e).__name__, str(e)[:120])
            path.unlink()
            return False
        return True

    def _snapshot(self) -> None:
        self._good_state = copy.deepcopy(self.state_dict())
        if self.checkpoint_path is not None:
            self.save(self.checkpoint_path)

    def _rollback(self, reason: str) -> None:
        if self._good_state is None:
            raise FloatingPointError(f"training diverged at step {self.step} ({reason}) before any good state")
        if self.rollbacks >= self.tp.max_rollbacks:
            raise FloatingPointError(f"training diverged at step {self.step} ({reason}); "
                                     f"gave up after {self.rollbacks} rollbacks")
        bad_step = self.step
        rollbacks = self.rollbacks + 1
        events = list(self.events)  # the record of earlier rollbacks outlives the state it restores
        self.load_state_dict(copy.deepcopy(self._good_state))
        self.events = events
        self.rollbacks = rollbacks
        # new draws from here (seeded by the run's seed and the rollback count, so a rerun repeats them): with
        # the restored generators the same batch that broke the step would come back at any lr
        self.rng.manual_seed(self.run.seed + 1_000_003 * rollbacks)
        torch.manual_seed(self.run.seed + 2_000_003 * rollbacks)
        self.lr_scale *= self.tp.rollback_lr_factor
        self._good_state["lr_scale"] = self.lr_scale
        self._good_state["rollbacks"] = self.rollbacks
        self._loss_ema = self._ema_t = None
        ev = {"event": "rollback", "at_step": bad_step, "to_step": self.step, "reason": reason,
              "lr_scale": self.lr_scale}
        self.events.append(ev)
        log.warning("step %d: %s -> rolled back to step %d, lr scale now %.3g", bad_step, reason, self.step,
                    self.lr_scale)

    # ------------------------------------------------------------------ training
    def schedule_step(self) -> int:
        """Step used by the lr schedules: the iteration, or, with a time budget, the iteration the
        elapsed fraction of the budget corresponds to when that is further (so the cosine decay
        completes by the budget)."""
        if self._budget and self._t_start is not None:
            frac = (self.clock() - self._t_start) / self._budget
            return max(self.step, int(frac * self.run.iters))
        return self.step

    def set_lr(self) -> None:
        st = self.schedule_step()
        f = lr_factor(st, self.run.iters, self.warmup, self.tp.lr_min_ratio) * self.lr_scale
        for g in self.opt.param_groups:
            g["lr"] = g["base_lr"] * f
        self.cams.set_lr(lr_factor(st, self.run.iters, self.run.pose_warmup, self.tp.pose_lr_min_ratio) * self.lr_scale)

    def update_cache(self) -> None:
        if self.cache is not None:
            was = self.field.training
            self.field.eval()
            self.cache.update(lambda x: self.field.sdf(x))
            self.field.train(was)

    def train_step(self, inject_nan: bool = False) -> dict:
        """One iteration. Returns {'loss', 'terms', 'status', 'info'} (or a rollback record); with
        ``train.check_every`` > 1, 'loss' is None and 'terms' empty between checks (see :meth:`_deferred_step`)."""
        if self.tp.check_every > 1:
            return self._deferred_step(inject_nan)
        total, field_loss, lv, terms, status = self._step_losses(host=True)
        if inject_nan:
            total = total * float("nan")
            lv = float("nan")
        if not math.isfinite(lv):
            self._rollback("non-finite loss")
            return {"rollback": True}
        # The field's loss only: the pose term enters at pose_start, at a size set by how far the
        # initial poses are from the matches (a perturbed start: 20x the field's), and is not a divergence.
        if (self._loss_ema is not None and self.step > self.warmup
                and field_loss > self.tp.diverge_factor * self._loss_ema):
            self._rollback(f"loss {field_loss:.4g} > {self.tp.diverge_factor} x running mean {self._loss_ema:.4g}")
            return {"rollback": True}
        self._loss_ema = field_loss if self._loss_ema is None else 0.98 * self._loss_ema + 0.02 * field_loss
        grads = self._backward(total)
        # one reduction per tensor: a NaN / inf anywhere makes its sum non-finite
        if grads and not bool(torch.isfinite(torch.stack([g.sum() for g in grads])).all()):
            bad = next(n for n, p in self.field.named_parameters()
                       if p.grad is not None and not torch.isfinite(p.grad).all())
            self._rollback(f"non-finite gradient in {bad}")
            return {"rollback": True}
        self._update()
        return self._step_record(lv, terms, status)

    def _backward(self, total: torch.Tensor) -> list:
        """The gradients of ``total``; returns the field's (those that exist)."""
        self.opt.zero_grad(set_to_none=True)
        self.cams.zero_grad()
        with record_function("train/backward"):
            total.backward()
        return [p.grad for p in self.field.parameters() if p.grad is not None]

    def _update(self) -> None:
        """The optimisers' step of an iteration whose checks passed (or are deferred)."""
        with record_function("train/optimiser"):
            self.opt.step()
            self.cams.step()
        self.step += 1

    def _step_losses(self, host: bool):
        """The iteration up to its loss: the SDF cache, the first rollback state, the lr, the batch, the render,
        its losses and the free-space and pose terms. Returns (total, field loss, logged loss, terms, status);
        the losses and terms are floats with ``host``, else tensors (no host read)."""
        if self.cache is not None and (self.cache.grid is None or self.step % self.rp.cache_every == 0):
            with record_function("train/sdf_cache"):
                self.update_cache()
        if self._good_state is None:
            self._snapshot()
        self.set_lr()
        with record_function("train/sample_rays"):
            b = self.sample_batch(self.tp.batch_rays)
            bw = self.band_weights(b["view"], self.step)
        with record_function("train/render"):
            if host and self.tp.compile == "off":
                total, terms, status = self._render_losses(b, bw)
            else:  # a compiled graph holds no host read: the terms come back as tensors
                total, terms, status = self._loss_fn(b, bw, host=False)
                terms = {k: float(v) for k, v in terms.items()} if host else terms
        read = float if host else torch.Tensor.detach
        with record_function("train/losses"):
            if self.free_space is not None:
                free = self.free_space(self.field.sdf, self.rng)
                total = total + self.lp.w_free_space * free
                terms["free_space"], status["free_space"] = read(free.detach()), "on"
        field_loss = read(total.detach())  # what the divergence check watches (the pose term jumps by design)
        lv = field_loss
        if self.pose_loss is not None and self.cams.active(self.step):
            with record_function("train/pose_term"):
                extra = self.pose_loss(self.poses(), self.rng, self.step)
            if extra is not None:
                terms["corr"] = read(extra.detach())
                total = total + self.pose_loss.weight * extra
                lv = field_loss + self.pose_loss.weight * terms["corr"]  # no second device sync
        self.loss_status = status
        return total, field_loss, lv, terms, status

    def _step_record(self, lv: float, terms: dict, status: dict) -> dict:
        """After an iteration's update: its history entry (every log_every) and rollback state (every ckpt_every)."""
        info = None
        if self.step % self.tp.log_every == 0 or self.step == self._target:
            # recorded before the snapshot below, so a checkpoint's history includes its own step
            info = {"step": self.step, "loss": lv, **{f"loss_{k}": v for k, v in terms.items()},
                    "inv_s": float(self.field.inv_s().detach()), "lr": self.opt.param_groups[0]["lr"]}
            self.history.append(info)
            if self.recorder is not None:
                self.recorder(self, info)
        if self.step % self.tp.ckpt_every == 0:
            jump = self.pose_jump()
            if jump is not None:
                self._rollback(jump)
                return {"rollback": True}
            self._snapshot()
        return {"loss": lv, "terms": terms, "status": status, "info": info}

    def _deferred_step(self, inject_nan: bool) -> dict:
        """:meth:`train_step` with ``train.check_every`` > 1: the same iteration, its checks kept on the device.
        The loss, its running mean and the flags of a non-finite loss, a divergence or a non-finite gradient stay
        tensors; every check_every-th iteration (and every logged or checkpointed one) reads them in one host
        read and, if a flag is set, rolls back to the last good state as :meth:`train_step` does at once."""
        total, field_loss, lv, terms, status = self._step_losses(host=False)
        if inject_nan:
            total = total * float("nan")
            lv = lv * float("nan")
        self._last_loss = lv
        loss64 = field_loss.double()  # the running mean in float64, as the Python float of train_step
        flags = (~torch.isfinite(lv)).to(torch.uint8) * LOSS_NAN
        if self._ema_t is not None and self.step > self.warmup:
            flags = flags | (loss64 > self.tp.diverge_factor * self._ema_t).to(torch.uint8) * DIVERGED
        self._ema_t = loss64 if self._ema_t is None else 0.98 * self._ema_t + 0.02 * loss64
        grads = self._backward(total)
        if grads:  # one multi-tensor norm: a NaN / inf anywhere makes its tensor's norm non-finite
            finite = torch.isfinite(torch.stack(torch._foreach_norm(grads))).all()
            flags = flags | (~finite).to(torch.uint8) * GRAD_NAN
        self._flags = flags if self._flags is None else self._flags | flags
        self._update()
        if (self.step % self.tp.check_every and self.step % self.tp.log_every and self.step != self._target
                and self.step % self.tp.ckpt_every):
            return {"loss": None, "terms": {}, "status": status, "info": None}
        checked = self._check(lv, terms)
        if checked is None:
            return {"rollback": True}
        return self._step_record(*checked, status)

    def _check(self, lv: torch.Tensor, terms: dict):
        """The deferred checks of the iterations since the last: one host read of the flags, the running mean,
        the loss and its terms. Rolls back (and returns None) if a flag is set, else (loss, {term: float})."""
        if self._flags is None:
            return float(lv), {k: float(v) for k, v in terms.items()}
        values = torch.stack([self._flags.double(), self._ema_t, lv.double(),
                              *(v.double() for v in terms.values())]).tolist()
        flags, self._flags = int(values[0]), None
        if flags:
            why = ("non-finite loss" if flags & LOSS_NAN else
                   f"loss > {self.tp.diverge_factor} x running mean" if flags & DIVERGED else "non-finite gradient")
            self._rollback(f"{why} (checked every {self.tp.check_every} iterations)")
            return None
        self._loss_ema = values[1]
        return values[2], dict(zip(terms, values[3:]))

    def pose_jump(self) -> str | None:
        """Why the learned poses count as diverged since the last rollback state, or None."""
        if self._good_state is None:
            return None
        why = self.cams.jump(self._good_state["cams"]["xi"], self.step, self.tp.pose_jump_deg, self.views.names)
        if why is None or why.startswith("non-finite"):
            return why
        return f"{why} in {self.tp.ckpt_every} iterations (pose_jump_deg = {self.tp.pose_jump_deg:g})"

    def train(self, iters: int | None = None, time_budget_s: float | None = None, callback=None, on_step=None) -> dict:
        """Train until ``iters`` (default ``run.iters``) total iterations or the time budget.
        ``callback(trainer, info)`` runs every ``log_every`` iterations (and may return True to stop);
        ``on_step(step)`` after every iteration (a progress bar's tick). Returns a summary dict."""
        iters = self.run.iters if iters is None else iters
        budget = self.tp.time_budget_s if time_budget_s is None else time_budget_s
        t0 = self.clock()
        t_wall = time.time()
        if budget and self._t_start is None:
            # the schedule follows the budget (set once, so repeated train() calls keep it)
            self._budget, self._t_start = budget, t0
        last = {}
        self.field.train()
        self._target, self._t_train = iters, t0
        while self.step < iters:
            r = self.train_step()
            if r.get("rollback"):
                continue
            last = r
            if on_step is not None:
                on_step(self.step)
            info = r["info"]
            if info is not None:
                # the time goes to the log, not the history: a resumed run must write the same files
                log.info("step %d loss %.4f %s s=%.1f (%.0f s)", self.step, r["loss"],
                         " ".join(f"{k}={v:.4f}" for k, v in r["terms"].items()), info["inv_s"], self.clock() - t0)
                if self.progress is not None:
                    self.progress(self.step, info)
                if callback is not None and callback(self, info):
                    break
            if budget and self.clock() - t0 > budget:
                log.info("time budget %.0f s reached at step %d", budget, self.step)
                break
        self.field.eval()
        if last.get("loss", 0.0) is None:  # check_every > 1, stopped between checks (a time budget): check now
            checked = self._check(self._last_loss, {})
            last = {"loss": None if checked is None else checked[0]}
        # a run resumed at its last step trains no step here: its final loss is its history's last
        final = last.get("loss") if last.get("loss") is not None else (self.history[-1]["loss"] if self.history else None)
        return {"steps": self.step, "seconds": time.time() - t_wall, "final_loss": final,
                "loss_status": self.loss_status, "rollbacks": self.rollbacks, "events": list(self.events),
                "background": self.bg_kind}

    # ------------------------------------------------------------------ inference
    def render_view(self, i: int, K=None, w2c=None, size: tuple[int, int] | None = None,
                    want_normals: bool = True) -> dict:
        """Render view ``i`` at the training resolution with its current pose (or given K / w2c,
        K at the training resolution: ``trainer.views.K``). See :func:`render_image`."""
        H, W = size or (self.H, self.W)
        K = self.views.K[i] if K is None else K
        w2c = self.poses_numpy()[i] if w2c is None else w2c
        self.field.eval()
        return render_image(self.field, K, w2c, H, W, self.rp, cache=self.cache, background=self.background,
                            device=self.device, want_normals=want_normals)

    def sdf_fn(self):
        """Callable numpy [P,3] -> numpy [P] SDF (no gradients), e.g. for meshing."""

        def f(x):
            with torch.no_grad():
                t = torch.as_tensor(np.asarray(x), dtype=torch.float32, device=self.device)
                return self.field.sdf(t).cpu().numpy()

        return f
