"""Looking at a scene's artifacts: the end-of-run summary, `status` and `params-diff` (why a stage is
stale), `verify` (re-hash), `show` (what a version holds) and `view` (the viewer page)."""
from __future__ import annotations

import json
import shlex
from pathlib import Path

from manifoldneus.data.artifacts import MESH, load_evaluation, load_schedule_meta  # `artifacts` is the folder here
from manifoldneus.output.export import FRAME
from manifoldneus.data.scenes import resolve_scene
from runner.common import DEFAULT_ARTIFACTS, DEFAULT_PARAMS, PipelineError
from runner.execute import RunReport, _refuse_damaged, cli_hint
from runner.fingerprint import compute_fingerprints
from runner.params import resolve_params
from runner.registry import for_params, load_stages
from runner.store import MANIFEST, Store


def run_summary(scene_name: str, report: RunReport, artifacts=DEFAULT_ARTIFACTS, data_root=None,
                preset=None) -> str:
    """What a run did and where its results are: per stage ran / cached and its time, the final
    poses' and held-out views' scores where the scene has ground truth, and the paths to open."""
    store = Store(artifacts, resolve_scene(scene_name, data_root).name, preset)
    version = report.fingerprints

    def command(verb: str) -> str:  # the same scene, artifacts (and preset: the viewer's), quoted for a shell
        words = ["python", "pipeline.py", verb, "--scene", scene_name]
        if Path(artifacts).resolve() != Path(DEFAULT_ARTIFACTS).resolve():
            words += ["--artifacts", str(artifacts)]
        words += ["--data-root", str(data_root)] if data_root is not None else []
        return shlex.join(words + (["--preset", preset] if preset and verb == "view" else []))

    lines, total = [], 0.0
    for name, how in report.items():
        seconds = store.manifest(name, version[name])["wall_seconds"] if how == "computed" else 0.0
        total += seconds
        lines.append(f"  {name:<18} {'ran' if how == 'computed' else 'cached':<7}"
                     + (f"{seconds:8.1f} s" if how == "computed" else ""))
    ran = sum(how == "computed" for how in report.values())
    out = [f"{store.scene_dir.name}: {len(report)} stages, {ran} ran ({total:.0f} s), {len(report) - ran} cached", *lines]
    if "successors" in report:
        out += posed_lines(store.version_dir("successors", version["successors"]),
                           store.version_dir("schedule", version["schedule"]))
    if "evaluate" in report:
        ev = load_evaluation(store.version_dir("evaluate", version["evaluate"]))
        if ev.get("poses") and "summary" not in ev["poses"][-1]:  # e.g. 2 views posed: no Sim3 to score them
            final = ev["poses"][-1]
            out.append(f"poses ({final['label']}, {final['n_views']} views): not scored against ground truth, "
                       f"{final.get('skipped', 'no summary')}")
        elif ev.get("poses"):
            final = ev["poses"][-1]
            rot, centre = final["summary"]["rot_err_deg"], final["summary"].get("center_err_units", {})
            units = ev.get("geometry", {}).get("units", "")
            out.append(f"poses ({final['label']}, {final['n_views']} views, against ground truth after a Sim3): "
                       f"rotation {rot['mean']:.3f} deg mean, {rot['median']:.3f} median; centre "
                       f"{centre.get('mean', float('nan')):.3g} {units}".rstrip())
        if ev.get("intrinsics"):
            out.append(camera_line(ev["intrinsics"]))
        nvs = ev.get("novel_views", {}).get("summary", {})
        if nvs.get("psnr_masked") is not None:
            line = f"held-out views: masked PSNR {nvs['psnr_masked']:.2f} dB, SSIM {nvs.get('ssim_masked', 0):.3f}"
            if nvs.get("aligned_psnr_masked") is not None:
                line += (f" at the Sim3-mapped GT poses; {nvs['aligned_psnr_masked']:.2f} dB, SSIM "
                         f"{nvs.get('aligned_ssim_masked', 0):.3f} after test-time alignment")
            out.append(line)
        geo = ev.get("geometry", {})
        if geo.get("chamfer_units") is not None:
            out.append(f"surface: Chamfer {geo['chamfer_units']:.3g} {geo.get('units', '')} to {geo.get('reference', 'the reference')}")
    if "export" in report and store.current("export"):  # first: what a user takes away, in the input's frame
        export_dir = store.version_dir("export", store.current("export"))
        frame = json.loads((export_dir / FRAME).read_text())
        where = "the input's world" if frame["frame"] == "input" else "the method's unit-sphere frame"
        out.append(f"result:  {export_dir} (transforms.json, colmap/, mesh.glb, mesh.ply, sparse_points.ply; "
                   f"{where}, {frame['units']})")
        out.append(f"viewer:  {command('view')}")
    if "mesh" in report:
        mesh_dir = store.version_dir("mesh", version["mesh"])
        out += [f"mesh:    {mesh_dir / MESH} (the method's unit-sphere frame)",
                f"cameras: {mesh_dir / 'colmap'} (COLMAP text model, the method's frame)"]
    if "evaluate" in report:
        out.append(f"report:  {command('report')}")
    return "\n".join(out)


