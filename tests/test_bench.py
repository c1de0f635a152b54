"""The bench on the tiny synthetic scene: every system over two seeds in one run, one JSON, one
table with the spread over seeds and ratio columns; and README's Results generated from that JSON,
between the markers only."""
from __future__ import annotations

import contextlib
import io
import itertools
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import ONE_SUCCESSOR_ROUND, TINY

from bench import bench, match_precision, pose_observability, results_md
from manifoldneus.data import synthetic

POSE_ERRORS = ("rot_err_deg_mean", "rot_err_deg_median", "center_err_units_mean", "center_err_units_median",
               "pre_r_deg_mean", "pre_t_deg_mean")
NEURAL_SYSTEMS = ("manifoldneus", "neus-barf", "neus-colmap", "sfm-all")


@pytest.fixture(scope="module")
def tiny_bench(tmp_path_factory):
    """(output dir, printed text) of `bench.py` on the tiny scene with every system, seeds 0 and 1."""
    tmp = tmp_path_factory.mktemp("bench")
    argv = ["--scene", "synthetic", "--seeds", "0,1", "--artifacts", str(tmp / "artifacts"), "--out-dir", str(tmp / "out")]
    # half TINY's anchor and surface iterations: the bench's bookkeeping is under test here, not the fields
    # (the observability test's field still tells a turned pose from a swung one: colour L1 0.292 against 0.273)
    fewer = ("anchors.iters=20", "surface.iters=20")
    argv += [arg for override in (*TINY, ONE_SUCCESSOR_ROUND, *fewer) for arg in ("--set", override)]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert bench.main(argv) == 0
    return tmp / "out", printed.getvalue()


def bench_json(out_dir: Path) -> tuple[Path, dict]:
    [path] = (out_dir / "synthetic").glob("*.json")
    return path, json.loads(path.read_text())


def test_json_has_every_system_with_finite_pose_errors(tiny_bench):
    path, result = bench_json(tiny_bench[0])
    assert path.stem == result["date"][:10]  # a full bench: <date>.json, what README's Results read
    systems = result["systems"]
    assert list(systems) == list(bench.SYSTEMS)
    for key, s in systems.items():
        assert all(math.isfinite(s[e]) for e in POSE_ERRORS), key
        assert s["wall_seconds"] > 0 and s["peak_rss_mib"] > 0 and not s["missing_stages"]
        assert all(math.isfinite(v) for v in s["over_pycolmap"].values()), key
    base = systems["pycolmap"]
    for key in NEURAL_SYSTEMS:  # each ratio is the system's figure over pycolmap's, in the same run
        ratios = systems[key]["over_pycolmap"]
        assert ratios["rotation"] == pytest.approx(systems[key]["rot_err_deg_mean"] / base["rot_err_deg_mean"])
        assert ratios["centre"] == pytest.approx(systems[key]["center_err_units_mean"] / base["center_err_units_mean"])
        assert ratios["time"] == pytest.approx(systems[key]["wall_seconds"] / base["wall_seconds"])
    for key in NEURAL_SYSTEMS:
        assert math.isfinite(systems[key]["chamfer_units"]) and systems[key]["psnr"] > 0
        assert 0 < systems[key]["colour_spread"] < 1  # beside Chamfer, from evaluate
        assert systems[key]["psnr_aligned"] > 0  # scored again after test-time alignment
    header = bench.systems_table(result).splitlines()[0].split(" | ")
    chamfer = next(i for i, name in enumerate(header) if name.startswith("Chamfer"))
    assert header[chamfer + 1] == "colour spread"
    # the front-end is one version, computed once in this run and charged to every NeuS system
    features = [systems[key]["stages"]["features"] for key in NEURAL_SYSTEMS]
    assert len({f["fingerprint"] for f in features}) == 1 and all(f["computed_in_this_bench"] for f in features)
    assert "reference" in systems["neus-colmap"]["stages"] and "reference" not in systems["manifoldneus"]["stages"]
    # sfm-all holds the mapper's poses of every training view: its final round is its initialisation
    store = bench.runner.Store(tiny_bench[0].parent / "artifacts", "synthetic", "sfm-all")
    ev = json.loads((store.version_dir("evaluate", store.current("evaluate")) / "evaluation.json").read_text())
    assert [r["label"] for r in ev["poses"]][:2] == ["initial", "anchors"]
    first, last = ev["poses"][0]["summary"], ev["poses"][-1]["summary"]
    for key in ("rot_err_deg", "center_err_units"):  # a round that learns no pose keeps its start to the last bit
        assert last[key]["mean"] == first[key]["mean"], key
    assert ev["poses"][-1]["n_views"] > 3 and last["rot_err_deg"]["mean"] > 0
    assert result["summary"]["front_end_over_pycolmap"] > 0
    # NeuS on fixed poses is compared at equal iterations: as many as the method's rounds together, per seed
    for seed, systems_of_seed in result["per_seed"].items():
        ours = systems_of_seed["manifoldneus"]["field_iters"]
        assert ours > 0 and all(systems_of_seed[k]["field_iters"] == ours for k in ("neus-colmap", "sfm-all")), seed
    assert "equal iterations" in bench.comparison_markdown(result)


