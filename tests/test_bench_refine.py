"""bench/bench_refine.py on the tiny synthetic scene: two seeds, the JSON and the table."""
from __future__ import annotations

import json

import pytest

from bench import bench_refine
from tests.test_end_to_end import TINY


def test_refinement_bench_two_seeds(tmp_path, tiny_copy, capsys):
    # seed 0's method run is the TINY run: its stages are reused
    over = [f"--set={o}" for o in TINY]
    assert bench_refine.main(["--scenes", "synthetic", "--seeds", "0,1", "--reference-seeds", "0", "--gt-pose", *over,
                              "--artifacts", str(tiny_copy), "--out-dir", str(tmp_path / "bench"),
                              "--label", "tiny"]) == 0
    printed = capsys.readouterr().out
    (path,) = (tmp_path / "bench" / "refine").glob("tiny-*.json")
    result = json.loads(path.read_text())
    runs = result["scenes"]["synthetic"]["runs"]
    assert result["grid_kernel"] == "fused"  # the kernel make setup builds; a fallback would be recorded here
    assert [r["seed"] for r in runs] == [0, 1]
    for r in runs:
        labels = [x["label"] for x in r["rounds"]]
        assert labels[:2] == ["initial", "anchors"] and labels[-1].startswith("round_")
        assert all("start" in x for x in r["rounds"][1:])  # every round: its start and its end
        assert r["placement"]["rot_deg"] > 0 and r["pycolmap"]["rot_deg"] is not None
        # every trained round tested each of its views' pose update on its held-out tracks
        assert all(0 <= x["kept"] <= x["checked"] == x["n_views"] for x in r["rounds"][1:])
        assert r["stage_seconds"]["anchors"] > 0
        assert r["psnr_masked_aligned"] > 0  # held-out views scored again after test-time alignment
    # the GT-pose NeuS at the surface's iterations, trained once (its own seed): both seeds read it
    assert runs[0]["gt_pose_iters"] == runs[0]["surface_iters"] == 40 and runs[0]["rounds_iters"] > 40
    assert runs[1]["gt_pose_psnr_masked"] == runs[0]["gt_pose_psnr_masked"]
    # sfm-all: poses for every seed, NeuS on them (its surface stage) for the reference seed only
    assert runs[0]["sfm_all"]["psnr_masked"] > 0 and "psnr_masked" not in runs[1]["sfm_all"]
    assert all(r["sfm_all"]["rot_deg"] > 0 for r in runs)
    s = result["scenes"]["synthetic"]["summary"]
    finals = [r["final"]["rot_deg"] for r in runs]  # the summary is the seeds' mean and sample std
    assert s["final_rot_deg"]["n"] == 2 and s["final_rot_deg"]["mean"] == pytest.approx(sum(finals) / 2)
    assert s["final_rot_deg"]["std"] == pytest.approx(abs(finals[0] - finals[1]) / 2 ** 0.5)
    assert {t["target"] for t in result["scenes"]["synthetic"]["targets"]} >= {
        "final <= 0.5 x initialisation", "spread over seeds <= 0.02 deg", "final <= 0.85 x sfm-all",
        "final centre <= sfm-all's", "final relative rotation (PRE_r) <= sfm-all's",
        "Chamfer <= NeuS on sfm-all's poses at equal iterations",
        "aligned held-out PSNR >= NeuS on sfm-all's poses at equal iterations"}
    # the surface against NeuS on sfm-all's poses: the seed that trains it, both figures of both
    surface = {t["target"]: t for t in result["scenes"]["synthetic"]["targets"]}
    chamfer = surface["Chamfer <= NeuS on sfm-all's poses at equal iterations"]["per_seed"]
    assert [x["seed"] for x in chamfer] == [0] and chamfer[0]["value"] == runs[0]["chamfer"] > 0
    assert chamfer[0]["limit"] == runs[0]["sfm_all"]["chamfer"] > 0
    assert runs[0]["sfm_all"]["psnr_masked_aligned"] > 0 and s["sfm_all_chamfer"]["n"] == 1
    # the alignment-free comparison: relative rotations over view pairs, per seed and summarised
    assert all(r["final"]["pre_r_deg"] > 0 and r["sfm_all"]["pre_r_deg"] > 0 for r in runs)
    assert s["final_pre_r_deg"]["mean"] == pytest.approx(sum(r["final"]["pre_r_deg"] for r in runs) / 2)
    assert "| synthetic | 0,1 |" in printed and "±" in printed
    # docs/REFINEMENT.md's current figures: the refinement table, each seed's targets
    from bench import results_md

    md = results_md.refinement_markdown(tmp_path / "bench", root=tmp_path)
    assert "| synthetic | 0,1 |" in md and "synthetic targets:" in md


def test_the_seeds_share_one_gt_pose_training_and_the_summary_counts_it_once(tmp_path):
    """The GT-pose NeuS has a seed of its own (`reference_surface.seed`): runs of several seeds that read one
    training count it once (no "± 0.00" that reads as three trainings), a second training counts again."""
    from bench import results_md
    from manifoldneus.data import io

    result = json.loads(results_md.refine_files(bench_refine.ROOT / "bench")[-1].read_text())
    runs = [dict(r) for r in result["scenes"]["scan24"]["runs"]]
    value = next(r["gt_pose_psnr_masked"] for r in runs if r.get("gt_pose_psnr_masked") is not None)
    for r in runs:  # every seed reads the one training (`--reference-seeds` naming them all)
        r["gt_pose_psnr_masked"] = value
    shared = [value] * len(runs)
    assert len(shared) >= 2
    result["scenes"]["scan24"].update(runs=runs, summary=bench_refine.summarise(runs))
    s = bench_refine.summarise(runs)
    assert s["gt_pose_psnr_masked"]["n"] == 1 and s["gt_pose_psnr_masked"]["mean"] == shared[0]
    assert s["final_rot_deg"]["n"] == len(runs)  # everything else is per seed
    (tmp_path / "refine").mkdir()
    io.save_json(tmp_path / "refine" / "r.json", result)
    assert "one training shared by the seeds" in results_md.headline_markdown(tmp_path, tmp_path)
    other = [dict(r) for r in runs]
    other[-1]["gt_pose_psnr_masked"] = shared[0] + 0.5  # another training (another reference seed)
    assert bench_refine.summarise(other)["gt_pose_psnr_masked"]["n"] == 2
    result["scenes"]["scan24"]["runs"] = other
    result["scenes"]["scan24"]["summary"] = bench_refine.summarise(other)
    io.save_json(tmp_path / "refine" / "r.json", result)
    assert "one training shared" not in results_md.headline_markdown(tmp_path, tmp_path)
