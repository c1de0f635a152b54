"""Profile of the neural trainer's step: where a step's time goes, rays per CPU-second, samples per
second and the fraction of the machine's peak (docs/PERFORMANCE.md).

Trains on a scene's views with its ground-truth poses, poses learned as the anchors learn them
(every 8th view held out), the project's default field, render and train parameters at the fast
profile's resolution. After ``--warm`` steps (the field has formed a surface) it times ``--steps``
steps (wall and process CPU seconds), then profiles ``--profile-steps`` more with torch.profiler and
groups them by the trainer's labelled parts, counts the operator launches (leaf aten calls) and the
host reads (``.item()``, ``float(t)``, ``.cpu()``, ...: each a synchronisation on a GPU) a step makes, and
the samples it evaluates. ``--code DIR`` runs another checkout's manifoldneus
(the same script measures old and new code in one run). Several seeds: mean and spread.

``--profile NAME`` takes a params.yaml profile's field, render, loss and train sections (its rays per step
and image size too) and ``--form`` picks the step: ``eager`` (train.compile off, check_every 1: the step as
it ran before the compiled one) or ``profile`` (the profile's own compile and check_every); on the CPU the
grids use the 'torch' kernel in both (the kernel a GPU runs), so both forms do the same work. Launches
then count inductor's fused C++ kernels too (its kernel profiling is switched on), and the profiled steps
end on a check step of a ``check_every`` window.

    .venv/bin/python -m bench.profile_step --scene scan24 --seeds 0,1,2
    .venv/bin/python -m bench.profile_step --code /tmp/old --label old     # a checkout of older code
    .venv/bin/python -m bench.profile_step --profile gpu --form eager --scene synthetic --seeds 0 --warm 2 \
        --steps 1 --profile-steps 2 --label gpu-eager
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# inductor's C++ kernels record a profiler event each: a compiled step's launches are counted, not hidden
os.environ.setdefault("TORCHINDUCTOR_CPP_ENABLE_KERNEL_PROFILE", "1")

import argparse
import collections
import contextlib
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

HERE = Path(__file__).resolve().parent
PARTS = ("train/sdf_cache", "train/sample_rays", "train/render", "train/losses", "train/pose_term",
         "train/backward", "train/optimiser")


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def peak_gflops(threads: int, seconds: float = 1.0) -> float:
    """Measured fp32 matmul rate of this machine (a 1024^3 GEMM on ``threads`` threads): the peak
    the step's FLOPs are compared with."""
    import torch

    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    a @ b
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a @ b
        n += 1
    return 2 * 1024**3 * n / (time.perf_counter() - t0) / 1e9