def test_each_figure_is_the_mean_over_seeds_with_its_spread(tiny_bench):
    _, result = bench_json(tiny_bench[0])
    assert result["seeds"] == [0, 1] and list(result["per_seed"]) == ["0", "1"]
    for key, s in result["systems"].items():
        runs = [result["per_seed"][seed][key] for seed in ("0", "1")]
        for figure in ("rot_err_deg_mean", "wall_seconds"):
            values = [r[figure] for r in runs]
            assert s[figure] == pytest.approx(sum(values) / 2), (key, figure)
            assert s["spread"][figure]["std"] == pytest.approx(abs(values[0] - values[1]) / math.sqrt(2)), (key, figure)
    # the seeds train differently (the front-end and pycolmap do not depend on it)
    ours = [result["per_seed"][seed]["manifoldneus"] for seed in ("0", "1")]
    assert ours[0]["psnr"] != ours[1]["psnr"]
    assert ours[0]["stages"]["features"]["fingerprint"] == ours[1]["stages"]["features"]["fingerprint"]
    # the GT-pose reference surface (Chamfer's yardstick) has a seed of its own and reads only the
    # pixels of the method's ingest: one version for both seeds and for the photos alone
    store = bench.runner.Store(tiny_bench[0].parent / "artifacts", "synthetic")
    versions = [d for d in store.stage_dir("reference_surface").iterdir() if not d.name.startswith("current")]
    assert len(versions) == 1, versions
    # photos alone: the layout's intrinsics and masks dropped, yet every figure scored
    alone = result["systems"]["photos-alone"]
    assert alone["psnr"] > 0 and math.isfinite(alone["chamfer_units"])
    assert alone["stages"]["ingest"]["fingerprint"] != result["systems"]["manifoldneus"]["stages"]["ingest"]["fingerprint"]


