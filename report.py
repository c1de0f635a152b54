"""Report: one self-contained ``report.md`` (PNGs beside it) comparing the systems on a scene,
built only from existing artifacts. It never trains: a system whose artifacts are missing is
named as missing and the report goes on.

    python pipeline.py report [--scene S] [--artifacts DIR] [--data-root DIR] [--out DIR]   # or: make report SCENE=S

Systems: ManifoldNeuS (the default run), the presets ``neus-barf`` and ``neus-colmap`` (their
``current@<preset>`` pointers) and the pycolmap reference (stages ``reference`` + ``evaluate_poses``).
Sections: a link to the interactive viewer page (mesh and cameras in a browser, written beside the
report: ``viewer.html``), schedule (supplement Fig. A6), aligned cameras (Fig. A2), pose error per
round, loss curves, mesh previews, rendered vs real held-out views, and the easy-view-bias analysis of
Fig. A1 for NeuS-BARF and ManifoldNeuS. Output: ``artifacts/<scene>/report/`` unless ``--out``;
``report.json`` beside the page holds the numbers behind the tables and plots.

The report is an evaluation tool, so it reads the ``ground_truth`` stage. Pose errors are
computed here from the rounds' poses with :func:`manifoldneus.geometry.pose_metrics.evaluate_poses`
(the same function and view selection as the ``evaluate`` stage), so the table exists even when
``evaluate`` has not run.
"""
from __future__ import annotations

import datetime as dt
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from manifoldneus.data import artifacts, io
from manifoldneus.geometry import pose_metrics
from manifoldneus.data.artifacts import CAMERAS_PLOT, SCHEDULE_PLOT, load_views_meta  # build_report's `artifacts` is the folder
from manifoldneus.data.scenes import SceneError, resolve_scene
from runner.common import DEFAULT_ARTIFACTS, PipelineError
from runner.store import Store

SYSTEMS = {"ManifoldNeuS": None, "NeuS-BARF": "neus-barf", "NeuS-COLMAP": "neus-colmap",
           "SfM-all + NeuS": "sfm-all"}  # name -> preset
REFERENCE = "pycolmap"
BIAS_SYSTEMS = ("NeuS-BARF", "ManifoldNeuS")  # Fig. A1: the uniform baseline, then ours
TOP_P = 20.0  # % of views in the easy (top) and hard (bottom) groups by overlap c_i
MAX_HELDOUT_IMAGES = 8


# ---------------------------------------------------------------------------- artifacts


class Pointers:
    """Current versions of a scene's stages as one system sees them (its preset's pointers)."""

    def __init__(self, artifacts: Path, scene: str, preset: str | None):
        self.preset = preset
        self.store = Store(artifacts, scene, preset)

    def get(self, stage: str) -> Path | None:
        fp = self.store.current(stage)
        return None if fp is None else self.store.version_dir(stage, fp)

    def file(self, stage: str, name: str) -> Path | None:
        """A file of the stage's current version, if both exist."""
        folder = self.get(stage)
        return folder / name if folder is not None and (folder / name).is_file() else None


def shared_stage(pointers: list[Pointers], stage: str) -> Path | None:
    """A stage every preset computes the same way (ground truth, the pycolmap reference): the
    first pointer that has it, the default run's first."""
    return next((p for p in (ptr.get(stage) for ptr in pointers) if p is not None), None)


@dataclass
class RoundPoses:
    """The poses a system ended one round with (or started from: label 'initial')."""

    label: str
    w2c: np.ndarray  # [N,4,4]
    valid: np.ndarray  # bool [N]: views this round placed and optimised
    trained: dict | None = None  # artifacts.load_round() output (traces, round.json) for trained rounds


def neural_rounds(ptr: Pointers) -> list[RoundPoses]:
    """initial poses, the anchor round, then every successor round (the order `evaluate` uses)."""
    anchors, successors = ptr.get("anchors"), ptr.get("successors")
    if anchors is None:
        return []
    init = artifacts.load_initial_poses(anchors)
    dirs = [anchors / artifacts.ANCHOR_ROUND]
    if successors is not None:
        dirs += artifacts.successor_rounds(successors)
    out = [RoundPoses("initial", init["w2c"], init["placed"].astype(bool))]
    for d in dirs:
        r = artifacts.load_round(d)
        label = "anchors" if d.name == artifacts.ANCHOR_ROUND else d.name
        out.append(RoundPoses(label, r["w2c"], r["placed"].astype(bool) & r["optimised"].astype(bool), r))
    return out


