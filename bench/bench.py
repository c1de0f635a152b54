#!/usr/bin/env python
"""Benchmark: ManifoldNeuS, its NeuS baselines and the pycolmap reference on one scene, in one bench run.

    python -m bench.bench --scene scan24 [--scene S ...] [--seeds 0,1,2]
                          [--systems manifoldneus,neus-barf,neus-colmap,sfm-all,photos-alone,pycolmap]
                          [--set section.key=value ...] [--until STAGE] [--force STAGE | --force-all]
                          [--artifacts DIR] [--out-dir DIR] [--executor dask|dask://HOST:PORT|slurm] [--workers N]

A system is a pipeline preset (ManifoldNeuS: the default parameters) plus the stages it is charged
with; `photos-alone` is ManifoldNeuS on the images alone (the layout's intrinsics and masks dropped,
as on a user's own photos). With several `--seeds` (``run.seed``) every system runs once per seed and
each figure is the mean with its spread (std, ddof 1) beside it; the JSON keeps every seed's results
(``per_seed``). The GT-pose reference surface, the yardstick of Chamfer, has a seed of its own
(`reference_surface.seed`): one reference for all seeds. Each scene and preset is one run: by default in this process, one after the other; with
``--executor`` side by side on Dask workers (runner/executor.py). Versions are shared by
fingerprint, so a stage common to several systems (ingest, the front-end, the reference) is
computed once, before the runs fan out, and the wall time in its manifest is counted for each
system that uses it.
Errors come from each preset's `evaluate` artifact (pycolmap: `evaluate_poses`).

Prints a per-system table (ratios against pycolmap in columns of their own, since absolute times
on a shared machine drift), a stage x system wall-time table and the per-stage table; writes
``<out-dir>/<scene>/<YYYY-MM-DD>.json`` (``bench/results_md.py`` turns the latest into README's
Results; a subset of the systems gets a suffix and replaces those systems' rows there, an `--until` run a
suffix and is not shown). `--force-all`
recomputes every version once, so that all times are of this run. Speed targets are checked
here, never in tests.

Other scripts and tests use it as ``from bench import bench``; its helpers (``collect``,
``systems_table``, ``markdown_table``, ``fmt``, ...) are meant to be shared.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import math
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import runner
from manifoldneus.data.artifacts import ANCHOR_ROUND, REFERENCE_POSE_METRICS, ROUND_META, load_evaluation, successor_rounds
from manifoldneus.data import io
from runner import executor

ROOT = Path(__file__).resolve().parent.parent

FRONT_END = ("features", "matching", "covisibility", "spectral", "schedule")
NEURAL = ("anchors", "successors", "surface", "mesh")
BASELINE = "pycolmap"
DEFAULT_OUT_DIR = ROOT / "bench"


@dataclass(frozen=True)
class System:
    key: str                # name for --systems and key in the JSON
    label: str              # name in the tables
    preset: str | None      # pipeline preset whose `current@<preset>` pointers hold its versions
    scored_by: str          # the stage whose artifact holds its errors


SYSTEMS = {s.key: s for s in (
    System("manifoldneus", "ManifoldNeuS", None, "evaluate"),
    System("neus-barf", "NeuS-BARF", "neus-barf", "evaluate"),
    System("neus-colmap", "NeuS-COLMAP", "neus-colmap", "evaluate"),
    System("sfm-all", "SfM-all + NeuS", "sfm-all", "evaluate"),
    System("photos-alone", "ManifoldNeuS, photos alone", "photos-alone", "evaluate"),
    System(BASELINE, "pycolmap", None, "evaluate_poses"),
)}

# (column, key in a system's JSON): errors and time as multiples of pycolmap's.
RATIOS = (("rotation", "rot_err_deg_mean"), ("centre", "center_err_units_mean"), ("time", "wall_seconds"))


# ---------------------------------------------------------------------------- running


@dataclass
class Run:
    """One pipeline run of a preset in this bench."""

    preset: str | None
    params: dict             # section -> resolved parameters of the run
    report: dict[str, str]   # stage -> "computed" | "reused" (by this run)
    rows: dict[str, dict]    # stage -> manifest summary (see `collect`) + computed_in_this_bench
    error: str | None = None  # the run failed: its rows are empty


def targets_per_preset(systems: list[System], until: str | None) -> dict[str | None, list[str]]:
    """Preset -> the stages its runs bring up to date (with what they depend on): what its systems
    are scored by, each cut at `--until`."""
    order = list(runner.load_stages())
    if until is not None and until not in order:
        raise runner.PipelineError(f"unknown stage {until!r} for --until (stages: {', '.join(order)})")
    out: dict[str | None, list[str]] = {}
    for s in systems:
        target = s.scored_by if until is None else min(s.scored_by, until, key=order.index)
        out.setdefault(s.preset, [])
        if target not in out[s.preset]:
            out[s.preset].append(target)
    return out


def collect(scene: str, artifacts: Path, preset: str | None = None, stages=None,
            versions: dict[str, str] | None = None) -> dict[str, dict]:
    """Stage -> fingerprint, wall / CPU seconds, peak RSS and metrics of the versions a run used
    (`versions`: stage -> fingerprint), else of the preset's current versions (all stages that
    have one, or just `stages`)."""
    store = runner.Store(artifacts, runner.resolve_scene(scene).name, preset)
    rows = {}
    for name in stages if stages is not None else runner.load_stages():
        m = store.manifest(name, (versions or {}).get(name))
        if m is not None:
            rows[name] = {k: m[k] for k in ("fingerprint", "wall_seconds", "cpu_seconds", "peak_rss_mib", "metrics")}
    return rows


def rounds_total_iters(store: runner.Store, versions: dict[str, str] | None = None) -> int:
    """Iterations of the anchors' round and every successor round: of the store's current versions, or
    of ``versions`` (stage -> fingerprint)."""
    def version(stage):
        return store.version_dir(stage, (versions or {}).get(stage) or store.current(stage))

    steps = io.load_json(version("anchors") / ANCHOR_ROUND / ROUND_META)["train"]["steps"]
    for d in successor_rounds(version("successors")):
        steps += io.load_json(d / ROUND_META)["train"]["steps"]
    return int(steps)


def surface_iters(store: runner.Store, version: str | None = None) -> int | None:
    """Iterations of the field the mesh and the renderings come from (the surface stage's; the last
    round's field where it trained none: then every round's together)."""
    info = io.load_json(store.version_dir("surface", version or store.current("surface")) / ROUND_META)
    return int(info["train"]["steps"]) if info.get("iters") else None


def run_systems(scenes: list[str], systems: list[System], overrides: list[str], until: str | None, force: list[str],
                artifacts: Path, executor_name: str = "in-process", workers: int | None = None) -> dict[str, list[Run]]:
    """Bring every selected system of every scene up to date: one run per scene and preset, on
    `executor_name`. Versions that runs share (the front-end, the reference) are computed once,
    forced stages included, before the runs fan out. Every system's surface stage trains as many
    iterations (`surface.iters`): NeuS on fixed poses and the method compare at equal iterations.
    Returns scene -> its runs."""
    stages = runner.load_stages()
    targets = targets_per_preset(systems, until)
    specs = [executor.RunSpec(f"{scene} {preset or 'default'}", scene,
                              dict(until=targets[preset], overrides=list(overrides), preset=preset,
                                   artifacts=artifacts, force=force))
             for scene in scenes for preset in targets]
    done = list(executor.run_all(specs, executor_name, workers))  # the runs and each scene's shared preparation
    outcomes = {o.name: o for o in done}
    computed = set().union(*(o.computed for o in done))  # (stage, fingerprint) computed by this bench
    runs: dict[str, list[Run]] = {}
    for spec in specs:
        preset, outcome = spec.args["preset"], outcomes[spec.name]
        params = runner.resolve_params(stages, overrides=spec.args["overrides"], preset=preset)
        rows = {} if outcome.error else collect(spec.scene, artifacts, preset, outcome.report, outcome.report.fingerprints)
        for stage, row in rows.items():  # a later preset reuses what an earlier one computed: still of this bench
            row["computed_in_this_bench"] = (stage, row["fingerprint"]) in computed
        runs.setdefault(spec.scene, []).append(Run(preset, params, dict(outcome.report or {}), rows, outcome.error))
    return runs


# ---------------------------------------------------------------------------- per-system results


def charged_stages(system: System, params: dict) -> tuple[str, ...]:
    """The stages whose time a system pays. Evaluation stages never count. The neural systems pay
    for `reference` only when they start from its poses (`anchors.pose_init=reference`, the only case
    in which `anchors` reads it)."""
    if system.key == BASELINE:
        return ("ingest", "reference")
    uses_reference = params["anchors"].pose_init == "reference"
    return ("ingest", *FRONT_END, *(("reference",) if uses_reference else ()), *NEURAL)


def pose_errors(summary: dict) -> dict:
    """Flat pose-error scalars from a `pose_metrics` summary."""
    wanted = (("rot_err_deg", ("mean", "median")), ("center_err_units", ("mean", "median")),
              ("center_err_pct", ("mean",)), ("pre_r_deg", ("mean",)), ("pre_t_deg", ("mean",)))
    return {f"{key}_{stat}": summary[key][stat] for key, stats in wanted for stat in stats}


def neural_scores(evaluate_dir: Path, units: str | None) -> dict:
    """Final-round pose errors, Chamfer and held-out novel views from `evaluation.json`."""
    ev = load_evaluation(evaluate_dir)
    final = (ev.get("poses") or [{}])[-1]
    if "summary" not in final:  # no rounds, or a final round of < 3 views (not scored)
        return {}
    out = {"units": units, "n_valid": final["n_views"], "n_views": len(final["per_view"]),
           "pose_round": final["label"], **pose_errors(final["summary"])}
    if "geometry" in ev:
        geometry = ev["geometry"]
        out.update(chamfer_units=geometry["chamfer_units"], chamfer_reference=geometry["reference"])
        for key in ("colour_spread", "reference_colour_spread"):  # evaluations since 2026-11-28
            if geometry.get(key):
                out[key] = geometry[key]["median"]
    views = ev.get("novel_views", {}).get("summary", {})
    if views:
        masked = "psnr_masked" in views
        aligned = views.get("aligned_psnr_masked" if masked else "aligned_psnr")
        out.update(psnr=views["psnr_masked" if masked else "psnr"], ssim=views["ssim_masked" if masked else "ssim"],
                   psnr_aligned=aligned,
                   images_masked=masked, lpips=views.get("lpips"), lpips_status=views.get("lpips_status"))
    return out


def reference_scores(evaluate_poses_dir: Path) -> dict:
    """pycolmap's pose errors from `evaluate_poses` (a sparse model: no surface, no renderings)."""
    res = io.load_json(evaluate_poses_dir / REFERENCE_POSE_METRICS)
    if not res.get("evaluated"):
        return {}
    return {"units": res["units"], "n_valid": res["n_valid"], "n_views": res["n_views"], **pose_errors(res["summary"])}


