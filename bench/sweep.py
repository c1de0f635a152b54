#!/usr/bin/env python
"""The supplement's experiments as sweep commands on the pipeline's cache.

    python -m bench.sweep TABLE [--scene scan24] [--values V ...] [--set section.key=value ...]
                          [--profile fast|paper] [--artifacts DIR] [--out DIR] [--tag NAME]
                          [--executor in-process|dask|dask://HOST:PORT|slurm] [--workers N]

TABLE (default values in brackets; ``--values`` picks others):
  A3      alpha of MaVOS                          [1.0 0.85 0.65 0.5 0.35]
  A4      anchors K % / successors per round M    [K=10 K=20 K=30 K=40 K=50 M=10 M=20 M=30]
  A5      parts of the MaVOS-gated PE, lambda     [base +S +S+eta_f +S+eta_t full lam=0.1 lam=0.3 lam=1.0]
  A6      losses                                  [recon depth normal all]
  A7      strategy x coverage (Fig. A7)           [FPS-E FPS-SE MaVOS-E MaVOS-SE]
  sparse  every n-th view (Sec. 4.4)              [1 2 3 5]  (of 49 views: 49, 25, 17, 10)

Each setting is one ``runner.run`` with the setting's overrides on top of ``--set``; the
runner's cache reruns only the stages whose parameters the setting touches (an alpha sweep
reuses ingest .. spectral, the pycolmap reference and the GT-pose reference surface). Every
setting runs up to ``evaluate``, whose ``evaluation.json`` holds the pose errors per round.
With ``--executor dask`` (or a scheduler, or SLURM) the settings run side by side, after the
stages they share have been computed once; a setting that fails is a row that says so.
A6 rows also retrain the GT-pose reference surface (it shares the ``loss`` section; add
``--set reference_surface.enabled=false`` when only the poses matter). Sparse rows hold out
no view (``split.holdout_every=0``): the supplement's 25 / 17 / 10 views are all inputs.

Prints a markdown table in the supplement's layout: one row per setting; rotation error (deg)
and camera-centre error of the anchor round ("Anc. Opt.") and of the first successor round
("Succ. Opt."), the supplement's value in brackets where its text prints one, the views per
round, the wall seconds of the setting in this run and from an empty cache, and which
stages were computed (the rest were reused). Writes ``<out>/<scene>/sweep_<TABLE>_<date>.json``
after every setting, so a long sweep that stops keeps what it measured.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import math
import os
import platform
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.stats import rankdata

import runner
from manifoldneus.data import io
from manifoldneus.data.artifacts import load_evaluation, load_gt_meta, load_schedule_meta, load_views_meta, round_folder
from runner import executor
from manifoldneus.config import ParamError
from manifoldneus.data.scenes import SceneError

ROOT = Path(__file__).resolve().parent.parent

ANCHOR_ROUND, FIRST_SUCCESSOR_ROUND = "anchors", round_folder(1)  # round labels of evaluation.json


@dataclasses.dataclass(frozen=True)
class Column:
    key: str      # in the JSON
    header: str   # in the markdown table
    round: str    # evaluation.json round label
    metric: str   # evaluation.json summary key (its mean is reported)
    digits: int


# In the supplement's order (Tables A5, A6): rotation anchor / successor, translation anchor / successor.
COLUMNS = (
    Column("rot_anchors", "ΔR anc. (deg)", ANCHOR_ROUND, "rot_err_deg", 3),
    Column("rot_successors", "ΔR succ. (deg)", FIRST_SUCCESSOR_ROUND, "rot_err_deg", 3),
    Column("centre_anchors", "ΔT anc.", ANCHOR_ROUND, "center_err", 4),
    Column("centre_successors", "ΔT succ.", FIRST_SUCCESSOR_ROUND, "center_err", 4),
)


class SweepError(ValueError):
    """A bad table name or value: printed as one message naming what is accepted."""


@dataclasses.dataclass(frozen=True)
class Setting:
    value: str                    # as given with --values
    label: str                    # the row's label (the supplement's row, where it has one)
    overrides: tuple[str, ...]    # `section.key=value`, applied after the user's --set


@dataclasses.dataclass(frozen=True)
class Table:
    name: str
    title: str
    defaults: tuple[str, ...]
    setting: Callable[[str], Setting]
    # row label -> (ΔR anc., ΔR succ., ΔT anc., ΔT succ.) as printed in the supplement; None = not reported
    paper: dict[str, tuple]
    source: str


def _number(value: str, what: str) -> float:
    try:
        x = float(value)
    except ValueError:
        raise SweepError(f"{what}: {value!r} is not a number") from None
    if not math.isfinite(x):
        raise SweepError(f"{what}: {value!r} is not finite")
    return x


# ---------------------------------------------------------------------------- A3: alpha

def alpha_setting(value: str) -> Setting:
    alpha = _number(value, "A3 (alpha)")
    return Setting(value, f"alpha = {alpha:.2f}", (f"schedule.alpha={alpha}",))


# The supplement's Table A3 header reads "ΔR (Anc., Succ.), ΔT (Anc., Succ.)", but its default row
# (alpha = 0.65: 3.883, 0.225, 1.076, 0.050) equals the full model of Tables A4-A6 only when read
# as ΔR anc., ΔT anc., ΔR succ., ΔT succ.; we read every row so and store it in our column order.
PAPER_A3 = {
    "alpha = 1.00": (5.735, 1.563, 0.348, 0.086),
    "alpha = 0.85": (4.305, 1.530, 0.251, 0.070),
    "alpha = 0.65": (3.883, 1.076, 0.225, 0.050),
    "alpha = 0.50": (6.500, 1.191, 0.401, 0.061),
    "alpha = 0.35": (9.800, 2.281, 0.577, 0.105),
}


# ---------------------------------------------------------------------------- A4: K and M

def anchors_or_successors_setting(value: str) -> Setting:
    m = re.fullmatch(r"\s*([KkMm])\s*=\s*(\S+)\s*", value)
    if not m:
        raise SweepError(f"A4: {value!r} should be K=<anchor percent> or M=<successors per round>, e.g. K=20 M=10")
    x = _number(m.group(2), f"A4 ({m.group(1).upper()})")
    if m.group(1) in "Kk":
        return Setting(value, f"K = {x:g} %", (f"schedule.anchor_percent={x:g}",))
    if x != int(x):
        raise SweepError(f"A4: M must be a whole number of views, got {value!r}")
    return Setting(value, f"M = {int(x)}", (f"schedule.successors_per_round={int(x)}",))


# Table A4: K is evaluated on the anchor round only, M on the successor round only.
PAPER_A4 = {
    **{f"K = {k} %": (r, None, t, None) for k, r, t in
       ((10, 2.941, 0.166), (20, 2.811, 0.162), (30, 3.883, 0.225), (40, 5.117, 0.306), (50, 6.517, 0.373))},
    **{f"M = {m}": (None, r, None, t) for m, r, t in
       ((10, 0.938, 0.027), (15, 1.073, 0.044), (20, 1.076, 0.050), (25, 1.386, 0.052), (30, 1.620, 0.062))},
}


# ---------------------------------------------------------------------------- A5: gate parts, lambda

# value -> (label, lambda (None = as configured), use_s, use_eta_f, use_eta_t). Every row sets all
# three switches, so that a row means the same whatever params.yaml says.
GATE_PARTS = {
    "base": ("Base (BARF, lambda = 0)", 0.0, True, True, True),
    "+S": ("+ S~", None, True, False, False),
    "+S+eta_f": ("+ S~ + eta_f", None, True, True, False),
    "+S+eta_t": ("+ S~ + eta_t", None, True, False, True),
    "full": ("Full: lambda S~ eta_f eta_t", None, True, True, True),
}


def gate_setting(value: str) -> Setting:
    if value.startswith("lam="):
        lam = _number(value[len("lam="):], "A5 (lambda)")
        label, switches = f"lambda = {lam:g}", (True, True, True)
    elif value in GATE_PARTS:
        label, lam, *switches = GATE_PARTS[value]
    else:
        raise SweepError(f"A5: {value!r} is not one of {', '.join(GATE_PARTS)} or lam=<lambda>")
    use_s, use_eta_f, use_eta_t = switches
    overrides = (f"gate.use_s={use_s}", f"gate.use_eta_f={use_eta_f}", f"gate.use_eta_t={use_eta_t}")
    return Setting(value, label, overrides + (() if lam is None else (f"gate.lam={lam}",)))


# The supplement's lambda = 0.3 row (4.402 ...) differs from its full model (3.883 ...), which also
# has lambda = 0.3; it does not say what else differs. Here lam=0.3 is the full model (same version).
PAPER_A5 = {
    "Base (BARF, lambda = 0)": (3.206, 3.574, 0.158, 0.152),
    "+ S~": (5.150, 1.981, 0.282, 0.084),
    "+ S~ + eta_f": (4.156, 1.351, 0.248, 0.067),
    "+ S~ + eta_t": (4.560, 1.662, 0.271, 0.076),
    "lambda = 0.1": (3.858, 1.432, 0.219, 0.066),
    "lambda = 0.3": (4.402, 1.416, 0.261, 0.066),
    "lambda = 1": (4.874, 1.934, 0.275, 0.831),
    "Full: lambda S~ eta_f eta_t": (3.883, 1.076, 0.225, 0.050),
}


# ---------------------------------------------------------------------------- A6: losses

# Terms a row switches off; the others keep their configured weights ("Recon." = rgb, eikonal, mask).
LOSS_ROWS = {
    "recon": ("Recon.", ("loss.w_depth=0", "loss.w_normal=0")),
    "depth": ("+ Depth", ("loss.w_normal=0",)),
    "normal": ("+ Normal", ("loss.w_depth=0",)),
    "all": ("All", ()),
}


def loss_setting(value: str) -> Setting:
    if value not in LOSS_ROWS:
        raise SweepError(f"A6: {value!r} is not one of {', '.join(LOSS_ROWS)}")
    label, overrides = LOSS_ROWS[value]
    return Setting(value, label, overrides)


PAPER_A6 = {
    "Recon.": (9.741, 7.545, 0.600, 0.467),
    "+ Depth": (7.271, 6.661, 0.452, 0.413),
    "+ Normal": (4.113, 2.073, 0.289, 0.076),
    "All": (3.883, 1.076, 0.225, 0.050),
}


# ---------------------------------------------------------------------------- A7: strategy x coverage

STRATEGY_ROWS = {
    "FPS-E": ("fps", "E"),
    "FPS-SE": ("fps", "SE"),
    "MaVOS-E": ("mavos", "E"),
    "MaVOS-SE": ("mavos", "SE"),
}


def strategy_setting(value: str) -> Setting:
    if value not in STRATEGY_ROWS:
        raise SweepError(f"A7: {value!r} is not one of {', '.join(STRATEGY_ROWS)}")
    strategy, coverage = STRATEGY_ROWS[value]
    return Setting(value, value, (f"schedule.strategy={strategy}", f"schedule.coverage={coverage}"))


# ---------------------------------------------------------------------------- sparse views

def sparse_setting(value: str) -> Setting:
    stride = _number(value, "sparse (view stride)")
    if stride < 1 or stride != int(stride):
        raise SweepError(f"sparse: the view stride must be a whole number >= 1, got {value!r}")
    stride = int(stride)
    suffix = {2: "nd", 3: "rd"}.get(stride, "th")
    label = "all views" if stride == 1 else f"every {stride}{suffix} view"
    # Every kept view is an input (the supplement's 25 / 17 / 10 views), none held out for novel
    # views: the schedule does not know the hold-out, so on 10 views a held-out anchor would leave
    # too few anchors to train and to align.
    return Setting(value, label, (f"ingest.view_stride={stride}", "split.holdout_every=0"))


TABLES = {t.name: t for t in (
    Table("A3", "alpha of MaVOS (local constraint vs coverage)", ("1.0", "0.85", "0.65", "0.5", "0.35"),
          alpha_setting, PAPER_A3, "supplement Table A3"),
    Table("A4", "anchor views K % and successor views per round M",
          ("K=10", "K=20", "K=30", "K=40", "K=50", "M=10", "M=20", "M=30"),
          anchors_or_successors_setting, PAPER_A4,
          "supplement Table A4 (K: anchor round only; M: successor round only)"),
    Table("A5", "parts of the MaVOS-gated positional encoding and its scale lambda",
          ("base", "+S", "+S+eta_f", "+S+eta_t", "full", "lam=0.1", "lam=0.3", "lam=1.0"),
          gate_setting, PAPER_A5, "supplement Table A5"),
    Table("A6", "loss terms", tuple(LOSS_ROWS), loss_setting, PAPER_A6, "supplement Table A6"),
    Table("A7", "schedule strategy x coverage distance (FPS / MaVOS, E / SE)", tuple(STRATEGY_ROWS),
          strategy_setting, {}, "supplement Fig. A7 prints its ΔR/ΔT inside the figure only, not in the text"),
    Table("sparse", "every n-th view (views 0, n, 2n, ...)", ("1", "2", "3", "5"), sparse_setting, {},
          "supplement Sec. 4.4 / Fig. A5 print their ΔR/ΔT inside the figure only, not in the text"),
)}


def settings_for(table: str, values: list[str] | None = None) -> list[Setting]:
    if table not in TABLES:
        raise SweepError(f"unknown table {table!r} (tables: {', '.join(TABLES)})")
    t = TABLES[table]
    settings = [t.setting(str(v)) for v in (values or t.defaults)]
    labels = [s.label for s in settings]
    twice = sorted({label for label in labels if labels.count(label) > 1})
    if twice:
        raise SweepError(f"{table}: {', '.join(twice)} given twice")
    return settings


# ---------------------------------------------------------------------------- running


def upstream_manifests(store: runner.Store, stage: str, fingerprint: str, out: dict | None = None) -> dict:
    """Stage -> manifest of a version and of every version upstream of it: what its results rest on.
    Followed through the manifests, not recomputed fingerprints: code edited while a sweep runs
    changes fingerprints, not what was run."""
    out = {} if out is None else out
    if stage not in out:
        out[stage] = store.manifest(stage, fingerprint)
        for up, fp in out[stage]["upstream"].items():
            upstream_manifests(store, up, fp, out)
    return out


def _round_errors(evaluation: dict) -> list[dict]:
    """evaluation.json's pose errors per round, without the per-view lists."""
    return [{"label": r["label"], "n_views": r["n_views"],
             "summary": {k: {s: v[s] for s in ("mean", "median")} for k, v in r["summary"].items()}}
            for r in evaluation.get("poses", []) if "summary" in r]  # rounds of < 3 views are not scored


