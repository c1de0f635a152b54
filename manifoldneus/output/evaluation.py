"""Evaluation helpers shared by `reference_surface`, `mesh` and `evaluate`: restoring a trained
model, meshing it, novel-view metrics on held-out views."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from manifoldneus.geometry import cameras
from manifoldneus.data import io
from manifoldneus.data.views import own
from manifoldneus.output import meshing, metrics
from manifoldneus.config import param
from manifoldneus.neural.field import FieldParams
from manifoldneus.neural.losses import LossParams
from manifoldneus.neural.render import RenderParams
from manifoldneus.neural.train import Trainer, TrainParams, TrainRun, Views


@dataclass
class MeshParams:
    """Section `meshing`: SDF -> triangle mesh."""

    resolution: int = param(512, "Marching-cubes grid resolution over the unit sphere's cube (NeuS's; the narrow "
                            "band evaluates the field near the surface only)", lo=16, hi=1024)
    coarse_step: int = param(8, "Evaluate the field only near its surface: a grid every coarse_step nodes, then the "
                             "cells that may hold surface split level by level (a power of two; 0 = every grid "
                             "node: slower, the same mesh)", lo=0, hi=64)
    band: float = param(2.0, "Narrow band: a cell is split when its corners change sign or one lies within this many "
                        "cell diagonals of the surface (a learned SDF can be steeper than a distance: at 1.5 a few "
                        "cells of scan24 were missed)", lo=1.0)
    keep_components: int = param(1, "Keep this many largest connected components (0 = all)", lo=0)
    cull_by_masks: bool = param(True, "Cull vertices outside the training views' dilated masks (when masks exist)")
    cull_dilation: float = param(3.0, "Mask dilation for culling, in pixels of the images the field was trained on "
                                 "(its surface is no sharper than they are): 6 px of scan24's 384 px masks at the "
                                 "192 px training size, 12.5 px of 800 px ones. At 12 px on scan24 a thin loop of "
                                 "surface 8-12 px outside every mask above the roof survived", lo=0.0)
    silhouette_dilation: float = param(9.0, "Dilation of the SfM points' silhouettes (silhouette_vote), in pixels of "
                                       "the training images: the convex hull of sparse points is a rougher silhouette "
                                       "than a mask, short of a textureless part at its edge (at 6 px the vote cut a "
                                       "hole in scan65's white skull top). Photos alone, seed 0, remeshed offline, "
                                       "Chamfer at 6 / 9 / 12 px: scan65_idr 1.68 / 1.48 / 1.57 mm, scan24 5.83 / "
                                       "5.79 / 5.80, scan24_idr 5.25 / 5.16 / 5.19, synthetic 0.0104 at all three",
                                       lo=0.0)
    cull_unseen: bool = param(True, "Cull surface that no training view sees (self-occlusion z-buffer)")
    drop_sphere_closure: bool = param(True, "Remove the surface marching cubes puts on the grid's bounding sphere where "
                                      "the SDF is still negative there (no view saw it as surface)")
    crop_to_object: str = param("auto", "Crop the surface to the object's region the anchors found from the SfM "
                                "points (ball and support plane; manifoldneus/geometry/object_region.py): auto = when the "
                                "run has no masks | on | off", choices=("auto", "on", "off"))
    support: str = param("cut", "What the crop to the object does with the support it stands on (the plane the "
                         "anchors found under it): cut = the surface sliced along the plane (support_margin above "
                         "it), a straight edge where the object meets it, and the support's SfM points left out of the silhouettes "
                         "(silhouette_vote); keep = the support kept, as far as the "
                         "object's region (ball) and the silhouettes of the SfM points on it reach",
                         choices=("cut", "keep"))
    support_margin: float = param(0.02, "support=cut: the cut lies this far above the support plane (in units of the "
                                  "object region's radius), so the support itself goes", lo=0.0, hi=0.5)
    silhouette_vote: float = param(0.9, "The crop to the object also keeps only surface inside the silhouettes of "
                                   "the object's SfM points (per view the convex hull of their projections, dilated "
                                   "by silhouette_dilation: masks from the points alone) in at least this fraction of the "
                                   "views whose image it falls in. A textureless support (scan24's white table) gives "
                                   "no points, so no plane, and the field makes a bowl of it around the object: it "
                                   "falls outside; below 1 so that one view whose points miss a part of the object "
                                   "does not cut it. Measured on scan24_idr's photos alone (seeds 0-2): Chamfer "
                                   "5.90 / 5.13 / 5.45 mm with the crop to within 0.12 of a point it replaces -> "
                                   "5.25 / 4.67 / 5.01 (remeshed offline at 0.95: 5.45 / 4.71 / 4.77); 0 = off",
                                   lo=0.0, hi=1.0)
    visibility_size: int = param(128, "Image size (longest side, px) of the z-buffers that decide visibility", lo=16)
    vertex_colours: bool = param(True, "Colour the mesh's vertices with the field's colour seen head-on (one field "
                                 "evaluation per vertex); every export of the mesh keeps them")
    preview_size: int = param(320, "Side of each of the 3 preview renderings (px)", lo=64)


@dataclass
class NovelViewParams:
    """Section `novel_views`: how held-out views are scored (by `evaluate` and the GT-pose `reference_surface`
    alike). Besides the figure at the held-out view's given pose (GT mapped into the model's frame), each
    held-out pose is refined against the frozen field first, as BARF, NoPe-NeRF and CF-3DGS score pose-free
    methods, so that the figure measures the surface and appearance rather than the pose error."""

    align_steps: int = param(150, "Test-time alignment: Adam steps on the held-out views' poses, field frozen "
                             "(0 = off: only the figure at the given pose)", lo=0)
    align_rays: int = param(1024, "Test-time alignment: rays per step over all held-out views", lo=16)
    align_lr: float = param(2e-3, "Test-time alignment: peak lr of the se(3) corrections (cosine to a tenth)", lo=0.0)


def trainer_from_checkpoint(path: Path, views: Views, device: str = "cpu") -> Trainer:
    """Rebuild the trainer a ``model.pt`` was saved from (its params travel inside it) and load it."""
    state = torch.load(str(path), map_location=device, weights_only=False)
    prm = state["params"]
    run = dataclasses.replace(TrainRun(**prm["run"]), device=device)
    t = Trainer(views, FieldParams(**prm["field"]), RenderParams(**prm["render"]), LossParams(**prm["loss"]),
                TrainParams(**prm["train"]), run=run)
    t.load_state_dict(state)
    t.field.eval()
    return t


@dataclass
class Surface:
    """The surface stage's result: its field's ``trainer`` over the posed views ``ids`` at their poses in
    the field's frame; ``field_from_model`` [4,4] maps the rounds' frame (the poses', the mesh's) to it."""

    trainer: Trainer
    field_from_model: np.ndarray
    result: dict  # the round (artifacts.load_surface): w2c [N,4,4] in the rounds' frame, K, placed, optimised, ...
    views: Views  # all N views with the round's intrinsics (and its lens distortion removed), poses in the rounds' frame
    ids: np.ndarray


def load_surface_field(surface_dir: Path, ingest_dir: Path, device: str = "cpu") -> Surface:
    """The field of ``surface/<version>`` with the views of ``ingest/<version>`` posed by its round."""
    from manifoldneus.data import artifacts

    result = artifacts.load_surface(surface_dir)
    views = artifacts.load_views(ingest_dir, result["w2c"], result["K"], result.get("distortion"))
    G = result[artifacts.FIELD_FROM_MODEL]
    ids = np.flatnonzero(result["optimised"].astype(bool))
    w2c = cameras.transform_w2c(result["w2c"], *cameras.sim3_from_matrix(G))  # [N,4,4] in the field's frame
    sub = views.subset(ids, w2c)
    return Surface(trainer_from_checkpoint(Path(surface_dir) / artifacts.MODEL, sub, device), G, result, views, ids)


def field_vertex_colours(trainer: Trainer, vertices: np.ndarray, normals: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """uint8 [V,3]: the field's colour at each vertex [V,3] seen head-on (view direction = -normal,
    normals [V,3] unit): one field evaluation per vertex, no rendering."""
    out = np.zeros((len(vertices), 3), np.uint8)
    with torch.no_grad():
        for a in range(0, len(vertices), chunk):
            x = torch.as_tensor(vertices[a:a + chunk], dtype=torch.float32, device=trainer.device)
            n = torch.as_tensor(normals[a:a + chunk], dtype=torch.float32, device=trainer.device)
            _, rgb = trainer.field(x, -n, normals=n)  # [C,3] in [0,1]
            out[a:a + chunk] = (rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
    return out


# the keys only a surface cropped to the object reads: a change to them leaves masked runs' meshes as they were
CROP_KEYS = ("support", "support_margin", "silhouette_vote", "silhouette_dilation")


def crops_to_object(crop_to_object: str, masked: bool) -> bool:
    """Whether the mesh is cropped to the object's region (``meshing.crop_to_object``; auto: without masks)."""
    return crop_to_object == "on" or (crop_to_object == "auto" and not masked)


