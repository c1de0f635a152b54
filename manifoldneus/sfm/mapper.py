"""Structure from motion through pycolmap: mapping, bundle adjustment and absolute pose for the stages.

Both users go through here: the anchors' initialisation (our SIFT keypoints and verified matches
written into a COLMAP database, then COLMAP's incremental mapper and bundle adjustment, the way
hloc hands its features to COLMAP) and the ``reference`` stage (COLMAP's own features and
matches). Successors are placed with COLMAP's absolute pose solver (LO-RANSAC + refinement).

Conventions (shared with :mod:`manifoldneus.geometry.cameras`): COLMAP's ``cam_from_world`` is the
OpenCV-frame world-to-camera pose, and COLMAP's pixel centres are at +0.5 like ours, so
keypoints and K pass through unchanged. Cameras are SIMPLE_PINHOLE (f, cx, cy) or PINHOLE
(fx != fy), or SIMPLE_RADIAL (f, cx, cy, k1) when a radial term is asked for.

Intrinsics: one COLMAP camera per distinct K (a folder of one image size is one shared camera,
so a refined focal length is shared by every view taken with it). ``refine`` names what bundle
adjustment may change: ``()`` holds K fixed; any of ``"focal"``, ``"principal_point"``,
``"radial"`` frees it. The principal point is poorly determined at a narrow field of view with few
views (it trades against the rotations), and a radial term fitted to an undistorted lens only
absorbs noise, so where ``principal_point_p`` / ``radial_p`` is given each is freed only when that
lowers the reprojection error significantly (:func:`free_intrinsic`, a likelihood-ratio test).
A radial term is COLMAP's SIMPLE_RADIAL k1, which is OpenCV's distortion [k1, 0, 0, 0]
(:func:`opencv_distortion`): the rest of the project removes it from images and keypoints
(:func:`manifoldneus.geometry.cameras.undistort_points`) and works with pinhole cameras.
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Sequence

import numpy as np


REFINABLE = ("focal", "principal_point", "radial")


# --------------------------------------------------------------------------- cameras


def intrinsics_mode(setting: str, source: str) -> str:
    """``auto`` -> ``fixed`` for calibrated or given intrinsics (the ingest's ``intrinsics_source``),
    ``refine`` for an EXIF prior or a guess; any other setting stands."""
    if setting != "auto":
        return setting
    return "fixed" if source in ("calibrated", "given") else "refine"


def shared_K(K: np.ndarray, sizes: np.ndarray, ids: Sequence[int], K_ids: np.ndarray,
             values: np.ndarray | None = None) -> np.ndarray:
    """K [N,3,3] with the intrinsics ``K_ids`` [len(ids),3,3] estimated for views ``ids`` given to
    every view of the same camera (:func:`shared_cameras` of K); views of other cameras keep theirs.
    With ``values`` [N,...] (e.g. distortion), those are spread instead: ``K_ids`` is then [len(ids),...]."""
    cam = shared_cameras(K, sizes)
    out = np.array(K if values is None else values, np.float64)
    for k, v in enumerate(ids):
        out[cam == cam[v]] = K_ids[k]
    return out


def opencv_distortion(extra: np.ndarray) -> np.ndarray:
    """OpenCV distortion [N,4] (k1, k2, p1, p2) of the extra parameters [N,e] :func:`read_poses` gives:
    SIMPLE_RADIAL's [k1] (none for the pinhole models: zeros)."""
    extra = np.asarray(extra, np.float64).reshape(len(extra), -1)
    out = np.zeros((len(extra), 4))
    out[:, :min(extra.shape[1], 1)] = extra[:, :1]
    return out


def camera_from_K(K: np.ndarray, width: int, height: int, radial: bool = False):
    """pycolmap.Camera of a pixel K [3,3]: SIMPLE_PINHOLE (one focal length, the better-posed
    unknown when it is refined) when fx = fy, else PINHOLE; SIMPLE_RADIAL (k1 = 0) when ``radial``."""
    import pycolmap

    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    if radial:
        return pycolmap.Camera(model="SIMPLE_RADIAL", width=int(width), height=int(height),
                               params=[0.5 * (fx + fy), cx, cy, 0.0])
    if abs(fx - fy) <= 1e-9 * max(fx, 1.0):
        return pycolmap.Camera(model="SIMPLE_PINHOLE", width=int(width), height=int(height), params=[fx, cx, cy])
    return pycolmap.Camera(model="PINHOLE", width=int(width), height=int(height), params=[fx, fy, cx, cy])


def K_of_camera(camera) -> tuple[np.ndarray, np.ndarray]:
    """(K [3,3], extra parameters e.g. [k1]) of a pycolmap.Camera."""
    K = np.eye(3)
    K[0, 0], K[1, 1] = camera.focal_length_x, camera.focal_length_y
    K[0, 2], K[1, 2] = camera.principal_point_x, camera.principal_point_y
    n_intrinsic = 4 if camera.model.name == "PINHOLE" else 3  # f (or fx, fy), cx, cy
    return K, np.asarray(camera.params, np.float64)[n_intrinsic:]


def shared_cameras(K: np.ndarray, sizes: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Camera index per view [N]: views with the same K and image size share one camera."""
    keys: dict = {}
    out = np.zeros(len(K), np.int64)
    for v, (k, hw) in enumerate(zip(np.asarray(K, np.float64), np.asarray(sizes))):
        key = (tuple(np.round(k.ravel() / tol).astype(np.int64)), tuple(int(x) for x in hw))
        out[v] = keys.setdefault(key, len(keys))
    return out


# --------------------------------------------------------------------------- database


def write_database(path: Path, names: Sequence[str], K: np.ndarray, sizes: np.ndarray,
                   keypoints: Sequence[np.ndarray], pairs: Sequence, radial: bool = False,
                   prior_focal: bool = True) -> dict[int, int]:
    """A COLMAP database of our features: views ``names`` with K [N,3,3], sizes [N,2] (H, W),
    keypoints [K_v,2] px and ``pairs`` (:class:`~manifoldneus.sfm.pose_init.PairMatch`, indices into
    ``names``) as matches and verified two-view geometries (their essential-matrix pose when they
    have one). One rig, frame and image per view; one camera per distinct (K, size).
    ``prior_focal``: the focal length is known (COLMAP trusts it when choosing initial pairs).
    Returns view index -> COLMAP image id."""
    import pycolmap

    from manifoldneus.geometry.cameras import skew

    path = Path(path)
    if path.exists():
        path.unlink()
    db = pycolmap.Database.open(str(path))
    try:
        cam_of_view = shared_cameras(K, sizes)
        camera_ids, rig_ids = {}, {}
        for v, c in enumerate(cam_of_view):
            if c in camera_ids:
                continue
            cam = camera_from_K(K[v], sizes[v][1], sizes[v][0], radial)
            cam.has_prior_focal_length = bool(prior_focal)
            camera_ids[c] = db.write_camera(cam)
            rig = pycolmap.Rig(rig_id=len(rig_ids) + 1)
            rig.add_ref_sensor(pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=camera_ids[c]))
            rig_ids[c] = db.write_rig(rig)
        image_ids = {}
        for v, name in enumerate(names):
            cid = camera_ids[cam_of_view[v]]
            image_ids[v] = db.write_image(pycolmap.Image(name=str(name), camera_id=cid))
            frame = pycolmap.Frame(rig_id=rig_ids[cam_of_view[v]])
            frame.add_data_id(pycolmap.data_t(sensor_id=pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=cid),
                                              id=image_ids[v]))
            db.write_frame(frame)
            db.write_keypoints(image_ids[v], np.asarray(keypoints[v], np.float32).reshape(-1, 2))
        for p in pairs:
            if p.i == p.j or len(p.matches) == 0:
                continue
            m = np.asarray(p.matches, np.uint32).reshape(-1, 2)
            db.write_matches(image_ids[p.i], image_ids[p.j], m)
            geometry = pycolmap.TwoViewGeometry()
            geometry.inlier_matches = m
            if p.valid:
                t = np.asarray(p.t, np.float64) / max(float(np.linalg.norm(p.t)), 1e-12)
                geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                geometry.E = skew(t) @ np.asarray(p.R, np.float64)
                geometry.cam2_from_cam1 = pycolmap.Rigid3d(np.concatenate([p.R, t[:, None]], 1))
            else:
                geometry.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            db.write_two_view_geometry(image_ids[p.i], image_ids[p.j], geometry)
    finally:
        db.close()
    return image_ids


# --------------------------------------------------------------------------- mapping


def mapping_options(refine: Sequence[str] = (), *, num_threads: int = 1, seed: int = 0, min_num_matches: int = 15,
                    reproj_px: float = 4.0, min_tri_angle_deg: float = 1.5):
    """COLMAP's incremental mapper options: intrinsics held fixed except those in ``refine``."""
    import pycolmap

    unknown = set(refine) - set(REFINABLE)
    if unknown:
        raise ValueError(f"cannot refine {sorted(unknown)}: choose from {', '.join(REFINABLE)}")
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.random_seed = seed
    opts.min_num_matches = min_num_matches
    opts.ba_refine_focal_length = "focal" in refine
    opts.ba_refine_principal_point = "principal_point" in refine
    opts.ba_refine_extra_params = "radial" in refine
    opts.mapper.abs_pose_refine_focal_length = "focal" in refine
    opts.mapper.abs_pose_refine_extra_params = "radial" in refine
    # COLMAP registers a view with >= 30 PnP inliers by default; small or sparse captures have
    # anchors linked by fewer verified matches (the synthetic scene at every other view: 24-51)
    opts.mapper.abs_pose_min_num_inliers = min_num_matches
    opts.mapper.filter_max_reproj_error = reproj_px
    opts.triangulation.min_angle = min_tri_angle_deg
    opts.extract_colors = False  # the database holds our features, not the images
    return opts


def incremental_mapping(database: Path, options, work_dir: Path, image_dir: Path | None = None):
    """COLMAP's incremental mapper on a database; (largest model or None, number of models).
    image_dir: the images, when the points should get their colours (``options.extract_colors``)."""
    import pycolmap

    out = Path(work_dir) / "models"
    out.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(str(database), str(image_dir or work_dir), str(out), options=options)
    if not models:
        return None, 0
    return max(models.values(), key=lambda r: r.num_reg_images()), len(models)


def read_poses(rec, names: Sequence[str], K_default: np.ndarray | None = None) -> dict:
    """Poses and cameras of a reconstruction, by image name, in ``names`` order.

    Returns dict(w2c [N,4,4] (identity where unregistered), registered bool [N], K [N,3,3]
    (the reconstruction's, else ``K_default``), extra [N,e] camera extra params)."""
    n = len(names)
    w2c = np.tile(np.eye(4), (n, 1, 1))
    registered = np.zeros(n, bool)
    K = np.array(K_default, np.float64) if K_default is not None else np.tile(np.eye(3), (n, 1, 1))
    extra: list = [np.zeros(0)] * n
    if rec is not None:
        index = {str(nm): v for v, nm in enumerate(names)}
        for image in rec.images.values():
            v = index.get(image.name)
            if v is None or not image.has_pose:
                continue
            w2c[v, :3, :4] = np.asarray(image.cam_from_world().matrix(), np.float64)
            registered[v] = True
            K[v], extra[v] = K_of_camera(image.camera)
    width = max((len(e) for e in extra), default=0)
    extra_arr = np.zeros((n, width))
    for v, e in enumerate(extra):
        extra_arr[v, :len(e)] = e
    return {"w2c": w2c, "registered": registered, "K": K, "extra": extra_arr}


def observations(rec, names: Sequence[str]) -> dict:
    """The reconstruction's 3D points and their observations: points [P,3], obs_view [O] (index
    into ``names``), obs_point [O] (index into points), obs_uv [O,2] px."""
    index = {str(nm): v for v, nm in enumerate(names)}
    ids = sorted(rec.points3D.keys())
    row = {pid: k for k, pid in enumerate(ids)}
    points = np.array([rec.points3D[pid].xyz for pid in ids], np.float64).reshape(-1, 3)
    view, point, uv = [], [], []
    for image in rec.images.values():
        if image.name not in index or not image.has_pose:
            continue
        for p2d in image.points2D:
            if p2d.has_point3D():
                view.append(index[image.name])
                point.append(row[p2d.point3D_id])
                uv.append(p2d.xy)
    return {"points": points, "obs_view": np.asarray(view, np.int64), "obs_point": np.asarray(point, np.int64),
            "obs_uv": np.asarray(uv, np.float64).reshape(-1, 2)}


def robust_bundle_adjustment(rec, refine: Sequence[str] = (), loss: str = "cauchy", scale_px: float = 1.0) -> None:
    """A last global bundle adjustment of a reconstruction with a robust loss (COLMAP's mapper uses
    a plain squared loss in its global adjustments), in place; intrinsics as in ``refine``."""
    import pycolmap

    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = "focal" in refine
    opts.refine_principal_point = "principal_point" in refine
    opts.refine_extra_params = "radial" in refine
    opts.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, loss.upper())
    opts.ceres.loss_function_scale = float(scale_px)
    opts.ceres.solver_options.num_threads = 1
    pycolmap.bundle_adjustment(rec, opts)


def reprojection_sq_errors(rec) -> np.ndarray:
    """Squared reprojection errors [O] (px^2) of every observation of a reconstruction's points, in a fixed
    order (image id, then keypoint), so that two adjustments of one reconstruction compare term by term."""
    out = []
    for image_id in sorted(rec.images):
        image = rec.images[image_id]
        if not image.has_pose:
            continue
        obs = [(p2d.xy, rec.points3D[p2d.point3D_id].xyz) for p2d in image.points2D if p2d.has_point3D()]
        if not obs:
            continue
        uv = np.array([o[0] for o in obs], np.float64)  # [M,2]
        X = np.array([o[1] for o in obs], np.float64)  # [M,3]
        M = np.asarray(image.cam_from_world().matrix(), np.float64)  # [3,4]
        out.append(((image.camera.img_from_cam(X @ M[:, :3].T + M[:, 3]) - uv) ** 2).sum(1))  # its lens model
    return np.concatenate(out) if out else np.zeros(0)


# what free_intrinsic can test, in the order map_views tests them, and its degrees of freedom per camera. Radial
# first (COLMAP's own default refines k1, never the principal point): an unmodelled lens bends the residuals
# symmetrically about the centre, and tested first the principal point moved 7 px to absorb part of it
# (synthetic, 256 px, k1 = -0.8: k1 then came out 17 % short and the focal length 2.5 % off)
TESTED = {"radial": 1, "principal_point": 2}


def _tested_value(rec, term: str) -> list[float]:
    """The first camera's value of a tested term: the principal point [cx, cy] or [k1]."""
    K, extra = K_of_camera(next(iter(rec.cameras.values())))
    return [round(float(x), 2) for x in K[:2, 2]] if term == "principal_point" else [float(x) for x in extra[:1]]


def free_intrinsic(rec, refine: Sequence[str], term: str, p_value: float, loss: str = "trivial",
                   scale_px: float = 1.0, inlier_px: float = 4.0, log=None):
    """Whether freeing ``term`` (:data:`TESTED`) is worth it (a likelihood-ratio test between nested models).

    ``rec`` was adjusted with ``refine`` minus ``term``; a copy is adjusted again with it free.
    Over the observations within ``inlier_px`` in both, chi2 = (SSE_fixed - SSE_free) / sigma^2 / L with
    sigma^2 the free fit's mean squared error per coordinate and L the mean track length: the
    observations of one 3D point are not independent (its position is fitted to them, and SIFT's
    localisation errors in the views of one feature correlate), so each track counts once. Without L,
    the synthetic scene's centred pinhole camera (192 px) got a principal point 4.6 px off and a
    radial term k1 = 0.26 (chi2 80 and 90, tracks of 8.7 views): rotations 0.62 deg instead of 0.17.
    The free fit is kept when chi2 exceeds the chi-square quantile at ``p_value`` (1 = always) with
    the term's degrees of freedom per camera.
    Returns (the reconstruction to keep, a record of the test), which ``log`` is told."""
    import copy

    from scipy.stats import chi2 as chi_square

    free = copy.deepcopy(rec)
    robust_bundle_adjustment(free, refine, loss, scale_px)
    e_fixed, e_free = reprojection_sq_errors(rec), reprojection_sq_errors(free)
    inliers = (e_fixed < inlier_px ** 2) & (e_free < inlier_px ** 2)
    sigma2 = max(float(e_free[inliers].mean()) / 2, 1e-12) if inliers.any() else 1.0  # per coordinate
    tracks = [p.track.length() for p in rec.points3D.values()]
    track_length = float(np.mean(tracks)) if tracks else 1.0
    statistic = float((e_fixed[inliers].sum() - e_free[inliers].sum()) / sigma2 / track_length)
    threshold = float(chi_square.isf(p_value, TESTED[term] * len(rec.cameras)))
    keep = statistic > threshold
    values = [_tested_value(r, term) for r in (rec, free)]
    record = {"chi2": statistic, "threshold": threshold, "p_value": p_value, "n_observations": int(inliers.sum()),
              "sigma_px": float(np.sqrt(sigma2)), "mean_track_length": track_length, "fixed": values[0],
              "free": values[1], "freed": bool(keep)}
    if log is not None:
        log(f"{term.replace('_', ' ')} {'freed' if keep else 'kept'}: chi2 {statistic:.1f} vs {threshold:.1f} "
            f"(p = {p_value:g}), {values[0]} -> {values[1]}")
    return (free if keep else rec), record


def map_views(names: Sequence[str], K: np.ndarray, sizes: np.ndarray, keypoints: Sequence[np.ndarray],
              pairs: Sequence, *, refine: Sequence[str] = (), prior_focal: bool = True, num_threads: int = 1,
              seed: int = 0, min_num_matches: int = 15, reproj_px: float = 4.0, min_tri_angle_deg: float = 1.5,
              final_ba_loss: str = "trivial", final_ba_scale_px: float = 1.0, principal_point_p: float | None = None,
              radial_p: float | None = None, log=None) -> dict:
    """Our features -> COLMAP database -> incremental mapping (-> a robust bundle adjustment unless
    ``final_ba_loss`` is "trivial"); everything indexed like ``names``. With ``principal_point_p`` and
    the principal point in ``refine`` (``radial_p`` and radial), it is held at its start until
    :func:`free_intrinsic` at that p-value says freeing it pays (the radial term first).

    Returns :func:`read_poses`'s dict plus :func:`observations`' (empty without a model), ``n_models``,
    ``reconstruction``, ``seconds``, ``principal_point_test`` and ``radial_test`` (the tests' records,
    or None)."""
    import pycolmap

    say = log or (lambda s: None)
    t0 = time.perf_counter()
    pycolmap.set_random_seed(seed)
    p_values = {"principal_point": principal_point_p, "radial": radial_p}
    tested = [t for t in TESTED if p_values[t] is not None and t in refine]
    first = tuple(r for r in refine if r not in tested)
    with tempfile.TemporaryDirectory(prefix="manifoldneus_sfm_") as tmp:
        db = Path(tmp) / "database.db"
        write_database(db, names, K, sizes, keypoints, pairs, radial="radial" in refine, prior_focal=prior_focal)
        opts = mapping_options(first, num_threads=num_threads, seed=seed, min_num_matches=min_num_matches,
                               reproj_px=reproj_px, min_tri_angle_deg=min_tri_angle_deg)
        rec, n_models = incremental_mapping(db, opts, Path(tmp))
    if rec is not None and final_ba_loss != "trivial":
        robust_bundle_adjustment(rec, first, final_ba_loss, final_ba_scale_px)
    tests: dict = {}
    freed = first
    for term in tested if rec is not None else ():
        rec, tests[term] = free_intrinsic(rec, (*freed, term), term, p_values[term], final_ba_loss, final_ba_scale_px,
                                          inlier_px=reproj_px, log=say)
        freed = (*freed, term) if tests[term]["freed"] else freed
    out = read_poses(rec, names, K)
    empty = {"points": np.zeros((0, 3)), "obs_view": np.zeros(0, np.int64), "obs_point": np.zeros(0, np.int64),
             "obs_uv": np.zeros((0, 2))}
    out.update(observations(rec, names) if rec is not None else empty)
    out.update(n_models=n_models, reconstruction=rec, seconds=time.perf_counter() - t0,
               principal_point_test=tests.get("principal_point"), radial_test=tests.get("radial"),
               mean_reproj_px=float(rec.compute_mean_reprojection_error()) if rec is not None else None)
    say(f"pycolmap mapping: {int(out['registered'].sum())}/{len(names)} views registered, {len(out['points'])} points, "
        f"{n_models} model(s), {out['seconds']:.1f} s")
    return out


# --------------------------------------------------------------------------- one view


def absolute_pose(K: np.ndarray, uv: np.ndarray, X: np.ndarray, size: tuple[int, int] | None = None, *,
                  reproj_px: float = 3.0, min_inliers: int = 12, seed: int = 0) -> tuple[np.ndarray | None, int]:
    """COLMAP's absolute pose (P3P LO-RANSAC, then refinement) of one view from pixels uv [M,2] and
    world points X [M,3]; size = (H, W), default twice the principal point. Non-finite points are
    ignored. Returns (w2c [4,4] or None, number of inliers); None below ``min_inliers``."""
    import pycolmap

    K = np.asarray(K, np.float64)
    size = size or (int(round(2 * K[1, 2])), int(round(2 * K[0, 2])))
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    X = np.asarray(X, np.float64).reshape(-1, 3)
    ok = np.isfinite(X).all(1) & np.isfinite(uv).all(1)
    uv, X = uv[ok], X[ok]
    if len(X) < max(min_inliers, 4):
        return None, 0
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.max_error = float(reproj_px)
    estimation.ransac.random_seed = int(seed)
    res = pycolmap.estimate_and_refine_absolute_pose(uv, X, camera_from_K(K, size[1], size[0]), estimation)
    if res is None:
        return None, 0
    n = int(np.sum(res["inlier_mask"]))
    if n < min_inliers:
        return None, n
    w2c = np.eye(4)
    w2c[:3, :4] = np.asarray(res["cam_from_world"].matrix(), np.float64)
    return w2c, n
