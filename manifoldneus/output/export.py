"""Exports of the method's result in other tools' formats.

* COLMAP text model (:func:`write_colmap_text`; pycolmap, COLMAP, most NeRF/GS tools read it): one
  camera per physical camera, the SfM points as ``points3D``;
* nerfstudio's ``transforms.json`` (:func:`write_transforms_json`, read back by
  :func:`read_transforms_json`): camera-to-world poses with OpenGL camera axes
  (:func:`manifoldneus.geometry.cameras.opengl_c2w`), intrinsics at the top level when shared (else per
  frame), image paths relative to the file, ``ply_file_path`` the SfM points (:func:`write_points_ply`);
* the mesh as PLY and as binary glTF (``.glb``: browsers, Blender, three.js), with vertex colours;
  the glTF turned so that the scene's vertical is its +Y (:func:`manifoldneus.geometry.cameras.gltf_from_world`);
* ``world_from_model.json``: the similarity from the method's unit-sphere frame to the frame of the
  exports (:func:`write_frame`), so that any result of the pipeline can be brought into it.

Image file names are ``<view name>.<format>``, white space as ``_`` (:func:`image_filename`).
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from manifoldneus.geometry import cameras

TRANSFORMS = "transforms.json"
FRAME = "world_from_model.json"


def image_filename(name: str, suffix: str = ".png") -> str:
    """The file name of a view's image in every export (and in the reference stage's COLMAP run): white
    space becomes ``_``, since COLMAP's text models end a name at the first space; ``suffix`` the file's
    format (a PNG of the ingested pixels, or the input file's own)."""
    return re.sub(r"\s", "_", name) + suffix


def image_sizes(width, height, n: int) -> np.ndarray:
    """[n,2] (width, height) of each view: ``width`` and ``height`` one for all, or one per view [n] each
    (photos of several sizes)."""
    return np.stack([np.broadcast_to(np.asarray(v, np.int64), (n,)) for v in (width, height)], -1)


def shared_cameras(K: np.ndarray, valid: np.ndarray, sizes: np.ndarray | None = None) -> np.ndarray:
    """Camera index [N] per view: views whose intrinsics agree (to 1e-9 relative) and, given ``sizes`` [N,2],
    whose image sizes agree share one camera, as the photos of one physical camera do (COLMAP: a camera per
    size); numbered in order of first use among the ``valid`` views."""
    index, reps = np.full(len(K), -1), []
    same = (lambda i, r: True) if sizes is None else (lambda i, r: np.array_equal(sizes[i], sizes[r]))
    for i in np.flatnonzero(valid):
        match = next((c for c, r in enumerate(reps) if np.allclose(K[i], K[r], rtol=1e-9, atol=0.0) and same(i, r)),
                     None)
        if match is None:
            reps.append(i)
            match = len(reps) - 1
        index[i] = match
    return index


def write_colmap_text(folder: Path, names, K: np.ndarray, w2c: np.ndarray, width, height, valid=None,
                      points: np.ndarray | None = None, colours: np.ndarray | None = None,
                      tracks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, suffixes=None) -> None:
    """COLMAP text model: a PINHOLE camera per set of equal intrinsics and image size (:func:`shared_cameras`;
    ``width``, ``height`` one for all or per view, :func:`image_sizes`), poses
    world-to-camera, and ``points`` [P,3] with ``colours`` [P,3] uint8 as 3D points; ``tracks`` = (view [O],
    point [O], uv [O,2] px) their observations (the images' POINTS2D and the points' TRACK[]: what COLMAP's
    image_undistorter and patch_match_stereo read); observations in views not ``valid`` are left out.
    ``suffixes``: each view's image format (:func:`image_filename`; default PNG)."""
    from scipy.spatial.transform import Rotation

    folder.mkdir(parents=True, exist_ok=True)
    valid = np.ones(len(names), bool) if valid is None else np.asarray(valid, bool)
    n_points = 0 if points is None else len(points)
    view, point, uv = tracks if tracks is not None else (np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2)))
    keep = valid[view] & (point < n_points)
    view, point, uv = np.asarray(view)[keep], np.asarray(point)[keep], np.asarray(uv)[keep]
    order = np.argsort(view, kind="stable")  # each image's observations together, in their order
    view, point, uv = view[order], point[order], uv[order]
    index = np.arange(len(view)) - np.searchsorted(view, view)  # [O] the observation's POINT2D_IDX in its image
    wh = image_sizes(width, height, len(names))
    camera_of = shared_cameras(K, valid, wh)
    cams = ["# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    imgs = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "# POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, name in enumerate(names):
        if not valid[i]:
            continue
        if camera_of[i] == len(cams) - 1:  # a camera's first view
            k = K[i]
            cams.append(f"{camera_of[i] + 1} PINHOLE {wh[i, 0]} {wh[i, 1]} {k[0, 0]:.17g} {k[1, 1]:.17g} {k[0, 2]:.17g} "
                        f"{k[1, 2]:.17g}")
        x, y, z, w = Rotation.from_matrix(w2c[i][:3, :3]).as_quat()
        t = w2c[i][:3, 3]
        imgs.append(f"{i + 1} {w:.17g} {x:.17g} {y:.17g} {z:.17g} {t[0]:.17g} {t[1]:.17g} {t[2]:.17g} "
                    f"{camera_of[i] + 1} {image_filename(name, *([] if suffixes is None else [suffixes[i]]))}")
        a, b = np.searchsorted(view, [i, i + 1])
        imgs.append(" ".join(f"{u:.6g} {v:.6g} {j + 1}" for (u, v), j in zip(uv[a:b], point[a:b])))
    pts = ["# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    by_point = np.argsort(point, kind="stable")
    starts = np.searchsorted(point[by_point], np.arange(n_points + 1))
    for j, (X, c) in enumerate(zip(np.zeros((0, 3)) if points is None else points,
                                   np.zeros((0, 3), np.uint8) if colours is None else colours)):
        obs = by_point[starts[j]:starts[j + 1]]
        track = "".join(f" {view[o] + 1} {index[o]}" for o in obs)
        pts.append(f"{j + 1} {X[0]:.9g} {X[1]:.9g} {X[2]:.9g} {int(c[0])} {int(c[1])} {int(c[2])} 0{track}")
    (folder / "cameras.txt").write_text("\n".join(cams) + "\n")
    (folder / "images.txt").write_text("\n".join(imgs) + "\n")
    (folder / "points3D.txt").write_text("\n".join(pts) + "\n")


def point_colours(points: np.ndarray, images: np.ndarray, K: np.ndarray, w2c: np.ndarray, views,
                  sizes: np.ndarray | None = None) -> np.ndarray:
    """Colour [P,3] uint8 of each point: the median over the ``views`` whose image it falls in (grey
    where none); ``sizes`` [N,2] (H, W) each view's own part of the images' canvas (None: all of it)."""
    samples = np.full((len(views), len(points), 3), np.nan)
    for k, i in enumerate(views):
        H, W = images.shape[1:3] if sizes is None else sizes[i]
        xc = points @ w2c[i][:3, :3].T + w2c[i][:3, 3]  # [P,3]
        uv = (xc @ K[i].T)[:, :2] / np.clip(xc[:, 2:], 1e-9, None)
        ok = (xc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        samples[k, ok] = images[i][uv[ok, 1].astype(int), uv[ok, 0].astype(int), :3]
    scale = 255.0 if images.dtype != np.uint8 and images.max() <= 1.0 else 1.0
    with np.errstate(all="ignore"):
        median = np.nanmedian(samples, 0) * scale if len(views) else np.full((len(points), 3), np.nan)
    return np.nan_to_num(median, nan=128.0).clip(0, 255).round().astype(np.uint8)


def write_points_ply(path: Path, points: np.ndarray, colours: np.ndarray) -> None:
    """A coloured point cloud (``ply_file_path`` of transforms.json: splatfacto starts from it)."""
    import trimesh

    trimesh.PointCloud(points, colors=colours).export(path)


def write_transforms_json(path: Path, names, K: np.ndarray, w2c: np.ndarray, width, height, valid=None,
                          image_dir: str = "images", mask_dir: str | None = None,
                          ply_file_path: str | None = None, test=None, suffixes=None) -> dict:
    """nerfstudio's ``transforms.json`` (its ``nerfstudio-data`` layout) for the ``valid`` views:
    per frame ``file_path`` (relative to the file) and ``transform_matrix``, the camera-to-world pose
    with OpenGL camera axes; pinhole intrinsics ``fl_x fl_y cx cy w h`` in pixels (pixel centres at
    +0.5, as COLMAP and nerfstudio; ``width``, ``height`` one for all or per view, :func:`image_sizes`) at the
    top level when every view shares them, else per frame;
    ``ply_file_path`` (relative) names the initial point cloud. ``test`` (bool [N]): views of nerfstudio's
    test and validation split (``test_filenames``, ``val_filenames``; the other valid views are
    ``train_filenames``); None or none of them: no split is written. ``suffixes``: each view's image format
    (:func:`image_filename`; default PNG; masks are PNGs). Returns what it wrote."""
    valid = np.ones(len(names), bool) if valid is None else np.asarray(valid, bool)
    c2w = cameras.opengl_c2w(w2c)  # [N,4,4]

    wh = image_sizes(width, height, len(names))

    def intrinsics(i) -> dict:
        k = K[i]
        return {"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2]),
                "w": int(wh[i, 0]), "h": int(wh[i, 1])}

    shared = valid.any() and shared_cameras(K, valid, wh).max() == 0
    frames = []
    for i in np.flatnonzero(valid):
        image = image_filename(names[i], *([] if suffixes is None else [suffixes[i]]))
        frame = {"file_path": f"{image_dir}/{image}", **({} if shared else intrinsics(i)),
                 "transform_matrix": c2w[i].tolist()}
        if mask_dir is not None:
            frame["mask_path"] = f"{mask_dir}/{image_filename(names[i])}"
        frames.append(frame)
    out = {"camera_model": "OPENCV", **(intrinsics(np.flatnonzero(valid)[0]) if shared else {})}
    if ply_file_path is not None:
        out["ply_file_path"] = ply_file_path
    out["frames"] = frames
    if test is not None and np.any(test):
        test = np.asarray(test, bool)[np.flatnonzero(valid)]
        split = {"train": [f["file_path"] for f, t in zip(frames, test) if not t],
                 "val": [f["file_path"] for f, t in zip(frames, test) if t]}
        out.update(train_filenames=split["train"], val_filenames=split["val"], test_filenames=split["val"])
    Path(path).write_text(json.dumps(out, indent=1) + "\n")
    return out


def read_transforms_json(path: Path) -> dict:
    """A ``transforms.json`` (nerfstudio's layout; intrinsics per frame or shared at the top level)
    in this project's conventions: ``files`` (paths as written), ``K`` [N,3,3], ``w2c`` [N,4,4]
    (OpenCV camera axes), ``size`` [N,2] (w, h)."""
    meta = json.loads(Path(path).read_text())

    def get(frame: dict, key: str):
        value = frame.get(key, meta.get(key))
        if value is None:
            raise ValueError(f"{path}: frame {frame.get('file_path')!r} has no {key!r} (nor does the file)")
        return float(value)

    frames = meta["frames"]
    K = np.array([[[get(f, "fl_x"), 0.0, get(f, "cx")], [0.0, get(f, "fl_y"), get(f, "cy")], [0.0, 0.0, 1.0]]
                  for f in frames]).reshape(-1, 3, 3)
    c2w = np.array([f["transform_matrix"] for f in frames], np.float64).reshape(-1, 4, 4)
    return {"files": [f["file_path"] for f in frames], "K": K, "w2c": cameras.w2c_from_opengl_c2w(c2w),
            "size": np.array([[get(f, "w"), get(f, "h")] for f in frames]).reshape(-1, 2).astype(int)}


def write_mesh(mesh, folder: Path, gltf_from_world: np.ndarray, stem: str = "mesh") -> None:
    """``<stem>.ply`` (as given) and ``<stem>.glb`` (binary glTF, turned by ``gltf_from_world`` [4,4]
    so that up is +Y as glTF wants; vertex colours as COLOR_0 when the mesh has them)."""
    folder.mkdir(parents=True, exist_ok=True)
    mesh.export(folder / f"{stem}.ply")
    mesh.copy().apply_transform(gltf_from_world).export(folder / f"{stem}.glb", file_type="glb")


def write_frame(path: Path, world_from_model: np.ndarray, frame: str, units: str, how: str,
                gltf_from_world: np.ndarray) -> dict:
    """``world_from_model.json``: the 4x4 similarity ``y = s R x + t`` taking the method's frame
    (the poses and mesh of the ``successors``/``mesh`` stages) to the exports' frame, as a matrix
    and as (s, R, t), with a word on which frame that is and how the similarity was found; and the
    rotation from that frame to the glTF file's (+Y up)."""
    s, R, t = cameras.sim3_from_matrix(world_from_model)
    out = {"world_from_model": np.asarray(world_from_model, np.float64).tolist(), "s": s, "R": R.tolist(),
           "t": t.tolist(), "frame": frame, "units": units, "how": how,
           "convention": "y = s R x + t maps a point of the method's frame to this frame; poses map with "
                         "manifoldneus.geometry.cameras.transform_w2c(w2c, s, R, t)",
           "gltf_from_world": np.asarray(gltf_from_world, np.float64).tolist(),
           "gltf": "mesh.glb holds gltf_from_world @ the points of this frame: the cameras' vertical is its +Y "
                   "(glTF's up); mesh.ply, colmap/ and transforms.json are in this frame"}
    Path(path).write_text(json.dumps(out, indent=1) + "\n")
    return out


def read_frame(path: Path) -> dict:
    """:func:`write_frame`'s file, ``world_from_model`` as a [4,4] array."""
    out = json.loads(Path(path).read_text())
    out["world_from_model"] = np.asarray(out["world_from_model"], np.float64)
    return out