def system_result(system: System, run: Run, store: runner.Store) -> dict:
    rows = run.rows
    charged = charged_stages(system, run.params)
    stages = {s: {k: rows[s][k] for k in ("fingerprint", "wall_seconds", "cpu_seconds", "peak_rss_mib",
                                          "computed_in_this_bench")} for s in charged if s in rows}
    scores = {}
    if system.scored_by in rows:
        version = store.version_dir(system.scored_by, rows[system.scored_by]["fingerprint"])
        scores = (reference_scores(version) if system.key == BASELINE
                  else neural_scores(version, rows[system.scored_by]["metrics"].get("units")))
    return {
        "label": system.label,
        "preset": system.preset,
        **({"error": run.error} if run.error else {}),
        "scored_by": system.scored_by,
        "stages": stages,
        "missing_stages": [s for s in dict.fromkeys((*charged, system.scored_by)) if s not in rows],
        "wall_seconds": round(sum(r["wall_seconds"] for r in stages.values()), 2),
        "peak_rss_mib": max((r["peak_rss_mib"] for r in stages.values()), default=None),
        **({"field_iters": surface_iters(store, rows["surface"]["fingerprint"])}
           if system.key != BASELINE and "surface" in rows else {}),
        **scores,
    }


def ratio(value, baseline) -> float | None:
    if not (is_number(value) and is_number(baseline)) or baseline == 0:
        return None
    return value / baseline