def reference_rounds(reference_dir: Path | None) -> list[RoundPoses]:
    if reference_dir is None:
        return []
    ref = artifacts.load_reference_poses(reference_dir, ["w2c", "registered"])
    return [RoundPoses("final", ref["w2c"], ref["registered"].astype(bool))]


@dataclass
class GroundTruth:
    w2c: np.ndarray
    units: str
    units_per_scene_unit: float


def load_ground_truth(gt_dir: Path | None) -> GroundTruth | None:
    if gt_dir is None:
        return None
    meta = artifacts.load_gt_meta(gt_dir)
    if not meta.get("has_poses"):
        return None
    w2c = artifacts.load_ground_truth_poses(gt_dir, ["w2c"])["w2c"]
    return GroundTruth(w2c, meta["units"], float(meta["units_per_scene_unit"]))


# ---------------------------------------------------------------------------- pose errors


def pose_error_rows(rounds: list[RoundPoses], gt: GroundTruth) -> list[dict]:
    """Per round: Sim3-aligned errors of the round's valid views (None where < 3 views)."""
    rows = []
    for r in rounds:
        if r.valid.sum() < 3:
            rows.append({"label": r.label, "n_views": int(r.valid.sum()), "summary": None})
            continue
        res = pose_metrics.evaluate_poses(r.w2c, gt.w2c, valid=r.valid, units_scale=gt.units_per_scene_unit)
        rows.append({"label": r.label, "n_views": res["n_valid"], "summary": res["summary"],
                     "w2c_aligned": res["w2c_aligned"], "valid": res["valid"], "rot_err_deg": res["rot_err_deg"]})
    return rows


def placement_round(rounds: list[RoundPoses]) -> RoundPoses | None:
    """Every view at the pose it was placed with: the anchors at their initialisation, a successor at
    the start of the round that added it (what the rounds then refine)."""
    if not rounds or rounds[0].label != "initial":
        return None
    w2c, valid = rounds[0].w2c.copy(), rounds[0].valid.copy()
    for r in rounds[2:]:  # the successor rounds
        new = [v for v in (r.trained or {}).get("info", {}).get("new_views", []) if r.valid[v]]
        w2c[new] = r.trained["w2c_init"][new]
        valid[new] = True
    return RoundPoses("placement", w2c, valid)


def section_pose_per_view(page: Page, rows: dict[str, list[dict]], placement: list[dict] | None,
                          names: list[str]) -> None:
    """Each view's rotation error at placement, after each of ManifoldNeuS's rounds, and in sfm-all
    (COLMAP's mapper on our matches over every view): where the rounds help a view and where not."""
    ours, sfm = rows.get("ManifoldNeuS"), rows.get("SfM-all + NeuS")
    if not ours:
        return
    columns = [*(placement or []), *[r for r in ours if r["summary"] is not None]]
    if sfm and sfm[-1]["summary"] is not None:
        columns.append({**sfm[-1], "label": "sfm-all"})
    page.add("## Rotation error per view (deg)", "",
             "Each column Sim3-aligned on its own views; `placement`: each view at the pose it was placed with "
             "(anchors: their initialisation; the others: the start of the round that added them); `sfm-all`: "
             "COLMAP's mapper and bundle adjustment on our matches over every training view (the preset of that "
             "name; run it with `--preset sfm-all`)." if sfm else "Each column Sim3-aligned on its own views; "
             "`placement`: each view at the pose it was placed with. Run `--preset sfm-all` for its column.", "",
             "| view | " + " | ".join(c["label"] for c in columns) + " |",
             "|---|" + "---:|" * len(columns))
    for v, name in enumerate(names):
        cells = [_fmt(c["rot_err_deg"][v]) if c["valid"][v] else "" for c in columns]
        if any(cells):
            page.add(f"| {name} | " + " | ".join(cells) + " |")
    page.add("")