def posed_lines(successors_dir: Path, schedule_dir: Path) -> list[str]:
    """How many of the views meant to get a pose got one; a warning naming those that did not."""
    from manifoldneus.data import artifacts

    schedule = load_schedule_meta(schedule_dir)
    placed = artifacts.load_round_arrays(successors_dir / artifacts.FINAL_ROUND, ["placed"])["placed"].astype(bool)
    held = set(schedule["held_out_views"])
    meant = [v for v in schedule["views"] if v["view"] not in held]  # those outside the largest component too
    missing = [v["name"] for v in meant if not placed[v["view"]]]
    line = f"posed:   {len(meant) - len(missing)} of {len(meant)} views" + (
        f" ({len(held)} more held out for evaluation)" if held else "")
    if not missing:
        return [line]
    return [line, f"WARNING: {len(missing)} view(s) got no pose: {', '.join(missing[:8])}"
                  f"{' ...' if len(missing) > 8 else ''} (too few verified matches to the posed views: covisibility.png "
                  f"and the schedule stage's log show which)"]


def camera_line(intrinsics: dict) -> str:
    """One line on the camera the poses ended with (evaluation.json's ``intrinsics``): what it started
    from, and its error where the layout has a calibration."""
    start, final = intrinsics["start"], intrinsics["final"]
    line = (f"camera ({intrinsics['source']}): focal {final['focal_px']:.1f} px, principal point "
            f"({final['principal_point_px'][0]:.1f}, {final['principal_point_px'][1]:.1f})")
    if abs(start["focal_px"] - final["focal_px"]) > 1e-6 or start["principal_point_px"] != final["principal_point_px"]:
        line += (f"; self-calibrated from {start['focal_px']:.1f} px, ({start['principal_point_px'][0]:.1f}, "
                 f"{start['principal_point_px'][1]:.1f})")
    if final.get("distortion") and final["distortion"][0]:  # the self-calibration frees k1 only (SIMPLE_RADIAL)
        line += f"; lens distortion k1 {final['distortion'][0]:+.4f} (removed from the images)"
    if "focal_err_pct" in final:
        line += f"; ground truth {intrinsics['ground_truth']['focal_px']:.1f} px, {final['focal_err_pct']:.2f} % off"
    return line


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def explain(stage: str, fps: dict, store: Store) -> tuple[str, list[str]]:
    """(state, reasons): state is fresh | stale | cached | missing."""
    expected = fps[stage]["fingerprint"]
    current = store.current(stage)
    if current == expected:
        problems = store.damage(stage, current)
        return ("damaged", [*problems, f"rebuild: run --force {stage}"]) if problems else ("fresh", [])
    if current is None:
        if store.is_complete(stage, expected):
            return "cached", ["a complete version for these parameters exists; `run` reuses it"]
        return "missing", ["never computed"]
    old = store.manifest(stage, current)
    reasons = []
    now_p, old_p = _flatten(fps[stage]["params"]), _flatten(old.get("params", {}))
    for key in sorted(set(now_p) | set(old_p)):
        if now_p.get(key, "<absent>") != old_p.get(key, "<absent>"):
            reasons.append(f"param {key}: {old_p.get(key, '<absent>')!r} -> {now_p.get(key, '<absent>')!r}")
    if old.get("code") != fps[stage]["code"]:
        reasons.append("code of the stage (or a module it uses) changed")
    for up, content in fps[stage]["upstream_content"].items():
        if old.get("upstream_content", {}).get(up) != content:
            reasons.append(f"upstream {up} changed" if not content.startswith("recipe:")
                           else f"upstream {up} is not computed with these parameters")
    if old.get("inputs") != fps[stage].get("inputs"):
        reasons.append("input files changed")
    if store.is_complete(stage, expected):
        reasons.append("a complete version for the new parameters exists and will be reused")
    return "stale", reasons or ["fingerprint differs"]


def status(scene_name, overrides=(), profile=None, preset=None, artifacts=DEFAULT_ARTIFACTS,
           params_path=DEFAULT_PARAMS, data_root=None) -> dict[str, tuple[str, list[str]]]:
    stages = load_stages()
    scene = resolve_scene(scene_name, data_root)
    resolved = resolve_params(stages, params_path, overrides, profile, preset)
    stages = for_params(stages, resolved)
    store = Store(artifacts, scene.name, preset)
    fps = compute_fingerprints(stages, resolved, scene, store)
    return {name: explain(name, fps, store) for name in stages}


