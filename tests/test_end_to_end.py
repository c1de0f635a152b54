"""The whole pipeline on a tiny synthetic scene, on the CPU: every stage runs, artifacts are
complete, evaluation reports each round; a parameter change reruns only what depends on it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import ONE_SUCCESSOR_ROUND, TINY

import runner
import trimesh

from manifoldneus.config import ParamError
from manifoldneus.geometry import cameras
from manifoldneus.output import evaluation
from manifoldneus.data import io


def current(artifacts, stage, preset=None):
    store = runner.Store(artifacts, "synthetic", preset)
    return store.version_dir(stage, store.current(stage))


def test_every_stage_ran_and_published(tiny_run):
    artifacts, report = tiny_run
    assert set(report) == set(runner.load_stages())
    assert all(v == "computed" for v in report.values())
    for stage in report:
        assert (current(artifacts, stage) / "manifest.json").is_file()


def test_rounds_and_evaluation(tiny_run):
    artifacts, _ = tiny_run
    sched = io.load_json(current(artifacts, "schedule") / "schedule.json")
    succ = current(artifacts, "successors")
    rounds = sorted(p.name for p in succ.glob("round_*"))
    assert len(rounds) == sched["n_rounds"] - 1 >= 1
    steps = [io.load_json(succ / f"round_{r}" / "round.json")["train"]["steps"] for r in range(1, len(rounds) + 1)]
    assert steps == [30] * (len(rounds) - 1) + [40]  # successors.iters, then final_iters for the last round
    polish = [io.load_json(succ / f"round_{r}" / "round.json")["train"].get("polish") for r in range(1, len(rounds) + 1)]
    assert polish[:-1] == [None] * (len(rounds) - 1)  # successors.polish_rounds = last
    assert polish[-1]["steps"] == 20 and polish[-1]["turn_deg_mean"] > 0  # the last round's poses moved after training
    assert sched["held_out_views"] == [0, 8, 16] and not set(sched["anchors"]) & {0, 8, 16}  # never scheduled
    final = io.load_arrays(succ / "final" / "poses.zarr")
    held = np.zeros(20, bool)
    held[::8] = True
    assert final["placed"][~held].sum() >= 14 and not final["placed"][held].any()
    ev = io.load_json(current(artifacts, "evaluate") / "evaluation.json")
    labels = [r["label"] for r in ev["poses"]]
    assert labels[:2] == ["initial", "anchors"] and labels[2:] == rounds
    assert ev["poses"][0]["summary"]["rot_err_deg"]["mean"] < 2.0  # matches-based init, before any training
    assert np.isfinite(ev["geometry"]["chamfer"]) and ev["novel_views"]["per_view"]
    assert 0 < ev["geometry"]["colour_spread"]["median"] < 1 and ev["geometry"]["colour_spread"]["share_scored"] > 0
    for row in ev["novel_views"]["per_view"]:  # scored at the mapped GT pose and after test-time alignment
        assert np.isfinite(row["psnr"]) and np.isfinite(row["aligned_psnr"]) and row["align_rot_deg"] >= 0
    colmap = current(artifacts, "mesh") / "colmap"
    assert (colmap / "images.txt").read_text().count(".png") == int(final["placed"].sum())
    # every trained round tested each view's pose update on its held-out tracks; a view that did not keep
    # its update is where the round started it, to the last bit
    for row in ev["poses"][1:]:
        guard = row["guard"]
        assert guard["checked"] and guard["kind"] == "reprojection" and guard["held_out"] > 0 and "start_summary" in row
        assert len(guard["keep"]) == guard["n_views"] == row["n_views"] and guard["kept"] == sum(guard["keep"])
        assert guard["z_limit"] > 2 and guard["error_kept"] <= guard["error_start"]
    optimised = np.flatnonzero(final["optimised"].astype(bool))
    keep = np.asarray(io.load_json(succ / "final" / "round.json")["train"]["guard"]["keep"], bool)
    assert np.array_equal(final["w2c"][optimised[~keep]], final["w2c_init"][optimised[~keep]])
    assert ev["placement"]["rot_err_deg"]["mean"] > 0  # the final views at the poses they were placed with


def artifacts_round(artifacts, report, stage):
    from manifoldneus.data import artifacts as rounds

    return rounds.load_round(artifacts / "synthetic" / stage / report.fingerprints[stage] / "final")


def test_a_view_without_a_pose_is_named_in_the_summary(tmp_path):
    schedule, successors = tmp_path / "schedule", tmp_path / "successors"
    schedule.mkdir()
    io.save_json(schedule / "schedule.json", {"held_out_views": [0], "views": [
        {"view": i, "name": f"IMG_{i}", "role": r} for i, r in enumerate(["excluded", "anchor", "round1", "excluded"])]})
    io.save_arrays(successors / "final" / "poses.zarr", {"placed": np.array([False, True, False, False])})
    lines = runner.posed_lines(successors, schedule)
    assert lines[0] == "posed:   1 of 3 views (1 more held out for evaluation)"
    assert lines[1].startswith("WARNING: 2 view(s) got no pose: IMG_2, IMG_3 (")


def test_the_summary_says_what_the_run_found_and_where(tiny_run):
    artifacts, report = tiny_run
    text = runner.run_summary("synthetic", report, artifacts)
    ev = io.load_json(artifacts / "synthetic" / "evaluate" / report.fingerprints["evaluate"] / "evaluation.json")
    rot = ev["poses"][-1]["summary"]["rot_err_deg"]["mean"]
    assert f"rotation {rot:.3f} deg mean" in text
    K_gt = io.load_arrays(artifacts / "synthetic" / "ground_truth" / report.fingerprints["ground_truth"] / "poses.zarr",
                          ["K"])["K"]
    focal = K_gt[:, [0, 1], [0, 1]].mean()  # calibrated: the run keeps the scene's own camera
    assert f"camera (calibrated): focal {focal:.1f} px, principal point (64.0, 64.0); ground truth {focal:.1f} px, " \
           "0.00 % off" in text
    paths = [line.split()[0] for line in text.splitlines() if line.split()[0] in ("result:", "mesh:", "cameras:")]
    assert paths == ["result:", "mesh:", "cameras:"]  # the exports first, each path with its frame
    result = next(line for line in text.splitlines() if line.startswith("result:"))
    assert "the input's world" in result and (Path(result.split()[1]) / "mesh.glb").is_file()
    mesh = next(line for line in text.splitlines() if line.startswith("mesh:"))
    assert Path(mesh.split()[1]).is_file() and "the method's unit-sphere frame" in mesh
    final = artifacts_round(artifacts, report, "successors")
    held = io.load_json(artifacts / "synthetic" / "schedule" / report.fingerprints["schedule"] / "schedule.json")[
        "held_out_views"]
    meant = [v for v in range(len(final["placed"])) if v not in held]
    posed = int(final["placed"][meant].sum())
    assert f"posed:   {posed} of {len(meant)} views ({len(held)} more held out for evaluation)" in text
    assert ("WARNING" in text) == (posed < len(meant))
    # a self-calibrated camera says where it started
    intr = {"source": "default", "start": {"focal_px": 960.0, "principal_point_px": [400.0, 300.0]},
            "final": {"focal_px": 1436.4, "principal_point_px": [411.9, 313.0], "focal_err_pct": 0.52},
            "ground_truth": {"focal_px": 1443.9, "principal_point_px": [411.6, 309.5]}}
    assert runner.camera_line(intr) == ("camera (default): focal 1436.4 px, principal point (411.9, 313.0); "
                                          "self-calibrated from 960.0 px, (400.0, 300.0); ground truth 1443.9 px, "
                                          "0.52 % off")


def test_alpha_change_reruns_schedule_and_after_only(tiny_run):
    artifacts, _ = tiny_run
    st = runner.status("synthetic", overrides=TINY + ["schedule.alpha=0.3"], artifacts=artifacts)
    stale = {s for s, (state, _) in st.items() if state != "fresh"}
    assert stale == {"schedule", "anchors", "successors", "surface", "mesh", "evaluate", "export"}


def test_the_surface_is_a_field_of_every_posed_view_at_its_final_pose(tiny_run):
    """The surface stage keeps the last round's poses to the last bit and trains a field of its own on
    every view they pose; its keys change the surface and what reads it, never the rounds."""
    artifacts, _ = tiny_run
    store = runner.Store(artifacts, "synthetic")
    versions = store.lineage("evaluate")
    final, surface = versions["successors"] / "final", versions["surface"]
    ours, last = io.load_arrays(surface / "poses.zarr"), io.load_arrays(final / "poses.zarr")
    assert set(ours) == set(last) and all(np.array_equal(ours[k], last[k]) for k in last)
    info = io.load_json(surface / "round.json")
    assert info["train"]["steps"] == 40 and info["views"] == np.flatnonzero(last["optimised"]).tolist()
    fresh, rounds = (torch.load(d / "model.pt", weights_only=False) for d in (surface, final))
    assert any(not torch.equal(fresh["field"][k], rounds["field"][k]) for k in rounds["field"])
    assert fresh["params"]["field"] == rounds["params"]["field"]  # with masks, the field's own view encoding
    # its field's frame fits every posed view's points (surface.frame = views); the mesh is back in the rounds'
    G = np.asarray(info["field_from_model"])
    points = last["track_points"]  # [T,3] the rounds' frame
    lo, hi = np.percentile(cameras.transform_points(G, points), [1, 99], axis=0)
    assert np.abs(G - np.eye(4)).max() > 0.01 and 0.6 < 0.5 * np.linalg.norm(hi - lo) < 1.0  # gauge_radius: 0.8
    # it is the gauge of the SfM the last round restarted from (sfm-all's), not the anchors' SfM's
    from_sfm = G @ np.asarray(io.load_json(final / "round.json")["round_from_sfm"])  # [4,4] SfM's gauge -> field
    assert np.allclose(from_sfm, np.eye(4), atol=1e-12) and not np.allclose(G[:3, :3], np.eye(3), atol=1e-3)
    # without that SfM (surface.axes = rounds, or a last round placed by depth): the same gauge refitted to
    # the round's tracks of the object, in the rounds' axes
    from stages import anchors, surface as surface_stage

    field = evaluation.load_surface_field(surface, versions["ingest"])  # the last round's poses and tracks, its views
    refit = surface_stage.field_frame(field.result, field.views, field.ids, anchors.Params(), "rounds")
    lo, hi = np.percentile(cameras.transform_points(refit, points), [1, 99], axis=0)
    assert np.allclose(refit[:3, :3] / refit[0, 0], np.eye(3)) and 0.7 < 0.5 * np.linalg.norm(hi - lo) < 0.9
    vertices = np.asarray(trimesh.load(versions["mesh"] / "mesh.ply", process=False).vertices)  # the rounds' frame
    sdf = field.trainer.sdf_fn()
    on_surface = np.abs(sdf(cameras.transform_points(G, vertices)))  # [V] the field's zero level, in its frame
    assert np.median(on_surface) < 0.1 * np.median(np.abs(sdf(vertices)))
    with pytest.raises(ParamError, match="surface.frame = rounds"):
        runner.status("synthetic", overrides=TINY + ["surface.start=rounds"], artifacts=artifacts)
    st = runner.status("synthetic", overrides=TINY + ["surface.iters=0"], artifacts=artifacts)
    assert {s for s, (state, _) in st.items() if state != "fresh"} == {"surface", "mesh", "evaluate", "export"}
    report = runner.run("synthetic", until="surface", overrides=TINY + ["surface.iters=0"], artifacts=artifacts)
    assert report["successors"] == "reused" and report["surface"] == "computed"
    copied = current(artifacts, "surface")  # iters 0: the last round's field is the surface
    assert (copied / "model.pt").read_bytes() == (final / "model.pt").read_bytes()
    assert set(runner.run("synthetic", overrides=TINY, artifacts=artifacts).values()) == {"reused"}  # pointers back


def test_each_value_has_one_home(tiny_run):
    """The reference's length is its own: changing it touches the reference and the evaluation
    only, and the pose-free stages' lengths are not in `train`."""
    artifacts, _ = tiny_run
    st = runner.status("synthetic", overrides=TINY + ["reference_surface.iters=41"], artifacts=artifacts)
    assert {s for s, (state, _) in st.items() if state != "fresh"} == {"reference_surface", "evaluate"}
    for key in ("train.iters", "train.pose_lr", "train.seed", "train.device"):
        with pytest.raises(ParamError, match=f"unknown parameter {key}"):
            runner.status("synthetic", overrides=TINY + [f"{key}=1"], artifacts=artifacts)