def add_ratios(systems: dict[str, dict]) -> None:
    """`over_pycolmap`: each system's errors and time as multiples of pycolmap's (when both ran whole)."""
    base = systems.get(BASELINE, {})
    for result in systems.values():
        whole = base and not base["missing_stages"] and not result["missing_stages"]
        result["over_pycolmap"] = {col: ratio(result.get(key), base.get(key)) if whole else None
                                   for col, key in RATIOS}


def stage_rows(runs: list[Run]) -> dict[str, dict]:
    """Every version used in this bench, once: `stage` for the first run's, `stage @preset` for a
    version of a later preset that differs (e.g. its schedule)."""
    rows, seen = {}, set()
    for run in runs:
        for stage, row in run.rows.items():
            if (stage, row["fingerprint"]) in seen:
                continue
            seen.add((stage, row["fingerprint"]))
            label = stage if run is runs[0] else f"{stage} @{run.preset or 'default'}"
            rows[label] = row
    return rows


def summarise(rows: dict) -> dict:
    """Our front-end (features -> schedule) against pycolmap's extraction + matching."""
    out = {}
    front = [rows[s]["wall_seconds"] for s in FRONT_END if s in rows]
    if len(front) == len(FRONT_END):
        out["front_end_seconds"] = round(sum(front), 2)
        ref = rows.get("reference", {}).get("metrics", {})
        if "extract_match_seconds" in ref:
            out["pycolmap_extract_match_seconds"] = ref["extract_match_seconds"]
            out["front_end_over_pycolmap"] = round(out["front_end_seconds"] / ref["extract_match_seconds"], 3)
    return out


