"""A params.yaml profile's training step on one device, in each of its forms: iterations and network samples
per second, host-device synchronisations per step (``torch.cuda.set_sync_debug_mode`` on cuda) and the time
the first step takes (compiling). The Python part of ``bench/gpu_check.sh`` (docs/PERFORMANCE.md, "A step for
the GPU"); on the CPU, with small sizes, a check of itself.

Forms: ``eager`` (train.compile off, check_every 1: the step before the compiled one), ``profile`` (the profile's
own train.compile and check_every) or a train.compile mode (``default``, ``reduce-overhead``) with the profile's
check_every. Every form does the same work: the same rays and samples per step.

    python3 -m bench.gpu_step --device cuda --forms eager,default,reduce-overhead --seconds 15
    .venv/bin/python -m bench.gpu_step --device cpu --forms eager,default --warm 1 --seconds 1 \\
        --set train.batch_rays=128 --set render.n_importance=8 --set field.grid_levels=4
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import warnings
from pathlib import Path


def measure(form: str, args, views) -> dict:
    import torch

    import runner
    from manifoldneus.neural.train import Trainer, TrainRun

    resolved = runner.resolve_params(runner.load_stages(), profile=args.profile,
                                     overrides=[*args.set, f"run.device={args.device}"])
    fp, rp, lp, tp = (resolved[s] for s in ("field", "render", "loss", "train"))
    if form == "eager":
        tp = dataclasses.replace(tp, compile="off", check_every=1)
    elif form != "profile":
        tp = dataclasses.replace(tp, compile=form)
    if args.device == "cpu":
        fp = dataclasses.replace(fp, grid_kernel="torch")  # the kernel a GPU runs: the same work
    dev = torch.device(args.device)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    tr = Trainer(views, fp, rp, lp, tp, run=TrainRun(iters=args.iters, learn_poses=True, pose_lr=2e-4, seed=0,
                                                     threads=args.threads, device=args.device),
                 train_views=[i for i in range(views.n) if i % 8])
    t0 = time.perf_counter()
    tr.train_step()  # compiles, where the form compiles
    sync()
    first_s = time.perf_counter() - t0
    for _ in range(args.warm):
        tr.train_step()
    sync()
    n, t0 = 0, time.perf_counter()
    while n < args.min_steps or time.perf_counter() - t0 < args.seconds:
        tr.train_step()
        n += 1
    sync()
    step_s = (time.perf_counter() - t0) / n
    syncs = None
    if dev.type == "cuda":  # every synchronisation of a window of check_every steps, one warning each
        window = max(tp.check_every, 1)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                for _ in range(window):
                    tr.train_step()
                sync()
            finally:
                torch.cuda.set_sync_debug_mode("default")
        syncs = sum("synchroniz" in str(w.message) for w in caught) / window
    samples = tp.batch_rays * (rp.n_uniform + rp.n_importance)  # network samples at the rays' samples
    extra = rp.eikonal_samples + rp.eikonal_uniform  # Eikonal points (x4 with finite differences)
    res = {"form": form, "compile": tp.compile, "check_every": tp.check_every, "device": args.device,
           "first_step_s": first_s, "step_ms": 1e3 * step_s, "its": 1.0 / step_s, "samples_per_step": samples,
           "eikonal_points_per_step": extra, "samples_per_s": samples / step_s, "timed_steps": n,
           "syncs_per_step": syncs, "rollbacks": tr.rollbacks, "step": tr.step,
           "max_memory_gib": torch.cuda.max_memory_allocated(dev) / 2**30 if dev.type == "cuda" else None}
    print(f"{form:>16}: {res['its']:7.2f} it/s, {res['samples_per_s'] / 1e6:7.2f} M samples/s "
          f"({samples} a step), first step {first_s:6.1f} s, syncs/step "
          f"{'n/a (cpu)' if syncs is None else f'{syncs:.2f}'}, rollbacks {tr.rollbacks}", flush=True)
    del tr
    if dev.type == "cuda":
        torch.cuda.empty_cache()
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--profile", default="gpu")
    ap.add_argument("--scene", default="synthetic", help="a scene with ground-truth poses (synthetic needs no data)")
    ap.add_argument("--forms", default="eager,default,reduce-overhead")
    ap.add_argument("--warm", type=int, default=20, help="steps after the first before timing")
    ap.add_argument("--seconds", type=float, default=15.0, help="timed seconds per form (at least --min-steps)")
    ap.add_argument("--min-steps", type=int, default=3)
    ap.add_argument("--iters", type=int, default=20000, help="the run's length (its lr schedule)")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="repeatable")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    import torch

    from bench.bench_neural import load_scene

    print(f"torch {torch.__version__}, device {args.device}"
          + (f" ({torch.cuda.get_device_name(0)})" if args.device.startswith("cuda") else ""), flush=True)
    views = load_scene(args.scene)
    runs = []
    for form in args.forms.split(","):
        try:
            runs.append(measure(form, args, views))
        except Exception as e:  # one form's failure (out of memory, a compiler's error) leaves the others
            print(f"{form:>16}: FAILED {type(e).__name__}: {str(e).strip()[:400]}", flush=True)
            runs.append({"form": form, "error": f"{type(e).__name__}: {str(e).strip()[:2000]}"})
        if args.json:  # after every form: a run stopped by its time limit keeps the forms it measured
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"profile": args.profile, "scene": args.scene, "set": args.set,
                                             "torch": torch.__version__, "runs": runs}, indent=2) + "\n")
    return 0 if all("error" not in r for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