def verify(scene_name: str, artifacts=DEFAULT_ARTIFACTS, data_root=None, preset=None) -> dict[str, tuple[str, list]]:
    """Re-hash every file of each stage's current version against its manifest: stage -> (state,
    problems), state ok | DAMAGED | unverified (a manifest written before file hashes were
    recorded). Stages with no current version are left out."""
    scene = resolve_scene(scene_name, data_root)
    store = Store(artifacts, scene.name, preset)
    out = {}
    for name in load_stages():
        fp = store.pointed(name)
        if fp is None:
            continue
        if not store.is_complete(name, fp):  # the pointer names a version whose manifest cannot be read
            manifest = store.version_dir(name, fp) / MANIFEST
            out[name] = ("DAMAGED", [f"{manifest}: missing or not valid JSON; `run --force {name}` recomputes it"])
            continue
        if "files" not in store.manifest(name, fp):
            out[name] = ("unverified", ["its manifest predates file hashes; `run --force` it to record them"])
            continue
        problems = store.damage(name, fp, deep=True)
        out[name] = ("DAMAGED" if problems else "ok", problems)
    return out


def describe_artifact(path: Path) -> list[str]:
    lines = []
    for item in sorted(path.iterdir()):
        if item.suffix == ".zarr":
            import zarr

            group = zarr.open_group(str(item), mode="r")
            lines.append(f"  {item.name}/")
            for name, arr in sorted(group.arrays()):
                lines.append(f"      {name:<20} {str(arr.dtype):<8} {list(arr.shape)}")
            if group.attrs:
                lines.append(f"      attrs: {json.dumps(dict(group.attrs), default=str)[:200]}")
        elif item.is_dir():
            n = sum(1 for _ in item.rglob("*") if _.is_file())
            lines.append(f"  {item.name}/ ({n} files)")
        else:
            lines.append(f"  {item.name:<28} {item.stat().st_size / 1024:9.1f} KiB")
    return lines


def show(scene_name: str, stage: str, artifacts=DEFAULT_ARTIFACTS, data_root=None, preset=None) -> str:
    stages = load_stages()
    if stage not in stages:
        raise PipelineError(f"unknown stage {stage!r} (stages: {', '.join(stages)})")
    scene = resolve_scene(scene_name, data_root)
    store = Store(artifacts, scene.name, preset)
    fp = store.current(stage)
    if fp is None:
        raise PipelineError(f"stage {stage} has no current version for scene {scene.name}; run it first")
    m = store.manifest(stage, fp)
    path = store.version_dir(stage, fp)
    out = [
        f"{stage} @ {fp}   ({path})",
        f"profile {m.get('profile')}, preset {m.get('preset')}, started {m['started']}, "
        f"wall {m['wall_seconds']} s, cpu {m['cpu_seconds']} s, peak {m['peak_rss_mib']} MiB",
        f"upstream: {m['upstream']}",
        "params:",
    ]
    out += [f"  {k} = {v!r}" for k, v in _flatten(m["params"]).items()]
    out.append("metrics:")
    out += [f"  {k} = {v}" for k, v in _flatten(m["metrics"]).items()]
    out.append("files:")
    out += describe_artifact(path)
    return "\n".join(out)


def view(scene_name: str, artifacts=DEFAULT_ARTIFACTS, data_root=None, preset=None, out: Path | None = None,
         max_faces: int | None = None) -> tuple[Path, dict]:
    """Write the viewer page of a scene's run: its ``export`` stage's current version and the
    versions that one was computed from (:meth:`Store.lineage`). Default path:
    ``<artifacts>/<scene>/viewer/viewer.html`` (``viewer@<preset>.html`` for a preset). Returns
    (path, what the page holds: camera counts, triangles, bytes)."""
    from manifoldneus.output import viewer

    scene = resolve_scene(scene_name, data_root)
    store = Store(artifacts, scene.name, preset)
    versions = store.lineage("export", beside=("reference",))
    if not versions:
        for_preset = f" --preset {preset}" if preset else ""
        raise PipelineError(f"scene {scene.name}{for_preset} has no exported result to view in {Path(artifacts)}; "
                            f"run: {cli_hint('run', scene_name, artifacts=artifacts, data_root=data_root, preset=preset)}")
    for stage, folder in versions.items():
        _refuse_damaged(store, stage, folder.name, cli_hint("run", scene_name, "--until", stage, "--force", stage,
                                                            artifacts=artifacts, data_root=data_root, preset=preset))
    path = Path(out) if out else store.scene_dir / "viewer" / ("viewer.html" if preset is None else f"viewer@{preset}.html")
    title = scene.name + (f" ({preset})" if preset else "")
    return path, viewer.write_page(versions, path, title, max_faces or viewer.MAX_FACES)
