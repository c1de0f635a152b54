"""Self-calibration: photos whose focal length is a guess. Before the anchors'
initialisation, COLMAP's bundle adjustment on every training view refines the shared camera's focal
length and principal point, and every later stage uses the refined K. Tiny synthetic scene without masks, CPU."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import runner
from manifoldneus.geometry import cameras
from manifoldneus.data import io, scenes, synthetic
from tests.conftest import ONE_SUCCESSOR_ROUND, TINY

RES = 256  # the focal length is weakly determined at this narrow field of view: 192 px keypoints leave it 2.2 % off
F_TRUE = synthetic.FOCAL_FACTOR * RES
# the surface is not what these tests examine: the mesh and the renderings are the last round's field's
UNMASKED = [*TINY, ONE_SUCCESSOR_ROUND, f"ingest.synthetic_resolution={RES}", "ingest.load_masks=false",
            "reference_surface.enabled=false", "surface.iters=0"]
OFF = [f"ingest.intrinsics=[{0.7 * F_TRUE}, {0.7 * F_TRUE}, {RES / 2}, {RES / 2}]"]  # 30 % short
METHOD = ["evaluate", "export"]  # the method's stages, not pycolmap's reference beside them


def evaluation(root):
    store = runner.Store(root, "synthetic")
    return io.load_json(store.version_dir("evaluate", store.current("evaluate")) / "evaluation.json")


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    root = tmp_path_factory.mktemp("calibrated")
    runner.run("synthetic", until="evaluate", overrides=UNMASKED, artifacts=root)
    return evaluation(root)


def test_given_intrinsics_are_held_fixed_unless_refined(tmp_path, calibrated):
    runner.run("synthetic", until="anchors", overrides=[*UNMASKED, *OFF], artifacts=tmp_path)
    store = runner.Store(tmp_path, "synthetic")
    K = io.load_arrays(store.version_dir("anchors", store.current("anchors")) / "initial_poses.zarr")["K"]
    assert np.allclose(K[:, 0, 0], 0.7 * F_TRUE)  # given = known: auto keeps them
    assert calibrated["intrinsics"]["source"] == "calibrated"
    assert calibrated["intrinsics"]["final"]["focal_err_pct"] == pytest.approx(0.0, abs=1e-9)


def test_a_focal_length_30_percent_off_is_recovered(tmp_path, calibrated):
    runner.run("synthetic", until=METHOD, overrides=[*UNMASKED, *OFF, "anchors.intrinsics=refine"], artifacts=tmp_path)
    out = evaluation(tmp_path)
    intr = out["intrinsics"]
    assert intr["source"] == "given" and intr["start"]["focal_err_pct"] == pytest.approx(30.0, abs=1e-6)
    assert intr["ground_truth"]["focal_px"] == pytest.approx(F_TRUE)
    assert intr["final"]["focal_err_pct"] < 2.0, intr
    assert np.abs(np.subtract(intr["final"]["principal_point_px"], RES / 2)).max() < 0.02 * RES, intr
    # estimated once on every training view, then held fixed by the anchors' initialisation
    store = runner.Store(tmp_path, "synthetic")
    round_0 = io.load_json(store.version_dir("anchors", store.current("anchors")) / "round_0" / "round.json")
    calibration = round_0["init"]["calibration"]
    assert calibration["registered"] == calibration["views"] > len(round_0["views"]), calibration
    assert round_0["init"]["refine_intrinsics"] == []
    assert not calibration["radial_test"]["freed"], calibration  # a pinhole camera: no distortion to remove
    assert "distortion" not in io.array_names(store.version_dir("anchors", store.current("anchors")) / "initial_poses.zarr")
    # the rounds, the mesh and the exports use the refined K, not the ingest's
    final_K = io.load_arrays(store.version_dir("successors", store.current("successors")) / "final" / "poses.zarr",
                             ["K"])["K"]
    assert np.allclose(final_K[:, 0, 0], intr["final"]["focal_px"])
    exported = io.load_json(store.version_dir("export", store.current("export")) / "transforms.json")
    assert exported["fl_x"] == pytest.approx(intr["final"]["focal_px"])  # one shared camera: at the top level
    # poses within 2x those of the run that knew K (both unmasked)
    ours, theirs = (r["poses"][-1]["summary"]["rot_err_deg"]["mean"] for r in (out, calibrated))
    assert ours <= 2 * theirs, (ours, theirs)


def test_a_lens_with_radial_distortion_is_estimated_and_removed(tmp_path, calibrated):
    """Photos taken through a lens with radial distortion (k1 = -0.8: 2-3 px at the object's edge here), the
    focal length a guess: the self-calibration frees k1 (a likelihood-ratio test), every later stage works on
    images and keypoints without it, the poses are as good as the pinhole run's, and the exported images are
    what a pinhole camera with the exported K sees."""
    k1 = -0.8
    runner.run("synthetic", until=METHOD,
               overrides=[*UNMASKED, *OFF, "anchors.intrinsics=refine", f"ingest.synthetic_lens_k1={k1}"],
               artifacts=tmp_path)
    out = evaluation(tmp_path)
    store = runner.Store(tmp_path, "synthetic")
    calibration = io.load_json(store.version_dir("anchors", store.current("anchors")) / "round_0" / "round.json"
                               )["init"]["calibration"]
    assert calibration["radial_test"]["freed"], calibration
    # k1 trades against the focal length at this narrow field of view (both 16 % / 2.3 % short here)
    assert calibration["distortion"][0] == pytest.approx(k1, rel=0.25), calibration
    final = io.load_arrays(store.version_dir("successors", store.current("successors")) / "final" / "poses.zarr")
    assert np.allclose(final["distortion"][:, 0], calibration["distortion"][0])
    assert out["intrinsics"]["final"]["distortion"][0] == pytest.approx(calibration["distortion"][0])
    assert out["intrinsics"]["final"]["focal_err_pct"] < 3.0, out["intrinsics"]
    ours, theirs = (r["poses"][-1]["summary"]["rot_err_deg"]["mean"] for r in (out, calibrated))
    assert ours <= 2 * theirs, (ours, theirs)
    # an exported image against the pinhole render of its view: closer than the photo through the lens
    export = store.version_dir("export", store.current("export"))
    frame = io.load_json(export / "transforms.json")["frames"][0]
    view = int(Path(frame["file_path"]).stem.split("_")[-1])
    exported = io.read_image(export / frame["file_path"]).astype(float)
    lens, mask = synthetic.render_view(synthetic.intrinsics(RES, RES), synthetic.camera_poses(20)[view], RES, RES, k1=k1)[:2]
    pinhole = synthetic.render_view(synthetic.intrinsics(RES, RES), synthetic.camera_poses(20)[view], RES, RES)[0]
    inner = mask & np.roll(mask, 3, 0) & np.roll(mask, -3, 0) & np.roll(mask, 3, 1) & np.roll(mask, -3, 1)
    after, before = (np.abs(x.astype(float) - pinhole)[inner].mean() for x in (exported, lens))
    assert after < 0.5 * before, (after, before)


def test_use_calibration_false_starts_from_the_uncalibrated_guess(tmp_path):
    """The layout's cameras dropped (as for photos copied alone into a folder); the ground truth
    keeps them, so evaluation can score what self-calibration finds."""
    p = runner.resolve_params(runner.load_stages(), overrides=[*TINY, "ingest.use_calibration=false"])["ingest"]
    views = scenes.read_views(scenes.resolve_scene("synthetic"), p)
    h, w = views["images"].shape[1:3]
    assert views["intrinsics_source"] == "default"
    assert np.allclose(views["K"], scenes.default_intrinsics(h, w))
    own = scenes.layout_reference(scenes.resolve_scene("synthetic"), p)
    assert np.allclose(own["K"], synthetic.intrinsics(h, w))
    assert own["masks"] is not None and own["masks"].shape == views["masks"].shape


def test_the_calibration_gives_every_training_views_lines_of_sight(tmp_path):
    """anchors.sight_lines_from=calibration: the self-calibration's reconstruction's lines of sight, brought
    onto the anchors' frame, start at every training view's camera centre, not only the anchors'."""
    runner.run("synthetic", until=["anchors", "ground_truth"], artifacts=tmp_path, overrides=[
        *UNMASKED, *OFF, "anchors.intrinsics=refine", "anchors.sight_lines_from=calibration"])
    store = runner.Store(tmp_path, "synthetic")
    anchors = store.version_dir("anchors", store.current("anchors"))
    init = io.load_arrays(anchors / "initial_poses.zarr")
    gt = io.load_arrays(store.version_dir("ground_truth", store.current("ground_truth")) / "poses.zarr", ["w2c"])["w2c"]
    placed = init["placed"].astype(bool)
    s, R, t = cameras.align_centres(gt[placed], init["w2c"][placed])  # ground truth -> the anchors' frame
    views = io.load_json(anchors / "round_0" / "round.json")["init"]["calibration"]["views"]
    centres = cameras.transform_points(cameras.sim3_matrix(s, R, t), cameras.camera_centers(gt))  # [N,3]
    gap = np.linalg.norm(init["sight_lines"][:, None, 0] - centres[None], axis=2)  # [O,N]
    assert np.median(gap.min(1)) < 0.02 * np.linalg.norm(centres, axis=1).mean()
    assert len(np.unique(gap.argmin(1))) > placed.sum() and views > placed.sum()
