"""bench/sweep.py: every table of the supplement's experiments runs at a reduced size (2 values) on
the tiny synthetic scene, prints a table with finite numbers and writes its JSON; settings share
one artifacts folder, so the cache shows (an alpha change reuses the front-end)."""
from __future__ import annotations

import contextlib
import json
import math
import shutil
from io import StringIO
from pathlib import Path

import pytest

import runner
from bench import sweep
from manifoldneus.data import io
from tests.test_end_to_end import TINY

# On top of TINY: one successor round (the tables read the anchor and the first successor round
# only), fewer iterations and no surface training of its own (the mesh is the last round's field's), so
# that each back-end rerun takes seconds; poses learn from the first iteration (the fast profile's frozen
# first half would leave 10-iteration rounds at their initial poses).
SWEEP_TINY = [*TINY, "schedule.successors_per_round=20", "anchors.iters=10", "successors.iters=10",
              "successors.final_iters=0", "surface.iters=0", "reference_surface.iters=10", "anchors.pose_start_frac=0",
              "successors.pose_start_frac=0"]
NOT_REACHED_BY_ALPHA = ("ingest", "ground_truth", "features", "matching", "covisibility", "spectral", "reference",
                        "evaluate_poses", "reference_surface")


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    return root / "artifacts", root / "bench"


def run(dirs, table, values, capsys) -> tuple[list[dict], str]:
    """The sweep's rows and printed table, after checking both and the JSON."""
    artifacts, out = dirs
    result = sweep.run_sweep(table, "synthetic", values, SWEEP_TINY, artifacts, out_root=out)
    return checked(result, capsys.readouterr().out, table, values, out)


def checked(result, printed, table, values, out) -> tuple[list[dict], str]:
    rows = result["settings"]
    assert [r["value"] for r in rows] == values
    for r in rows:
        assert "error" not in r, r.get("error")
        assert all(math.isfinite(x) for x in r["errors"].values()), r["errors"]
        assert f"| {r['label']} |" in printed
    path = Path(result["json"])
    assert path.parent == out / "synthetic" and path.name.startswith(f"sweep_{table}_")
    saved = json.loads(path.read_text())
    assert saved["table"] == table and len(saved["settings"]) == 2 and saved["markdown"] in printed
    return rows, printed


A3_VALUES = ["0.65", "0.35"]


@pytest.fixture(scope="module")
def a3_serial(dirs):
    """(result, printed table) of the A3 sweep run serially into the module's fresh artifacts folder: its
    own test checks the cache, the Dask test that a cluster gives the same JSON."""
    printed = StringIO()
    with contextlib.redirect_stdout(printed):
        result = sweep.run_sweep("A3", "synthetic", A3_VALUES, SWEEP_TINY, dirs[0], out_root=dirs[1])
    return result, printed.getvalue()


def test_a3_alpha_reuses_the_front_end(a3_serial, dirs):
    (_, second), _ = checked(*a3_serial, "A3", A3_VALUES, dirs[1])
    assert all(second["stages"][s] == "reused" for s in NOT_REACHED_BY_ALPHA)
    assert {s for s, how in second["stages"].items() if how == "computed"} == {
        "schedule", "anchors", "successors", "surface", "mesh", "evaluate", "export"}
    assert second["cost_seconds"] > second["wall_seconds"]  # the cache saved the front-end's time


# What differs between two runs of the same sweep: times, paths, which run computed a shared
# stage, and the versions after the first trained stage (its files record its training time).
RUN_FACTS = ("date", "total_wall_seconds", "artifacts", "markdown", "json", "executor", "workers", "wall_seconds",
             "cost_seconds", "stages", "fingerprints")