def test_neus_barf_preset_reuses_the_front_end(tiny_run):
    artifacts, _ = tiny_run
    report = runner.run("synthetic", overrides=TINY, preset="neus-barf", artifacts=artifacts)
    assert report["features"] == report["matching"] == report["reference"] == "reused"
    assert report["schedule"] == report["anchors"] == "computed"
    barf = current(artifacts, "successors", "neus-barf")
    assert not list(barf.glob("round_*"))  # uniform: all views in the anchor stage
    ev = io.load_json(current(artifacts, "evaluate", "neus-barf") / "evaluation.json")
    assert [r["label"] for r in ev["poses"]] == ["initial", "anchors"]
    # the default run's pointers did not move
    assert runner.status("synthetic", overrides=TINY, artifacts=artifacts)["evaluate"][0] == "fresh"
    # alpha is not used by the uniform schedule: the schedule reruns (its recipe changed), writes the
    # same bytes, and nothing after it is recomputed
    again = runner.run("synthetic", overrides=TINY + ["schedule.alpha=0.3"], preset="neus-barf", artifacts=artifacts)
    assert again["schedule"] == "computed"
    assert {s for s, how in again.items() if how == "computed"} == {"schedule"}


def test_the_photos_alone_share_the_gt_pose_reference_surface(tiny_run):
    """The GT-pose reference reads only the pixels of the method's ingest (READS) and the layout's own
    cameras and masks: a run on the photos alone reuses the calibrated, masked run's version."""
    artifacts, _ = tiny_run
    report = runner.run("synthetic", until="reference_surface", overrides=TINY, preset="photos-alone",
                          artifacts=artifacts)
    assert report["ingest"] == report["ground_truth"] == "computed"  # no masks, K a guess: other bytes
    assert report["reference_surface"] == "reused"
    views = io.load_arrays(current(artifacts, "ingest", "photos-alone") / "views.zarr")
    assert "masks" not in views
    assert current(artifacts, "reference_surface", "photos-alone") == current(artifacts, "reference_surface")


