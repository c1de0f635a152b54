#!/usr/bin/env python
"""Refinement benchmark: do the joint field-and-pose rounds refine the poses they start from?

    python -m bench.bench_refine [--scenes synthetic,scan24,scan24_idr,scan65_idr] [--seeds 0,1,2]
                                 [--set section.key=value ...] [--reference-seeds 0] [--gt-pose] [--artifacts DIR]
                                 [--label NAME] [--out-dir DIR]

Per scene and seed (``run.seed``): the whole pipeline, then from the artifacts the mean rotation /
centre error of the anchors' initialisation, of every view at its placement pose (what the rounds
refine, on the final views), after each round (with that round's start), and the final; how many
views kept the last round's pose update (the held-out tracks' per-view test, the others keep the
round's start); pycolmap's errors and `sfm-all`'s (our matches, COLMAP's mapper and bundle adjustment
on every training view at once: the preset of that name) in the same run; held-out masked PSNR and
Chamfer of the method's surface stage and of NeuS on `sfm-all`'s poses (that preset's surface stage,
the same keys: equal iterations; for the seeds in --reference-seeds, default all); with --gt-pose the
GT-pose NeuS (`reference_surface`, as many iterations; its seed is its own, `reference_surface.seed`,
so it is trained once; on DTU it is what Chamfer is measured against); wall time per stage. Prints
mean +- std over seeds, per scene, and writes ``<out-dir>/refine/<label>-<date>.json``;
``bench/results_md.py`` puts the newest into
README. Targets are checked here (``targets``), never in tests.
"""
from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path


import runner
from manifoldneus.data.artifacts import load_evaluation, load_reference_surface_meta
from bench import bench
from bench.bench import git_commit, spread
from manifoldneus.data import io

ROOT = Path(__file__).resolve().parent.parent

PRESETS = ("default", "sfm-all")  # what its runs resolve their parameters with (README's staleness check)
TIMED = ("ingest", "features", "matching", "covisibility", "spectral", "schedule", "reference", "anchors",
         "successors", "surface", "mesh", "reference_surface", "evaluate")


def one_run(scene: str, seed: int, overrides: list[str], artifacts: Path, with_neus: bool, with_gt_pose: bool) -> dict:
    """The pipeline for one seed, and what it measured."""
    over = [*overrides, f"run.seed={seed}"]
    iters = runner.resolve_params(runner.load_stages(), overrides=over)["surface"].iters
    t0 = time.time()
    over += [f"reference_surface.iters={iters}"] if with_gt_pose else ["reference_surface.enabled=false"]
    runner.run(scene, overrides=over, artifacts=artifacts)
    store = runner.Store(artifacts, runner.resolve_scene(scene).name)
    rows = bench.collect(scene, artifacts, None, TIMED)
    ev = load_evaluation(store.version_dir("evaluate", store.current("evaluate")))
    out = {"seed": seed, "overrides": over, "rounds_iters": bench.rounds_total_iters(store), "surface_iters": iters,
           "wall_seconds_run": time.time() - t0, "stage_seconds": {s: r["wall_seconds"] for s, r in rows.items()}}
    if not ev.get("poses"):
        return {**out, "error": "no ground truth: nothing to score"}

    def errs(summary):
        return {"rot_deg": summary["rot_err_deg"]["mean"], "centre": summary["center_err_units"]["mean"],
                "centre_pct": summary["center_err_pct"]["mean"],
                # relative rotation over view pairs: what no alignment changes (the Sim3 is fitted on centres)
                "pre_r_deg": summary["pre_r_deg"]["mean"]}

    out["units"] = rows["evaluate"]["metrics"].get("units")
    out["rounds"] = []
    for r in ev["poses"]:
        if "summary" not in r:
            continue
        row = {"label": r["label"], "n_views": r["n_views"], **errs(r["summary"])}
        if r.get("start_summary"):
            row["start"] = errs(r["start_summary"])
        if r.get("guard", {}).get("checked"):  # how many of the round's views kept their pose update
            g = r["guard"]
            row.update(kept=g["kept"], checked=g["n_views"], held_out_px=g["kept_median_px"],
                       held_out_start_px=g["start_median_px"])
        out["rounds"].append(row)
    out["initial"] = out["rounds"][0]
    out["final"] = out["rounds"][-1]
    out["placement"] = errs(ev["placement"]) if "placement" in ev else None
    ref = bench.reference_scores(store.version_dir("evaluate_poses", store.current("evaluate_poses")))
    out["pycolmap"] = {"rot_deg": ref.get("rot_err_deg_mean"), "centre": ref.get("center_err_units_mean"),
                       "n_valid": ref.get("n_valid"), "n_views": ref.get("n_views")}
    out.update(surface_scores(ev))
    if with_gt_pose:
        refj = load_reference_surface_meta(store.version_dir("reference_surface", store.current("reference_surface")))
        if refj.get("trained"):
            s = refj["novel_views"]["summary"]
            out["gt_pose_psnr_masked"] = s.get("psnr_masked", s.get("psnr"))
            out["gt_pose_psnr_masked_aligned"] = s.get("aligned_psnr_masked", s.get("aligned_psnr"))
            out["gt_pose_iters"] = refj["train"]["steps"]
    out["sfm_all"] = sfm_all(scene, over, with_neus, artifacts, errs)
    return out


