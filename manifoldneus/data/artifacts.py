"""Readers of the stages' artifacts, and the writers of those several modules read, in one place (as
hloc's ``utils/io.py``): a stage writes its files (through the ``save_*`` here where there is one),
every other module reads them through these functions, and the package never imports from
``stages/``. Each takes the version folder of the stage (``ctx.input(stage)``) or the file.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from manifoldneus.data import io
from manifoldneus.data.views import Views
from manifoldneus.geometry import segmentation

VIEWS = "views.zarr"  # ingest's arrays: images, sizes, K, masks, priors
INPUT_CAMERAS = "input_cameras.zarr"  # ingest's poses a COLMAP model gave (w2c, its points): anchors.pose_init = input
VIEWS_META = "views.json"  # ingest's names, layout, intrinsics_source, has_cameras, ...
GT_META = "gt.json"  # ground_truth's has_poses, has_surface, units
FEATURES = "features.zarr"
MATCHES = "matches.zarr"
SCHEDULE = "schedule.zarr"
SCHEDULE_META = "schedule.json"
REFERENCE_SURFACE_META = "reference.json"  # reference_surface's trained / why, its iterations and PSNR
EVALUATION = "evaluation.json"
INITIAL_POSES = "initial_poses.zarr"
COVISIBILITY = "covisibility.zarr"
POSES = "poses.zarr"  # the same name in reference, ground_truth, mesh and every pose-free round
MESH = "mesh.ply"  # a surface mesh: mesh's, reference_surface's, export's (PLY)
MODEL = "model.pt"  # a trained field with its pose corrections (a round's, reference_surface's)
ROUND_META = "round.json"  # a round's info: views, training summary, initialisation
PHOTO_MASKS = "photo_masks.zarr"  # surface's masks made from the photos (surface.photo_masks), where it made them
PHOTO_MASKS_PLOT = "photo_masks.png"
SPECTRAL = "spectral.zarr"  # spectral's embedding phi and component labels
COMPONENTS = "components.json"  # covisibility's connected components
REFERENCE_POSE_METRICS = "reference_pose_metrics.json"  # evaluate_poses' scores of the pycolmap reference
# plots the report shows
ANCHOR_ROUND = "round_0"  # the anchors' round: anchors/<version>/round_0/ (and its checkpoint round_0.pt)
FINAL_ROUND = "final"  # successors/<version>/final: a link to its last round (a copy of round_0 when it has none)
FIELD_FROM_MODEL = "field_from_model"  # in surface's round.json: the 4x4 similarity rounds' frame -> its field's
SCHEDULE_PLOT = "schedule.png"
CAMERAS_PLOT = "cameras.png"
POSE_ERROR_PLOT = "pose_error_rounds.png"
REFERENCE_CAMERAS_PLOT = "reference_cameras.png"  # evaluate_poses' plot of pycolmap's cameras against the truth


def load_views_meta(ingest_dir: Path) -> dict:
    """``ingest``'s ``views.json``: ``names``, ``layout``, ``intrinsics_source``, ``has_cameras``, ..."""
    return io.load_json(Path(ingest_dir) / VIEWS_META)


def load_input_cameras(ingest_dir: Path) -> dict | None:
    """``ingest``'s ``input_cameras.zarr``: the poses the input's COLMAP model gave, ``w2c`` float64 [N,4,4]
    in the model's world frame, and its ``points`` [P,3] (possibly none); None for a scene without them."""
    path = Path(ingest_dir) / INPUT_CAMERAS
    return io.load_arrays(path) if path.exists() else None


def load_views_arrays(ingest_dir: Path, names: list[str] | None = None) -> dict:
    """``ingest``'s ``views.zarr``: ``images`` (on one canvas), ``sizes`` [N,2] (H, W) of each view's own pixels
    in it (:mod:`manifoldneus.data.views`), ``K`` and, where the scene has them, ``masks``, ``mono_depth``,
    ``mono_normal`` (all, or ``names``)."""
    return io.load_arrays(Path(ingest_dir) / VIEWS, names)


VIEW_PIXELS = ("images", "sizes", "mono_depth", "mono_normal")  # what views.zarr holds that is not a camera or a mask


def load_view_pixels(ingest_dir: Path) -> dict:
    """``ingest``'s ``images``, ``sizes`` and, where the scene has them, ``mono_depth`` and ``mono_normal``: the
    arrays of ``views.zarr`` that :data:`VIEW_PIXELS` names."""
    path = Path(ingest_dir) / VIEWS
    return io.load_arrays(path, [a for a in VIEW_PIXELS if a in io.array_names(path)])


