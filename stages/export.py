"""export: the result in other tools' formats, in the input's world frame.

Writes, for the views with a final pose: the COLMAP text model (``colmap/``: one camera per set of
shared intrinsics, the last round's tracks as ``points3D`` with their observations), nerfstudio's ``transforms.json`` (OpenGL
camera-to-world, shared intrinsics at the top level, ``ply_file_path`` = ``sparse_points.ply``, those
points coloured from the images), the images they name
(``images/<view>.<format>``: the input's own files where their pixels are those K refers to, else PNGs of the
ingested images, ``export.image_files``; ``masks/`` where the scene has masks),
and the final mesh as ``mesh.ply`` and ``mesh.glb`` with vertex colours from the final field (the
glTF turned so that the cameras' vertical is +Y, glTF's up; the turn is in ``world_from_model.json``).

Frame (``export.frame``): ``input`` is the world of the input's own cameras where the scene has
them (DTU's ``cameras*.npz`` in mm, a COLMAP model's world, the synthetic scene's frame): the
similarity fitted on the final camera centres onto those cameras (Umeyama, as ``evaluate``), then
the input's unit-sphere normalisation undone. That is why this stage reads ``ground_truth``; only
this frame is taken from it, nothing of the method. In that frame the views held out for evaluation
(the schedule's) are exported too, at the input's own cameras (they have no pose of the method), and
transforms.json lists them as nerfstudio's test and validation split (``test_filenames``), the
method's views as its training split. A scene without cameras of its own (a plain
photo folder) has no input world: the exports stay in the method's unit-sphere frame. Either way
``world_from_model.json`` holds the similarity from the method's frame to the exports' frame.
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manifoldneus.data import artifacts, io
from manifoldneus.data.views import own
from manifoldneus.geometry import cameras
from manifoldneus.output import evaluation, export, meshing
from manifoldneus.config import param


@dataclass
class Params:
    """Section `export` of params.yaml."""

    frame: str = param("input", "Frame of the exports: input (the input cameras' world, where the scene has "
                       "cameras; else the method's) | model (the method's unit-sphere frame)",
                       choices=["input", "model"])
    images: bool = param(True, "Write the ingested images (and masks) that transforms.json and the COLMAP model name "
                         "(without the lens distortion the self-calibration found, if it found one: the exported "
                         "cameras are pinhole cameras)")
    vertex_colours: bool = param(True, "Colour the mesh's vertices with the final field's colour seen head-on")
    image_files: str = param("as_given", "as_given: each exported image is the input's own file (its format and "
                             "bytes) where its pixels are the ingested ones (no lens distortion removed, no downscale, "
                             "no EXIF rotation to apply), else a PNG of the ingested pixels; png: always a PNG",
                             choices=["as_given", "png"])


UPSTREAM = ("ingest", "ground_truth", "schedule", "anchors", "surface", "mesh")
SECTIONS = ("export", "run.device")
OUTPUTS = ("colmap", export.TRANSFORMS, artifacts.MESH, "mesh.glb", export.FRAME)


def world_from_model(gt_dir, w2c: np.ndarray, valid: np.ndarray, frame: str) -> tuple[np.ndarray, str, str, str]:
    """(4x4 similarity method -> export frame, frame name, units, how it was found)."""
    gt_meta = artifacts.load_gt_meta(gt_dir)
    if frame == "model":
        return np.eye(4), "model", "model units", "export.frame = model"
    if not gt_meta.get("has_poses"):
        return np.eye(4), "model", "model units", "the input has no cameras of its own, so no world frame"
    if valid.sum() < 3:
        return np.eye(4), "model", "model units", f"only {int(valid.sum())} final views: too few for a Sim3"
    gt = artifacts.load_ground_truth_poses(gt_dir, ["w2c", "normalization"])
    s, R, t = cameras.align_centres(w2c, gt["w2c"], valid)
    M = gt["normalization"] @ cameras.sim3_matrix(s, R, t)
    how = (f"Sim3 (Umeyama) of the {int(valid.sum())} final camera centres onto the input's cameras "
           f"(scale {s:.6g}), then the input's normalisation to the unit sphere undone")
    return M, "input", gt_meta["units"], how


def rigid(w2c: np.ndarray) -> np.ndarray:
    """Poses [N,4,4] with each rotation replaced by its nearest rotation matrix: the rounds store float32
    poses, orthonormal to 1e-7 only, and a COLMAP model (quaternions) can hold nothing but rotations;
    so both exports hold the same poses."""
    from scipy.spatial.transform import Rotation

    out = cameras.to_4x4(w2c)
    out[:, :3, :3] = Rotation.from_matrix(out[:, :3, :3]).as_matrix()
    return out


def given_files(files: list | None, n: int, pinhole: bool, how: str) -> list:
    """Per view the input's own image file to export as it is, or None (a PNG of the ingested pixels):
    only where the ingest kept the file's pixels, no lens distortion was removed (``pinhole``) and the file
    asks no viewer to rotate it (EXIF orientation 1: the ingest reads pixels as stored)."""
    from PIL import Image

    def as_is(path) -> bool:
        if path is None or not Path(path).is_file():
            return False
        with Image.open(path) as im:
            return im.getexif().get(0x0112, 1) == 1

    if files is None or how != "as_given" or not pinhole:
        return [None] * n
    return [f if as_is(f) else None for f in files]


def run(ctx) -> None:
    p: Params = ctx.params
    final_dir = ctx.input("surface")
    final = artifacts.load_round(final_dir)
    w2c, placed = final["w2c"], final["placed"].astype(bool)
    valid = placed & final["optimised"].astype(bool)
    views = artifacts.load_views(ctx.input("ingest"), w2c, final["K"], final.get("distortion"))
    lens_k1 = None if final.get("distortion") is None else float(final["distortion"][valid][:, 0].mean())
    if lens_k1 is not None:  # the images written below are undistorted, so every exported camera is a pinhole
        ctx.log.info("the images are exported without the lens distortion the self-calibration found (k1 %.4g): "
                     "every exported camera is a pinhole camera", lens_k1)
    M, frame, units, how = world_from_model(ctx.input("ground_truth"), w2c, valid, p.frame)
    ctx.log.info("exports in the %s frame (%s): %s", frame, units, how)
    s, R, t = cameras.sim3_from_matrix(M)
    w2c_world = rigid(cameras.transform_w2c(w2c, s, R, t))  # [N,4,4]
    held = np.isin(np.arange(len(w2c)), artifacts.load_schedule_meta(ctx.input("schedule"))["held_out_views"])
    held &= ~placed & (frame == "input")  # the input's own cameras place them in its frame only
    if held.any():
        gt = artifacts.load_ground_truth_poses(ctx.input("ground_truth"), ["w2c", "normalization"])
        w2c_world[held] = rigid(cameras.transform_w2c(gt["w2c"][held], *cameras.sim3_from_matrix(gt["normalization"])))
        ctx.log.info("%d held-out views exported at the input's own cameras (transforms.json: test_filenames)",
                     int(held.sum()))
    exported = placed | held

    import trimesh

    mesh = meshing.load_mesh(ctx.input("mesh") / artifacts.MESH)
    coloured = mesh.visual.kind == "vertex"  # the mesh stage's colours (meshing.vertex_colours)
    if not p.vertex_colours and coloured:
        mesh.visual = trimesh.visual.ColorVisuals(mesh)
    elif p.vertex_colours and len(mesh.faces) and not coloured:
        surface = evaluation.load_surface_field(final_dir, ctx.input("ingest"), ctx.section("run").device)
        in_field = mesh.copy().apply_transform(surface.field_from_model)  # the mesh is in the rounds' frame
        colours = evaluation.field_vertex_colours(surface.trainer, np.array(in_field.vertices),
                                                  np.array(in_field.vertex_normals))
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=colours)
    mesh.apply_transform(M)
    gltf_from_world = cameras.gltf_from_world(w2c_world[valid])
    export.write_mesh(mesh, ctx.out, gltf_from_world)

    h, w = views.view_sizes[:, 0], views.view_sizes[:, 1]  # [N] each: photos of several sizes, a camera each
    # the last round's tracks over every view (the method's frame; else the SfM points that initialised the
    # anchors, without observations), as COLMAP's points3D and splatfacto's start
    tracks = None
    if final.get("track_obs_view") is not None:
        points = final["track_points"]
        tracks = (final["track_obs_view"], final["track_obs_point"], final["track_obs_uv"])
    else:
        points = artifacts.load_initial_poses(ctx.input("anchors"), ["object_points"])["object_points"]
    points = cameras.transform_points(M, np.asarray(points, np.float64).reshape(-1, 3))
    colours = export.point_colours(points, views.images, views.K, w2c_world, np.flatnonzero(placed), views.view_sizes)
    ply = None
    if len(points):
        ply = "sparse_points.ply"
        export.write_points_ply(ctx.out / ply, points, colours)
    given = given_files(artifacts.load_views_meta(ctx.input("ingest")).get("files"), len(views.names), lens_k1 is None,
                        p.image_files)
    suffixes = [".png" if f is None else Path(f).suffix for f in given]
    export.write_colmap_text(ctx.out / "colmap", views.names, views.K, w2c_world, w, h, valid=exported,
                             points=points, colours=colours, tracks=tracks, suffixes=suffixes)
    mask_dir = "masks" if p.images and views.masks is not None else None
    export.write_transforms_json(ctx.out / export.TRANSFORMS, views.names, views.K, w2c_world, w, h, valid=exported,
                                 mask_dir=mask_dir, ply_file_path=ply, test=held, suffixes=suffixes)
    if p.images:
        for folder, stack in (("images", views.images), (mask_dir, views.masks)):
            if folder is None:
                continue
            (ctx.out / folder).mkdir()
            for i in np.flatnonzero(exported):
                if folder == "images" and given[i] is not None:
                    shutil.copyfile(given[i], ctx.out / folder / export.image_filename(views.names[i], suffixes[i]))
                else:  # at the view's own size
                    io.save_png(ctx.out / folder / export.image_filename(views.names[i]), own(stack[i], views.view_sizes[i]))
    export.write_frame(ctx.out / export.FRAME, M, frame, units, how, gltf_from_world)
    ctx.metrics.update(frame=frame, units=units, scale=s, views_exported=int(placed.sum()), held_out_exported=int(held.sum()), sfm_points=len(points),
                       lens_k1_removed=lens_k1,
                       vertices=int(len(mesh.vertices)), faces=int(len(mesh.faces)),
                       vertex_colours=bool(p.vertex_colours and len(mesh.faces)))