def test_max_rounds_stops_after_the_first_successor_round(tiny_run):
    """successors.max_rounds=1 makes round 1 the last, final round: its length is final_iters, and with
    successors.final_image_size=0 (coarse-to-fine over image resolution) it trains at the images' own
    128 px while the anchors trained at train.image_size (32 px)."""
    artifacts, _ = tiny_run
    report = runner.run("synthetic", overrides=TINY + ["successors.max_rounds=1", "successors.final_iters=45",
                                                         "successors.final_image_size=0"],
                          until="successors", artifacts=artifacts)
    assert report["anchors"] == "reused" and report["successors"] == "computed"
    succ = current(artifacts, "successors")
    assert sorted(p.name for p in succ.glob("round_*")) == ["round_1"]
    assert (succ / "final").resolve().name == "round_1"
    assert io.load_json(succ / "round_1" / "round.json")["train"]["steps"] == 45  # the last round run is final
    size = {d: torch.load(d / "model.pt", map_location="cpu", weights_only=False)["params"]["train"]["image_size"]
            for d in (current(artifacts, "anchors") / "round_0", succ / "round_1")}
    assert list(size.values()) == [32, 0]


def test_refine_placed_off_learns_only_the_new_views(tiny_run):
    artifacts, _ = tiny_run
    report = runner.run("synthetic", overrides=TINY + ["successors.refine_placed=false", "successors.max_rounds=2",
                                                         "successors.sfm_restart=none", "successors.polish_steps=0"],
                          until="successors", artifacts=artifacts)
    assert report["anchors"] == "reused" and report["successors"] == "computed"
    succ = current(artifacts, "successors")
    r1, r2 = (np.asarray(io.load_arrays(succ / f"round_{r}" / "poses.zarr")["w2c"]) for r in (1, 2))
    before = io.load_arrays(succ / "round_1" / "poses.zarr")["placed"].astype(bool)
    new = io.load_json(succ / "round_2" / "round.json")["new_views"]
    assert new and before.sum() > 0
    # the views round 1 ended with keep their poses through round 2 (float32 round trip); the new ones learnt
    # (the training's last recorded poses; whether a view keeps its update is the held-out tracks' decision)
    assert np.abs(r2[before] - r1[before]).max() < 1e-6
    arrays = io.load_arrays(succ / "round_2" / "poses.zarr", ["w2c_init", "pose_trace"])
    trained = np.asarray(arrays["pose_trace"])[-1]  # [N,4,4]
    assert np.abs(trained[new] - arrays["w2c_init"][new]).max() > 1e-6
    assert np.abs(trained[before] - r1[before]).max() < 1e-6