def make_mesh(trainer: Trainer, p: MeshParams, K=None, w2c=None, masks=None, hw=None, region=None,
              object_points=None, sizes=None, silhouettes=None):
    """Mesh of the trainer's SDF; culled by the given views' dilated masks, to the surface they
    see and to the object's ``region`` (:class:`~manifoldneus.geometry.object_region.ObjectRegion`, the field's
    frame) and the silhouettes of its ``object_points`` [P,3], when asked (K [N,3,3] and w2c [N,4,4] at image size
    hw = (H, W), the masks' size; ``sizes`` [N,2] (H, W) each view's own part of it, None: all). ``silhouettes``
    [N,H,W] bool, where the run has them (the masks the surface stage made from the photos), replace the points'."""
    mesh = meshing.extract_mesh(trainer.sdf_fn(), p.resolution, trainer.rp.radius, p.keep_components,
                                coarse_step=p.coarse_step, band=p.band)
    trained = (trainer.H, trainer.W)  # the culls' tolerances are in its pixels
    culled = False
    if p.drop_sphere_closure and len(mesh.faces):
        mesh, culled = meshing.keep_vertices(mesh, meshing.off_sphere_closure(
            np.asarray(mesh.vertices), trainer.rp.radius, p.resolution)), True
    # the crop's keys are read only where there is something to crop to: a caller without a region
    # (the GT-pose reference) need not declare them, so they do not enter its fingerprint
    crop = (region is not None or object_points is not None) and crops_to_object(p.crop_to_object, masks is not None)
    unseen = p.cull_unseen and K is not None and hw is not None
    if unseen and crop and len(mesh.faces):
        # what the views see is decided on the whole surface the field has: cropped first, the background and
        # support it drops would no longer hide the surface behind them (scan65's photos alone: inner shells)
        mesh, culled = meshing.cull_unseen(mesh, K, w2c, hw, p.visibility_size, sizes=sizes), True
    if crop and region is not None and len(mesh.faces):
        mesh, culled = meshing.keep_vertices(mesh, region.contains(np.asarray(mesh.vertices), None)), True
        if region.plane is not None and p.support == "cut" and len(mesh.faces):
            # sliced, not vertex-culled: removing the faces that touch the plane would leave a ragged edge
            mesh = meshing.cut_by_plane(mesh, region.plane, p.support_margin * region.radius)
            if object_points is not None:
                # the support's own points out of the silhouettes: their hulls kept the skirt the field makes of
                # a table around the object's base (scan65's photos alone: Chamfer 5.39 -> 1.65 mm, offline)
                object_points = object_points[region.contains(object_points, p.support_margin * region.radius)]
    if (crop and object_points is not None and len(object_points) and K is not None and p.silhouette_vote > 0
            and len(mesh.faces)):
        if silhouettes is None:
            silhouettes = meshing.point_silhouettes(object_points, K, w2c, hw)  # [N,H,W]
        mesh = meshing.cull_by_masks(mesh, K, w2c, silhouettes, image_px(p.silhouette_dilation, hw, trained),
                                     min_fraction=p.silhouette_vote, sizes=sizes)
        culled = True
    if p.cull_by_masks and masks is not None and len(mesh.faces):
        dilation = image_px(p.cull_dilation, masks.shape[1:], trained)
        mesh, culled = meshing.cull_by_masks(mesh, K, w2c, masks, dilation=dilation, sizes=sizes), True
    if unseen and not crop and len(mesh.faces):
        mesh, culled = meshing.cull_unseen(mesh, K, w2c, hw, p.visibility_size, sizes=sizes), True
    if culled and p.keep_components > 0 and len(mesh.faces):
        mesh = meshing.largest_components(mesh, p.keep_components)
    return mesh


