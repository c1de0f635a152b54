"""reference: the pycolmap incremental-SfM baseline on the same images.

COLMAP's own SIFT extraction, exhaustive matching with its two-view verification, and
incremental mapping (:mod:`manifoldneus.sfm.mapper`'s options), on the ingest's images. Intrinsics
(``intrinsics``): ``fixed`` holds the ingest's K (PINHOLE from K; nothing refined); ``refine``
starts from the ingest's K (one camera for one K) and refines ``refine_intrinsics`` (focal length
and principal point) by bundle adjustment; ``estimate`` starts from COLMAP's own guess and refines
the same; ``auto`` (default) is ``fixed`` for
calibrated or given intrinsics and ``refine`` when the ingest's K is an EXIF prior or a guess
(``views.json``'s ``intrinsics_source``). The estimated focal length is in the metrics.

Outputs:

- ``poses.zarr``: ``w2c`` float64 [N,4,4] world-to-camera in the project's convention
  (COLMAP's ``cam_from_world`` is already OpenCV-frame world-to-camera), in COLMAP's arbitrary
  world frame and scale (align with a similarity before comparing); ``registered`` bool [N]
  (unregistered views get the identity pose, so the array is NaN-free); ``K`` float64 [N,3,3]
  of the cameras used (the ingest's K when fixed); ``points3d`` float64 [P,3] and
  ``points3d_rgb`` uint8 [P,3] of the sparse model.
- ``sparse/``: the COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``);
  image names are ``<view name>.png``.

Metrics: ``extract_match_seconds`` (COLMAP feature extraction + exhaustive matching and
verification, reading PNGs written beforehand) and ``mapping_seconds`` (incremental mapping)
separately, registered count, unregistered view names.
"""
from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manifoldneus.data import artifacts
from manifoldneus.data.views import own
from manifoldneus.sfm import mapper as sfm
from manifoldneus.config import ParamError, param
from manifoldneus.data.io import native_output_to


@dataclass
class Params:
    """Section `reference` of params.yaml."""

    intrinsics: str = param(
        "auto", "fixed: the ingest's K held constant; refine: focal length refined from the ingest's K; estimate: "
        "COLMAP's own guess, refined; auto: fixed for calibrated or given intrinsics, else refine",
        choices=["auto", "fixed", "refine", "estimate"])
    refine_intrinsics: list[str] = param(["focal", "principal_point"], "What refine and estimate change (the anchors' "
                                         "self-calibration refines the same): focal, principal_point")
    principal_point_p: float = param(1e-3, "The principal point is freed only when a likelihood-ratio test at this "
                                     "p-value says it pays, as in the anchors' self-calibration (anchors."
                                     "principal_point_p); 1 = always", lo=0.0, hi=1.0)
    max_features: int = param(8192, "COLMAP SIFT max_num_features per image", lo=1)
    num_threads: int = param(1, "Threads for COLMAP extraction, matching and mapping (-1 = all cores). COLMAP's "
                             "result is the same twice only single-threaded (measured: 2 threads moved a tiny scene's "
                             "poses by 2.6e-3 between two runs)", lo=-1)
    seed: int = param(0, "Random seed of COLMAP's RANSAC and mapper", lo=0)
    min_num_matches: int = param(15, "Minimum verified matches of a pair used by the mapper", lo=1)
    when: str = param("cameras", "cameras: only for an input with cameras of its own to score it against (a user's "
                      "photos skip it); always: every input (what the anchors need to start from it, "
                      "anchors.pose_init = reference, on photos)", choices=["cameras", "always"])

    def __post_init__(self):
        unknown = set(self.refine_intrinsics) - {"focal", "principal_point"}
        if unknown:
            raise ParamError(f"reference.refine_intrinsics: {sorted(unknown)} not among focal, principal_point")


UPSTREAM = ("ingest",)
SECTIONS = ("reference",)
OUTPUTS = (artifacts.POSES, "sparse")


# --------------------------------------------------------------------------- plain functions


def _same_K(K: np.ndarray, tol: float = 1e-3) -> bool:
    return bool(np.all(np.abs(K - K[0]) < tol))