def test_where_the_rounds_keep_sfm_alls_poses_the_surface_is_neus_on_them_to_the_bit(tiny_bench):
    """The last round restarts every view from the matches' SfM over all views (sfm-all's, same seed) and the
    surface's field takes that SfM's gauge: the views the round kept at their start are trained on sfm-all's
    poses to the float32 bit, and where it kept none the surface is NeuS on sfm-all's poses, parameter for
    parameter."""
    import torch

    from manifoldneus.data import artifacts, io as mio
    from manifoldneus.geometry import cameras

    root = tiny_bench[0].parent / "artifacts"
    trained = {}
    for preset in (None, "sfm-all"):
        store = bench.runner.Store(root, "synthetic", preset)
        versions = store.lineage("surface")
        surface = artifacts.load_surface(versions["surface"])  # the last round's poses and the field's frame
        w2c = cameras.transform_w2c(surface["w2c"], *cameras.sim3_from_matrix(surface[artifacts.FIELD_FROM_MODEL]))
        trained[preset] = (mio.load_json(versions["surface"] / "manifest.json")["params"]["run"]["seed"], surface,
                           mio.load_json(versions["successors"] / artifacts.FINAL_ROUND / artifacts.ROUND_META),
                           w2c[:, :3, :4].astype(np.float32),  # [N,3,4] as the trainer holds them
                           torch.load(versions["surface"] / artifacts.MODEL, weights_only=False))
    (seed, ours, info, ours_w2c, ours_model), (sfm_seed, sfm, _, sfm_w2c, sfm_model) = trained[None], trained["sfm-all"]
    assert seed == sfm_seed and "round_from_sfm" in info
    ids = np.flatnonzero(ours["optimised"])
    assert np.array_equal(ids, np.flatnonzero(sfm["optimised"]))
    kept = info["train"]["guard"]["kept_views"]
    held = np.setdiff1d(ids, kept)
    assert len(held) > 0 and np.array_equal(ours_w2c[held], sfm_w2c[held])
    if not kept:
        for part in ("field", "background"):
            assert all(torch.equal(ours_model[part][k], sfm_model[part][k]) for k in sfm_model[part]), part


def test_table_has_one_row_per_system_with_ratio_columns(tiny_bench):
    lines = tiny_bench[1].splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| system |"))
    block = itertools.takewhile(lambda line: line.startswith("|"), lines[start:])  # up to the blank line
    table = [[cell.strip() for cell in line.strip("|").split(" | ")] for line in block]
    header, rows = table[0], table[2:]
    for column in ("rotation ÷ pycolmap", "centre ÷ pycolmap", "time ÷ pycolmap"):
        assert column in header
    assert [r[0] for r in rows] == [s.label for s in bench.SYSTEMS.values()]
    assert all(len(r) == len(header) for r in rows)
    ours = rows[0]
    assert " ± " in ours[header.index("PSNR dB")] and "seeds 0, 1" in tiny_bench[1]
    pycolmap = rows[-1]
    assert [pycolmap[header.index(c)] for c in header if c.endswith("÷ pycolmap")] == ["1.00"] * 3


def test_pose_observability_of_the_tracks_and_the_field(tiny_bench, tmp_path):
    """bench/pose_observability.py on the bench's artifacts: sfm-all's tracks rebuilt and the final field
    loaded, each scored under sfm-all's, the ground truth's and the method's poses and two controls of
    a known rotation."""
    art = tiny_bench[0].parent / "artifacts"
    with contextlib.redirect_stdout(io.StringIO()):
        assert pose_observability.main(["--scenes", "synthetic", "--artifacts", str(art), "--out-dir", str(tmp_path),
                                        "--control-deg", "1", "--rays-per-view", "256"]) == 0
    [path] = (tmp_path / "observability").glob("pose-observability-*.json")
    scene = json.loads(path.read_text())["scenes"]["synthetic"]
    rows, field = scene["poses"], scene["field"]
    assert scene["final_seed"] == 1 and scene["tracks"] > 20
    assert list(rows)[:3] == ["sfm-all", "ground truth", "ManifoldNeuS final"]
    assert rows["ground truth"]["rot_err_deg"] < 1e-4 and rows["sfm-all"]["rot_err_deg"] > 0
    # a degree about each camera's centre moves every track's image: the error grows several-fold; the same
    # degree about the object keeps it in view and costs the tracks less
    assert rows["sfm-all turned"]["median_px"] > 3 * rows["sfm-all"]["median_px"]
    assert rows["sfm-all"]["median_px"] < rows["sfm-all swung"]["median_px"] < rows["sfm-all turned"]["median_px"]
    # the field was fitted under its final poses: turning them costs its colour loss more than swinging them
    assert field["final"]["colour_l1"] < field["turned"]["colour_l1"]
    assert field["swung"]["colour_l1"] < field["turned"]["colour_l1"]
    assert 0 < scene["swing_over_turn"]["tracks"] < 1 and scene["swing_over_turn"]["field"] < 1