def round_position(label: str) -> int:
    """x position of a round in the pose-error plot: initial 0, anchors 1, round_r r + 1."""
    fixed = {"initial": 0, "anchors": 1}
    return fixed[label] if label in fixed else int(label.split("_")[1]) + 1


# ---------------------------------------------------------------------------- Fig. A1


def overlap_groups(c: np.ndarray, p: float = TOP_P) -> tuple[np.ndarray, np.ndarray]:
    """Positions of the top-p % and the bottom-p % entries of ``c`` (overlap), at least one each;
    ceil like the schedule's anchor count; ties keep view order."""
    c = np.asarray(c, float)
    k = max(1, math.ceil(p / 100.0 * len(c)))
    order = np.argsort(-c, kind="stable")
    return order[:k], order[len(c) - k:]


def top_p_share(grad_norm: np.ndarray, c: np.ndarray, p: float = TOP_P) -> np.ndarray:
    """Share of the total pose-gradient norm carried by the top-p % views by overlap ``c``.
    grad_norm [..., n] -> [...]; NaN where the total is 0 (poses frozen at that iteration)."""
    g = np.asarray(grad_norm, float)
    top, _ = overlap_groups(c, p)
    total = g.sum(-1)
    return np.where(total > 0, g[..., top].sum(-1) / np.where(total > 0, total, 1.0), np.nan)


def logged_steps(rnd: dict) -> np.ndarray:
    """Iteration of each pose_trace sample: the trainer logs history and the traces together;
    after a resume both restart, so the traces match the last entries of the history."""
    n = len(rnd["pose_trace"])
    steps = [h["step"] for h in rnd["info"].get("history", [])][-n:]
    return np.asarray(steps if len(steps) == n else np.arange(1, n + 1), float)


def easy_view_bias(rnd: dict, gt: GroundTruth, c: np.ndarray, p: float = TOP_P) -> dict | None:
    """Fig. A1 for one round: per logged iteration, mean rotation / centre error (Sim3-aligned at
    that iteration over the round's views) and mean pose-gradient norm of the top-p % (easy) and
    bottom-p % (hard) views by overlap, and the top-p share of the gradient norm."""
    ids = np.flatnonzero(rnd["optimised"].astype(bool))
    if len(ids) < 3 or len(rnd["pose_trace"]) == 0:  # a Sim3 needs 3 views; nothing logged, nothing to show
        return None
    valid = np.zeros(len(c), bool)
    valid[ids] = True
    top, bottom = (ids[g] for g in overlap_groups(c[ids], p))
    rot, centre = [], []
    for w2c in rnd["pose_trace"]:
        res = pose_metrics.evaluate_poses(w2c, gt.w2c, valid=valid, units_scale=gt.units_per_scene_unit)
        rot.append(res["rot_err_deg"])
        centre.append(res["center_err_units"])
    rot, centre = np.array(rot), np.array(centre)
    grads = np.asarray(rnd["pose_grad_norm"], float)
    moving = grads[:, ids].sum(1) > 0  # poses frozen (pose_start_frac) -> no gradient to compare

    def grad_mean(group):
        return np.where(moving, grads[:, group].mean(1), np.nan)

    return {"step": logged_steps(rnd), "n_views": int(len(ids)), "n_group": int(len(top)),
            "easy_views": top.tolist(), "hard_views": bottom.tolist(),
            "rot_easy": rot[:, top].mean(1), "rot_hard": rot[:, bottom].mean(1),
            "centre_easy": centre[:, top].mean(1), "centre_hard": centre[:, bottom].mean(1),
            "grad_easy": grad_mean(top), "grad_hard": grad_mean(bottom),
            "top_share": top_p_share(grads[:, ids], c[ids], p)}


def round_offsets(rounds: list[RoundPoses]) -> dict[str, int]:
    """Global iteration at which each trained round starts (rounds run one after another)."""
    out, total = {}, 0
    for r in rounds:
        if r.trained is not None:
            out[r.label] = total
            total += int(r.trained["info"]["train"]["steps"])
    return out