def image_px(training_px: float, hw, trained_hw) -> int:
    """A length in pixels of the training images (size trained_hw), in pixels of images of size hw."""
    return int(round(training_px * max(hw) / max(trained_hw)))


def save_mesh_with_preview(mesh, out_dir: Path, p: MeshParams, stem: str = "mesh", w2c=None) -> None:
    """PLY + a 3-view PNG preview (seen from three of the cameras ``w2c`` when given)."""
    meshing.save_ply(mesh, out_dir / f"{stem}.ply")
    if len(mesh.faces):
        directions, up = meshing.preview_directions(w2c) if w2c is not None and len(w2c) >= 3 else (None, None)
        io.save_png(out_dir / f"{stem}_preview.png", meshing.render_preview(mesh, p.preview_size, directions, up))


def align_test_poses(trainer: Trainer, small: Views, ids, w2c: np.ndarray, p: NovelViewParams, seed: int = 0):
    """Refine the poses ``w2c`` [N,4,4] of views ``ids`` against the trainer's frozen field
    (:func:`manifoldneus.neural.pose_alignment.align_poses`; the views' own images at the trainer's resolution
    ``small``), all views at once, ``p.align_steps`` Adam steps. Returns (w2c [N,4,4] with those views
    refined, {view: (rotation change deg, centre change)})."""
    from manifoldneus.neural.pose_alignment import align_poses

    dev = trainer.device
    ids = np.asarray(ids, int)
    HW = trainer.H * trainer.W
    images = torch.as_tensor(small.float_images()[ids].reshape(len(ids), HW, 3), device=dev)  # [M,HW,3]
    masks = None if small.masks is None else torch.as_tensor(small.masks[ids].reshape(len(ids), HW), device=dev)
    K = torch.as_tensor(small.K[ids], dtype=torch.float32, device=dev)  # [M,3,3]
    start = torch.as_tensor(np.asarray(w2c)[ids, :3, :4], dtype=torch.float32, device=dev)  # [M,3,4]
    sizes = None if small.one_size else torch.as_tensor(small.view_sizes[ids], dtype=torch.long)
    refined = align_poses(trainer, start, images, masks, K, steps=p.align_steps, rays=p.align_rays, lr=p.align_lr,
                          seed=seed, sizes=sizes).double().cpu().numpy()  # [M,3,4]
    out_w2c = np.array(w2c, dtype=np.float64)
    out_w2c[ids, :3, :4] = refined
    given = np.asarray(w2c, dtype=np.float64)
    turns = cameras.rotation_angle_deg(refined[:, :, :3] @ given[ids, :3, :3].transpose(0, 2, 1))  # [M]
    shifts = np.linalg.norm(cameras.camera_centers(out_w2c[ids]) - cameras.camera_centers(given[ids]), axis=-1)  # [M]
    return out_w2c, {int(i): (float(r), float(c)) for i, r, c in zip(ids, turns, shifts)}