def setting_row(setting: Setting, outcome: executor.Outcome, scene: str, artifacts: Path, data_root=None) -> dict:
    """One row: the evaluation of the setting's run, read by the versions it used."""
    store = runner.Store(artifacts, runner.resolve_scene(scene, data_root).name)
    manifests = upstream_manifests(store, "evaluate", outcome.report.fingerprints["evaluate"])
    versions = {name: store.version_dir(name, m["fingerprint"]) for name, m in manifests.items()}
    gt = load_gt_meta(versions["ground_truth"])
    schedule = load_schedule_meta(versions["schedule"])
    views = load_views_meta(versions["ingest"])
    rounds = _round_errors(load_evaluation(versions["evaluate"]))
    by_label = {r["label"]: r for r in rounds}
    return {
        "value": setting.value, "label": setting.label, "overrides": list(setting.overrides),
        "errors": {c.key: (by_label[c.round]["summary"][c.metric]["mean"] if c.round in by_label else None)
                   for c in COLUMNS},
        "views": {"anchors": by_label.get(ANCHOR_ROUND, {}).get("n_views"),
                  "first_successor_round": by_label.get(FIRST_SUCCESSOR_ROUND, {}).get("n_views"),
                  "total": len(views["names"])},
        "rounds": rounds,
        "schedule": {k: schedule[k] for k in ("n_anchors", "round_sizes", "anchors_connected")},
        "priors": {k: views[k] for k in ("has_mono_depth", "has_mono_normal")},
        "units": gt.get("units"), "units_per_scene_unit": gt.get("units_per_scene_unit"),
        "stages": dict(outcome.report),
        "wall_seconds": outcome.wall_seconds,
        # what this row costs from an empty cache: the compute times of the versions it rests on
        "cost_seconds": round(sum(m["wall_seconds"] for m in manifests.values()), 1),
        "fingerprints": {name: m["fingerprint"] for name, m in manifests.items()},
    }


