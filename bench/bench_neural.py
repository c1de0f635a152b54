"""Benchmark of the neural surface core on DTU scan24 with ground-truth poses.

Trains on all views but every 8th (held out: 0, 8, 16, ...), within a wall-clock budget, and
reports masked held-out PSNR (MSE over foreground pixels only), SSIM, throughput (rays/s), peak
memory (max RSS) and wall time. Prints a table and writes JSON.

    .venv/bin/python -m bench.bench_neural --field grid --budget 420 --out /tmp/bench_neural.json
    .venv/bin/python -m bench.bench_neural --throughput-only      # rays/s of both fields

The scene is read by manifoldneus.data.scenes (the ingest and ground_truth stages' readers).
"""
from __future__ import annotations

import os

# OpenMP busy-waiting collapses throughput when the 2 cores are shared with other processes.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import json
import resource
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from manifoldneus.neural.field import FieldParams
from manifoldneus.neural.losses import LossParams
from manifoldneus.output.metrics import psnr, ssim
from manifoldneus.neural.render import RenderParams
from manifoldneus.data.scenes import read_ground_truth, read_views, resolve_scene
from manifoldneus.neural.train import TrainParams, Trainer, TrainRun, Views
from stages.ingest import Params as IngestParams


def load_scene(data: str) -> Views:
    """The scene's views as the ingest stage reads them (default ingest params) with its ground-truth poses."""
    ref = resolve_scene(data)
    p = IngestParams()
    views, gt = read_views(ref, p), read_ground_truth(ref, p)
    if gt is None:
        raise SystemExit(f"{data}: no ground-truth poses; this benchmark trains with them (pass --data)")
    return Views(views["images"], views["K"], gt["w2c"], views.get("masks"), views.get("mono_depth"),
                 views.get("mono_normal"), views["names"])


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def evaluate(tr: Trainer, test_ids, save_dir: Path | None = None) -> dict:
    imgs = tr.views.float_images()
    ps, pm, ss, sm = [], [], [], []
    t0 = time.time()
    for i in test_ids:
        out = tr.render_view(int(i), want_normals=False)
        gt = imgs[i]
        m = tr.views.masks[i] if tr.views.masks is not None else None
        pred = np.clip(out["rgb"], 0, 1)
        ps.append(psnr(pred, gt))
        ss.append(ssim(pred, gt))
        if m is not None:
            pm.append(psnr(pred, gt, m))
            sm.append(ssim(pred, gt, m))
        if save_dir is not None:
            from manifoldneus.data.io import save_png

            save_dir.mkdir(parents=True, exist_ok=True)
            save_png(save_dir / f"view{i:02d}.png", np.concatenate([pred, gt], 1))
    r = {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "eval_s": time.time() - t0,
         "psnr_per_view": [float(x) for x in ps]}
    if pm:
        r.update({"psnr_masked": float(np.mean(pm)), "ssim_masked": float(np.mean(sm)),
                  "psnr_masked_per_view": [float(x) for x in pm]})
    return r