def grid_kernel_used() -> str:
    """The neural grids' kernel in this process: "fused", or "torch: <why the fused one did not
    load>" (a warning in the run's log only, and about twice the CPU time)."""
    from manifoldneus.neural import grid_encoding

    return "fused" if grid_encoding.fused_kernel() is not None else f"torch: {grid_encoding.fused_unavailable_reason()}"


def machine() -> dict:
    import psutil

    cpuinfo = Path("/proc/cpuinfo")
    models = [ln.split(":", 1)[1].strip() for ln in cpuinfo.read_text().splitlines()
              if ln.startswith("model name")] if cpuinfo.exists() else []
    return {"platform": platform.platform(), "cpus": os.cpu_count(),
            "cpu_model": models[0] if models else platform.processor(),
            "memory_gib": round(psutil.virtual_memory().total / 2**30, 1),
            # how busy the machine was: times on a shared machine drift
            "load_average_at_start": [round(x, 2) for x in os.getloadavg()]}


def scene_results(scene: str, scene_runs: list[Run], systems: list[System], artifacts: Path) -> dict[str, dict]:
    """System key -> its JSON-ready result in one seed's runs of a scene."""
    by_preset = {run.preset: run for run in scene_runs}
    store = runner.Store(artifacts, runner.resolve_scene(scene).name)
    out = {s.key: system_result(s, by_preset[s.preset], store) for s in systems}
    add_ratios(out)
    return out