def one_seed(args, seed: int) -> dict:
    import torch
    from torch.profiler import ProfilerActivity, profile

    from bench.bench_neural import load_scene
    from manifoldneus.neural.field import FieldParams
    from manifoldneus.neural.losses import LossParams
    from manifoldneus.neural.render import RenderParams
    from manifoldneus.neural.train import TrainParams, Trainer, TrainRun

    sections = [FieldParams(), RenderParams(), LossParams(), TrainParams(batch_rays=args.rays, image_size=args.size)]
    if getattr(args, "profile", None):
        sections = profile_sections(args.profile, args.form)
    for item in args.set:
        key, value = item.split("=", 1)
        owner = next((s for s in sections if hasattr(s, key)), None)
        if owner is None:
            raise SystemExit(f"--set {item}: no field, render, loss or train parameter {key!r}")
        setattr(owner, key, type(getattr(owner, key))(yaml.safe_load(value)))
    views = load_scene(args.scene)
    train_ids = [i for i in range(views.n) if i % 8]
    tr = Trainer(views, *sections, train_views=train_ids,
                 run=TrainRun(iters=args.iters, learn_poses=True, pose_lr=2e-4, seed=seed, threads=args.threads))
    compile_s = None
    ce = getattr(tr.tp, "check_every", 1)  # older code: no deferred checks, no compiled step
    if getattr(tr.tp, "compile", "off") != "off":  # the first step compiles: timed apart
        t0 = time.perf_counter()
        tr.train_step()
        compile_s = time.perf_counter() - t0
    for _ in range(args.warm - (compile_s is not None)):
        tr.train_step()
    t0, c0 = time.perf_counter(), cpu_s()
    for _ in range(args.steps):
        tr.train_step()
    wall, cpu = (time.perf_counter() - t0) / args.steps, (cpu_s() - c0) / args.steps
    # network-evaluated samples per ray, as the step renders them (no gradients, same sampler)
    from manifoldneus.neural.render import render_rays

    with torch.no_grad():
        if ce > 1:  # not the trainer's batch size: its check window's queue is left alone
            b = tr.sample_batch(args.rays + 1)
            b = {k: None if v is None else v[:args.rays] for k, v in b.items()}
        else:
            b = tr.sample_batch(args.rays)
        out = render_rays(tr.field, b["o"], b["d"], tr.rp, cache=tr.cache, background=tr.background, perturb=True)
    evaluated = out.get("evaluated", out["t"].numel()) / args.rays
    # the profiled steps end on a check (check_every > 1): its one host read is among those counted
    while ce > 1 and (tr.step + args.profile_steps) % ce:
        tr.train_step()
    with counting_host_reads() as reads, profile(activities=[ProfilerActivity.CPU], with_flops=True) as prof:
        for _ in range(args.profile_steps):
            tr.train_step()
    # operator launches: the aten calls with no aten call inside (on a GPU, about one kernel each)
    # and inductor's fused kernels (named cpp_fused_* by its kernel profiling; triton_* on a GPU)
    launched = collections.Counter(
        "fused kernels" if is_fused_kernel(e.name) else e.name for e in prof.events()
        if (e.name.startswith("aten::") and not any(c.name.startswith("aten::") for c in e.cpu_children))
        or is_fused_kernel(e.name))
    launches = sum(launched.values()) / args.profile_steps
    fused = sum(1 for e in prof.events() if is_fused_kernel(e.name)) / args.profile_steps
    events = prof.key_averages()
    parts = {e.key: e.cpu_time_total / 1e3 / args.profile_steps for e in events if e.key in PARTS}
    flops = sum(e.flops for e in events if e.flops) / args.profile_steps
    ops = sorted(((e.key, e.self_cpu_time_total / 1e3 / args.profile_steps) for e in events
                  if not e.key.startswith("train/")), key=lambda kv: -kv[1])[:16]
    return {"seed": seed, "wall_ms": 1e3 * wall, "cpu_ms": 1e3 * cpu, "rays_per_cpu_s": args.rays / cpu,
            "rays_per_wall_s": args.rays / wall, "evaluated_per_ray": evaluated,
            "samples_per_cpu_s": evaluated * args.rays / cpu, "inv_s": float(tr.field.inv_s().detach()),
            "parts_ms": parts, "top_ops_ms": dict(ops), "gflop_per_step_matmul": flops / 1e9,
            "samples_per_step": evaluated * args.rays, "launches_per_step": launches,
            "fused_kernels_per_step": fused,
            "launches_by_name": {k: v / args.profile_steps for k, v in launched.most_common(20)},
            "compile_s": compile_s, "check_every": ce,
            "train": {k: getattr(tr.tp, k, None) for k in ("batch_rays", "image_size", "check_every", "compile")},
            "render": dict(vars(tr.rp)), "field": dict(vars(tr.fp)),
            "host_reads_per_step": {k: v / args.profile_steps for k, v in sorted(reads.items())}}


def is_fused_kernel(name: str) -> bool:
    return "cpp_fused" in name or name.startswith("triton_")


def profile_sections(name: str, form: str) -> list:
    """The field, render, loss and train sections of params.yaml's profile ``name``; ``form`` 'eager' turns its
    compiled step and deferred checks off. On the CPU the grids use the 'torch' kernel (a GPU's)."""
    import dataclasses

    import runner

    resolved = runner.resolve_params(runner.load_stages(), profile=name)
    fp, rp, lp, tp = (resolved[s] for s in ("field", "render", "loss", "train"))
    fp = dataclasses.replace(fp, grid_kernel="torch")
    if form == "eager":
        tp = dataclasses.replace(tp, compile="off", check_every=1)
    return [fp, rp, lp, tp]


# nonzero too: its result's size is read on the host (a compaction to the samples kept)
HOST_READS = ("item", "tolist", "cpu", "numpy", "__float__", "__int__", "__bool__", "nonzero")