def build_params(args):
    fp = FieldParams(kind=args.field)
    if args.field == "mlp":
        fp = replace(fp, mlp_width=args.mlp_width, mlp_depth=args.mlp_depth, color_width=args.mlp_width,
                     mlp_skip=args.mlp_depth // 2 if args.mlp_depth >= 4 else -1)
    else:
        fp = replace(fp, grid_levels=args.levels, grid_max_res=args.max_res, grid_min_res=args.min_res,
                     grid_channels=args.channels)
    rp = RenderParams(n_uniform=args.n_uniform, n_importance=args.n_importance, sampler=args.sampler,
                      cache_res=args.cache_res)
    lp = LossParams(w_depth=args.w_depth, w_normal=args.w_normal, w_mask=args.w_mask, w_eikonal=args.w_eik)
    tp = TrainParams(batch_rays=args.rays, image_size=args.size, warmup=args.warmup,
                     time_budget_s=args.budget, log_every=50, c2f_iters=args.c2f,
                     fg_ray_fraction=args.fg_frac, lr=args.lr, grid_lr=args.grid_lr, ckpt_every=250)
    run = TrainRun(iters=args.iters, threads=args.threads)
    for k, v in (args.set or []):
        for obj in (fp, rp, lp, tp, run):
            if hasattr(obj, k):
                cur = getattr(obj, k)
                if isinstance(cur, bool):
                    v = v.lower() in ("1", "true", "yes", "on")
                setattr(obj, k, type(cur)(v))
                break
        else:
            raise SystemExit(f"unknown parameter {k}")
    return fp, rp, lp, tp, run


def throughput(views: Views, args, kinds=("grid", "mlp"), n_iter: int = 10) -> dict:
    out = {}
    for kind in kinds:
        a = argparse.Namespace(**vars(args))
        a.field = kind
        fp, rp, lp, tp, run = build_params(a)
        tr = Trainer(views, fp, rp, lp, tp, run=run, train_views=[i for i in range(views.n) if i % 8])
        tr.train_step()
        tr.train_step()
        t0 = time.time()
        for _ in range(n_iter):
            tr.train_step()
        dt = (time.time() - t0) / n_iter
        out[kind] = {"s_per_iter": dt, "rays_per_s": tp.batch_rays / dt,
                     "samples_per_ray": rp.n_uniform + rp.n_importance}
        print(f"throughput {kind}: {dt:.3f} s/iter, {tp.batch_rays / dt:.0f} rays/s")
    return out


def main():
    # defaults are the project's (the Params dataclasses), so the bench follows them when they change
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="scan24", help="a scene name under the data root, or a folder")
    ap.add_argument("--field", default="grid", choices=["grid", "mlp"])
    ap.add_argument("--size", type=int, default=TrainParams.image_size, help="training / evaluation image size (longest side)")
    ap.add_argument("--budget", type=float, default=420.0, help="training wall-clock budget in seconds")
    ap.add_argument("--budget-cpu", type=float, default=0.0,
                    help="also stop when training used this many CPU seconds (user+sys of this process; "
                         "a load-independent budget when the cores are shared)")
    ap.add_argument("--iters", type=int, default=3000,
                    help="iteration cap (the lr schedule follows the time budget when that ends first)")
    ap.add_argument("--warmup", type=int, default=TrainParams.warmup)
    ap.add_argument("--rays", type=int, default=TrainParams.batch_rays)
    ap.add_argument("--lr", type=float, default=0.0, help="network lr (0 = auto: grid 1e-2, mlp 5e-4)")
    ap.add_argument("--grid-lr", type=float, default=TrainParams.grid_lr)
    ap.add_argument("--n-uniform", type=int, default=RenderParams.n_uniform)
    ap.add_argument("--n-importance", type=int, default=RenderParams.n_importance)
    ap.add_argument("--sampler", default=RenderParams.sampler, choices=["cache", "neus"])
    ap.add_argument("--cache-res", type=int, default=RenderParams.cache_res)
    ap.add_argument("--levels", type=int, default=FieldParams.grid_levels)
    ap.add_argument("--min-res", type=int, default=FieldParams.grid_min_res)
    ap.add_argument("--max-res", type=int, default=FieldParams.grid_max_res)
    ap.add_argument("--channels", type=int, default=FieldParams.grid_channels)
    ap.add_argument("--mlp-width", type=int, default=256, help="mlp: width (NeuS: 256)")
    ap.add_argument("--mlp-depth", type=int, default=8, help="mlp: depth (NeuS: 8)")
    ap.add_argument("--c2f", type=int, default=TrainParams.c2f_iters)
    ap.add_argument("--fg-frac", type=float, default=TrainParams.fg_ray_fraction)
    ap.add_argument("--w-depth", type=float, default=LossParams.w_depth)
    ap.add_argument("--w-normal", type=float, default=LossParams.w_normal)
    ap.add_argument("--w-mask", type=float, default=LossParams.w_mask)
    ap.add_argument("--w-eik", type=float, default=LossParams.w_eikonal)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--no-masks", action="store_true", help="drop the masks (unmasked training)")
    ap.add_argument("--no-priors", action="store_true", help="drop the mono depth / normal priors")
    ap.add_argument("--eval-at", type=float, nargs="*", default=[], help="also evaluate after these training seconds")
    ap.add_argument("--throughput-only", action="store_true")
    ap.add_argument("--set", nargs=2, action="append", metavar=("KEY", "VALUE"), help="any *Params field")
    ap.add_argument("--out", type=Path, default=Path("/tmp/manifoldneus_bench/bench_neural.json"))
    ap.add_argument("--save-images", type=Path, default=None)
    ap.add_argument("--mesh", type=Path, default=None, help="also extract a mesh (PLY + preview PNG) here")
    args = ap.parse_args()

    t_start = time.time()
    views = load_scene(args.data)
    if args.no_masks:
        views.masks = None
    if args.no_priors:
        views.mono_depth = views.mono_normal = None
    test_ids = [i for i in range(views.n) if i % 8 == 0]
    train_ids = [i for i in range(views.n) if i % 8]
    load_s = time.time() - t_start
    if args.throughput_only:
        res = {"throughput": throughput(views, args), "load_s": load_s, "peak_rss_gib": peak_rss_gib(),
               "threads": torch.get_num_threads(), "loadavg": os.getloadavg()}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=2))
        return

    fp, rp, lp, tp, run = build_params(args)
    if args.budget_cpu:
        tp.time_budget_s = args.budget_cpu
    tr = Trainer(views, fp, rp, lp, tp, run=run, train_views=train_ids)
    if args.budget_cpu:
        tr.clock = cpu_s  # budget and lr schedule in CPU seconds of this process
    evals = []
    pending = sorted(args.eval_at)
    t_train0 = time.time()
    cpu0 = cpu_s()
    eval_time = [0.0]
    eval_cpu = [0.0]
    stop = [False]

    def cb(trainer, info):
        el = time.time() - t_train0 - eval_time[0]
        cel = cpu_s() - cpu0 - eval_cpu[0]
        if args.budget_cpu and cel >= args.budget_cpu:
            stop[0] = True
        clock = cel if args.budget_cpu else el
        if pending and clock >= pending[0]:
            pending.pop(0)
            t0, c0 = time.time(), cpu_s()
            r = evaluate(trainer, test_ids)
            trainer.field.train()
            eval_time[0] += time.time() - t0
            eval_cpu[0] += cpu_s() - c0
            if trainer._t_start is not None:  # keep evaluations out of the lr schedule's clock
                trainer._t_start += (cpu_s() - c0) if args.budget_cpu else (time.time() - t0)
            r.update(step=trainer.step, train_s=el, train_cpu_s=cel, loadavg=os.getloadavg()[0])
            evals.append(r)
            print(f"  eval @ {el:.0f}s step {trainer.step}: masked PSNR {r.get('psnr_masked', float('nan')):.2f} "
                  f"PSNR {r['psnr']:.2f}", flush=True)
        if info["step"] % 200 == 0:
            print(f"  step {info['step']} loss {info['loss']:.4f} " + " ".join(
                f"{k[5:]}={v:.4f}" for k, v in info.items() if k.startswith("loss_")) +
                f" s={info['inv_s']:.0f} t={el:.0f}s cpu={cel:.0f}s load={os.getloadavg()[0]:.1f}", flush=True)
        return stop[0]

    # the budget counts training only; intermediate evaluations are excluded from it
    while True:
        remaining = (args.budget_cpu - (cpu_s() - cpu0 - eval_cpu[0])) if args.budget_cpu else \
            (args.budget - (time.time() - t_train0 - eval_time[0]))
        if remaining <= 0 or tr.step >= run.iters or stop[0]:
            break
        tr.train(time_budget_s=remaining, callback=cb)
        if args.budget_cpu and stop[0]:
            break
    train_s = time.time() - t_train0 - eval_time[0]
    train_cpu = cpu_s() - cpu0 - eval_cpu[0]
    final = evaluate(tr, test_ids, args.save_images)
    wall = time.time() - t_start - eval_time[0]
    res = {
        "field": args.field, "size": f"{tr.W}x{tr.H}", "steps": tr.step, "train_s": train_s,
        "s_per_iter": train_s / max(tr.step, 1), "rays_per_s": tr.step * tp.batch_rays / train_s,
        "train_cpu_s": train_cpu, "cpu_s_per_iter": train_cpu / max(tr.step, 1),
        "final": final, "intermediate": evals, "wall_s_excl_intermediate_evals": wall, "load_s": load_s,
        "peak_rss_gib": peak_rss_gib(), "loss_status": tr.loss_status, "rollbacks": tr.rollbacks,
        "background": tr.bg_kind, "threads": torch.get_num_threads(), "loadavg_end": os.getloadavg(),
        "params": {"field": asdict(fp), "render": asdict(rp), "loss": asdict(lp), "train": asdict(tp)},
        "aabb": tr.field.aabb.tolist() if hasattr(tr.field, "aabb") else None,
        "history": tr.history,
    }
    if args.mesh is not None:
        from manifoldneus.data.artifacts import MESH  # here: `profile_step --code` imports this module on older code
        from manifoldneus.output.meshing import extract_mesh, save_ply, save_preview

        t0 = time.time()
        args.mesh.mkdir(parents=True, exist_ok=True)
        mesh = extract_mesh(tr.sdf_fn(), resolution=192)
        save_ply(mesh, args.mesh / MESH)
        save_preview(mesh, args.mesh / "mesh.png")
        res["mesh"] = {"faces": int(len(mesh.faces)), "seconds": time.time() - t0}
        if tr.views.masks is not None:
            from manifoldneus.output.meshing import cull_by_masks, largest_components

            dil = max(1, round(12 * tr.W / 384))  # ~12 px at the data's 384 px
            tv = np.asarray(train_ids)
            culled = largest_components(cull_by_masks(mesh, tr.views.K[tv], tr.poses_numpy()[tv],
                                                      tr.views.masks[tv], dilation=dil, rule="all"))
            save_ply(culled, args.mesh / "mesh_culled.ply")
            save_preview(culled, args.mesh / "mesh_culled.png")
            res["mesh"]["faces_culled"] = int(len(culled.faces))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2))
    print()
    print("| field | size | steps | train s | train CPU s | s/iter | rays/s | held-out PSNR (masked) | PSNR | SSIM (masked) | peak GiB | wall s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    print(f"| {args.field} | {res['size']} | {tr.step} | {train_s:.0f} | {train_cpu:.0f} | {res['s_per_iter']:.3f} | {res['rays_per_s']:.0f} | "
          f"{final.get('psnr_masked', float('nan')):.2f} | {final['psnr']:.2f} | {final.get('ssim_masked', float('nan')):.3f} | "
          f"{res['peak_rss_gib']:.2f} | {wall:.0f} |")
    for e in evals:
        print(f"  @ {e['train_s']:.0f}s / {e['train_cpu_s']:.0f} CPU s (step {e['step']}): masked PSNR {e.get('psnr_masked', float('nan')):.2f}")
    print(f"JSON: {args.out}")


if __name__ == "__main__":
    main()