def test_the_last_round_can_restart_every_view_from_the_matches_sfm(tiny_run, tmp_path):
    """successors.sfm_restart=last (the fast profile's): the final round starts its earlier-placed
    views from the SfM over every view, not where the previous round left them; none keeps them."""
    import shutil

    from manifoldneus.data import artifacts as rounds

    artifacts, report = tiny_run
    copy = tmp_path / "artifacts"
    shutil.copytree(artifacts, copy, symlinks=True)
    kept = runner.run("synthetic", only="successors", overrides=[*TINY, "successors.sfm_restart=none"], artifacts=copy)
    for where, fp, restarted in ((artifacts, report.fingerprints["successors"], True),
                                 (copy, kept.fingerprints["successors"], False)):
        succ = where / "synthetic" / "successors" / fp
        last = max(succ.glob("round_*"), key=lambda d: int(d.name.split("_")[1]))
        before = rounds.load_round(succ / f"round_{int(last.name.split('_')[1]) - 1}")
        end = rounds.load_round(last)
        carried = np.flatnonzero(before["placed"])
        moved = np.abs(end["w2c_init"][carried] - before["w2c"][carried]).max()
        assert (moved > 1e-6) == restarted, (where, moved)



def test_a_round_gates_only_the_views_it_does_not_keep(tiny_run):
    """successors.regate_kept = 1: the rays of the views an earlier round fitted see every band of the
    field from the round's first step; the round's new views start coarse, as with the default 0."""
    from manifoldneus import posefree

    artifacts, _ = tiny_run
    store = runner.Store(artifacts, "synthetic")
    resolved = runner.resolve_params(runner.load_stages(), overrides=TINY)
    cfg = posefree.RoundConfig.from_sections(lambda name: resolved[name])
    inputs = posefree.load_inputs(**{s: store.version_dir(s, store.current(s)) for s in posefree.INPUT_STAGES})
    ids = np.flatnonzero(inputs.train_mask)
    kept = ids[: len(ids) // 2]  # the rest are the round's new views
    w2c = np.tile(np.eye(4), (len(inputs.names), 1, 1))
    s_tilde = np.ones(len(inputs.names))
    weights = {}
    for frac in (0.0, 1.0):
        rnd = posefree.Round(cfg, inputs, ids, w2c, s_tilde, iters=100, kept_ids=kept, kept_frac=frac)
        weights[frac] = rnd.trainer.band_weight_fn(torch.arange(len(ids)), 0)  # [views of the round, L]
    is_kept = torch.as_tensor(np.isin(ids, kept))
    assert (weights[0.0][:, -1] < 1).all()  # the default: every view starts coarse
    assert torch.equal(weights[1.0][is_kept], torch.ones_like(weights[1.0][is_kept]))
    assert torch.equal(weights[1.0][~is_kept], weights[0.0][~is_kept]) and (weights[1.0][~is_kept][:, -1] < 1).all()


def test_a_video_of_an_object_comes_out_with_every_frame_posed(tmp_path):
    """A short clip of an object (the synthetic scene's 20 views as frames, mp4, no cameras, no masks, the
    focal length unknown: the guess is half the true one): every frame gets a pose and is exported, the
    self-calibration finds the focal length, and the exports parse in pycolmap and trimesh."""
    import json

    import cv2
    import pycolmap
    import trimesh

    from manifoldneus.data import synthetic

    res, n = 192, 20
    scene = synthetic.make_scene(seed=0, n_views=n, resolution=res)
    clip = tmp_path / "object.mp4"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), 10, (res, res))
    for image in scene.images:
        writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    writer.release()
    overrides = [*(o for o in TINY if not o.startswith("ingest.synthetic")), ONE_SUCCESSOR_ROUND,
                 f"ingest.video_frames={n}"]
    runner.run(str(clip), overrides=overrides, artifacts=tmp_path / "artifacts")
    store = runner.Store(tmp_path / "artifacts", runner.resolve_scene(str(clip)).name)
    out = store.version_dir("export", store.current("export"))
    meta = json.loads((out / "transforms.json").read_text())
    assert len(meta["frames"]) == n and "test_filenames" not in meta  # nothing held out: no cameras to score it
    assert meta["fl_x"] == pytest.approx(synthetic.intrinsics(res, res)[0, 0], rel=0.1)  # from 1.2 x 192 = 230 px
    assert len(pycolmap.Reconstruction(str(out / "colmap")).images) == n
    assert len(trimesh.load(out / "mesh.glb", force="mesh").faces) > 0