@contextlib.contextmanager
def counting_host_reads():
    """Counts, per Tensor method of :data:`HOST_READS`, the calls made inside: on a GPU each one waits for
    the device (a host-device synchronisation); on the CPU the same calls mark the loop's code paths that
    would."""
    import torch

    counts: collections.Counter = collections.Counter()
    originals = {name: getattr(torch.Tensor, name) for name in HOST_READS}

    def counted(name, method):
        def wrapper(self, *args, **kwargs):
            counts[name] += 1
            return method(self, *args, **kwargs)
        return wrapper

    for name, method in originals.items():
        setattr(torch.Tensor, name, counted(name, method))
    try:
        yield counts
    finally:
        for name, method in originals.items():
            setattr(torch.Tensor, name, method)


def spread(values) -> str:
    v = np.asarray(values, float)
    return f"{v.mean():.1f} ± {v.std(ddof=1) if len(v) > 1 else 0.0:.1f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="scan24")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--warm", type=int, default=200, help="steps before timing (the surface forms)")
    ap.add_argument("--steps", type=int, default=50, help="timed steps")
    ap.add_argument("--profile-steps", type=int, default=10)
    ap.add_argument("--iters", type=int, default=600, help="the run's length (its lr schedule); the anchors' 600")
    ap.add_argument("--rays", type=int, default=1024)
    ap.add_argument("--size", type=int, default=192, help="training image size (longest side)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--code", type=Path, default=HERE.parent, help="the checkout whose manifoldneus is measured")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a field, render, loss or train parameter (e.g. n_importance=16); repeatable")
    ap.add_argument("--profile", default=None, help="a params.yaml profile's field, render, loss and train sections "
                    "(its rays and image size too; --rays and --size are then ignored)")
    ap.add_argument("--form", choices=("eager", "profile"), default="profile",
                    help="with --profile: 'eager' = compile off and check_every 1; 'profile' = the profile's own")
    ap.add_argument("--label", default="current")
    ap.add_argument("--out", type=Path, default=None, help="JSON (default bench/perf/profile-<label>-<date>.json)")
    args = ap.parse_args()
    sys.path.insert(0, str(args.code.resolve()))  # the checkout to measure, on purpose: possibly not this one
    import manifoldneus

    code = Path(manifoldneus.__file__).resolve().parent.parent
    commit = subprocess.run(["git", "-C", str(code), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    if args.profile:
        tp = profile_sections(args.profile, args.form)[3]
        args.rays, args.size = tp.batch_rays, tp.image_size
    runs = [one_seed(args, int(s)) for s in args.seeds.split(",")]
    peak = peak_gflops(args.threads)
    dirty = subprocess.run(["git", "-C", str(code), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    commit += "+uncommitted" if dirty else ""
    res = {"label": args.label, "code": str(code), "commit": commit, "set": args.set, "scene": args.scene,
           "profile": args.profile, "form": args.form if args.profile else None, "rays": args.rays,
           "size": args.size, "threads": args.threads, "warm": args.warm, "steps": args.steps,
           "peak_gflops_measured": peak, "runs": runs, "date": time.strftime("%Y-%m-%d %H:%M")}
    print(f"{args.label} ({commit}), {args.scene}, {args.rays} rays/step at {args.size} px, {args.threads} threads")
    for key in ("wall_ms", "cpu_ms", "rays_per_cpu_s", "rays_per_wall_s", "evaluated_per_ray", "samples_per_cpu_s",
                "samples_per_step", "launches_per_step", "fused_kernels_per_step"):
        print(f"  {key:<20} {spread([r[key] for r in runs])}")
    print("  host reads per step (each a host-device synchronisation on a GPU), seed 0: "
          + (", ".join(f"{k} {v:g}" for k, v in runs[0]["host_reads_per_step"].items()) or "none"))
    print("  where a step's time goes (ms, CPU total of each labelled part, seed 0):")
    for k, v in runs[0]["parts_ms"].items():
        print(f"    {k:<22} {v:7.1f}")
    print("  heaviest operators (ms self CPU per step, seed 0): "
          + ", ".join(f"{k} {v:.1f}" for k, v in runs[0]["top_ops_ms"].items()))
    gf = np.mean([r["gflop_per_step_matmul"] for r in runs])
    cpu = np.mean([r["cpu_ms"] for r in runs]) / 1e3
    print(f"  matmul FLOPs {gf:.2f} GFLOP/step: {gf / cpu:.1f} GFLOP per CPU-second; measured peak "
          f"{peak:.0f} GFLOP/s on {args.threads} threads ({100 * gf / cpu / (peak / args.threads):.0f} % of one "
          f"core's peak per CPU-second)")
    out = args.out or HERE / "perf" / f"profile-{args.label}-{time.strftime('%Y-%m-%d')}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