def run_colmap(
    image_dir: Path,
    names: list[str],
    K: np.ndarray | None,
    work_dir: Path,
    *,
    intrinsics: str = "fixed",
    refine: tuple = ("focal",),
    principal_point_p: float = 1.0,
    max_features: int = 8192,
    num_threads: int = 1,
    seed: int = 0,
    min_num_matches: int = 15,
    one_size: bool = True,
    log=None,
) -> dict:
    """pycolmap extraction + exhaustive matching + incremental mapping.

    image_dir holds ``names`` (file names); K: [N,3,3] pixel intrinsics in COLMAP's convention
    (top-left pixel centre at (0.5, 0.5), the project's too), required when intrinsics="fixed".
    ``one_size`` False: the images have several sizes, a camera each when they are calibrated here.
    Returns dict(w2c [N,4,4], registered [N], K [N,3,3], points3d, points3d_rgb,
    reconstruction (pycolmap.Reconstruction or None), extract_match_seconds, mapping_seconds,
    n_models).
    """
    import pycolmap

    say = log.info if log is not None else (lambda *_: None)
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    db = work_dir / "database.db"
    if db.exists():
        db.unlink()
    if num_threads == 0:
        num_threads = -1
    pycolmap.set_random_seed(seed)

    fixed = intrinsics in ("fixed", "refine")  # the camera starts from the ingest's K
    if fixed and K is None:
        raise ValueError(f"reference.intrinsics={intrinsics} needs intrinsics K from the ingest")
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    if fixed and _same_K(K):
        camera_mode = pycolmap.CameraMode.SINGLE
        k = K[0]
        reader.camera_params = ",".join(f"{v:.10g}" for v in (k[0, 0], k[1, 1], k[0, 2], k[1, 2]))
    elif fixed:
        camera_mode = pycolmap.CameraMode.PER_IMAGE  # per-view K written into the database below
    else:  # AUTO: COLMAP's camera per image size (and EXIF)
        camera_mode = pycolmap.CameraMode.SINGLE if one_size else pycolmap.CameraMode.AUTO

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.sift.max_num_features = max_features
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed

    t0 = time.perf_counter()
    pycolmap.extract_features(
        db, image_dir, image_names=list(names), camera_mode=camera_mode, reader_options=reader,
        extraction_options=extraction, device=pycolmap.Device.cpu,
    )
    if fixed and camera_mode == pycolmap.CameraMode.PER_IMAGE:
        database = pycolmap.Database.open(str(db))
        index = {nm: v for v, nm in enumerate(names)}
        for image in database.read_all_images():
            cam = database.read_camera(image.camera_id)
            k = K[index[image.name]]
            cam.params = [k[0, 0], k[1, 1], k[0, 2], k[1, 2]]
            cam.has_prior_focal_length = True
            database.update_camera(cam)
        database.close()
    pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu)
    t_extract = time.perf_counter() - t0
    say(f"pycolmap extraction + exhaustive matching: {t_extract:.2f} s")

    refine = () if intrinsics == "fixed" else tuple(refine)
    first = tuple(r for r in refine if r != "principal_point")  # the principal point only if the test says so
    opts = sfm.mapping_options(first, num_threads=num_threads, seed=seed, min_num_matches=min_num_matches)
    opts.extract_colors = True
    t0 = time.perf_counter()
    rec, n_models = sfm.incremental_mapping(db, opts, work_dir, image_dir)
    pp_test = None
    if rec is not None and first != refine:
        rec, pp_test = sfm.free_intrinsic(rec, refine, "principal_point", principal_point_p, log=say)
    t_map = time.perf_counter() - t0
    say(f"pycolmap incremental mapping: {t_map:.2f} s, {n_models} model(s)")
    poses = sfm.read_poses(rec, names, K)
    w2c, registered, K_out = poses["w2c"], poses["registered"], poses["K"]
    pts = [(p.xyz, p.color) for p in rec.points3D.values()] if rec is not None else []
    return {
        "w2c": w2c,
        "registered": registered,
        "K": K_out,
        "points3d": np.array([p[0] for p in pts], np.float64).reshape(-1, 3),
        "points3d_rgb": np.array([p[1] for p in pts], np.uint8).reshape(-1, 3),
        "reconstruction": rec,
        "extract_match_seconds": float(t_extract),
        "mapping_seconds": float(t_map),
        "n_models": n_models,
        "principal_point_test": pp_test,
    }


# --------------------------------------------------------------------------- stage