# ---------------------------------------------------------------------------- plots


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_pose_errors(rows_by_system: dict[str, list[dict]], units: str, path: Path) -> None:
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    labels: dict[int, str] = {}
    for name, rows in rows_by_system.items():
        rows = [r for r in rows if r["summary"]]
        for ax, key in zip(axes, ("rot_err_deg", "center_err_units")):
            y = [r["summary"][key]["mean"] for r in rows]
            if name == REFERENCE:  # one final result: a level to compare the rounds against
                ax.axhline(y[0], color="k", ls=":", label=f"{name} (final)")
                continue
            x = [round_position(r["label"]) for r in rows]
            ax.plot(x, y, "o-", label=name)
        labels.update({round_position(r["label"]): r["label"] for r in rows if name != REFERENCE})
    for ax, title in zip(axes, ("rotation error, mean (deg)", f"centre error, mean ({units})")):
        ax.set_xticks(sorted(labels), [labels[k] for k in sorted(labels)])
        io.log_y(ax)
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=8)
    fig.tight_layout()
    io.save_figure(path, fig)


def _round_boundaries(ax, offsets: dict[str, int]) -> None:
    for label, start in offsets.items():
        if start > 0:
            ax.axvline(start, color="0.7", lw=0.8, ls="--")
            ax.text(start, 1.0, f" {label}", transform=ax.get_xaxis_transform(), fontsize=7, va="top")


def plot_losses(rounds: list[RoundPoses], title: str, path: Path) -> None:
    """Total loss and each term, from the trainer's history in round.json, on a global iteration axis."""
    plt = _pyplot()
    offsets = round_offsets(rounds)
    fig, ax = plt.subplots(figsize=(8, 3.6))
    keys = sorted({k for r in rounds if r.trained for h in r.trained["info"]["history"] for k in h
                   if k == "loss" or k.startswith("loss_")})
    for k, key in enumerate(keys):
        x, y = [], []
        for r in rounds:
            if r.trained:
                hist = [h for h in r.trained["info"]["history"] if key in h]
                x += [offsets[r.label] + h["step"] for h in hist]
                y += [h[key] if h[key] > 0 else np.nan for h in hist]  # log axis
        ax.plot(x, y, lw=2.0 if key == "loss" else 1.0, color="k" if key == "loss" else f"C{k}",
                label="total" if key == "loss" else key[5:])
    _round_boundaries(ax, offsets)
    io.log_y(ax)
    ax.set_xlabel("iteration")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    io.save_figure(path, fig)


