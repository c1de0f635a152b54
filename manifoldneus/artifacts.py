"""Readers of the stages' artifacts, in one place (as hloc's ``utils/io.py``): a stage writes its
files, every other module reads them through these functions, and the package never imports
from ``stages/``. Each takes the version folder of the stage (``ctx.input(stage)``) or the file.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from manifoldneus import io
from manifoldneus.train import Views


def load_views(ingest_dir: Path, w2c: np.ndarray | None = None, K: np.ndarray | None = None) -> Views:
    """``ingest``'s ``views.zarr`` as :class:`~manifoldneus.train.Views` (poses: ``w2c`` [N,4,4], or
    identity placeholders: ingest never holds poses; intrinsics: ``K`` [N,3,3], e.g. a round's, which
    the anchors may have refined, else the ingest's)."""
    arrays = io.load_arrays(Path(ingest_dir) / "views.zarr")
    names = io.load_json(Path(ingest_dir) / "views.json")["names"]
    w2c = np.tile(np.eye(4), (len(names), 1, 1)) if w2c is None else w2c
    return Views(arrays["images"], arrays["K"] if K is None else K, w2c, arrays.get("masks"), arrays.get("mono_depth"),
                 arrays.get("mono_normal"), names)


def load_features(path: Path) -> tuple[list[dict], dict]:
    """``features.zarr`` -> (per-view dicts of keypoints [K,2] px, scales, orientations, responses,
    descriptors; attrs with ``featureless`` [N])."""
    arrays = io.load_arrays(Path(path))
    attrs = io.load_attrs(Path(path))
    off = arrays["offsets"]
    feats = []
    for v in range(len(off) - 1):
        a, b = int(off[v]), int(off[v + 1])
        feats.append({k: arrays[k][a:b] for k in ("keypoints", "scales", "orientations", "responses", "descriptors")})
    attrs["featureless"] = arrays["featureless"]
    return feats, attrs


def load_matches(path: Path) -> tuple[dict, dict]:
    """``matches.zarr`` -> (arrays, attrs). Per pair p: :func:`inliers_of` (arrays, p)."""
    return io.load_arrays(Path(path)), io.load_attrs(Path(path))


def inliers_of(arrays: dict, p: int) -> np.ndarray:
    """Verified matches [M,2] of pair index p (keypoint indices in views pairs[p])."""
    off = arrays["inlier_offsets"]
    return arrays["inlier_matches"][off[p] : off[p + 1]]


def load_schedule(schedule_dir: Path) -> dict:
    """The arrays of ``schedule.zarr`` plus ``schedule.json`` under 'meta'."""
    out = io.load_arrays(Path(schedule_dir) / "schedule.zarr")
    out["meta"] = io.load_json(Path(schedule_dir) / "schedule.json")
    return out


def load_round(round_dir: Path) -> dict:
    """A pose-free round (``anchors/round_0``, ``successors/round_<r>``, ``successors/final``):
    the arrays of ``poses.zarr`` plus ``round.json`` under 'info'."""
    out = io.load_arrays(Path(round_dir) / "poses.zarr")
    out["info"] = io.load_json(Path(round_dir) / "round.json")
    return out