def test_a_sweep_on_a_local_cluster_gives_the_serial_json(a3_serial, dirs, tmp_path, capsys):
    pytest.importorskip("distributed")
    # the serial run's stages up to the anchors, copied: the two workers train the settings' successors anew
    for stage in (*NOT_REACHED_BY_ALPHA, "schedule", "anchors"):
        shutil.copytree(dirs[0] / "synthetic" / stage, tmp_path / "artifacts" / "synthetic" / stage, symlinks=True)
    result = sweep.run_sweep("A3", "synthetic", A3_VALUES, SWEEP_TINY, tmp_path / "artifacts",
                             out_root=tmp_path / "bench", executor_name="dask", workers=2)
    err = capsys.readouterr().err
    assert "dask: LocalCluster, 2 workers x 1 thread, dashboard http" in err
    assert "[3/3] alpha = " in err  # a progress line per task: the shared stages, then the two settings
    serial, dask = (json.loads(Path(r["json"]).read_text()) for r in (a3_serial[0], result))
    assert dask["executor"] == "dask" and [r["label"] for r in dask["settings"]] == ["alpha = 0.65", "alpha = 0.35"]
    assert all("error" not in r for r in dask["settings"])
    # pose errors, rounds, views, schedule: the same
    assert io.without_keys(dask, RUN_FACTS) == io.without_keys(serial, RUN_FACTS)
    for ours, theirs in zip(dask["settings"], serial["settings"]):  # from the same versions
        assert ours["fingerprints"]["anchors"] == theirs["fingerprints"]["anchors"]
    assert all(how == ("reused" if s in ("schedule", "anchors") else "computed") for r in dask["settings"]
               for s, how in r["stages"].items() if s not in NOT_REACHED_BY_ALPHA)


@pytest.mark.parametrize("table, values", [
    ("A4", ["K=30", "M=20"]),  # K = 30 % is the default, M = 20 SWEEP_TINY's own setting
    ("A5", ["full", "lam=0.3"]),  # lambda = 0.3 with every part on is the default run
])
def test_settings_that_name_one_version_share_it(dirs, capsys, table, values):
    (first, second), printed = run(dirs, table, values, capsys)
    assert set(second["stages"].values()) == {"reused"} and "none (all reused)" in printed
    assert second["errors"] == first["errors"] and second["fingerprints"] == first["fingerprints"]


def resolved(dirs, row, stage) -> dict:
    """The resolved parameters recorded in the manifest of the version a sweep row used."""
    artifacts, _ = dirs
    store = runner.Store(artifacts, "synthetic")
    return json.loads((store.version_dir(stage, row["fingerprints"][stage]) / "manifest.json").read_text())["params"]


def test_a6_losses_without_priors(dirs, capsys):
    (everything, recon), printed = run(dirs, "A6", ["all", "recon"], capsys)
    # the setting reached the stage: recon switches the prior terms off in what anchors resolved
    assert resolved(dirs, recon, "anchors")["loss"]["w_depth"] == 0.0
    assert resolved(dirs, recon, "anchors")["loss"]["w_normal"] == 0.0
    assert resolved(dirs, everything, "anchors")["loss"]["w_depth"] > 0
    # the synthetic scene has no mono priors: the depth and normal terms are off in both rows
    assert "no monocular depth or normal priors" in printed
    assert recon["stages"]["reference_surface"] == "computed"  # it shares the `loss` section
    assert recon["errors"] == pytest.approx(everything["errors"])


def test_a7_strategies(dirs, capsys):
    (fps, mavos), _ = run(dirs, "A7", ["FPS-E", "MaVOS-SE"], capsys)
    assert fps["stages"]["schedule"] == "computed"
    assert (resolved(dirs, fps, "schedule")["schedule"]["strategy"], resolved(dirs, fps, "schedule")["schedule"]["coverage"]) == ("fps", "E")
    assert (resolved(dirs, mavos, "schedule")["schedule"]["strategy"], resolved(dirs, mavos, "schedule")["schedule"]["coverage"]) == ("mavos", "SE")


def test_sparse_views(dirs, capsys):
    (every, second), _ = run(dirs, "sparse", ["1", "2"], capsys)
    assert (every["views"]["total"], second["views"]["total"]) == (20, 10)
    # none held out: every view is an input (holdout_every 8 would hold views 0 and 8 out)
    artifacts, _ = dirs
    schedule_dir = runner.Store(artifacts, "synthetic").version_dir("schedule", second["fingerprints"]["schedule"])
    assert json.loads((schedule_dir / "schedule.json").read_text())["held_out_views"] == []
    assert second["stages"]["ingest"] == second["stages"]["ground_truth"] == "computed"