def load_gt_meta(gt_dir: Path) -> dict:
    """``ground_truth``'s ``gt.json`` (``has_poses``, ``has_surface``, ``units``); {} where the stage
    wrote none."""
    path = Path(gt_dir) / GT_META
    return io.load_json(path) if path.is_file() else {}


def load_views(ingest_dir: Path, w2c: np.ndarray | None = None, K: np.ndarray | None = None,
               distortion: np.ndarray | None = None) -> Views:
    """``ingest``'s ``views.zarr`` as :class:`~manifoldneus.data.views.Views` (poses: ``w2c`` [N,4,4], or
    identity placeholders: ingest never holds poses; intrinsics: ``K`` [N,3,3], e.g. a round's, which
    the anchors may have refined, else the ingest's; ``distortion`` [N,4]: the lens distortion the
    anchors' self-calibration found (a round's), removed from the images and masks)."""
    arrays = load_views_arrays(ingest_dir)
    names = load_views_meta(ingest_dir)["names"]
    w2c = np.tile(np.eye(4), (len(names), 1, 1)) if w2c is None else w2c
    return Views(arrays["images"], arrays["K"] if K is None else K, w2c, arrays.get("masks"), arrays.get("mono_depth"),
                 arrays.get("mono_normal"), names, arrays["sizes"]).undistorted(distortion)


def load_features(features_dir: Path) -> tuple[list[dict], dict]:
    """``features``' ``features.zarr`` -> (per-view dicts of keypoints [K,2] px, scales, orientations,
    responses, descriptors; attrs with ``featureless`` [N])."""
    path = Path(features_dir) / FEATURES
    arrays = io.load_arrays(path)
    attrs = io.load_attrs(path)
    off = arrays["offsets"]
    feats = []
    for v in range(len(off) - 1):
        a, b = int(off[v]), int(off[v + 1])
        feats.append({k: arrays[k][a:b] for k in ("keypoints", "scales", "orientations", "responses", "descriptors")})
    attrs["featureless"] = arrays["featureless"]
    return feats, attrs


def load_matches(matching_dir: Path, names: list[str] | None = None) -> tuple[dict, dict]:
    """``matching``'s ``matches.zarr`` -> (arrays (all, or ``names``), attrs). Per pair p:
    :func:`inliers_of` (arrays, p)."""
    path = Path(matching_dir) / MATCHES
    return io.load_arrays(path, names), io.load_attrs(path)


def inliers_of(arrays: dict, p: int) -> np.ndarray:
    """Verified matches [M,2] of pair index p (keypoint indices in views pairs[p])."""
    off = arrays["inlier_offsets"]
    return arrays["inlier_matches"][off[p] : off[p + 1]]


def load_schedule(schedule_dir: Path) -> dict:
    """The arrays of ``schedule.zarr`` plus ``schedule.json`` under 'meta'."""
    out = io.load_arrays(Path(schedule_dir) / SCHEDULE)
    out["meta"] = load_schedule_meta(schedule_dir)
    return out


def load_schedule_meta(schedule_dir: Path) -> dict:
    """``schedule``'s ``schedule.json``: the anchors and rounds by name, held-out views, settings."""
    return io.load_json(Path(schedule_dir) / SCHEDULE_META)


def load_evaluation(evaluate_dir: Path) -> dict:
    """``evaluate``'s ``evaluation.json``: poses per round, intrinsics, geometry, novel views."""
    return io.load_json(Path(evaluate_dir) / EVALUATION)


def load_reference_surface_meta(reference_surface_dir: Path) -> dict:
    """``reference_surface``'s ``reference.json``: whether the GT-pose NeuS was trained (and why not)."""
    return io.load_json(Path(reference_surface_dir) / REFERENCE_SURFACE_META)


def load_round_arrays(round_dir: Path, names: list[str] | None = None) -> dict:
    """A pose-free round's ``poses.zarr`` (``anchors/round_0``, ``successors/round_<r>``,
    ``successors/final``; written by :func:`manifoldneus.posefree.save_round`): all its arrays, or
    ``names``."""
    return io.load_arrays(Path(round_dir) / POSES, names)


def load_round(round_dir: Path) -> dict:
    """A pose-free round: :func:`load_round_arrays` plus ``round.json`` under 'info'."""
    out = load_round_arrays(round_dir)
    out["info"] = io.load_json(Path(round_dir) / ROUND_META)
    return out


def load_surface(surface_dir: Path) -> dict:
    """``surface``'s round (:func:`load_round`: the last round's poses, in the rounds' frame) and
    ``field_from_model`` [4,4], the similarity from that frame to the frame its field was trained in."""
    out = load_round(surface_dir)
    out[FIELD_FROM_MODEL] = np.asarray(out["info"][FIELD_FROM_MODEL], np.float64)
    return out