def sfm_all(scene: str, overrides: list[str], with_neus: bool, artifacts: Path, errs) -> dict:
    """Pose errors of the `sfm-all` preset (its poses are its initialisation) and, ``with_neus``, the
    held-out PSNR and Chamfer of NeuS on them: its surface stage, trained as the method's (the same
    `surface` keys: equal iterations). ``overrides`` say whether the GT-pose reference surface is
    trained: the same version as the default preset's (the presets do not change what it reads), so on
    DTU both Chamfer distances are to one reference."""
    over = [*overrides, *([] if with_neus else ["surface.iters=0"])]
    runner.run(scene, overrides=over, artifacts=artifacts, preset="sfm-all")
    store = runner.Store(artifacts, runner.resolve_scene(scene).name, "sfm-all")
    ev = load_evaluation(store.version_dir("evaluate", store.current("evaluate")))
    out = errs(ev["poses"][-1]["summary"])
    return {**out, **surface_scores(ev)} if with_neus else out


def surface_scores(ev: dict) -> dict:
    """Held-out masked PSNR (at the given poses and after test-time alignment) and Chamfer of an evaluation."""
    nvs = ev.get("novel_views", {}).get("summary", {})
    return {"psnr_masked": nvs.get("psnr_masked", nvs.get("psnr")),
            "psnr_masked_aligned": nvs.get("aligned_psnr_masked", nvs.get("aligned_psnr")),
            "chamfer": ev.get("geometry", {}).get("chamfer_units")}


def summarise(runs: list[dict]) -> dict:
    ok = [r for r in runs if "final" in r]
    s = {
        "initial_rot_deg": spread(r["initial"]["rot_deg"] for r in ok),
        "placement_rot_deg": spread(r["placement"]["rot_deg"] for r in ok if r["placement"]),
        "final_rot_deg": spread(r["final"]["rot_deg"] for r in ok),
        "final_centre": spread(r["final"]["centre"] for r in ok),
        "placement_centre": spread(r["placement"]["centre"] for r in ok if r["placement"]),
        "pycolmap_rot_deg": spread(r["pycolmap"]["rot_deg"] for r in ok),
        "pycolmap_centre": spread(r["pycolmap"]["centre"] for r in ok),
        "sfm_all_rot_deg": spread(r["sfm_all"]["rot_deg"] for r in ok),
        "sfm_all_centre": spread(r["sfm_all"]["centre"] for r in ok),
        "final_pre_r_deg": spread(r["final"]["pre_r_deg"] for r in ok),
        "sfm_all_pre_r_deg": spread(r["sfm_all"]["pre_r_deg"] for r in ok),
        "sfm_all_psnr_masked": spread(r["sfm_all"].get("psnr_masked") for r in ok),
        "sfm_all_psnr_masked_aligned": spread(r["sfm_all"].get("psnr_masked_aligned") for r in ok),
        "sfm_all_chamfer": spread(r["sfm_all"].get("chamfer") for r in ok),
        "chamfer": spread(r.get("chamfer") for r in ok),
        "psnr_masked": spread(r["psnr_masked"] for r in ok),
        "psnr_masked_aligned": spread(r.get("psnr_masked_aligned") for r in ok),
        # the GT-pose NeuS has a seed of its own (`reference_surface.seed`): the seeds share one training,
        # counted once
        "gt_pose_psnr_masked_aligned": spread({r.get("gt_pose_psnr_masked_aligned") for r in ok}),
        "gt_pose_psnr_masked": spread({r.get("gt_pose_psnr_masked") for r in ok}),
        "final_kept": int(sum(r["final"].get("kept", 0) for r in ok)),
        "final_checked": int(sum(r["final"].get("checked", 0) for r in ok)),
        "wall_seconds": spread(sum(r["stage_seconds"].get(k, 0) for k in TIMED if k not in ("reference_surface", "evaluate"))
                               for r in ok),
    }
    labels = [row["label"] for row in ok[0]["rounds"]] if ok else []
    s["per_round"] = {lab: {"rot_deg": spread(next(x["rot_deg"] for x in r["rounds"] if x["label"] == lab) for r in ok),
                            "start_rot_deg": spread(next((x.get("start") or {}).get("rot_deg") for x in r["rounds"]
                                                         if x["label"] == lab) for r in ok)}
                      for lab in labels}
    return s