def test_own_photos_end_to_end_say_the_camera_they_estimated(tmp_path):
    """A folder of photos, no cameras, no masks (a user's capture): every stage runs, nothing is scored, and the
    summary and evaluation.json still say which camera the run estimated (the evaluate stage wrote nothing of it
    without ground truth)."""
    from manifoldneus.data import synthetic

    from PIL import Image

    photos = tmp_path / "photos"
    photos.mkdir()
    K = synthetic.intrinsics(128, 128)
    for i, w2c in enumerate(synthetic.camera_poses(20)):  # TINY's synthetic scene, as photos: JPEGs and PNGs
        image = synthetic.render_view(K, w2c, 128, 128, seed=3)[0]
        if i % 2:
            io.save_png(photos / f"IMG_{i:04d}.png", image)
        else:
            exif = Image.Exif()
            exif[0x0112] = 3 if i == 4 else 1  # IMG_0004 asks viewers to turn it upside down
            Image.fromarray(image).save(photos / f"IMG_{i:04d}.jpg", quality=95, exif=exif)
    artifacts = tmp_path / "artifacts"
    report = runner.run(str(photos), overrides=[*TINY, ONE_SUCCESSOR_ROUND], artifacts=artifacts)
    assert report["evaluate"] == "computed" and report["export"] == "computed"
    name = runner.resolve_scene(str(photos)).name
    ev = io.load_json(artifacts / name / "evaluate" / report.fingerprints["evaluate"] / "evaluation.json")
    assert ev["has_ground_truth"] is False and "poses" not in ev
    final = ev["intrinsics"]["final"]
    assert final["focal_px"] > 0 and "focal_err_pct" not in final and "ground_truth" not in ev["intrinsics"]
    text = runner.run_summary(str(photos), report, artifacts)
    line = next(x for x in text.splitlines() if x.startswith("camera ("))
    assert line == runner.camera_line(ev["intrinsics"]) and "ground truth" not in line
    assert "rotation" not in text  # no pose scores without ground truth
    # the export hands the photos over as they came (the JPEGs' bytes), but for the one a viewer would turn
    exported = artifacts / name / "export" / report.fingerprints["export"]
    frames = {Path(f["file_path"]).name: f for f in io.load_json(exported / "transforms.json")["frames"]}
    assert {"IMG_0002.jpg", "IMG_0003.png", "IMG_0004.png"} <= set(frames)
    assert (exported / "images" / "IMG_0002.jpg").read_bytes() == (photos / "IMG_0002.jpg").read_bytes()
    assert (exported / "images" / "IMG_0004.png").is_file() and not (exported / "images" / "IMG_0004.jpg").exists()
    assert "IMG_0002.jpg" in (exported / "colmap" / "images.txt").read_text()
    # the report shows what the run made, not rows of what ground truth would have scored
    from report import build_report

    page = build_report(str(photos), artifacts).read_text()
    assert "no ground truth" in page and "not available" not in page and "NeuS-BARF" not in page
    assert "| surface |" in page and line in page  # each stage's time, and the camera the run estimated
    # pycolmap's reference SfM is evaluation: photos without cameras skip it, unless asked for
    store = runner.Store(artifacts, name)
    reference = store.version_dir("reference", report.fingerprints["reference"])
    assert io.load_json(reference / "manifest.json")["metrics"]["skipped"] is True
    assert not io.load_arrays(reference / "poses.zarr", ["registered"])["registered"].any()
    st = runner.status(str(photos), overrides=[*TINY, ONE_SUCCESSOR_ROUND, "reference.when=always"],
                       artifacts=artifacts)
    assert st["reference"][0] != "fresh" and st["anchors"][0] == "fresh"  # the method never read it
    with pytest.raises(ParamError, match="reference.when=always"):  # the anchors cannot start from a skipped one
        runner.run(str(photos), until="anchors", overrides=[*TINY, ONE_SUCCESSOR_ROUND, "anchors.pose_init=reference"],
                   artifacts=artifacts)