# ---------------------------------------------------------------------------- the table


def _cell(ours: float | None, paper: float | None, digits: int) -> str:
    text = "–" if ours is None else f"{ours:.{digits}f}"
    return text if paper is None else f"{text} [{paper:.3f}]"


def _computed(stages: dict) -> str:
    done = [s for s, how in stages.items() if how == "computed"]
    if len(done) == len(stages):
        return "all"
    return ", ".join(done) or "none (all reused)"


def trend_notes(rows: list[dict], paper: dict) -> list[str]:
    """Per column: the lowest error here and in the supplement, and their rank correlation."""
    notes = []
    for i, c in enumerate(COLUMNS):
        pairs = [(r["label"], r["errors"][c.key], paper[r["label"]][i]) for r in rows
                 if r["errors"][c.key] is not None and paper.get(r["label"], (None,) * 4)[i] is not None]
        if len(pairs) < 2:
            continue
        labels, ours, theirs = zip(*pairs)
        best_paper = f"lowest in the supplement `{labels[int(np.argmin(theirs))]}`"
        ro, rp = rankdata(ours), rankdata(theirs)
        if ro.std() == 0:
            notes.append(f"- {c.header}: our values are all equal; {best_paper}")
            continue
        line = f"- {c.header}: lowest here `{labels[int(np.argmin(ours))]}`, {best_paper}"
        if len(pairs) >= 3 and rp.std() > 0:
            rho = np.corrcoef(ro, rp)[0, 1]
            line += f"; rank correlation with the supplement {rho:+.2f} over {len(pairs)} settings"
        notes.append(line)
    return notes