def plot_bias(bias: dict[str, dict], offsets: dict[str, int], units: str, title: str, path: Path) -> None:
    """Fig. A1 (a)-(d): easy (top-p %) vs hard (bottom-p %) views along the training."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.4), sharex=True)
    panels = (("rot", "(a) rotation error (deg)"), ("centre", f"(b) centre error ({units})"),
              ("grad", "(c) pose-gradient L2 norm"))
    for i, (label, b) in enumerate(bias.items()):
        x = offsets[label] + b["step"]
        for ax, (key, name) in zip(axes, panels):
            ax.plot(x, b[f"{key}_easy"], "o-", ms=3, color="tab:green", label="easy (top 20 %)" if i == 0 else None)
            ax.plot(x, b[f"{key}_hard"], "s-", ms=3, color="tab:red", label="hard (bottom 20 %)" if i == 0 else None)
            ax.set_title(name, fontsize=9)
        axes[3].plot(x, b["top_share"], "o-", ms=3, color="tab:blue")
        # the share if every view's gradient were equal: the easy views' fraction of the round
        axes[3].plot(x, np.full(len(x), b["n_group"] / b["n_views"]), color="0.5", ls=":", lw=1,
                     label="equal gradients" if i == 0 else None)
    axes[3].set_ylim(0, 1)
    axes[3].set_title(f"(d) top-{TOP_P:g} % share of the gradient norm", fontsize=9)
    for ax in axes:
        _round_boundaries(ax, offsets)
        ax.set_xlabel("iteration")
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    io.save_figure(path, fig)


# ---------------------------------------------------------------------------- the page


@dataclass
class Page:
    """report.md being written; images are copied (or drawn) into ``out`` beside it."""

    out: Path
    lines: list[str] = field(default_factory=list)

    def add(self, *lines: str) -> None:
        self.lines.extend(lines)

    def image(self, filename: str, caption: str, source: Path | None = None) -> None:
        if source is not None:
            shutil.copyfile(source, self.out / filename)
        self.add(f"![{caption}]({filename})", "")

    def missing(self, what: str, how: str = "") -> None:
        self.add(f"_{what}: not available{' (' + how + ')' if how else ''}._", "")


def slug(name: str) -> str:
    return name.lower().replace("-", "_")


def _fmt(x, digits: int = 3) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def _run_hint(scene: str, preset: str | None) -> str:
    return f"`python pipeline.py run --scene {scene}{' --preset ' + preset if preset else ''}`"


SYSTEM_STAGES = ("schedule", "anchors", "successors", "surface", "mesh", "evaluate")


def section_systems(page: Page, systems: dict[str, Pointers], reference: tuple[Path | None, Path | None],
                    scene: str) -> None:
    """Which stages each system has; how to compute what is missing."""
    page.add("| system | preset | stages present | stages missing (nothing is computed here) |", "|---|---|---|---|")
    table = {name: (ptr.preset, {s: ptr.get(s) for s in SYSTEM_STAGES}) for name, ptr in systems.items()}
    table[REFERENCE] = (None, dict(zip(("reference", "evaluate_poses"), reference)))
    for name, (preset, stages) in table.items():
        present = [s for s, path in stages.items() if path is not None]
        missing = [s for s, path in stages.items() if path is None]
        todo = f"{', '.join(missing)}: {_run_hint(scene, preset)}" if missing else "-"
        page.add(f"| {name} | {preset or '(default)'} | {', '.join(present) or '-'} | {todo} |")
    page.add("")


def section_viewer(page: Page, systems: dict[str, Pointers], scene: str) -> None:
    """The viewer page of each system that has exported its result, written beside the report
    (the same page as ``pipeline.py view``), and a link to it."""
    from manifoldneus.output import viewer

    page.add("## Viewer", "")
    for name, ptr in systems.items():
        versions = ptr.store.lineage("export", beside=("reference",))
        if not versions:
            page.missing(f"{name} viewer", f"stage export: {_run_hint(scene, ptr.preset)}")
            continue
        filename = f"{slug(name)}_viewer.html"
        held = viewer.write_page(versions, page.out / filename, f"{scene}: {name}")
        page.add(f"- [{name}: mesh and cameras in the browser]({filename}) ({held['optimised']} optimised cameras, "
                 f"{held['held_out_drawn']} held-out cameras, {held['faces']} triangles; one self-contained file)")
    page.add("")


def section_schedule(page: Page, systems: dict[str, Pointers], scene: str) -> None:
    page.add("## Schedule (supplement Fig. A6)", "")
    for name, ptr in systems.items():
        png = ptr.file("schedule", SCHEDULE_PLOT)
        page.add(f"### {name}", "")
        if png:
            page.image(f"{slug(name)}_schedule.png", f"{name}: schedule", png)
        else:
            page.missing(f"{name} schedule", _run_hint(scene, ptr.preset))


def section_cameras(page: Page, systems: dict[str, Pointers], reference: tuple[Path | None, Path | None],
                    rows: dict[str, list[dict]], gt: GroundTruth | None) -> None:
    """Reuses the PNG the evaluation stages draw; plots the final round's alignment otherwise."""
    page.add("## Aligned cameras (supplement Fig. A2)", "",
             "Estimated cameras (red) Sim3-aligned to the ground truth (grey), final poses.", "")
    drawn = {name: ptr.file("evaluate", CAMERAS_PLOT) for name, ptr in systems.items()}
    ref_png = None if reference[1] is None else reference[1] / artifacts.REFERENCE_CAMERAS_PLOT
    drawn[REFERENCE] = ref_png if ref_png is not None and ref_png.is_file() else None
    for name, png in drawn.items():
        page.add(f"### {name}", "")
        filename = f"{slug(name)}_cameras.png"
        final = next((r for r in reversed(rows.get(name, [])) if r["summary"]), None)
        if png:
            page.image(filename, f"{name}: aligned cameras", png)
        elif final is not None:
            pose_metrics.plot_cameras(final["w2c_aligned"], gt.w2c, page.out / filename, valid=final["valid"],
                                      title=f"{name}: {final['label']} poses (Sim3-aligned) vs GT")
            page.image(filename, f"{name}: aligned cameras (drawn by the report)")
        else:
            page.missing(f"{name} poses")