def test_the_summary_of_a_run_too_small_to_score_still_ends_well(tiny_run, monkeypatch):
    """Two posed views (too few for a Sim3): the evaluation skips the score, and the summary says so
    instead of failing on the missing figures; its commands name the run's artifacts, quoted for a shell."""
    import shlex

    import runner.inspect

    artifacts, report = tiny_run
    real = runner.inspect.load_evaluation

    def two_views(path):
        ev = real(path)
        ev["poses"][-1] = {"label": "round_2", "n_views": 2, "skipped": "fewer than 3 views: no Sim3"}
        return ev

    monkeypatch.setattr(runner.inspect, "load_evaluation", two_views)
    text = runner.run_summary("synthetic", report, artifacts)
    assert "poses (round_2, 2 views): not scored against ground truth, fewer than 3 views: no Sim3" in text
    for verb, label in (("view", "viewer:"), ("report", "report:")):
        line = next(x for x in text.splitlines() if x.startswith(label))
        assert shlex.split(line.split(":", 1)[1])[2:] == [verb, "--scene", "synthetic", "--artifacts", str(artifacts)]


def test_the_camera_line_names_a_lens_distortion_found():
    intr = {"source": "exif", "start": {"focal_px": 500.0, "principal_point_px": [160.0, 120.0]},
            "final": {"focal_px": 512.3, "principal_point_px": [160.0, 120.0], "distortion": [0.031, 0.0, 0.0, 0.0]}}
    assert runner.camera_line(intr) == ("camera (exif): focal 512.3 px, principal point (160.0, 120.0); "
                                          "self-calibrated from 500.0 px, (160.0, 120.0); lens distortion k1 +0.0310 "
                                          "(removed from the images)")
    intr["final"]["distortion"] = [0.0, 0.0, 0.0, 0.0]  # none found: nothing to say
    assert "distortion" not in runner.camera_line(intr)


