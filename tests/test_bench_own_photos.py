"""bench/bench_own_photos.py on the tiny synthetic scene: photos alone (no K, no masks) against the
calibrated masked run, the JSON, the targets and a merge of runs made side by side."""
from __future__ import annotations

import json

import pytest

from bench import bench_own_photos
from tests.conftest import TINY


def test_own_photos_bench_scores_both_systems_against_one_ground_truth(tmp_path, tiny_copy, capsys):
    over = [f"--set={o}" for o in TINY]
    art, out = str(tiny_copy), str(tmp_path / "bench")  # the calibrated run: the TINY run's stages
    assert bench_own_photos.main(["--scene", "synthetic", "--seeds", "0", *over, "--artifacts", art, "--out-dir", out,
                                  "--label", "tiny"]) == 0
    (path,) = (tmp_path / "bench" / "own_photos").glob("tiny-*.json")
    result = json.loads(path.read_text())
    cal, alone = (next(r for r in result["runs"] if r["system"] == s) for s in bench_own_photos.SYSTEMS)
    assert cal["focal_err_pct"] == pytest.approx(0.0, abs=1e-9)  # the layout's K, held fixed
    assert alone["intrinsics"]["source"] == "default" and alone["intrinsics"]["start"]["focal_err_pct"] > 40
    assert alone["focal_err_pct"] < alone["intrinsics"]["start"]["focal_err_pct"]  # refined towards the truth
    for r in (cal, alone):
        assert r["rot_deg"] > 0 and r["chamfer"] > 0 and r["psnr_object"] > 0  # the object scored in both
    assert {t["target"].split(" ")[0] for t in result["targets"]} == {"focal", "final", "Chamfer"}
    assert "photos-alone" in capsys.readouterr().out
    # a second run's JSON merged with the first: one table over both
    second = tmp_path / "second.json"
    second.write_text(json.dumps({**result, "runs": [{**r, "seed": 1} for r in result["runs"]]}))
    assert bench_own_photos.main(["--merge", str(path), str(second), "--out-dir", out, "--label", "merged"]) == 0
    (merged,) = (tmp_path / "bench" / "own_photos").glob("merged-*.json")
    m = json.loads(merged.read_text())
    assert m["seeds"] == [0, 1] and m["summary"]["photos-alone"]["rot_deg"]["n"] == 2