def section_pose_errors(page: Page, rows: dict[str, list[dict]], gt: GroundTruth | None, scene: str) -> None:
    page.add("## Pose error per round", "")
    if gt is None:
        page.missing("Ground-truth poses", f"`python pipeline.py run --scene {scene} --until ground_truth`; "
                                           "a scene without GT poses has no pose errors")
        return
    u = gt.units
    page.add("Sim3 (Umeyama on camera centres) alignment per round over the views that round optimised "
             "(`initial`: the anchors' initial poses); PRE: relative pose errors over all pairs.", "",
             f"| system | round | views | rot mean (deg) | rot median (deg) | centre mean ({u}) | "
             f"centre median ({u}) | centre mean (%) | PRE_r mean (deg) | PRE_t mean (deg) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, system_rows in rows.items():
        for r in system_rows:
            s = r["summary"]
            if s is None:
                page.add(f"| {name} | {r['label']} | {r['n_views']} | fewer than 3 views: no alignment |||||||")
                continue
            vals = [s["rot_err_deg"]["mean"], s["rot_err_deg"]["median"], s["center_err_units"]["mean"],
                    s["center_err_units"]["median"], s["center_err_pct"]["mean"], s["pre_r_deg"]["mean"],
                    s["pre_t_deg"]["mean"]]
            page.add(f"| {name} | {r['label']} | {r['n_views']} | " + " | ".join(_fmt(v) for v in vals) + " |")
    page.add("")
    if any(r["summary"] for system_rows in rows.values() for r in system_rows):
        plot_pose_errors(rows, u, page.out / artifacts.POSE_ERROR_PLOT)
        page.image(artifacts.POSE_ERROR_PLOT, "pose error per round")


def section_losses(page: Page, rounds: dict[str, list[RoundPoses]]) -> None:
    page.add("## Loss curves", "", "Total loss and its terms as the trainer logged them (`history` in each "
             "round's `round.json`), rounds one after another (dashed lines: round starts).", "")
    for name, rr in rounds.items():
        page.add(f"### {name}", "")
        if any(r.trained and r.trained["info"].get("history") for r in rr):
            plot_losses(rr, f"{name}: training losses", page.out / f"{slug(name)}_losses.png")
            page.image(f"{slug(name)}_losses.png", f"{name}: losses")
        else:
            page.missing(f"{name} training history")


def section_run(page: Page, systems: dict[str, Pointers]) -> None:
    """The camera each run estimated and what each stage took (from the manifests): what a run on photos
    without ground truth has to show."""
    from runner.inspect import camera_line
    from runner.registry import load_stages

    page.add("## The run: camera and time per stage", "")
    for name, ptr in systems.items():
        ev = ptr.file("evaluate", artifacts.EVALUATION)
        intrinsics = io.load_json(ev).get("intrinsics") if ev else None
        page.add(f"### {name}", "", f"`{camera_line(intrinsics)}`" if intrinsics else "_camera: not evaluated yet._", "")
        rows = [(stage, ptr.store.manifest(stage)) for stage in load_stages() if ptr.get(stage) is not None]
        page.add("| stage | wall s | CPU s | peak MiB |", "|---|---:|---:|---:|",
                 *(f"| {stage} | {m['wall_seconds']:.1f} | {m.get('cpu_seconds', float('nan')):.1f} | "
                   f"{m.get('peak_rss_mib', float('nan')):.0f} |" for stage, m in rows), "")


def section_meshes(page: Page, systems: dict[str, Pointers]) -> None:
    page.add("## Mesh previews (3 viewpoints)", "")
    for name, ptr in systems.items():
        png = ptr.file("mesh", "mesh_preview.png")
        page.add(f"### {name}", "")
        if png:
            page.image(f"{slug(name)}_mesh.png", f"{name}: mesh", png)
        else:
            page.missing(f"{name} mesh preview", "stage mesh; an empty mesh has no preview")


def section_heldout(page: Page, systems: dict[str, Pointers]) -> None:
    page.add("## Held-out views: rendered | real", "",
             "Held-out views rendered from the final model at their GT poses mapped into the model's frame "
             "(left), next to the photo (right); `evaluate` stage.", "")
    for name, ptr in systems.items():
        page.add(f"### {name}", "")
        ev = ptr.get("evaluate")
        report = artifacts.load_evaluation(ev) if ev is not None else {}
        nvs = report.get("novel_views")
        if not nvs:
            page.missing(f"{name} held-out renderings", "stage evaluate")
            continue
        s = nvs["summary"]
        columns = (("psnr", "PSNR dB, whole image"), ("psnr_masked", "PSNR dB, object (mask)"),
                   ("ssim", "SSIM, whole image"), ("ssim_masked", "SSIM, object (mask)"), ("lpips", "LPIPS"))
        columns = [(k, label) for k, label in columns if k in s or f"aligned_{k}" in s]
        page.add("| mean over the held-out views | " + " | ".join(label for _, label in columns) + " |",
                 "|---|" + "---|" * len(columns))
        for what, prefix in (("at the Sim3-mapped GT poses", ""),
                             ("after test-time alignment (pose refined against the frozen field)", "aligned_")):
            if any(f"{prefix}{k}" in s for k, _ in columns):
                page.add(f"| {what} | " + " | ".join(_fmt(s.get(f"{prefix}{k}"), 3) for k, _ in columns) + " |")
        page.add("")
        for row in nvs["per_view"][:MAX_HELDOUT_IMAGES]:
            png = ev / "novel_views" / f"{row['name']}.png"
            if png.is_file():
                page.image(f"{slug(name)}_heldout_{row['name']}.png",
                           f"{name}: view {row['name']}, PSNR {_fmt(row['psnr'], 2)} dB", png)


def section_bias(page: Page, systems: dict[str, Pointers], rounds: dict[str, list[RoundPoses]],
                 gt: GroundTruth | None) -> dict:
    page.add("## Easy-view bias (supplement Fig. A1)", "",
             f"Per logged iteration of each round: views ranked by overlap c_i (covisibility stage); easy = top "
             f"{TOP_P:g} %, hard = bottom {TOP_P:g} % of the round's views. Errors after a Sim3 alignment of the "
             f"round's poses at that iteration; gradient norm = L2 norm of each view's se(3) pose gradient; "
             f"top-{TOP_P:g} % share = the easy views' part of the summed gradient norm (equal gradients would "
             "give the easy views' fraction of the round, about p). "
             "Gradient columns: mean over the iterations where poses learn (frozen at the start of a round); "
             "error columns: at the round's last logged iteration.", "")
    results = {}
    for name in BIAS_SYSTEMS:
        page.add(f"### {name}", "")
        cov = systems[name].get("covisibility")
        trained = [r for r in rounds.get(name, []) if r.trained is not None]
        if gt is None or cov is None or not trained:
            page.missing(f"{name} easy-view analysis", "needs ground truth, covisibility and trained rounds")
            continue
        c = artifacts.load_covisibility(cov, ["c"])["c"].astype(float)
        bias = {r.label: b for r in trained if (b := easy_view_bias(r.trained, gt, c)) is not None}
        if not bias:
            page.missing(f"{name} easy-view analysis", "no round with 3 or more views and logged iterations")
            continue
        results[name] = bias
        u = gt.units
        page.add(f"| round | views | easy/hard views | logged iters | rot easy / hard (deg) | "
                 f"centre easy / hard ({u}) | grad norm easy / hard | top-{TOP_P:g} % share |",
                 "|---|---:|---:|---:|---:|---:|---:|---:|")
        for label, b in bias.items():
            page.add(f"| {label} | {b['n_views']} | {b['n_group']} / {b['n_group']} | {len(b['step'])} | "
                     f"{_fmt(b['rot_easy'][-1])} / {_fmt(b['rot_hard'][-1])} | "
                     f"{_fmt(b['centre_easy'][-1])} / {_fmt(b['centre_hard'][-1])} | "
                     f"{_fmt(_nanmean(b['grad_easy']), 4)} / {_fmt(_nanmean(b['grad_hard']), 4)} | "
                     f"{_fmt(_nanmean(b['top_share']))} |")
        page.add("")
        plot_bias(bias, round_offsets(rounds[name]), u, f"{name}: easy (top {TOP_P:g} %) vs hard (bottom "
                  f"{TOP_P:g} %) views by overlap", page.out / f"{slug(name)}_easy_view_bias.png")
        page.image(f"{slug(name)}_easy_view_bias.png", f"{name}: easy-view bias")
    return results


def _nanmean(x) -> float:
    x = np.asarray(x, float)
    return float(x[np.isfinite(x)].mean()) if np.isfinite(x).any() else float("nan")


def scene_dir_name(scene: str, data_root=None) -> str:
    """The artifacts folder name of a scene (as the runner names it; the name itself if the data is absent)."""
    try:
        return resolve_scene(scene, data_root).name
    except SceneError:
        return scene


def build_report(scene: str, artifacts: Path = DEFAULT_ARTIFACTS, out: Path | None = None, data_root=None) -> Path:
    """Write ``report.md`` (+ PNGs, ``report.json``) for ``scene``; returns the page's path."""
    name = scene_dir_name(scene, data_root)
    if not (Path(artifacts) / name / "ingest").is_dir():
        raise PipelineError(f"no artifacts of scene {scene!r} in {artifacts}: run `make all SCENE={scene}` "
                            f"(or `python pipeline.py run --scene {scene}`) first; the report never trains")
    out = Path(out) if out is not None else Path(artifacts) / name / "report"
    out.mkdir(parents=True, exist_ok=True)
    systems = {system: Pointers(artifacts, name, preset) for system, preset in SYSTEMS.items()}
    pointers = list(systems.values())
    reference = (shared_stage(pointers, "reference"), shared_stage(pointers, "evaluate_poses"))
    gt = load_ground_truth(shared_stage(pointers, "ground_truth"))
    rounds = {system: neural_rounds(ptr) for system, ptr in systems.items()}
    rounds[REFERENCE] = reference_rounds(reference[0])
    rows = {system: pose_error_rows(rr, gt) for system, rr in rounds.items() if rr} if gt else {}

    page = Page(out)
    built = (f"Built {dt.datetime.now().isoformat(timespec='seconds')} from the artifacts in `{Path(artifacts)}` "
             "only (nothing was trained).")
    bias = {}
    if gt is None:  # a user's photos: nothing to score or compare; what the runs made
        systems = {s: ptr for s, ptr in systems.items() if any(ptr.get(st) for st in SYSTEM_STAGES)}
        page.add(f"# Report: {name}", "", f"{built} The scene has no ground truth: no pose errors, held-out views "
                 "or comparisons; below, what each run made (systems run: " + ", ".join(systems) + ").", "")
        section_run(page, systems)
        section_viewer(page, systems, scene)
        section_schedule(page, systems, scene)
        section_losses(page, {s: rounds[s] for s in systems})
        section_meshes(page, systems)
    else:
        page.add(f"# Report: {name}", "", f"{built} Systems: ManifoldNeuS (default run), the presets `neus-barf`, "
                 "`neus-colmap` and `sfm-all`, and the pycolmap reference (stages `reference` + `evaluate_poses`).", "")
        section_systems(page, systems, reference, scene)
        section_viewer(page, systems, scene)
        section_pose_errors(page, rows, gt, scene)
        if rows.get("ManifoldNeuS"):
            placed = placement_round(rounds["ManifoldNeuS"])
            names = load_views_meta(shared_stage(pointers, "ingest"))["names"]
            section_pose_per_view(page, rows, pose_error_rows([placed], gt) if placed else None, names)
        section_schedule(page, systems, scene)
        section_cameras(page, systems, reference, rows, gt)
        section_losses(page, {s: rounds[s] for s in systems})
        section_run(page, systems)
        section_meshes(page, systems)
        section_heldout(page, systems)
        bias = section_bias(page, systems, rounds, gt)

    (out / "report.md").write_text("\n".join(page.lines) + "\n")
    io.save_json(out / "report.json", {
        "scene": name, "units": gt.units if gt else None,
        "pose_errors": {s: [{k: r[k] for k in ("label", "n_views", "summary")} for r in rr] for s, rr in rows.items()},
        "easy_view_bias": bias, "top_p": TOP_P})
    return out / "report.md"