def test_a_colmap_models_poses_seed_the_anchors(tmp_path):
    """The synthetic scene handed over as a COLMAP model whose poses are off the truth by a few degrees:
    `anchors.pose_init = input` starts every anchor at the model's pose (its rotation to the bit: the gauge
    only scales and shifts), not at the truth nor at an SfM of its own; a scene without a model says so."""
    from manifoldneus.output import export
    from manifoldneus.data import synthetic

    scene = synthetic.make_scene(seed=0, n_views=20, resolution=128)
    rng = np.random.default_rng(0)
    turn = cameras.rotvec_to_matrix(rng.normal(size=(len(scene.w2c), 3)) * np.radians(2.0))  # [N,3,3] ~3 deg each
    model = scene.w2c.copy()  # [N,4,4] the model's world-to-camera poses: each camera turned
    model[:, :3, :] = np.einsum("nij,njk->nik", turn, model[:, :3, :])
    folder = tmp_path / "model"
    (folder / "images").mkdir(parents=True)
    for i, name in enumerate(scene.names):
        io.save_png(folder / "images" / export.image_filename(name), scene.images[i])
    export.write_colmap_text(folder / "sparse" / "0", scene.names, scene.K, model, 128, 128)
    artifacts = tmp_path / "artifacts"
    report = runner.run(str(folder), until="anchors", artifacts=artifacts,
                          overrides=TINY + ["anchors.pose_init=input"])
    store = runner.Store(artifacts, runner.resolve_scene(str(folder)).name)
    anchors_dir = store.version_dir("anchors", report.fingerprints["anchors"])
    assert io.load_json(anchors_dir / "round_0" / "round.json")["init"]["method"] == "input"
    start = io.load_arrays(anchors_dir / "initial_poses.zarr")
    ids = np.flatnonzero(start["placed"])
    assert len(ids) >= 3
    assert np.allclose(start["w2c"][ids, :3, :3], model[ids, :3, :3], atol=1e-9)
    assert np.abs(start["w2c"][ids, :3, :3] - scene.w2c[ids, :3, :3]).max() > 1e-3
    with pytest.raises(ParamError, match="sparse/0"):
        runner.run("synthetic", until="anchors", artifacts=artifacts, overrides=TINY + ["anchors.pose_init=input"])