def test_a_failed_system_is_named_under_the_table(tiny_bench):
    _, result = bench_json(tiny_bench[0])
    assert not any("failed" in n for n in bench.notes(result))
    result["systems"]["photos-alone"]["error"] = "seed 0: stage successors failed: FloatingPointError: diverged"
    assert "ManifoldNeuS, photos alone failed (seed 0: stage successors failed: FloatingPointError: diverged): " \
        "its row shows no mean." in bench.notes(result)


def test_the_surface_targets_per_seed_come_from_each_seeds_figures(tiny_bench):
    _, result = bench_json(tiny_bench[0])
    assert result["targets"] == bench.targets(result)  # stored as computed: a README from the JSON shows the same
    chamfer = next(t for t in result["targets"] if t["target"].startswith("Chamfer <= NeuS on sfm-all"))
    for row in chamfer["per_seed"]:
        seed = result["per_seed"][str(row["seed"])]
        assert (row["value"], row["limit"]) == (seed["manifoldneus"]["chamfer_units"], seed["sfm-all"]["chamfer_units"])
        assert row["met"] == (row["value"] <= row["limit"] * (1 + bench.CHAMFER_TIE))
    assert chamfer["met_every_seed"] == all(r["met"] for r in chamfer["per_seed"])
    assert not any("photos alone" in t["target"] for t in result["targets"])  # a DTU object's target only
    # the same figures as a DTU object's: photos alone against 1.3x the masked run, missed on one seed only
    dtu = json.loads(json.dumps({**result, "scene": "scan24_idr"}))
    masked = dtu["per_seed"]["1"]["manifoldneus"]["chamfer_units"]
    dtu["per_seed"]["0"]["photos-alone"]["chamfer_units"] = dtu["per_seed"]["0"]["manifoldneus"]["chamfer_units"]
    dtu["per_seed"]["1"]["photos-alone"]["chamfer_units"] = 1.31 * masked
    [alone] = [t for t in bench.targets(dtu) if "photos alone" in t["target"]]
    assert [r["met"] for r in alone["per_seed"]] == [True, False] and not alone["met_every_seed"]
    assert alone["per_seed"][1]["limit"] == pytest.approx(1.3 * masked)
    line = bench.targets_markdown(dtu)
    assert line.startswith("scan24_idr targets: ") and "MISSED (seed 0 " in line
    del dtu["per_seed"]["0"]["photos-alone"]  # a bench without the system: the target is left out, not failed
    assert not any("photos alone" in t["target"] for t in bench.targets(dtu))


def test_partial_runs_do_not_overwrite_the_full_bench(tmp_path):
    full = {"scene": "s", "date": "2026-01-02T10:00:00", "until": None, "systems": dict.fromkeys(bench.SYSTEMS)}
    assert bench.result_path(full, tmp_path).name == "2026-01-02.json"
    subset = {**full, "systems": {"pycolmap": None}, "until": "evaluate_poses"}
    assert bench.result_path(subset, tmp_path).name == "2026-01-02-pycolmap-until-evaluate_poses.json"