def test_a_tagged_sweep_from_perturbed_anchors(dirs, capsys):
    artifacts, out = dirs
    result = sweep.run_sweep("A3", "synthetic", ["0.65"], [*SWEEP_TINY, "anchors.perturb_rot_deg=[3,5]",
                                                           "anchors.perturb_centre_frac=0.05"],
                             artifacts, out_root=out, tag="perturbed")
    assert Path(result["json"]).name.startswith("sweep_A3_perturbed_") and "[perturbed]" in result["markdown"]
    (row,) = result["settings"]
    initial = next(r for r in row["rounds"] if r["label"] == "initial")["summary"]["rot_err_deg"]["mean"]
    assert initial > 2.0  # the synthetic scene's matches give ~0.2 deg; the perturbation adds 3-5 deg
    assert f"| {initial:.3f} |" in capsys.readouterr().out


def test_every_default_setting_resolves():
    """Each table's settings are valid overrides and distinct (no run needed)."""
    stages = runner.load_stages()
    for name, table in sweep.TABLES.items():
        settings = sweep.settings_for(name)
        assert len({s.label for s in settings}) == len({s.overrides for s in settings}) == len(settings), name
        for s in settings:
            runner.resolve_params(stages, overrides=list(s.overrides))
        assert set(table.paper) <= {s.label for s in settings} | {f"M = {m}" for m in (15, 25)}, name


@pytest.mark.parametrize("table, value, message", [
    ("A3", "high", "not a number"), ("A4", "N=3", "K=<anchor percent>"), ("A5", "eta", "lam=<lambda>"),
    ("A6", "rgb", "recon, depth, normal, all"), ("A7", "FPS", "FPS-E"), ("sparse", "1.5", "whole number"),
    ("A9", "1", "unknown table"),
])
def test_bad_values_name_what_is_accepted(table, value, message):
    with pytest.raises(sweep.SweepError, match=message):
        sweep.settings_for(table, [value])


def test_cli_rejects_a_bad_value_before_running(tmp_path, capsys):
    assert sweep.main(["A5", "--values", "eta", "--scene", "synthetic", "--artifacts", str(tmp_path)]) == 2
    assert "lam=<lambda>" in capsys.readouterr().err and not (tmp_path / "synthetic").exists()


def test_table_with_a_failed_row_and_the_trend_against_the_paper():
    def row(alpha, rot_anchors):
        errors = dict.fromkeys((c.key for c in sweep.COLUMNS), None) | {"rot_anchors": rot_anchors}
        return {"label": f"alpha = {alpha:.2f}", "errors": errors, "stages": {"schedule": "computed"},
                "views": {"anchors": 15, "first_successor_round": None, "total": 49}, "wall_seconds": 1.0,
                "cost_seconds": 2.0, "units": "mm", "units_per_scene_unit": 150.0, "priors": {}}

    rows = [row(1.0, 3.0), row(0.65, 1.0), row(0.35, 2.0),
            {"label": "alpha = 0.50", "error": "RuntimeError: no anchors\nat line 3"}]
    text = sweep.markdown({"table": "A3", "scene": "scan24", "profile": "fast", "settings": rows})
    # the supplement's values beside ours, also where ours are missing
    assert "| alpha = 0.65 | – | 1.000 [3.883] | – [1.076] | – [0.225] | – [0.050] | 15 / – / 49 |" in text
    assert "| alpha = 0.50 | failed: RuntimeError: no anchors |" in text and "1 unit = 150 mm" in text
    # ours rank 1.00 > 0.35 > 0.65, the supplement's 0.35 > 1.00 > 0.65
    assert "ΔR anc. (deg): lowest here `alpha = 0.65`, lowest in the supplement `alpha = 0.65`; " \
           "rank correlation with the supplement +0.50 over 3 settings" in text