def _score(pred: np.ndarray, real: np.ndarray, mask: np.ndarray | None, prefix: str = "") -> dict:
    row = {f"{prefix}psnr": metrics.psnr(pred, real), f"{prefix}ssim": metrics.ssim(pred, real)}
    if mask is not None:
        row[f"{prefix}psnr_masked"] = metrics.psnr(pred * mask[..., None], real * mask[..., None])
        row[f"{prefix}psnr_fg"] = metrics.psnr(pred, real, mask)
        row[f"{prefix}ssim_masked"] = metrics.ssim(pred * mask[..., None], real * mask[..., None])
    return row


def novel_views(trainer: Trainer, views: Views, ids, w2c: np.ndarray, out_dir: Path | None = None,
                progress=None, align: NovelViewParams | None = None) -> dict:
    """Render views ``ids`` at the trainer's resolution with poses ``w2c`` [N,4,4] (in the model's frame)
    and score them: PSNR/SSIM unmasked and, when masks exist, with the background masked out. With
    ``align`` (and ``align.align_steps`` > 0) each pose is also refined against the frozen field
    (:func:`align_test_poses`) and the view scored again: the ``aligned_*`` figures, with how far the
    alignment moved it (``align_rot_deg``, ``align_shift``). Writes ``<name>.png`` (rendered | real;
    aligned rendering below when aligned) per view to ``out_dir``. Each view is rendered and scored at its
    own size (``size`` of its row: views of several sizes lie on one canvas, :mod:`manifoldneus.data.views`)."""
    small = views.resized(max(trainer.H, trainer.W))
    aligned_w2c, moved = None, {}
    if align is not None and align.align_steps > 0 and len(ids):
        aligned_w2c, moved = align_test_poses(trainer, small, ids, w2c, align)
    rows = []
    images = small.float_images()
    it = progress(ids, desc="novel views") if progress else ids
    for i in it:
        h, w = (int(x) for x in small.view_sizes[i])
        real = own(images[i], (h, w))
        m = None if small.masks is None else own(small.masks[i], (h, w))

        def render(pose):
            out = trainer.render_view(0, K=small.K[i], w2c=pose, size=(h, w), want_normals=False)
            return np.clip(out["rgb"].reshape(h, w, 3), 0, 1)

        pred = render(w2c[i])
        row = {"view": int(i), "name": views.names[i], **_score(pred, real, m)}
        lp = metrics.lpips(pred, real)
        if lp is not None:
            row["lpips"] = lp
        panel = np.concatenate([pred, real], 1)
        if aligned_w2c is not None:
            pred_a = render(aligned_w2c[i])
            row.update(_score(pred_a, real, m, "aligned_"))
            row["align_rot_deg"], row["align_shift"] = moved[int(i)]
            panel = np.concatenate([panel, np.concatenate([pred_a, real], 1)], 0)
        rows.append({**row, "size": [h, w]})
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            io.save_png(out_dir / f"{views.names[i]}.png", panel)
    summary = {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k not in ("view", "name", "size")} if rows else {}
    ok, why = metrics.lpips_status()
    summary["lpips_status"] = "on" if ok else why
    summary["resolution"] = [trainer.H, trainer.W]
    return {"summary": summary, "per_view": rows}


def gt_in_model_frame(alignment: dict, w2c_gt: np.ndarray) -> np.ndarray:
    """GT poses expressed in the estimated (model) frame, through the inverse of the est -> gt Sim3."""
    s, R, t = cameras.sim3_inverse(alignment["s"], np.asarray(alignment["R"]), np.asarray(alignment["t"]))
    return cameras.transform_w2c(w2c_gt, s, R, t)
