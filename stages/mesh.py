"""mesh: the surface field's surface (stages/surface.py), and the export of the method's result.

SDF on a grid inside the unit sphere -> marching cubes -> largest component(s) -> the sphere's closure
removed -> culled by the training views' dilated masks (when masks exist), or, without masks, cropped to
the object's region the anchors found (ball and support plane) and to the silhouettes of the object's SfM
points in the views (``meshing.silhouette_vote``; where the surface stage made masks from the photos, what those
leave uncarved instead) -> cropped to the surface some training view sees.
The SfM points are the final round's tracks over every view it trained, triangulated under its final poses
(the anchors' points cover only what the anchors see: on the synthetic scene's photos alone their
silhouettes cut 3 % of the object, Chamfer 0.025 against 0.013), those in the views' common frustum
(``anchors.object_min_seen``); the anchors' when the round kept no tracks.
Output frame: the normalised object frame the method built (the middle of the anchors' points' robust box
at the origin, or their median: ``anchors.gauge_centre``; the box's half diagonal at `anchors.gauge_radius`);
the mesh (``mesh.ply``, vertex colours from the field: ``meshing.vertex_colours``) and the poses (``colmap/`` text model, ``poses.zarr``) are both in it.
"""
from __future__ import annotations

import numpy as np

from manifoldneus.data import artifacts, io
from manifoldneus.geometry import cameras, object_region
from manifoldneus.output import evaluation, export

Params = evaluation.MeshParams
UPSTREAM = ("ingest", "anchors", "surface")
SECTIONS = ("meshing", "run.device", "anchors.object_min_seen",  # run.seed and run.threads do not change a mesh
            "surface.photo_mask_erode")
OUTPUTS = (artifacts.MESH, artifacts.POSES, "colmap")


def run(ctx) -> None:
    surface = evaluation.load_surface_field(ctx.input("surface"), ctx.input("ingest"), ctx.section("run").device)
    result, views, ids, G = surface.result, surface.views, surface.ids, surface.field_from_model
    w2c, placed = result["w2c"], result["placed"].astype(bool)  # the rounds' frame
    masks = None if views.masks is None else views.masks[ids]
    found = io.load_json(ctx.input("anchors") / artifacts.ANCHOR_ROUND / artifacts.ROUND_META)["init"].get("object_region")
    region = None if found is None else object_region.ObjectRegion.from_json(found).transformed(G)
    object_points = object_points_of(result, views, ids, ctx.section("anchors").object_min_seen)
    if object_points is None:
        object_points = artifacts.load_initial_poses(ctx.input("anchors"), ["object_points"])["object_points"]
    # where the surface stage made masks from the photos, what they leave uncarved is the object's silhouette: the
    # points' hulls cut the textureless parts few points reach (scan24's roofs, seed 0: Chamfer 2.48 -> 2.34 mm)
    photo = artifacts.load_photo_silhouettes(ctx.input("surface"), ids, ctx.section("surface").photo_mask_erode)
    # meshed in the field's frame, saved in the rounds' (the poses' and every later stage's)
    mesh = evaluation.make_mesh(surface.trainer, ctx.params, views.K[ids], surface.trainer.views.w2c,
                                masks, views.images.shape[1:3], region, cameras.transform_points(G, object_points),
                                sizes=views.view_sizes[ids], silhouettes=photo)
    if ctx.params.vertex_colours and len(mesh.faces):
        import trimesh

        colours = evaluation.field_vertex_colours(surface.trainer, np.array(mesh.vertices),
                                                  np.array(mesh.vertex_normals))
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=colours)
    mesh.apply_transform(np.linalg.inv(G))
    evaluation.save_mesh_with_preview(mesh, ctx.out, ctx.params, w2c=w2c[ids])
    io.save_arrays(ctx.out / artifacts.POSES, {"w2c": w2c, "placed": placed}, chunk_first=False)
    export.write_colmap_text(ctx.out / "colmap", views.names, views.K, w2c, views.view_sizes[:, 1],
                             views.view_sizes[:, 0], valid=placed)
    ctx.metrics.update(faces=int(len(mesh.faces)), vertices=int(len(mesh.vertices)), views_exported=int(placed.sum()))


def object_points_of(result: dict, views, ids: np.ndarray, min_seen: float) -> np.ndarray | None:
    """The round's ``track_points`` [T,3] that at least ``min_seen`` of its views ``ids`` see in their frame
    (the common frustum: background and clutter at the frame's edges are seen by few), or None."""
    points = result.get("track_points")
    if points is None:
        return None
    sizes = views.view_sizes[ids]  # [N,2] (H, W)
    return points[object_region.seen_fraction(points, views.K[ids], result["w2c"][ids], sizes) >= min_seen]
