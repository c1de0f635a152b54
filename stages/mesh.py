"""mesh: the final model's surface, and the export of the method's result.

SDF on a grid inside the unit sphere -> marching cubes -> largest component(s) -> the sphere's closure
removed -> culled by the training views' dilated masks (when masks exist), or, without masks, cropped to
the object's region the anchors found (ball and support plane) and to the silhouettes of the object's SfM
points in the views (``meshing.silhouette_vote``) -> cropped to the surface some training view sees.
Output frame: the normalised object frame the method built (anchors' points median-centred, robust radius
`anchors.gauge_radius`); the mesh (``mesh.ply``) and the poses (``colmap/`` text model, ``poses.zarr``) are
both in it.
"""
from __future__ import annotations

import numpy as np

from manifoldneus import artifacts, evaluation, export, io, object_region, posefree

Params = evaluation.MeshParams
UPSTREAM = ("ingest", "anchors", "successors")
SECTIONS = ("meshing", "run.device")  # run.seed and run.threads do not change a mesh
OUTPUTS = (artifacts.MESH, artifacts.POSES, "colmap")


def run(ctx) -> None:
    final = ctx.input("successors") / "final"
    result = artifacts.load_round(final)
    w2c, placed = result["w2c"], result["placed"].astype(bool)
    views = artifacts.load_views(ctx.input("ingest"), w2c, result["K"], result.get("distortion"))
    ids = np.flatnonzero(result["optimised"].astype(bool))
    trainer = evaluation.trainer_from_checkpoint(final / artifacts.MODEL, posefree.subset_views(views, ids, w2c),
                                                 ctx.section("run").device)
    masks = None if views.masks is None else views.masks[ids]
    found = io.load_json(ctx.input("anchors") / "round_0" / artifacts.ROUND_META)["init"].get("object_region")
    region = None if found is None else object_region.ObjectRegion.from_json(found)
    object_points = artifacts.load_initial_poses(ctx.input("anchors"), ["object_points"])["object_points"]
    mesh = evaluation.make_mesh(trainer, ctx.params, views.K[ids], w2c[ids], masks, views.images.shape[1:3], region,
                                object_points)
    evaluation.save_mesh_with_preview(mesh, ctx.out, ctx.params, w2c=w2c[ids])
    io.save_arrays(ctx.out / artifacts.POSES, {"w2c": w2c, "placed": placed}, chunk_first=False)
    h, w = views.images.shape[1:3]
    export.write_colmap_text(ctx.out / "colmap", views.names, views.K, w2c, w, h, valid=placed)
    ctx.metrics.update(faces=int(len(mesh.faces)), vertices=int(len(mesh.vertices)), views_exported=int(placed.sum()))