def test_results_md_replaces_between_markers_only_and_is_idempotent(tiny_bench, tmp_path):
    path, result = bench_json(tiny_bench[0])
    bench_dir = tmp_path / "bench"
    (bench_dir / "synthetic").mkdir(parents=True)
    shutil.copy(path, bench_dir / "synthetic" / "2026-01-01.json")
    # an older-format file is newer: the newest file with systems is used; partial runs never are
    (bench_dir / "synthetic" / "2026-01-02.json").write_text(json.dumps({"scene": "synthetic", "stages": {}}))
    (bench_dir / "synthetic" / "2026-01-03-pycolmap.json").write_text(json.dumps({**result, "systems": {}}))
    before = "# project\n\n## Results\n\n"
    after = "\n\nHow we compare: written by hand.\n"
    readme = tmp_path / "README.md"
    readme.write_text(f"{before}{results_md.BEGIN}\nold numbers\n{results_md.END}{after}")
    # the refinement page too goes to a copy: the repository's own must not take this bench folder's (no
    # refinement bench) while other tests compare it with `make results`
    refinement = tmp_path / "REFINEMENT.md"
    shutil.copy(bench.ROOT / "docs" / "REFINEMENT.md", refinement)
    argv = ["--readme", str(readme), "--bench-dir", str(bench_dir), "--refinement-doc", str(refinement)]
    with contextlib.redirect_stdout(io.StringIO()):
        assert results_md.main(argv) == 0
        text = readme.read_text()
        assert results_md.main(argv) == 0
    assert readme.read_text() == text  # idempotent
    assert "No refinement bench yet" in refinement.read_text()
    assert text.startswith(before + results_md.BEGIN) and text.endswith(results_md.END + after)
    inside = text[len(before):-len(after)]
    assert "old numbers" not in inside and "2026-01-01.json" in inside
    assert "| synthetic | ManifoldNeuS |" in inside and "time ÷ pycolmap" in inside and result["date"][:10] in inside
    assert " ± " in inside and "stage (wall s" not in inside  # the spread over seeds; the stage table stays out
    assert "synthetic targets: Chamfer <= NeuS on sfm-all's poses at equal iterations: " in inside
    # the columns' definitions are linked, not repeated; what depends on the figures stays
    assert "docs/BENCHMARKS.md#the-columns" in inside and "Peak memory:" not in inside and "Times: sum" in inside
    assert "### The columns" in (bench.ROOT / "docs" / "BENCHMARKS.md").read_text()
    with pytest.raises(ValueError):
        results_md.replace_between_markers("no markers here", "body")


def test_match_precision_measures_a_known_offset_and_the_refinements_undo_it(tmp_path):
    """bench/match_precision.py: SIFT's matches land near the exact correspondence, a keypoint moved by 1 px
    measures 1 px off, and the affine patch alignment brings it back."""
    assert match_precision.main(["--resolution", "128", "--views", "12", "--neighbours", "2", "--out-dir", str(tmp_path)]) == 0
    [path] = (tmp_path / "observability").glob("match-precision-*.json")
    rows = json.loads(path.read_text())["rows"]
    raw = rows["SIFT (as matched)"]
    assert raw["matches"] > 50 and raw["median_px"] < 0.5
    scene = synthetic.make_scene(seed=0, n_views=12, resolution=128)
    moved = match_precision.match_errors(scene, neighbours=2, offset=(1.0, 0.0))
    assert 0.8 < np.median(moved["SIFT (as matched)"]) < 1.3
    assert np.median(moved["+ affine ECC 17 px"]) < 0.6 * np.median(moved["SIFT (as matched)"])


def test_the_step_profile_counts_launches_host_reads_and_samples():
    """bench.profile_step on the synthetic scene, a few tiny steps: operators launched, host reads (the
    trainer reads its loss back every step) and samples per step, as its JSON records them."""
    import argparse

    from bench import profile_step

    args = argparse.Namespace(scene="synthetic", rays=64, size=32, warm=2, steps=2, profile_steps=2, iters=50,
                              threads=1, set=[])
    run = profile_step.one_seed(args, 0)
    assert run["launches_per_step"] > 50  # a NeuS step is hundreds of small operators
    assert run["host_reads_per_step"].get("__float__", 0) >= 1  # the loss read back per step
    assert run["samples_per_step"] == run["evaluated_per_ray"] * 64 > 64
    import torch

    assert torch.Tensor.item.__name__ == "item"  # the counters are gone again
