"""report.py (`pipeline.py report`): the report page built from the tiny synthetic pipeline's artifacts (default run
and the neus-barf preset; neus-colmap left out, so the page must name it missing), and the
Fig. A1 helpers on hand-made numbers."""
from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import TINY, copy_of
from test_end_to_end import current

import runner
import pipeline
import report
from manifoldneus.data import io


def test_overlap_groups_and_top_p_share_by_hand():
    c = np.array([5.0, 4.0, 3.0, 2.0, 1.0])  # overlap: view 0 easiest, view 4 hardest
    grads = np.array([1.0, 2.0, 3.0, 4.0, 10.0])  # total 20
    top, bottom = report.overlap_groups(c, 20)
    assert top.tolist() == [0] and bottom.tolist() == [4]
    assert report.top_p_share(grads, c, 20) == pytest.approx(1 / 20)
    assert report.top_p_share(grads, c, 40) == pytest.approx((1 + 2) / 20)
    assert report.top_p_share(grads[::-1], c[::-1], 20) == pytest.approx(1 / 20)  # follows c, not position
    # per iteration ([T, n]); an iteration without gradients (poses frozen) has no share
    shares = report.top_p_share(np.stack([grads, np.zeros(5)]), c, 20)
    assert shares[0] == pytest.approx(0.05) and np.isnan(shares[1])


@pytest.fixture(scope="module")
def built_report(tiny_build, tmp_path_factory):
    artifacts = copy_of(tiny_build[0], tmp_path_factory.mktemp("report") / "artifacts")  # the method's TINY run
    runner.run("synthetic", overrides=TINY, preset="neus-barf", artifacts=artifacts)
    out = artifacts.parent / "report"
    page = report.build_report("synthetic", artifacts, out)
    return artifacts, page


def test_page_references_existing_pngs(built_report):
    _, page = built_report
    text = page.read_text()
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert len(images) >= 10 and all(name.endswith(".png") and (page.parent / name).is_file() for name in images)
    for section in ("Viewer", "Schedule", "Aligned cameras", "Pose error per round", "Loss curves", "Mesh previews",
                    "Held-out views", "Easy-view bias"):
        assert f"## {section}" in text
    # the viewer pages of the two systems that ran, beside the report; the missing one says how to run it
    pages = re.findall(r"\]\(([^)]+\.html)\)", text)
    assert pages == ["manifoldneus_viewer.html", "neus_barf_viewer.html"]
    assert all('id="scene-data"' in (page.parent / name).read_text() for name in pages)
    # held-out scores say whether they are on the whole image or the object's mask, and at which pose
    ssim = next(line for line in text.splitlines() if line.startswith("| mean over the held-out views"))
    assert "SSIM, whole image" in ssim and "SSIM, object (mask)" in ssim
    assert "| at the Sim3-mapped GT poses |" in text and "| after test-time alignment" in text
    assert "NeuS-COLMAP viewer: not available (stage export: `python pipeline.py run --scene synthetic --preset " \
           "neus-colmap`)" in text


def test_pose_error_row_per_round_and_missing_system(built_report):
    artifacts, page = built_report
    text = page.read_text()
    successor_rounds = sorted(p.name for p in current(artifacts, "successors").glob("round_*"))
    assert len(successor_rounds) >= 2  # rounds laid end to end in the plots
    expected = {"ManifoldNeuS": ["initial", "anchors", *successor_rounds], "NeuS-BARF": ["initial", "anchors"],
                "pycolmap": ["final"]}
    for system, labels in expected.items():
        rows = re.findall(rf"^\| {system} \| (\w+) \| \d+ \| [\d.]+ \|", text, re.M)
        assert rows == labels, system
    assert re.search(r"^\| NeuS-COLMAP \| neus-colmap \| - \| schedule, anchors, successors, surface, mesh, evaluate: ",
                     text, re.M)
    assert "| NeuS-COLMAP | initial |" not in text


def test_easy_view_bias_numbers(built_report):
    _, page = built_report
    bias = io.load_json(page.parent / "report.json")["easy_view_bias"]
    assert set(bias) == {"NeuS-BARF", "ManifoldNeuS"}
    for system, rounds in bias.items():
        assert rounds, system
        shares = []
        for b in rounds.values():
            for key in ("rot_easy", "rot_hard", "centre_easy", "centre_hard"):
                assert np.isfinite(np.array(b[key], float)).all(), (system, key)
            learning = [i for i, s in enumerate(b["top_share"]) if s is not None]  # null: poses still frozen
            for key in ("grad_easy", "grad_hard", "top_share"):
                assert all(np.isfinite(b[key][i]) for i in learning), (system, key)
            shares += [b["top_share"][i] for i in learning]
        assert shares and all(0.0 <= s <= 1.0 for s in shares), system


def test_rotation_error_per_view_from_placement_to_the_last_round(built_report):
    artifacts, page = built_report
    text = page.read_text()
    rounds = sorted(p.name for p in current(artifacts, "successors").glob("round_*"))
    header = "| view | placement | initial | anchors | " + " | ".join(rounds) + " |"
    assert header in text and "Run `--preset sfm-all` for its column." in text  # sfm-all not run here
    table = text.split(header)[1].split("\n\n")[0].strip().splitlines()[1:]
    cells = [[c.strip() for c in row.strip("|").split("|")] for row in table]
    last = [float(c[-1]) for c in cells if c[-1]]
    placed = io.load_arrays(current(artifacts, "successors") / "final" / "poses.zarr")["placed"]
    assert len(last) == int(placed.sum()) and all(c[1] for c in cells)  # every posed view has a placement error
    # the last column is the last round's per-view errors: its mean is that round's row above
    mean = float(re.search(rf"^\| ManifoldNeuS \| {rounds[-1]} \| \d+ \| ([\d.]+) \|", text, re.M).group(1))
    assert np.mean(last) == pytest.approx(mean, abs=2e-3)


def test_a_scene_never_run_is_an_error_saying_what_to_run(tmp_path, capsys):
    assert pipeline.main(["report", "--artifacts", str(tmp_path / "artifacts")]) == 2  # the default scene, as `run`
    assert re.search(r"^error: no artifacts of scene 'synthetic' .* run `make all SCENE=synthetic`",
                     capsys.readouterr().err, re.M)
    assert not (tmp_path / "artifacts").exists()  # nothing written