def skip(ctx, names: list[str], K: np.ndarray) -> None:
    """No reference: every view unregistered, an empty model (what a failed mapping leaves)."""
    ctx.log.info("skipped: the input has no cameras of its own to score pycolmap against (reference.when = always "
                 "runs it)")
    (Path(ctx.out) / "sparse").mkdir()
    n = len(names)
    artifacts.save_reference_poses(ctx.out, {"w2c": np.tile(np.eye(4), (n, 1, 1)), "registered": np.zeros(n, bool),
                                             "K": np.asarray(K, np.float64), "points3d": np.zeros((0, 3)),
                                             "points3d_rgb": np.zeros((0, 3), np.uint8)},
                                   attrs={"names": names, "skipped": "the input has no cameras of its own"})
    ctx.metrics.update(skipped=True, n_registered=0, n_views=n)


def run(ctx) -> None:
    from manifoldneus.data.io import save_png

    p: Params = ctx.params
    src = Path(ctx.input("ingest"))
    meta = artifacts.load_views_meta(src)
    names = list(meta["names"])
    arrays = artifacts.load_views_arrays(src, ["images", "sizes", "K"])
    if p.when == "cameras" and not meta.get("has_cameras", True):
        skip(ctx, names, arrays["K"])
        return
    files = [f"{Path(nm).stem if Path(nm).suffix else nm}.png" for nm in names]
    intrinsics = sfm.intrinsics_mode(p.intrinsics, meta.get("intrinsics_source", "calibrated"))
    if len(set(files)) != len(files):
        files = [f"{v:06d}.png" for v in range(len(names))]

    tmp = Path(tempfile.mkdtemp(prefix="manifoldneus_reference_"))
    try:
        image_dir = tmp / "images"
        image_dir.mkdir()
        for f, im, hw in zip(files, arrays["images"], arrays["sizes"]):
            save_png(image_dir / f, own(im, hw))
        with native_output_to(ctx.log_path):  # COLMAP's own log (hundreds of lines) goes to log.txt
            res = run_colmap(
                image_dir, files, arrays["K"].astype(np.float64), tmp, intrinsics=intrinsics,
                refine=tuple(p.refine_intrinsics), principal_point_p=p.principal_point_p,
                max_features=p.max_features, num_threads=p.num_threads, seed=p.seed,
                min_num_matches=p.min_num_matches, one_size=len(np.unique(arrays["sizes"], axis=0)) == 1,
                log=ctx.log,
            )
        sparse = Path(ctx.out) / "sparse"
        sparse.mkdir()
        if res["reconstruction"] is not None:
            res["reconstruction"].write_text(str(sparse))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    artifacts.save_reference_poses(
        ctx.out,
        {k: res[k] for k in ("w2c", "registered", "K", "points3d", "points3d_rgb")},
        attrs={
            "names": names,
            "colmap_names": files,
            "frame": "COLMAP world frame (arbitrary similarity); OpenCV camera frame, world-to-camera",
            "intrinsics": intrinsics,
        },
    )
    reg = res["registered"]
    missing = [names[v] for v in np.flatnonzero(~reg)]
    if missing:
        ctx.log.warning(f"pycolmap left {len(missing)} of {len(names)} views unregistered: {', '.join(missing)}")
    ctx.log.info(
        f"pycolmap registered {int(reg.sum())}/{len(names)} views, {len(res['points3d'])} points, "
        f"{res['n_models']} model(s)"
    )
    ctx.metrics["n_registered"] = int(reg.sum())
    ctx.metrics["n_views"] = len(names)
    ctx.metrics["unregistered_views"] = ", ".join(missing)
    ctx.metrics["n_points3d"] = int(len(res["points3d"]))
    ctx.metrics["n_models"] = int(res["n_models"])
    ctx.metrics["extract_match_seconds"] = res["extract_match_seconds"]
    ctx.metrics["mapping_seconds"] = res["mapping_seconds"]
    ctx.metrics["intrinsics"] = intrinsics
    if res["principal_point_test"] is not None:
        ctx.metrics["principal_point_freed"] = res["principal_point_test"]["freed"]
    if reg.any():  # the focal length COLMAP ended with, beside the ingest's (they differ when refined)
        ctx.metrics["focal_px"] = float(np.mean(res["K"][reg][:, [0, 1], [0, 1]]))
        ctx.metrics["focal_px_ingest"] = float(np.mean(arrays["K"][reg][:, [0, 1], [0, 1]]))
        ctx.log.info(f"focal length {ctx.metrics['focal_px']:.1f} px (ingest: {ctx.metrics['focal_px_ingest']:.1f} px, "
                     f"intrinsics {intrinsics})")