def test_photos_of_two_sizes_are_two_cameras_end_to_end(tmp_path):
    """The synthetic scene as a COLMAP model whose every fourth photo is cropped to 128x96 (a second camera,
    its principal point moved; among them the held-out views), its calibration left unused (as photos alone:
    each size starts from its own guess and is self-calibrated apart): every stage runs, each size keeps its
    own camera through the SfM to the exports (images at their own size), the poses are the truth's, and the
    held-out views are rendered and scored on their own pixels only."""
    import pycolmap
    from PIL import Image

    from manifoldneus.output import export
    from manifoldneus.data import synthetic

    scene = synthetic.make_scene(seed=0, n_views=20, resolution=128)
    small = np.arange(20) % 4 == 0  # rows 16..111 kept
    K = scene.K.copy()
    K[small, 1, 2] -= 16
    heights = np.where(small, 96, 128)
    folder = tmp_path / "model"
    (folder / "images").mkdir(parents=True)
    for i, name in enumerate(scene.names):
        io.save_png(folder / "images" / export.image_filename(name), scene.images[i][16:112] if small[i] else scene.images[i])
    export.write_colmap_text(folder / "sparse" / "0", scene.names, K, scene.w2c, 128, heights)
    assert len(pycolmap.Reconstruction(str(folder / "sparse" / "0")).cameras) == 2
    artifacts = tmp_path / "artifacts"
    # export and evaluate, not pycolmap's reference: its scores are not this test's
    overrides = TINY + [ONE_SUCCESSOR_ROUND, "ingest.use_calibration=false"]
    report = {until: runner.run(str(folder), until=until, artifacts=artifacts, overrides=overrides).fingerprints[until]
              for until in ("export", "evaluate")}
    store = runner.Store(artifacts, runner.resolve_scene(str(folder)).name)
    out = store.version_dir("export", report["export"])
    rec = pycolmap.Reconstruction(str(out / "colmap"))
    assert len(rec.cameras) == 2 and len(rec.images) >= 14
    assert len({tuple(c.params) for c in rec.cameras.values()}) == 2  # each size calibrated apart
    for image in rec.images.values():
        i = scene.names.index(Path(image.name).stem)
        camera = rec.cameras[image.camera_id]
        assert (camera.width, camera.height) == (128, heights[i])
        assert camera.params[2:] == pytest.approx([64, K[i, 1, 2]])  # its own principal point
        assert camera.params[0] == pytest.approx(K[i, 0, 0], rel=0.1)  # self-calibrated from 1.2 x 128 = 154 px
        assert Image.open(out / "images" / image.name).size == (128, heights[i])
    frames = io.load_json(out / "transforms.json")["frames"]
    assert {(f["w"], f["h"]) for f in frames} == {(128, 96), (128, 128)}
    ev = io.load_json(store.version_dir("evaluate", report["evaluate"]) / "evaluation.json")
    assert ev["poses"][-1]["summary"]["rot_err_deg"]["mean"] < 2.0
    held = ev["novel_views"]["per_view"]
    assert [r["view"] for r in held] == [0, 8, 16]  # all cropped: 96x128 at the training's 1/4
    assert all(r["size"] == [24, 32] and np.isfinite(r["psnr"]) and r["psnr"] > 10 for r in held)