def markdown(result: dict) -> str:
    t = TABLES[result["table"]]
    rows = result["settings"]
    ok = [r for r in rows if "errors" in r]
    units = next(((r["units"], r["units_per_scene_unit"]) for r in ok if r.get("units_per_scene_unit")), None)
    lines = [
        f"### {t.name} on {result['scene']}: {result.get('title', t.title)} (profile {result['profile']})",
        "",
        f"| setting | ΔR init. (deg) | {' | '.join(c.header for c in COLUMNS)} | views anc. / succ. / all | wall s "
        "| cost s | stages computed |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        if "errors" not in r:
            lines.append(f"| {r['label']} | failed: {r['error'].splitlines()[0].replace('|', '/')} | | | | | | | | |")
            continue
        paper = t.paper.get(r["label"], (None,) * 4)
        cells = [_cell(r["errors"][c.key], paper[i], c.digits) for i, c in enumerate(COLUMNS)]
        counts = (r["views"]["anchors"], r["views"]["first_successor_round"], r["views"]["total"])
        views = " / ".join("–" if n is None else str(n) for n in counts)
        initial = next((x["summary"]["rot_err_deg"]["mean"] for x in r.get("rounds", [])
                        if x["label"] == "initial"), None)
        lines.append(f"| {r['label']} | {_cell(initial, None, 3)} | {' | '.join(cells)} | {views} | {r['wall_seconds']:.1f} "
                     f"| {r['cost_seconds']:.1f} | {_computed(r['stages'])} |")
    lines += [
        "",
        "ΔR init.: the anchors' initial poses (after any `anchors.perturb_*`); ΔR: rotation error (deg); ΔT: camera-centre error in the object-normalised frame (object inside the "
        "unit sphere" + (f"; 1 unit = {units[1]:.4g} {units[0]}" if units and units[0] != "unit" else "")
        + "); both after Sim3 alignment, "
        "mean over the views optimised in the anchor round (anc.) and in the first successor round (succ.), "
        "from evaluate's evaluation.json. "
        + (f"[x] = {t.source}: its ΔT units are not stated and its setup differs (GPU, full resolution, "
           "identity initialisation), so compare trends, not values." if t.paper
           else f"No supplement values: {t.source}.")
        + " wall s: this run; cost s: the setting's stage versions from an empty cache.",
    ]
    trend = trend_notes(ok, t.paper) if t.paper else []
    if trend:
        lines += ["", "Trend against the supplement:", *trend]
    if t.name == "A6" and ok and not any(p for r in ok for p in r["priors"].values()):
        lines += ["", "This scene has no monocular depth or normal priors: the depth and normal terms are off in "
                      "every row, so the rows differ only by their fingerprints."]
    return "\n".join(lines)


# ---------------------------------------------------------------------------- sweep


def run_sweep(table: str, scene: str = "scan24", values: list[str] | None = None, overrides: list[str] = (),
              artifacts: Path = runner.DEFAULT_ARTIFACTS, profile: str | None = None, data_root=None,
              out_root: Path = ROOT / "bench", tag: str = "", executor_name: str = "in-process",
              workers: int | None = None) -> dict:
    """Run every setting of a table, print its markdown table, write the JSON; returns the result.
    Each setting is one run of `executor_name` (module docstring of runner/executor.py)."""
    settings = settings_for(table, values)
    stages = runner.load_stages()
    for s in settings:  # every override is checked before hours of computing start
        resolved = runner.resolve_params(stages, runner.DEFAULT_PARAMS, [*overrides, *s.overrides], profile)
    scene_name = runner.resolve_scene(scene, data_root).name
    name = "_".join(["sweep", table, *([tag] if tag else []), dt.date.today().isoformat()])
    out = Path(out_root) / scene_name / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "table": table, "title": TABLES[table].title + (f" [{tag}]" if tag else ""), "tag": tag, "scene": scene, "profile": resolved["_profile"],
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "executor": executor_name, "workers": workers,
        "overrides": list(overrides), "artifacts": str(artifacts), "paper_source": TABLES[table].source,
        "paper": {label: dict(zip((c.key for c in COLUMNS), v)) for label, v in TABLES[table].paper.items()},
        "settings": [],
    }
    started = time.time()
    # later keys win: the setting's own
    specs = [executor.RunSpec(s.label, scene, dict(overrides=[*overrides, *s.overrides], profile=profile,
                                                   artifacts=artifacts, data_root=data_root)) for s in settings]
    rows = {}
    for outcome in executor.run_all(specs, executor_name, workers):
        if outcome.preparation:
            continue
        s = next(s for s in settings if s.label == outcome.name)
        rows[s.label] = setting_row(s, outcome, scene, artifacts, data_root) if not outcome.error else {
            "value": s.value, "label": s.label, "overrides": list(s.overrides), "error": outcome.error}
        result["settings"] = [rows[s.label] for s in settings if s.label in rows]  # the table's order
        result["total_wall_seconds"] = round(time.time() - started, 1)
        result["markdown"] = markdown(result)
        io.save_json(out, result)
    result["json"] = str(out)
    print(result["markdown"])
    print(f"\nwrote {out}")
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 2)[2])
    ap.add_argument("table", choices=list(TABLES))
    ap.add_argument("--scene", default="scan24")
    ap.add_argument("--values", nargs="+", default=None, metavar="V", help="settings to run (default: the table's)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="applied to every setting (the setting's own keys win)")
    ap.add_argument("--profile", default=None, help="fast | paper (default: params.yaml's `profile`)")
    ap.add_argument("--artifacts", type=Path, default=runner.DEFAULT_ARTIFACTS)
    ap.add_argument("--data-root", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=ROOT / "bench", help="JSON to OUT/<scene>/sweep_<TABLE>_<date>.json")
    ap.add_argument("--tag", default="", help="names a variant of the table (e.g. 'perturbed'): "
                    "OUT/<scene>/sweep_<TABLE>_<tag>_<date>.json, and the title says it")
    ap.add_argument("--all-rounds", action="store_true",
                    help="run every successor round (default: stop after round 1, all the tables read; half the time)")
    executor.add_arguments(ap)
    args = ap.parse_args(argv)
    # round 1 then is the last round run; final_iters=0 keeps it the length of any successor round
    stop = ["successors.max_rounds=1", "successors.final_iters=0"]
    overrides = args.overrides if args.all_rounds else [*stop, *args.overrides]
    try:
        result = run_sweep(args.table, args.scene, args.values, overrides, args.artifacts, args.profile,
                           args.data_root, args.out, args.tag, args.executor, args.workers)
    except (SweepError, ParamError, SceneError, runner.PipelineError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 1 if any("error" in r for r in result["settings"]) else 0


if __name__ == "__main__":
    sys.exit(main())