SFM_ALL_TARGETS = [  # every scene: the rounds never make structure-from-motion on the same matches worse
    ("final rotation <= sfm-all's", lambda r: (r["final"]["rot_deg"], r["sfm_all"]["rot_deg"])),
    ("final centre <= sfm-all's", lambda r: (r["final"]["centre"], r["sfm_all"]["centre"])),
    # the same comparison without the alignment, so a better-fitting Sim3 is not read as better rotations
    ("final relative rotation (PRE_r) <= sfm-all's", lambda r: (r["final"]["pre_r_deg"], r["sfm_all"]["pre_r_deg"])),
    # the last round starts from sfm-all's poses: its held-out tracks under them and under the final poses
    ("final held-out reprojection error <= sfm-all's (median px)",
     lambda r: (r["final"].get("held_out_px"), r["final"].get("held_out_start_px"))),
]
TARGETS = {  # scene -> list of (name, check(run) -> (value, limit, met))
    "synthetic": [("final <= 0.5 x initialisation", lambda r: (r["final"]["rot_deg"], 0.5 * r["initial"]["rot_deg"])),
                  # the ground truth is exact here: the rounds should add to SfM, not only hold it
                  ("final <= 0.85 x sfm-all", lambda r: (r["final"]["rot_deg"], 0.85 * r["sfm_all"]["rot_deg"]))],
    "scan24": [("final <= initialisation", lambda r: (r["final"]["rot_deg"], r["initial"]["rot_deg"])),
               ("final <= 0.8 x pycolmap", lambda r: (r["final"]["rot_deg"], 0.8 * r["pycolmap"]["rot_deg"]))],
    "scan24_idr": [("final <= initialisation", lambda r: (r["final"]["rot_deg"], r["initial"]["rot_deg"])),
                   ("final <= pycolmap", lambda r: (r["final"]["rot_deg"], r["pycolmap"]["rot_deg"]))],
}


def targets(scene: str, runs: list[dict]) -> list[dict]:
    out = []
    ok = [r for r in runs if "final" in r]

    def per_seed(name: str, rows: list[tuple[dict, float, float]], higher_is_better: bool = False,
                 tie: float = bench.TIE) -> dict:
        return bench.target_row(name, [(r["seed"], v, lim) for r, v, lim in rows], higher_is_better, tie)

    for name, check in [*TARGETS.get(scene, []), *SFM_ALL_TARGETS]:
        rows = [(r, *check(r)) for r in ok]
        if any(v is None or lim is None for _, v, lim in rows):
            continue  # a figure this run does not have (e.g. no held-out tracks)
        out.append(per_seed(name, rows))
    rot = spread(r["final"]["rot_deg"] for r in ok)
    out.append({"target": "spread over seeds <= 0.02 deg", "value": rot["std"],
                "met_every_seed": rot["std"] is not None and rot["std"] <= 0.02})
    # the surface: no worse than NeuS on sfm-all's poses at equal iterations (the seeds that train it)
    trained = [r for r in ok if r["sfm_all"].get("chamfer") is not None and r.get("chamfer") is not None]
    if trained:
        out.append(per_seed("Chamfer <= NeuS on sfm-all's poses at equal iterations",
                            [(r, r["chamfer"], r["sfm_all"]["chamfer"]) for r in trained], tie=bench.CHAMFER_TIE))
        out.append(per_seed("aligned held-out PSNR >= NeuS on sfm-all's poses at equal iterations",
                            [(r, r["psnr_masked_aligned"], r["sfm_all"]["psnr_masked_aligned"]) for r in trained
                             if r["sfm_all"].get("psnr_masked_aligned") is not None], higher_is_better=True))
    psnr = [(r["psnr_masked"], r["gt_pose_psnr_masked"]) for r in ok if r.get("gt_pose_psnr_masked") is not None]
    if psnr:
        out.append({"target": "held-out masked PSNR within 0.5 dB of the GT-pose NeuS at equal iterations",
                    "per_seed": [{"value": a, "limit": b - 0.5, "met": a >= b - 0.5} for a, b in psnr],
                    "met_every_seed": all(a >= b - 0.5 for a, b in psnr)})
    return out


