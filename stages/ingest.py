"""ingest: read a scene (any supported layout) into the canonical views artifact.

Writes no poses: ground truth goes to the separate `ground_truth` stage (see docs/STAGES.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from manifoldneus.data import artifacts, io, scenes
from manifoldneus.data.views import own
from manifoldneus.config import param


@dataclass
class Params:
    """Section `ingest` of params.yaml."""

    layout: str = param("auto", "Input layout; auto detects it",
                        choices=["auto", "monosdf", "idr", "colmap", "images"])
    downscale: int = param(1, "Integer factor to shrink images (and K, masks, priors) by", lo=1, hi=16)
    view_stride: int = param(1, "Keep every n-th view only (views 0, n, 2n, ...; ground truth alike): "
                                "the sparse-view settings of supplement Sec. 4.4 (2, 3, 5 -> 25, 17, 10 of 49)",
                             lo=1, hi=100)
    load_masks: bool = param(True, "Read foreground masks when the layout has them")
    load_priors: bool = param(True, "Read monocular depth/normal priors when the layout has them")
    intrinsics: list[float] = param([], "[fx, fy, cx, cy] in pixels of the input images, for any layout (held fixed "
                                    "unless anchors.intrinsics = refine); empty = the layout's cameras, else the EXIF "
                                    "focal length, else 1.2 x the larger side (refined downstream)",
                                    check=lambda k: None if not k or (len(k) == 4 and k[0] > 0 and k[1] > 0) else
                                    f"{k} is not [fx, fy, cx, cy] with positive focal lengths (pixels)")
    distortion: list[float] = param([], "OpenCV lens distortion [k1, k2, p1, p2] or [k1, k2, p1, p2, k3] of the input "
                                    "images (a known calibration, with their K: the layout's or ingest.intrinsics): "
                                    "images, masks and priors are undistorted at ingest, so every stage and export "
                                    "sees pinhole images with that K; empty = pinhole already",
                                    check=lambda d: None if len(d) in (0, 4, 5) else
                                    f"{d} is not [k1, k2, p1, p2] or [k1, k2, p1, p2, k3]")
    use_calibration: bool = param(True, "Read the layout's cameras' intrinsics; false = start from the uncalibrated "
                                  "guess (1.2 x the larger side) as a plain photo folder would, to measure "
                                  "self-calibration against the layout's own K")
    monosdf_original_size: list[int] = param([1600, 1200], "MonoSDF: size of the original images that "
                                             "world_mat projects into (centre-cropped to a square, resized)")
    video_frames: int = param(40, "A video (--scene clip.mp4): how many frames become views, the sharpest of each "
                              "of as many equal spans of the video", lo=3)
    synthetic_views: int = param(49, "Synthetic scene: number of views", lo=2, hi=400)
    synthetic_resolution: int = param(192, "Synthetic scene: image side in pixels", lo=32, hi=1024)
    synthetic_floor: bool = param(False, "Synthetic scene: the object stands on a textured floor (background, not in "
                                  "the masks), like an object on a table")
    synthetic_lens_k1: float = param(0.0, "Synthetic scene: radial distortion k1 of its lens (OpenCV's model; K is the "
                                     "pinhole part): the images are rendered through it, to test ingest.distortion "
                                     "(known) or anchors.intrinsics = refine (estimated)", lo=-2.0, hi=2.0)
    synthetic_surface_points: int = param(200000, "Synthetic scene: exact surface samples for Chamfer", lo=1000)


UPSTREAM = ()
SECTIONS = ("ingest",)
OUTPUTS = (artifacts.VIEWS, artifacts.VIEWS_META, "contact_sheet.png")


def input_signature(scene, p: Params) -> str:
    return scenes.input_signature(scene)


def contact_sheet(images, masks, columns: int = 10, side: int = 96) -> np.ndarray:
    """Thumbnails of every view (``images``: [H,W,3] each, of any size; ``masks`` likewise or None; masked-out
    background dimmed), for a quick look."""
    import cv2

    n = len(images)
    rows = (n + columns - 1) // columns
    sheet = np.zeros((rows * side, columns * side, 3), np.uint8)
    for i, im in enumerate(images):
        thumb = im if masks is None else np.where(masks[i][..., None], im, im // 3)
        thumb = cv2.resize(thumb, (side, side), interpolation=cv2.INTER_AREA)
        r, c = divmod(i, columns)
        sheet[r * side:(r + 1) * side, c * side:(c + 1) * side] = thumb
    return sheet


MIN_VIEWS = 3  # two views fix no more than their relative pose; the schedule needs anchors and successors


def run(ctx) -> None:
    p: Params = ctx.params
    views = scenes.read_views(ctx.scene_ref, p)
    names = views.pop("names")
    layout = views.pop("layout")
    intrinsics_source = views.pop("intrinsics_source")
    files = views.pop("files", None)  # the input's own image file of each view, where its pixels are the view's
    turned = views.pop("turned", [])  # photos stored the other way round, turned to the others' orientation
    given = {"w2c": views.pop("input_w2c"), "points": views.pop("input_points")} if "input_w2c" in views else None
    n, h, w = views["images"].shape[:3]
    if n < MIN_VIEWS:
        raise scenes.SceneError(f"{ctx.scene_ref.path or ctx.scene}: {n} view(s); pose-free reconstruction needs at "
                                f"least {MIN_VIEWS} overlapping photos of the object")
    ctx.log.info("read %d views of %dx%d (%s layout): %s", n, w, h, layout,
                 ", ".join(k for k in ("masks", "mono_depth", "mono_normal") if k in views) or "no masks or priors")
    cams = np.unique(views["sizes"], axis=0)
    if len(cams) > 1:  # each size its own camera (COLMAP's rule), on one canvas (manifoldneus.data.views)
        ctx.log.info("photos of %d sizes, one camera each, on a %dx%d canvas: %s", len(cams), w, h,
                     ", ".join(f"{int(c[1])}x{int(c[0])} ({int((views['sizes'] == c).all(1).sum())})" for c in cams))
    if turned:
        ctx.log.info("%d photo(s) stored %s turned by 90 deg to the others' %dx%d (the same camera held the other "
                     "way): %s", len(turned), "portrait" if w > h else "landscape", w, h, ", ".join(turned))
    io.save_arrays(ctx.out / artifacts.VIEWS, views)
    if given is not None:  # a COLMAP model's poses: kept apart from the views, read only where a run starts from them
        io.save_arrays(ctx.out / artifacts.INPUT_CAMERAS, given, chunk_first=False)
    io.save_json(ctx.out / artifacts.VIEWS_META, {
        "names": names, "height": h, "width": w, "layout": layout,
        "has_masks": "masks" in views, "has_mono_depth": "mono_depth" in views,
        "has_mono_normal": "mono_normal" in views, "intrinsics_source": intrinsics_source,
        "has_cameras": scenes.layout_has_cameras(layout), "has_input_poses": given is not None, "undistorted_with": list(p.distortion),
        "source": str(ctx.scene_ref.path) if ctx.scene_ref.path else ctx.scene_ref.name,
        "files": files, "turned_90": turned,
    })
    mine = [own(im, hw) for im, hw in zip(views["images"], views["sizes"])]  # each photo at its own size
    masks = None if views.get("masks") is None else [own(m, hw) for m, hw in zip(views["masks"], views["sizes"])]
    io.save_png(ctx.out / "contact_sheet.png", contact_sheet(mine, masks))
    ctx.metrics.update(n_views=n, width=w, height=h, n_sizes=len(cams), layout=layout, intrinsics_source=intrinsics_source,
                       fx_mean=float(views["K"][:, 0, 0].mean()), fy_mean=float(views["K"][:, 1, 1].mean()))
