"""Exports (manifoldneus/output/export.py, stages/export.py): the COLMAP text model read back by pycolmap,
nerfstudio's transforms.json read back by export.read_transforms_json, both to 1e-9; the OpenGL
camera convention; and the export stage's result on the tiny synthetic run, in the input's frame."""
import importlib.util
import json

import numpy as np
import pytest

import runner
from manifoldneus.data import artifacts, io
from manifoldneus.geometry import cameras
from manifoldneus.output import export


def random_cameras(n, seed=0, spread=3.0):
    rng = np.random.default_rng(seed)
    eyes = rng.normal(size=(n, 3)) * spread
    w2c = np.stack([cameras.look_at_w2c(e, rng.normal(size=3) * 0.1, np.array([0.0, 0.0, 1.0])) for e in eyes])
    K = np.stack([np.array([[300.0 + i, 0, 96.5], [0, 310.0, 64.25], [0, 0, 1]]) for i in range(n)])
    return K, w2c


def colmap_poses(folder):
    """name -> (w2c [4,4], K [3,3], (w, h)) of a COLMAP model, read by pycolmap."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(folder))
    out = {}
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        out[im.name] = (cameras.to_4x4(np.asarray(im.cam_from_world().matrix())), cam.calibration_matrix(),
                        (cam.width, cam.height))
    return out


def test_colmap_text_model_reads_back_with_the_same_cameras(tmp_path):
    pytest.importorskip("pycolmap")
    K, w2c = random_cameras(3)
    w2c[:, :3, 3] *= 250.0  # a world in millimetres: the text must keep 1e-9 at that size too
    export.write_colmap_text(tmp_path, ["a", "b", "plain 7"], K, w2c, 192, 128, valid=[True, False, True])
    back = colmap_poses(tmp_path)
    assert sorted(back) == ["a.png", "plain_7.png"]  # COLMAP's text ends a name at a space
    for i, name in ((0, "a.png"), (2, "plain_7.png")):
        np.testing.assert_allclose(back[name][0], w2c[i], rtol=0, atol=1e-9)
        np.testing.assert_allclose(back[name][1], K[i], rtol=0, atol=1e-9)
        assert back[name][2] == (192, 128)


def test_transforms_json_round_trip_and_its_opengl_convention(tmp_path):
    K, w2c = random_cameras(5, seed=1)
    path = tmp_path / "transforms.json"
    export.write_transforms_json(path, [f"v{i}" for i in range(5)], K, w2c, 192, 128, valid=[1, 1, 0, 1, 1],
                                 mask_dir="masks")
    back = export.read_transforms_json(path)
    keep = [0, 1, 3, 4]
    assert back["files"] == [f"images/v{i}.png" for i in keep]
    np.testing.assert_allclose(back["w2c"], w2c[keep], rtol=0, atol=1e-9)
    np.testing.assert_allclose(back["K"], K[keep], rtol=0, atol=1e-12)
    assert back["size"].tolist() == [[192, 128]] * 4
    frame = json.loads(path.read_text())["frames"][0]
    assert frame["mask_path"] == "masks/v0.png"
    # nerfstudio's matrix: camera-to-world with OpenGL axes, so the camera looks along its -z column
    # and its +y column is the image's up (the OpenCV camera's -y)
    c2w = np.array(frame["transform_matrix"])
    np.testing.assert_allclose(c2w[:3, 3], cameras.camera_centers(w2c[0]), atol=1e-12)
    np.testing.assert_allclose(-c2w[:3, 2], w2c[0, 2, :3], atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 1], -w2c[0, 1, :3], atol=1e-12)


def test_shared_intrinsics_are_written_once_at_the_top_level(tmp_path):
    K, w2c = random_cameras(2, seed=2)
    path = tmp_path / "transforms.json"
    written = export.write_transforms_json(path, ["a", "b"], K[[0, 0]], w2c, 192, 128, ply_file_path="points.ply")
    assert written["fl_x"] == K[0, 0, 0] and written["ply_file_path"] == "points.ply"
    assert not any("fl_x" in frame for frame in written["frames"])
    back = export.read_transforms_json(path)
    np.testing.assert_allclose(back["K"], K[[0, 0]], atol=1e-12)
    assert "fl_x" in export.write_transforms_json(path, ["a", "b"], K, w2c, 192, 128)["frames"][0]  # not shared
    del written["fl_x"]
    path.write_text(json.dumps(written))
    with pytest.raises(ValueError, match="has no 'fl_x'"):
        export.read_transforms_json(path)


def test_colmap_model_has_one_camera_per_set_of_intrinsics_and_the_points(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    K, w2c = random_cameras(4)
    K = K[[0, 1, 0, 0]]  # views 0, 2, 3 from one camera
    points = np.random.default_rng(0).normal(size=(5, 3))
    colours = np.arange(15, dtype=np.uint8).reshape(5, 3)
    export.write_colmap_text(tmp_path, ["a", "b", "c", "d"], K, w2c, 192, 128, points=points, colours=colours)
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert len(rec.cameras) == 2
    assert len({im.camera_id for im in rec.images.values() if im.name != "b.png"}) == 1
    back = sorted((tuple(p.xyz), tuple(p.color)) for p in rec.points3D.values())
    assert np.allclose([b[0] for b in back], sorted(map(tuple, points)), atol=1e-6)
    assert sorted(b[1] for b in back) == sorted(map(tuple, colours.tolist()))


def test_photos_of_two_sizes_are_two_cameras_in_both_exports(tmp_path):
    """Equal intrinsics but two image sizes: two COLMAP cameras (each its size), transforms.json per frame."""
    import pycolmap

    K = np.tile(np.array([[100.0, 0, 64], [0, 100, 48], [0, 0, 1]]), (3, 1, 1))
    w2c = np.tile(np.eye(4), (3, 1, 1))
    w2c[:, 2, 3] = 3.0
    export.write_colmap_text(tmp_path, ["a", "b", "c"], K, w2c, 128, np.array([96, 128, 96]))
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert sorted((c.width, c.height) for c in rec.cameras.values()) == [(128, 96), (128, 128)]
    assert rec.images[1].camera_id == rec.images[3].camera_id != rec.images[2].camera_id
    out = export.write_transforms_json(tmp_path / "t.json", ["a", "b", "c"], K, w2c, 128, np.array([96, 128, 96]))
    assert "w" not in out and [(f["w"], f["h"]) for f in out["frames"]] == [(128, 96), (128, 128), (128, 96)]
    assert export.read_transforms_json(tmp_path / "t.json")["size"].tolist() == [[128, 96], [128, 128], [128, 96]]


def test_colmap_model_carries_the_tracks_of_its_points(tmp_path):
    """Each point's observations become the images' POINTS2D and the point's TRACK[]: pycolmap finds every
    observation back, and projecting a point reproduces its observed pixels."""
    pycolmap = pytest.importorskip("pycolmap")
    K, w2c = random_cameras(3)
    points = np.random.default_rng(1).normal(scale=0.3, size=(6, 3))
    view, point = np.array([2, 0, 1, 0, 2, 1, 0, 2]), np.array([0, 0, 1, 1, 1, 3, 5, 5])
    Xc = np.einsum("oij,oj->oi", w2c[view, :3, :3], points[point]) + w2c[view, :3, 3]
    uv = np.einsum("oij,oj->oi", K[view], Xc)[:, :2] / Xc[:, 2:]
    valid = np.array([True, False, True])  # view 1 not exported: its observations neither
    export.write_colmap_text(tmp_path, ["a", "b", "c"], K, w2c, 192, 128, valid=valid, points=points,
                             colours=np.zeros((6, 3), np.uint8), tracks=(view, point, uv))
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert rec.compute_num_observations() == int(valid[view].sum()) == 6
    assert rec.compute_mean_reprojection_error() < 1e-4
    lengths = sorted(p.track.length() for p in rec.points3D.values())
    assert lengths == [0, 0, 0, 2, 2, 2]  # points 0, 1, 5 in views a and c; point 3 only in b (not exported)


def test_the_export_stage_writes_the_final_cameras_in_the_input_frame(tiny_run):
    """The tiny run's exports: the COLMAP model (read by pycolmap) and transforms.json give the same
    poses to 1e-9, namely the final poses mapped by world_from_model.json; in the synthetic scene
    that frame is its ground truth's, so the exported centres lie near the true cameras. The held-out
    views are exported too, at the input's own cameras, as nerfstudio's test split."""
    pytest.importorskip("pycolmap")
    import trimesh

    artifacts_dir, _ = tiny_run
    versions = runner.Store(artifacts_dir, "synthetic").lineage("export")
    out = versions["export"]
    final = artifacts.load_round(versions["successors"] / "final")
    placed = final["placed"].astype(bool)
    names = io.load_json(versions["ingest"] / "views.json")["names"]
    frame = export.read_frame(out / export.FRAME)
    assert frame["frame"] == "input" and frame["units"] == "unit"
    expected = cameras.transform_w2c(final["w2c"], *cameras.sim3_from_matrix(frame["world_from_model"]))
    gt_poses = artifacts.load_ground_truth_poses(versions["ground_truth"], ["w2c", "normalization"])
    held = np.isin(np.arange(len(names)), artifacts.load_schedule(versions["schedule"])["meta"]["held_out_views"])
    assert held.any() and not (held & placed).any()
    expected[held] = cameras.transform_w2c(gt_poses["w2c"][held], *cameras.sim3_from_matrix(gt_poses["normalization"]))
    exported = placed | held

    from_colmap = colmap_poses(out / "colmap")
    from_json = export.read_transforms_json(out / export.TRANSFORMS)
    assert sorted(from_colmap) == sorted(f"{names[i]}.png" for i in np.flatnonzero(exported))
    assert from_json["files"] == [f"images/{names[i]}.png" for i in np.flatnonzero(exported)]
    split = json.loads((out / export.TRANSFORMS).read_text())
    assert split["test_filenames"] == split["val_filenames"] == [f"images/{names[i]}.png" for i in np.flatnonzero(held)]
    assert split["train_filenames"] == [f"images/{names[i]}.png" for i in np.flatnonzero(placed)]
    for k, i in enumerate(np.flatnonzero(exported)):
        np.testing.assert_allclose(from_colmap[f"{names[i]}.png"][0], from_json["w2c"][k], rtol=0, atol=1e-9)
        # the rounds' poses are float32: exported, their rotations are made exactly orthonormal
        np.testing.assert_allclose(from_json["w2c"][k], expected[i], rtol=0, atol=1e-6)
        assert (out / from_json["files"][k]).is_file()
    gt = io.load_arrays(versions["ground_truth"] / "poses.zarr", ["w2c"])["w2c"]
    spread = np.linalg.norm(cameras.camera_centers(gt) - cameras.camera_centers(gt).mean(0), axis=1).mean()
    centre_error = np.linalg.norm(cameras.camera_centers(expected[placed]) - cameras.camera_centers(gt[placed]), axis=1)
    assert centre_error.mean() < 0.05 * spread

    # the mesh: the mesh stage's, mapped into the same frame, with the field's vertex colours
    ply, glb = trimesh.load(out / "mesh.ply", process=False), trimesh.load(out / "mesh.glb", force="mesh", process=False)
    model = trimesh.load(versions["mesh"] / "mesh.ply", process=False)
    np.testing.assert_allclose(ply.vertices, cameras.transform_points(frame["world_from_model"], model.vertices),
                               atol=1e-5)
    assert len(glb.faces) == len(ply.faces) == len(model.faces) > 0
    # glTF is +Y up: the synthetic world's up (+Z, the cameras' vertical) is the file's +Y
    gltf_from_world = np.asarray(frame["gltf_from_world"])
    np.testing.assert_allclose(gltf_from_world[:3, :3] @ [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], atol=0.02)
    np.testing.assert_allclose(np.sort(glb.vertices, 0),
                               np.sort(cameras.transform_points(gltf_from_world, ply.vertices), 0), atol=1e-5)
    colours = np.asarray(ply.visual.vertex_colors)[:, :3]
    assert ply.visual.kind == "vertex" and colours.std() > 0  # not one flat colour
    # the mesh stage's own mesh carries them already; the export keeps them
    assert model.visual.kind == "vertex" and np.array_equal(np.asarray(model.visual.vertex_colors)[:, :3], colours)

    # the last round's tracks: COLMAP's points3D with their observations and transforms.json's ply_file_path,
    # in the same frame; COLMAP's own reprojection error of them is what the rounds' tracks fit
    import pycolmap

    sfm = final["track_points"]
    meta = json.loads((out / export.TRANSFORMS).read_text())
    assert len(sfm) > 20 and meta["ply_file_path"] == "sparse_points.ply" and "fl_x" in meta  # one camera
    cloud = trimesh.load(out / meta["ply_file_path"])
    np.testing.assert_allclose(cloud.vertices, cameras.transform_points(frame["world_from_model"], sfm), atol=1e-5)
    rec = pycolmap.Reconstruction(str(out / "colmap"))
    assert len(rec.points3D) == len(sfm) and len(rec.cameras) == 1
    assert rec.compute_num_observations() == int(placed[final["track_obs_view"]].sum()) > 2 * len(sfm)
    assert all(p.track.length() >= 2 for p in rec.points3D.values())
    assert rec.compute_mean_reprojection_error() < 2.0  # px
    # coloured from the photos, not the grey of points no view sees
    assert np.asarray(cloud.colors)[:, :3].std() > 5


@pytest.mark.parametrize("tilt_deg", [0.0, 35.0, 80.0])
def test_the_vertical_is_found_from_level_cameras_looking_down_at_any_angle(tilt_deg):
    """Cameras on a ring above the object, held level (no roll), looking down by various amounts: the
    vertical is perpendicular to every camera's x axis, not their tilted mean up; the glTF turn takes
    it to +Y."""
    up = cameras.rotvec_to_matrix([0.4, -0.3, 0.2])[0] @ [0.0, 0.0, 1.0]  # a world whose up is no axis
    a, b = np.linalg.svd(np.eye(3) - np.outer(up, up))[0][:, :2].T  # the horizontal plane
    h = np.tan(np.radians(tilt_deg))
    eyes = [3.0 * (np.cos(t) * a + np.sin(t) * b + h * up) for t in np.linspace(0, 1.5 * np.pi, 9)]
    w2c = np.stack([cameras.look_at_w2c(e, np.zeros(3), up) for e in eyes])
    np.testing.assert_allclose(cameras.vertical_from_cameras(w2c), up, atol=1e-9)
    np.testing.assert_allclose(cameras.gltf_from_world(w2c)[:3, :3] @ up, [0.0, 1.0, 0.0], atol=1e-9)


def test_the_export_frame_undoes_the_alignment_and_the_normalisation(tmp_path):
    """world_from_model: the method's cameras are the input's under a known similarity and the input's
    own normalisation (DTU-like: mm, offset); the frame found maps them exactly onto the input's world."""
    from stages.export import world_from_model

    _, w2c_world = random_cameras(6, seed=3, spread=300.0)  # the input's cameras, in "mm"
    normalization = cameras.sim3_matrix(250.0, np.eye(3), np.array([10.0, -40.0, 600.0]))  # unit sphere -> mm
    gt_norm = cameras.transform_w2c(w2c_world, *cameras.sim3_from_matrix(np.linalg.inv(normalization)))
    model_from_gt = (0.7, cameras.rotvec_to_matrix([0.3, -0.2, 0.5])[0], np.array([0.1, 0.2, -0.3]))
    w2c_model = cameras.transform_w2c(gt_norm, *model_from_gt)  # what the method found, in its own gauge
    io.save_arrays(tmp_path / "poses.zarr", {"w2c": gt_norm, "normalization": normalization}, chunk_first=False)
    io.save_json(tmp_path / "gt.json", {"has_poses": True, "units": "mm"})
    valid = np.ones(6, bool)
    M, frame, units, how = world_from_model(tmp_path, w2c_model, valid, "input")
    assert (frame, units) == ("input", "mm") and "6 final camera centres" in how
    back = cameras.transform_w2c(w2c_model, *cameras.sim3_from_matrix(M))
    np.testing.assert_allclose(back, w2c_world, atol=1e-9)
    # asked for the method's frame, or too few views, or an input without cameras: identity
    assert world_from_model(tmp_path, w2c_model, valid, "model")[1] == "model"
    assert world_from_model(tmp_path, w2c_model, np.arange(6) < 2, "input")[1] == "model"
    io.save_json(tmp_path / "gt.json", {"has_poses": False})
    M, frame, _, how = world_from_model(tmp_path, w2c_model, valid, "input")
    assert frame == "model" and np.array_equal(M, np.eye(4)) and "no cameras of its own" in how


@pytest.mark.skipif(importlib.util.find_spec("nerfstudio") is None,
                    reason="nerfstudio is not installed; export.read_transforms_json checks the format")
def test_nerfstudio_reads_the_export_when_installed(tiny_run):
    """nerfstudio's own dataparser on transforms.json (shared intrinsics at the top, ply_file_path);
    skipped where nerfstudio is not installed (it is not a dependency: the format is checked above)."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    artifacts_dir, _ = tiny_run
    out = runner.Store(artifacts_dir, "synthetic").lineage("export")["export"]
    meta = json.loads((out / export.TRANSFORMS).read_text())
    parsed = NerfstudioDataParserConfig(data=out, orientation_method="none", center_method="none",
                                        auto_scale_poses=False, train_split_fraction=1.0,
                                        load_3D_points=True).setup().get_dataparser_outputs("train")
    assert len(parsed.image_filenames) == len(meta["train_filenames"]) < len(meta["frames"])
    assert float(parsed.cameras.fx[0]) == pytest.approx(meta["fl_x"])
    assert parsed.metadata["points3D_xyz"].shape[0] > 20