def pm(s: dict, spec: str = ".3f") -> str:
    if s.get("mean") is None:
        return "-"
    return f"{s['mean']:{spec}} ± {s['std']:{spec}}" if s["n"] > 1 else f"{s['mean']:{spec}}"


def markdown(result: dict) -> str:
    """The table of every scene, then each scene's rounds and its targets per seed."""
    header = ["scene", "seeds", "init (anchors) deg", "placement deg", "final deg", "sfm-all deg", "pycolmap deg",
              "final centre", "sfm-all centre", "pycolmap centre", "last round: views keeping their update", "masked PSNR dB", "aligned", "GT-pose PSNR dB (equal iters)", "aligned",
              "sfm-all + NeuS PSNR dB (equal iters)", "aligned", "Chamfer", "sfm-all + NeuS Chamfer",
              "pipeline wall s (no GT-pose NeuS)"]
    rows = []
    for scene, sc in result["scenes"].items():
        s = sc["summary"]
        rows.append([scene, ",".join(str(r["seed"]) for r in sc["runs"]), pm(s["initial_rot_deg"]),
                     pm(s["placement_rot_deg"]), pm(s["final_rot_deg"]), pm(s["sfm_all_rot_deg"]),
                     pm(s["pycolmap_rot_deg"]), pm(s["final_centre"], ".4f"), pm(s["sfm_all_centre"], ".4f"),
                     pm(s["pycolmap_centre"], ".4f"),
                     f"{s['final_kept']}/{s['final_checked']}" if "final_kept" in s else "-", pm(s["psnr_masked"], ".2f"),
                     pm(s["psnr_masked_aligned"], ".2f"), pm(s["gt_pose_psnr_masked"], ".2f"),
                     pm(s["gt_pose_psnr_masked_aligned"], ".2f"), pm(s["sfm_all_psnr_masked"], ".2f"),
                     pm(s["sfm_all_psnr_masked_aligned"], ".2f"), pm(s["chamfer"], ".3g"), pm(s["sfm_all_chamfer"], ".3g"),
                     pm(s["wall_seconds"], ".0f")])
    parts = [bench.markdown_table(header, rows)]
    for scene, sc in result["scenes"].items():
        per = sc["summary"]["per_round"]
        parts.append(f"{scene}, per round (mean rotation error of the round's views, deg: start -> end): " + "; ".join(
            f"{lab} {pm(v['start_rot_deg'])} -> {pm(v['rot_deg'])}" if v["start_rot_deg"]["n"] else f"{lab} {pm(v['rot_deg'])}"
            for lab, v in per.items()))
        parts.append(f"{scene} targets: " + "; ".join(f"{t['target']}: {bench.target_text(t)}" for t in sc["targets"]))
    return "\n\n".join(parts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="synthetic,scan24,scan24_idr,scan65_idr")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--reference-seeds", default=None, help="seeds that also train NeuS on sfm-all's poses (its surface "
                    "stage, as long as the method's; default: every seed)")
    ap.add_argument("--gt-pose", action="store_true", help="also train the GT-pose NeuS for as many iterations (once: "
                    "its seed is reference_surface.seed)")
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    ap.add_argument("--artifacts", type=Path, default=runner.DEFAULT_ARTIFACTS)
    ap.add_argument("--label", default="refine")
    ap.add_argument("--out-dir", type=Path, default=bench.DEFAULT_OUT_DIR)
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    ref_seeds = {int(s) for s in args.reference_seeds.split(",")} if args.reference_seeds else set(seeds)
    result = {"label": args.label, "date": dt.datetime.now().isoformat(timespec="seconds"),
              "commit": git_commit(), "machine": bench.machine(), "overrides": args.overrides,
              "resolved_params": bench.resolved_params(args.overrides, presets=PRESETS),
              "scenes": {}}
    path = args.out_dir / "refine" / f"{args.label}-{dt.date.today().isoformat()}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    for scene in args.scenes.split(","):
        runs = []
        for seed in seeds:
            print(f"== {scene}, seed {seed}", flush=True)
            runs.append(one_run(scene, seed, args.overrides, args.artifacts, seed in ref_seeds, args.gt_pose))
            result["scenes"][scene] = {"runs": runs, "summary": summarise(runs), "targets": targets(scene, runs)}
            result["grid_kernel"] = bench.grid_kernel_used()
            io.save_json(path, result)  # after every run: a stopped bench keeps what it measured
    print(markdown(result))
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
