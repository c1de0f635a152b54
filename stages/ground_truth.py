"""ground_truth: GT poses (object-normalised frame), normalisation and exact surface, kept apart.

Only the stages in GROUND_TRUTH_READERS (stages/__init__.py) may read this artifact; everything
the method computes is blind to it. Scenes without GT write ``gt.json`` with ``has_poses: false``.
"""
from __future__ import annotations

import numpy as np

from manifoldneus.data import artifacts, io, scenes
from stages.ingest import Params, input_signature  # same section: what to read and how  # noqa: F401

UPSTREAM = ("ingest",)
SECTIONS = ("ingest",)
OUTPUTS = (artifacts.GT_META,)


def run(ctx) -> None:
    gt = scenes.read_ground_truth(ctx.scene_ref, ctx.params)
    meta = artifacts.load_views_meta(ctx.input("ingest"))
    names = meta["names"]
    if gt is None:
        ctx.log.info("scene has no ground-truth poses; evaluation will report what it can without them")
        io.save_json(ctx.out / artifacts.GT_META, {"has_poses": False, "has_surface": False, "units": None})
        ctx.metrics["has_poses"] = False
        return
    if len(gt["w2c"]) != len(names):
        raise scenes.SceneError(f"{len(gt['w2c'])} ground-truth poses for {len(names)} views")
    arrays = {k: gt[k] for k in ("w2c", "normalization")}
    # the layout's own intrinsics and masks, whatever the method's ingest reads of them: for the error of the
    # intrinsics the method estimates, and for the GT-pose reference surface, which is then the same
    # (one version) for a run on the calibrated, masked layout and one on its photos alone
    if meta["intrinsics_source"] == "calibrated" and ctx.params.load_masks:  # the ingest read them: no second read
        own = artifacts.load_views_arrays(ctx.input("ingest"), ["K", "masks"] if meta.get("has_masks") else ["K"])
    else:
        own = scenes.layout_reference(ctx.scene_ref, ctx.params)
    arrays.update({k: own[k] for k in ("K", "masks") if own.get(k) is not None})
    if "surface_points" in gt:
        arrays["surface_points"] = gt["surface_points"]
    artifacts.save_ground_truth_poses(ctx.out, arrays)
    scale = float(abs(np.linalg.det(gt["normalization"][:3, :3])) ** (1 / 3))
    io.save_json(ctx.out / artifacts.GT_META, {"has_poses": True, "has_surface": "surface_points" in gt, "names": names,
                                       "units": gt["units"], "units_per_scene_unit": scale})
    ctx.metrics.update(has_poses=True, units=gt["units"])