def git_commit() -> str | None:
    """The checkout's commit (short), or None outside git."""
    import subprocess

    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def write_report(path: Path, result: dict, table: str) -> None:
    """A bench's JSON to ``path`` (its folder made), then its table and where the JSON went, printed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    io.save_json(path, result)
    print(table)
    print(f"\nwrote {path}")


def resolved_params(overrides=(), params_path: Path | None = None, presets=None) -> dict:
    """{preset (``default`` for none): {"section.key": value}}: what every system of the bench (or the
    ``presets`` named, ``default`` for none) resolves its parameters to (the fast profile, params.yaml, the
    bench's overrides). README compares it with what the checkout resolves to now
    (``bench/results_md.py``), so figures measured with other defaults are not shown as today's."""
    from runner.params import read_params_file, resolve_params

    stages = runner.load_stages()
    params_path = params_path or runner.DEFAULT_PARAMS
    out = {}
    defined = {None, *(read_params_file(params_path).get("presets") or {})}
    wanted = dict.fromkeys(s.preset for s in SYSTEMS.values()) if presets is None else \
        [None if p == "default" else p for p in presets]
    for preset in (p for p in wanted if p in defined):  # an older file may lack one
        resolved = resolve_params(stages, params_path, list(overrides), preset=preset)
        out[preset or "default"] = {f"{section}.{k}": v for section, values in resolved.items()
                                    if dataclasses.is_dataclass(values) for k, v in dataclasses.asdict(values).items()}
    return out


def spread(values) -> dict:
    """mean, std (ddof 1; 0 for one value), n, min, max of the numbers among `values`."""
    v = [float(x) for x in values if is_number(x)]
    if not v:
        return {"mean": None, "std": None, "n": 0}
    mean = sum(v) / len(v)
    std = math.sqrt(sum((x - mean) ** 2 for x in v) / (len(v) - 1)) if len(v) > 1 else 0.0
    return {"mean": mean, "std": std, "n": len(v), "min": min(v), "max": max(v)}


def over_seeds(per_seed: dict[str, dict]) -> dict:
    """One system's results of several seeds (seed -> result) as one: every number the mean over the
    seeds, with its `spread` beside it (key -> mean, std, n, min, max); the rest (labels, stages,
    units) from the first seed; ratios to pycolmap from the means (`add_ratios`)."""
    first = next(iter(per_seed.values()))
    numeric = [k for k, v in first.items() if is_number(v)]
    spreads = {k: spread(r.get(k) for r in per_seed.values()) for k in numeric}
    errors = [f"seed {seed}: {r['error']}" for seed, r in per_seed.items() if "error" in r]
    missing = sorted({st for r in per_seed.values() for st in r["missing_stages"]})
    out = {k: v for k, v in first.items() if k not in ("over_pycolmap", "error")}
    out.update({k: s["mean"] for k, s in spreads.items()}, spread=spreads, missing_stages=missing)
    return {**out, **({"error": "; ".join(errors)} if errors else {})}


# ---------------------------------------------------------------------------- targets

TIE = 1e-4  # relative: the same poses in another frame (a similarity there and back) are equal to about 1e-15
# the same mesh written (float32 vertices) in another frame: 100 k points sampled on it move its Chamfer by ~1e-4
CHAMFER_TIE = 1e-3
PHOTOS_ALONE_MAX_RATIO = 1.3  # photos alone's Chamfer, at most this multiple of the calibrated masked run's

# (name, check(one seed's systems) -> (value, limit), higher_is_better, tie)
SURFACE_TARGETS = [  # every scene: the surface no worse than NeuS on sfm-all's poses at equal iterations
    ("Chamfer <= NeuS on sfm-all's poses at equal iterations",
     lambda s: (s["manifoldneus"].get("chamfer_units"), s["sfm-all"].get("chamfer_units")), False, CHAMFER_TIE),
    ("aligned held-out PSNR >= NeuS on sfm-all's poses at equal iterations",
     lambda s: (s["manifoldneus"].get("psnr_aligned"), s["sfm-all"].get("psnr_aligned")), True, TIE),
]
PHOTOS_ALONE_TARGET = (
    f"photos alone's Chamfer <= {PHOTOS_ALONE_MAX_RATIO} x the calibrated masked run's",
    lambda s: (s["photos-alone"].get("chamfer_units"),
               PHOTOS_ALONE_MAX_RATIO * s["manifoldneus"]["chamfer_units"]
               if is_number(s["manifoldneus"].get("chamfer_units")) else None), False, TIE)
SCENE_TARGETS = {  # scene -> targets of its own (the DTU objects: photos alone against the masked run)
    "scan24": [PHOTOS_ALONE_TARGET,
               ("mesh stage <= 20 s", lambda s: (s["manifoldneus"]["stages"].get("mesh", {}).get("wall_seconds"), 20.0),
                False, TIE)],
    "scan24_idr": [PHOTOS_ALONE_TARGET],
    "scan65_idr": [PHOTOS_ALONE_TARGET],
}


def at_most(value: float, limit: float, tie: float = TIE) -> bool:
    """``value <= limit``, equal within ``tie`` (relative) counting as equal."""
    return value <= limit * (1 + tie)


def target_row(name: str, rows: list[tuple], higher_is_better: bool = False, tie: float = TIE) -> dict:
    """One target over seeds: ``rows`` of (seed, value, limit); met where value <= limit (>= with
    `higher_is_better`), ties within ``tie`` counting as met."""
    met = [at_most(lim, v, tie) if higher_is_better else at_most(v, lim, tie) for _, v, lim in rows]
    return {"target": name, "per_seed": [{"seed": seed, "value": v, "limit": lim, "met": m}
                                         for (seed, v, lim), m in zip(rows, met)],
            "met_every_seed": bool(rows) and all(met)}


def targets(result: dict) -> list[dict]:
    """The surface's targets of one scene's bench, each per seed (from `per_seed`, or the one run's
    `systems`); a target whose systems or figures the bench lacks is left out."""
    by_seed = result.get("per_seed") or {str((result.get("seeds") or [None])[0]): result["systems"]}
    out = []
    for name, check, higher_is_better, tie in [*SURFACE_TARGETS, *SCENE_TARGETS.get(result["scene"], [])]:
        try:
            rows = [(int(seed) if seed.isdigit() else seed, *check(systems)) for seed, systems in by_seed.items()]
        except KeyError:  # a system this bench did not run
            continue
        if rows and all(is_number(v) and is_number(lim) for _, v, lim in rows):
            out.append(target_row(name, rows, higher_is_better, tie))
    return out


def target_text(t: dict) -> str:
    """'met' or 'MISSED', with each seed's value against its limit."""
    verdict = "met" if t["met_every_seed"] else "MISSED"
    if "per_seed" in t:
        return verdict + " (" + ", ".join(("" if x.get("seed") is None else f"seed {x['seed']} ")
                                          + f"{x['value']:.4g} vs {x['limit']:.4g}" for x in t["per_seed"]) + ")"
    return verdict + (f" ({t['value']:.4g})" if t.get("value") is not None else "")


def targets_markdown(result: dict) -> str:
    """One line: the scene's targets, each met or MISSED with every seed's value against its limit."""
    found = targets(result)
    return f"{result['scene']} targets: " + "; ".join(f"{t['target']}: {target_text(t)}" for t in found) if found else ""


def run_benches(scenes: list[str], systems: list[System], overrides=(), until=None, force=(),
                artifacts=runner.DEFAULT_ARTIFACTS, executor_name: str = "in-process", workers: int | None = None,
                seeds: list[int] | None = None) -> dict[str, dict]:
    """Run the systems on every scene, once per seed (``run.seed``; None: the parameters' own); scene
    -> its JSON-ready result. With several scenes or seeds the run's total wall time and machine
    load are the whole run's. `force` applies to the first seed's runs only (the later ones
    reuse what it recomputed, e.g. the front-end)."""
    started, host = time.time(), machine()
    per_seed: dict[str, dict[str, dict]] = {}   # scene -> seed -> system -> result
    first_runs: dict[str, list[Run]] = {}
    for i, seed in enumerate(seeds or [None]):
        over = [*overrides, *([] if seed is None else [f"run.seed={seed}"])]
        runs = run_systems(scenes, systems, over, until, list(force) if i == 0 else [], artifacts, executor_name,
                           workers)
        for scene, scene_runs in runs.items():
            first_runs.setdefault(scene, scene_runs)
            per_seed.setdefault(scene, {})[str(seed)] = scene_results(scene, scene_runs, systems, artifacts)
    results = {}
    for scene, by_seed in per_seed.items():
        if seeds and len(seeds) > 1:
            systems_results = {s.key: over_seeds({seed: r[s.key] for seed, r in by_seed.items()}) for s in systems}
            add_ratios(systems_results)
        else:
            systems_results = next(iter(by_seed.values()))
        results[scene] = {
            "scene": runner.resolve_scene(scene).name,
            "date": dt.datetime.fromtimestamp(started).isoformat(timespec="seconds"),
            "machine": host,
            "commit": git_commit(),
            "grid_kernel": grid_kernel_used(),
            "executor": {"name": executor_name, "workers": workers, "scenes": list(scenes)},
            "overrides": list(overrides),
            "resolved_params": resolved_params(overrides),
            "until": until,
            "seeds": list(seeds or []),
            "total_wall_seconds": round(time.time() - started, 1),
            "systems": systems_results,
            **({"per_seed": by_seed} if seeds and len(seeds) > 1 else {}),
            "stages": stage_rows(first_runs[scene]),
            "summary": summarise({run.preset: run for run in first_runs[scene]}.get(None, first_runs[scene][0]).rows),
        }
        results[scene]["targets"] = targets(results[scene])
    return results


def result_path(result: dict, out_dir: Path) -> Path:
    """``<scene>/<date>.json`` for a full bench (what README's Results show); a subset of the systems
    or a run cut by --until gets a suffix, so it never overwrites the day's full bench."""
    name = result["date"][:10]
    if list(result["systems"]) != list(SYSTEMS):
        name += "-" + "+".join(result["systems"])
    if result["until"]:
        name += f"-until-{result['until']}"
    return Path(out_dir) / result["scene"] / f"{name}.json"


def write_result(result: dict, out_dir: Path) -> Path:
    path = result_path(result, out_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    io.save_json(path, result)
    return path


# ---------------------------------------------------------------------------- markdown


def is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def fmt(v, spec: str = ".3g") -> str:
    """A table cell: numbers formatted, anything missing as an em dash."""
    return format(v, spec) if is_number(v) else "—"


def cell(system: dict, key: str, spec: str = ".3g") -> str:
    """A system's figure, with ± its spread over seeds (std) where it has one."""
    s = system.get("spread", {}).get(key)
    mean = fmt(system.get(key), spec)
    if not (s and s["n"] > 1 and is_number(system.get(key))):
        return mean
    decimals = len(mean.partition(".")[2]) if "e" not in mean else 3  # the std to the mean's last digit
    return f"{mean} ± {s['std']:.{decimals}f}"


def markdown_table(header: list[str], rows: list[list[str]], align: str | None = None) -> str:
    """`align`: one letter per column, l or r (default: the first left, numbers right)."""
    align = align or "l" + "r" * (len(header) - 1)
    rule = ["---" if a == "l" else "---:" for a in align]
    return "\n".join("| " + " | ".join(r) + " |" for r in [header, rule, *rows])


def systems_table(result: dict, scene_column: bool = False) -> str:
    """One row per system: pose errors, Chamfer, novel views, time, memory, ratios to pycolmap (with
    `scene_column`, the scene first: README puts the scenes' tables one under the other)."""
    systems = result["systems"]
    units = next((s["units"] for s in systems.values() if s.get("units")), "units")
    with_lpips = any(is_number(s.get("lpips")) for s in systems.values())
    header = [*(["scene"] if scene_column else []), "system", "views", "rotation ° mean / median", f"centre ({units}) mean / median", "PRE_r °", "PRE_t °",
              f"Chamfer ({units})", "colour spread", "PSNR dB", "PSNR dB aligned", "SSIM", *(["LPIPS"] if with_lpips else []), "wall s", "peak MiB",
              *(f"{col} ÷ pycolmap" for col, _ in RATIOS)]
    rows = []
    for s in systems.values():
        views = f"{fmt(s['n_valid'], '.0f')}/{fmt(s['n_views'], '.0f')}" if "n_valid" in s else "—"
        rows.append([
            *([result["scene"]] if scene_column else []), s["label"], views,
            f"{cell(s, 'rot_err_deg_mean')} / {cell(s, 'rot_err_deg_median')}",
            f"{cell(s, 'center_err_units_mean')} / {cell(s, 'center_err_units_median')}",
            cell(s, "pre_r_deg_mean"), cell(s, "pre_t_deg_mean"), cell(s, "chamfer_units"),
            cell(s, "colour_spread", ".4f"), cell(s, "psnr", ".2f"), cell(s, "psnr_aligned", ".2f"), cell(s, "ssim", ".3f"),
            *([cell(s, "lpips", ".3f")] if with_lpips else []),
            cell(s, "wall_seconds", ".0f"), fmt(s["peak_rss_mib"], ".0f"),
            *(fmt(s["over_pycolmap"][col], ".2f") for col, _ in RATIOS),
        ])
    return markdown_table(header, rows, align=("ll" if scene_column else "l") + "r" * (len(header) - 1 - scene_column))


def stage_system_table(result: dict) -> str:
    """Wall seconds of each charged stage (rows) per system (columns), and the totals."""
    systems = result["systems"].values()
    order = list(runner.load_stages())
    stages = sorted({st for s in systems for st in s["stages"]}, key=order.index)
    rows = [[st, *(fmt(s["stages"].get(st, {}).get("wall_seconds"), ".1f") for s in systems)] for st in stages]
    totals = [sum(st["wall_seconds"] for st in s["stages"].values()) for s in systems]
    rows.append(["**total**", *(f"**{fmt(total, '.1f')}**" for total in totals)])
    seeds = result.get("seeds") or []
    what = f"wall s, seed {seeds[0]}" if len(seeds) > 1 else "wall s"
    return markdown_table([f"stage ({what})", *(s["label"] for s in systems)], rows)


def reference_colour_spread(result: dict) -> float | None:
    """The colour spread of the scene's reference surface (the GT-pose NeuS on DTU), None where it has none."""
    return next((s["reference_colour_spread"] for s in result["systems"].values()
                 if is_number(s.get("reference_colour_spread"))), None)


def notes(result: dict, definitions: bool = True, reference_spread: bool = True) -> list[str]:
    """Footnotes that say how the systems table was measured; without `definitions`, only those that
    depend on the result (docs/BENCHMARKS.md defines the pose errors, the ratios, the memory and the colour spread);
    without `reference_spread`, not the reference surface's own colour spread (README lists every scene's in one note)."""
    systems = result["systems"]
    charged = [st for s in systems.values() for st in s["stages"].values()]
    fresh = sum(st["computed_in_this_bench"] for st in charged)
    fresh_note = ("All of them are of this bench." if fresh == len(charged) else
                  f"{fresh} of the {len(charged)} are of this bench, the others of the run that first computed the "
                  "cached version (`--force-all` for a fresh bench).")
    seeds = result.get("seeds") or []
    out = [f"Mean ± std over the seeds {', '.join(map(str, seeds))} (`run.seed`; std with ddof 1); the ratios are "
           "of the means. Per seed: `per_seed` in the JSON."] if len(seeds) > 1 else []
    out.append(
        "Times: sum of the wall times recorded in the manifests of the stages charged to each system (per stage: "
        "the bench's stage table and the JSON). Versions shared between systems (ingest, the front-end, the pycolmap reference) are computed "
        f"once and counted for every system that uses them; evaluation stages are never counted. {fresh_note}")
    out += [
        "Pose errors after a Sim3 alignment to the ground truth, fitted on the camera centres; the NeuS systems "
        "over the views they optimise (held-out views excluded), pycolmap over the views it registers. PRE_r / "
        "PRE_t: mean relative pose errors over view pairs, which no alignment changes (a shift of the centres "
        "also re-aligns every rotation: compare PRE_r to tell better rotations from a better-fitting alignment).",
        "÷ pycolmap: the system's mean rotation error, mean centre error and wall time divided by pycolmap's; "
        "above 1, pycolmap is better.",
        "Peak memory: the largest peak RSS of the system's stages, measured on the one bench process, so it "
        "includes what earlier stages left allocated (an upper bound).",
    ] if definitions else []
    iters = {s["label"]: s.get("field_iters") for s in systems.values() if is_number(s.get("field_iters"))}
    if iters:
        out.append("Iterations of the field the mesh and the renderings come from (the surface stage's): "
                   + ", ".join(f"{k} {v:.0f}" for k, v in iters.items())
                   + ". NeuS on fixed poses trains as many as ManifoldNeuS's surface (equal iterations).")
    out += [f"{s['label']} failed ({s['error']}): its row shows no mean." for s in systems.values() if s.get("error")]
    chamfer_refs = {s["chamfer_reference"] for s in systems.values() if s.get("chamfer_reference")}
    if chamfer_refs:
        out.append(f"Chamfer against the {'; '.join(sorted(chamfer_refs))}. pycolmap makes a sparse model, "
                   "no surface and no renderings; NeuS-COLMAP is NeuS trained on its poses.")
    spread = reference_colour_spread(result)
    if any(is_number(s.get("colour_spread")) for s in systems.values()):
        if definitions:
            out.append("Colour spread: the median over the mesh's points of the grey level's standard deviation across "
                       "the views that see them, at the images' own size under the ground-truth cameras (lower is "
                       "better; blind to textureless surfaces), a check that needs no masks and no reference"
                       + (f"; the reference surface's own: {spread:.4f}." if spread is not None else "."))
        elif spread is not None and reference_spread:
            out.append(f"The reference surface's own colour spread: {spread:.4f}.")
    rendered = [s for s in systems.values() if "psnr" in s]
    if rendered:
        masked = "masked (background zeroed)" if all(s["images_masked"] for s in rendered) else "unmasked"
        lpips = "" if any(is_number(s.get("lpips")) for s in rendered) else f" {rendered[0]['lpips_status']}."
        out.append(f"PSNR / SSIM on the held-out views, {masked}, rendered from the final model with the "
                   f"ground-truth poses.{lpips}")
    missing = {st for s in systems.values() for st in s["missing_stages"]}
    if missing:
        names = ", ".join(sorted(missing, key=list(runner.load_stages()).index))
        out.append(f"Not run in this bench (`--until {result['until']}`): {names}; totals leave them out.")
    return out


def comparison_markdown(result: dict, with_stages: bool = True) -> str:
    """The systems table, its footnotes and (`with_stages`) the stage x system table; README's Results
    leave the last out (it is in the JSON and in what the bench prints)."""
    footnotes = "\n".join(f"{i}. {n}" for i, n in enumerate(notes(result), 1))
    return f"{systems_table(result)}\n\n{footnotes}" + (f"\n\n{stage_system_table(result)}" if with_stages else "")


def stages_table(rows: dict) -> str:
    """Every version used in the bench: wall, CPU, peak memory and the first metrics."""
    body = []
    for name, r in rows.items():
        metrics = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                            for k, v in list(r["metrics"].items())[:8] if not isinstance(v, (dict, list)))
        body.append([name, fmt(r["wall_seconds"], ".1f"), fmt(r["cpu_seconds"], ".1f"), fmt(r["peak_rss_mib"], ".0f"),
                     metrics])
    return markdown_table(["stage", "wall s", "cpu s", "peak MiB", "key metrics"], body, align="lrrrl")


# ---------------------------------------------------------------------------- CLI


def parse_systems(text: str) -> list[System]:
    keys = [k.strip() for k in text.split(",") if k.strip()]
    unknown = [k for k in keys if k not in SYSTEMS]
    if unknown or not keys:
        raise argparse.ArgumentTypeError(f"unknown system(s) {unknown} (known: {', '.join(SYSTEMS)})")
    return [SYSTEMS[k] for k in SYSTEMS if k in keys]  # table order, whatever the order given


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", action="append", default=None, help="scan24 (default), ...; repeat it for several")
    ap.add_argument("--seeds", default=None, help="comma-separated run.seed values, e.g. 0,1,2: each system runs once "
                    "per seed and the tables show mean ± std (default: params.yaml's run.seed, one run)")
    ap.add_argument("--systems", type=parse_systems, default=list(SYSTEMS.values()),
                    help=f"comma-separated subset of {','.join(SYSTEMS)} (default: all)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--until", default=None, help="stop every run after this stage")
    ap.add_argument("--force-all", action="store_true", help="recompute every version once (fresh timings)")
    ap.add_argument("--force", action="append", default=[], metavar="STAGE", help="recompute this stage")
    ap.add_argument("--artifacts", type=Path, default=runner.DEFAULT_ARTIFACTS)
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT_DIR, help="results go to OUT_DIR/<scene>/<date>.json")
    executor.add_arguments(ap)
    args = ap.parse_args(argv)
    force = list(runner.load_stages()) if args.force_all else args.force
    try:
        results = run_benches(list(dict.fromkeys(args.scene or ["scan24"])), args.systems, args.overrides, args.until,
                              force, args.artifacts, args.executor, args.workers,
                              seeds=[int(s) for s in args.seeds.split(",")] if args.seeds else None)
    except (runner.PipelineError, runner.ParamError, runner.SceneError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for result in results.values():
        path = write_result(result, args.out_dir)
        print(f"## {result['scene']}: systems\n\n{comparison_markdown(result)}\n\n{targets_markdown(result)}\n")
        print(f"## {result['scene']}: every version used\n\n{stages_table(result['stages'])}\n")
        for k, v in result["summary"].items():
            print(f"- {k}: {v}")
        print(f"\nwrote {path}\n")
    failed = sorted({f"{r['scene']} {s['preset'] or 'default'}: {s['error']}"
                     for r in results.values() for s in r["systems"].values() if "error" in s})
    if failed:
        print(f"error: {len(failed)} run(s) failed: {'; '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