def load_photo_silhouettes(surface_dir: Path, ids: np.ndarray, erode: int) -> np.ndarray | None:
    """bool [N,H,W]: for each view of ``ids`` [N] what the surface stage's masks made from the photos did not carve
    (neither its GrabCut mask nor the views' vote holds it, ``erode`` px in: the photo-mask term's background,
    :func:`manifoldneus.geometry.segmentation.object_labels`); everything in a view it made none for. None where
    it made none."""
    path = surface_dir / PHOTO_MASKS
    if not path.exists():
        return None
    made = io.load_arrays(path)  # masks, voted [V,H,W] bool; views [V]
    uncarved = segmentation.object_labels(made["masks"], made["voted"], erode) != 0
    out = np.ones((len(ids), *uncarved.shape[1:]), bool)
    row = {int(v): i for i, v in enumerate(made["views"])}
    for i, v in enumerate(ids):
        if int(v) in row:
            out[i] = uncarved[row[int(v)]]
    return out


def load_covisibility(cov_dir: Path, names: list[str] | None = None) -> dict:
    """``covisibility``'s ``covisibility.zarr``: ``W`` float64 [N,N], ``c`` float64 [N], ``component``
    int32 [N], ``in_largest`` bool [N] (all, or ``names``)."""
    return io.load_arrays(Path(cov_dir) / COVISIBILITY, names)


def save_covisibility(cov_dir: Path, arrays: dict, attrs: dict) -> None:
    io.save_arrays(Path(cov_dir) / COVISIBILITY, arrays, attrs=attrs, chunk_first=False)


def load_initial_poses(anchors_dir: Path, names: list[str] | None = None) -> dict:
    """``anchors``' ``initial_poses.zarr``, the anchors' poses before their round: ``w2c`` [N,4,4],
    ``placed`` [N], ``K`` [N,3,3] and the SfM points :data:`manifoldneus.posefree.SFM_POINTS` (all,
    or ``names``)."""
    return io.load_arrays(Path(anchors_dir) / INITIAL_POSES, names)


def save_initial_poses(anchors_dir: Path, arrays: dict) -> None:
    io.save_arrays(Path(anchors_dir) / INITIAL_POSES, arrays, chunk_first=False)


def load_ground_truth_poses(gt_dir: Path, names: list[str] | None = None) -> dict:
    """``ground_truth``'s ``poses.zarr`` (only where ``gt.json`` says ``has_poses``): ``w2c`` [N,4,4] and
    ``normalization`` [4,4] of the object-normalised frame; where known ``K``, ``masks``,
    ``surface_points`` (all, or ``names``). The method is blind to it: only ``GROUND_TRUTH_READERS``
    (stages/__init__.py), the report and its viewer read it."""
    return io.load_arrays(Path(gt_dir) / POSES, names)


def save_ground_truth_poses(gt_dir: Path, arrays: dict) -> None:
    io.save_arrays(Path(gt_dir) / POSES, arrays, chunk_first=False)


def load_reference_poses(reference_dir: Path, names: list[str] | None = None) -> dict:
    """``reference``'s (pycolmap's) ``poses.zarr``: ``w2c`` [N,4,4] in COLMAP's world frame,
    ``registered`` [N], ``K`` [N,3,3], ``points3d`` [P,3], ``points3d_rgb`` [P,3] (all, or ``names``)."""
    return io.load_arrays(Path(reference_dir) / POSES, names)


def save_reference_poses(reference_dir: Path, arrays: dict, attrs: dict) -> None:
    io.save_arrays(Path(reference_dir) / POSES, arrays, attrs=attrs, chunk_first=False)


def load_pose_estimate(est_dir: Path) -> dict:
    """``w2c`` of any artifact holding ``poses.zarr`` (the reference, the mesh, a round), and
    ``registered`` where it has one (only the reference leaves views unregistered)."""
    path = Path(est_dir) / POSES
    return io.load_arrays(path, [n for n in ("w2c", "registered") if n in io.array_names(path)])


def round_folder(r: int) -> str:
    """Round r's folder (and checkpoint stem): round_0 the anchors', round_1, round_2, ... the successors'."""
    return f"round_{r}"


def successor_rounds(successors_dir: Path) -> list[Path]:
    """The round folders of a successors version, in round order (``final`` is a link to the last)."""
    return sorted(Path(successors_dir).glob("round_*"), key=lambda d: int(d.name.split("_")[1]))
