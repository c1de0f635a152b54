"""The viewer page of a run: one self-contained HTML file (three.js inlined, works offline) that
shows the final mesh and every camera, built only from a run's artifacts (nothing is computed
again but the drawing geometry).

Everything is drawn in the frame of the ``export`` stage (``world_from_model.json``: the input's
world where the scene has cameras). Cameras are frusta coloured by role: the anchors, the views
each successor round added, the held-out views (drawn at their ground-truth pose, which is the
only one they have), and where ground truth exists the GT cameras with a line from each estimated
camera to its GT camera and the view's error on hover. The pycolmap reference cameras and its
sparse points (aligned to the final cameras by a Sim3 on the centres) can be switched on, and a
slider shows the cameras' poses after each round.

Entry point: :func:`write_page` with the version folders of a run (``pipeline.py view``).
"""
from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np

from manifoldneus.data import artifacts, io
from manifoldneus.geometry import cameras
from manifoldneus.output import export, meshing

ASSETS = Path(__file__).with_name("viewer_assets")
MAX_FACES = 200_000  # what a browser turns smoothly on a laptop; larger meshes are decimated to it
MAX_POINTS = 100_000  # sparse points of the reference drawn at most
FRUSTUM_FRACTION = 0.1  # a frustum's depth, as a fraction of the cameras' mean distance to their centroid


# ---------------------------------------------------------------------------- geometry


def decimate(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None, max_faces: int):
    """Vertex clustering: vertices [V,3] snapped to a grid whose cell grows until at most
    ``max_faces`` faces [F,3] remain (a cell's vertices merge into their mean, colours [V,3] too;
    faces that collapse are dropped). Returns (vertices, faces, colours) unchanged when small enough."""
    if len(faces) <= max_faces:
        return vertices, faces, colours
    lo = vertices.min(0)
    extent = float(np.ptp(vertices, 0).max())
    cell = extent / np.sqrt(max_faces)  # a surface of n^2 cells carries about 2 n^2 faces
    while True:
        keys = np.floor((vertices - lo) / cell).astype(np.int64)  # [V,3]
        _, cluster, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        cluster = cluster.ravel()
        f = cluster[faces]  # [F,3]
        keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
        f = np.unique(f[keep], axis=0)
        if len(f) <= max_faces:
            break
        cell *= 1.15

    def mean(a):
        out = np.zeros((len(counts), a.shape[1]))
        np.add.at(out, cluster, a)
        return out / counts[:, None]

    new_colours = None if colours is None else np.round(mean(colours.astype(np.float64))).astype(np.uint8)
    return mean(vertices), f, new_colours


def frustum_points(K: np.ndarray, w2c: np.ndarray, width, height, depth: float) -> np.ndarray:
    """Camera centre and the four image corners at z-depth ``depth``, in the world: [N,5,3] for
    K [N,3,3] and w2c [N,4,4] (OpenCV cameras), ``width`` and ``height`` one for all or per view."""
    c2w = cameras.invert_pose(w2c)  # [N,4,4]
    out = np.zeros((len(w2c), 5, 3))
    for i, (width, height) in enumerate(export.image_sizes(width, height, len(w2c))):
        corners = np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64)  # [4,2] px
        xc = np.c_[cameras.pixels_to_normalised(K[i], corners), np.ones(4)] * depth  # [4,3] camera frame
        out[i, 0] = c2w[i, :3, 3]
        out[i, 1:] = xc @ c2w[i, :3, :3].T + c2w[i, :3, 3]
    return out


def _b64(a: np.ndarray, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()).decode()


def _frusta_json(points: np.ndarray, present: np.ndarray) -> list:
    """[N,5,3] -> per view a flat list of 15 numbers (rounded to what a screen shows), or None."""
    return [np.round(points[i].ravel(), 6).tolist() if present[i] else None for i in range(len(points))]


# ---------------------------------------------------------------------------- the run's data


def _rounds(anchors_dir: Path, successors_dir: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(label, w2c [N,4,4], posed bool [N]) for the anchors' initial poses, the anchor round and
    each successor round, in order (as the ``evaluate`` stage lists them)."""
    init = artifacts.load_initial_poses(anchors_dir)
    out = [("initial", init["w2c"], init["placed"].astype(bool))]
    dirs = [anchors_dir / artifacts.ANCHOR_ROUND] + artifacts.successor_rounds(successors_dir)
    for d in dirs:
        r = artifacts.load_round(d)
        label = "anchors" if d.name == artifacts.ANCHOR_ROUND else d.name.replace("_", " ")
        out.append((label, r["w2c"], r["placed"].astype(bool) & r["optimised"].astype(bool)))
    return out


def _errors(w2c: np.ndarray, gt: np.ndarray, present: np.ndarray) -> list:
    """Per view [rotation deg, centre distance] between two sets of poses in one frame, or None."""
    rot = cameras.rotation_angle_deg(w2c[:, :3, :3] @ np.swapaxes(gt[:, :3, :3], -1, -2))
    centre = np.linalg.norm(cameras.camera_centers(w2c) - cameras.camera_centers(gt), axis=1)
    return [[round(float(rot[i]), 5), round(float(centre[i]), 6)] if present[i] else None for i in range(len(w2c))]


def scene_data(versions: dict[str, Path], max_faces: int = MAX_FACES) -> dict:
    """What the page draws, from the version folders of one run (stage -> folder; ``ingest``,
    ``ground_truth``, ``schedule``, ``anchors``, ``successors``, ``export`` and, when it was run, ``reference``)."""

    views_meta = artifacts.load_views_meta(versions["ingest"])
    sizes = artifacts.load_views_arrays(versions["ingest"], ["sizes"])["sizes"]  # each view's own (H, W)
    names, width, height = views_meta["names"], sizes[:, 1], sizes[:, 0]
    K = artifacts.load_round_arrays(versions["successors"] / artifacts.FINAL_ROUND, ["K"])["K"]  # the intrinsics the poses belong to
    n = len(names)
    schedule = artifacts.load_schedule_meta(versions["schedule"])
    held_out = np.zeros(n, bool)
    held_out[schedule["held_out_views"]] = True
    world_from_model = export.read_frame(versions["export"] / export.FRAME)
    model_rounds = _rounds(versions["anchors"], versions["successors"])
    to_world = cameras.sim3_from_matrix(world_from_model["world_from_model"])
    rounds = [(label, cameras.transform_w2c(w2c, *to_world), posed) for label, w2c, posed in model_rounds]
    final_w2c, final_posed = rounds[-1][1], rounds[-1][2]
    centres = cameras.camera_centers(final_w2c[final_posed])
    depth = FRUSTUM_FRACTION * float(np.linalg.norm(centres - centres.mean(0), axis=1).mean() or 1.0)

    gt = None
    gt_meta = artifacts.load_gt_meta(versions["ground_truth"])
    if gt_meta.get("has_poses") and final_posed.sum() >= 3:
        gt_w2c = artifacts.load_ground_truth_poses(versions["ground_truth"], ["w2c"])["w2c"]
        # the Sim3 final -> GT that `evaluate` and `export` fit, undone: GT in the method's frame, then this one
        gt_from_model = cameras.align_centres(model_rounds[-1][1], gt_w2c, final_posed)
        world_from_gt = world_from_model["world_from_model"] @ np.linalg.inv(cameras.sim3_matrix(*gt_from_model))
        gt_world = cameras.transform_w2c(gt_w2c, *cameras.sim3_from_matrix(world_from_gt))
        gt = {"frusta": _frusta_json(frustum_points(K, gt_world, width, height, depth), np.ones(n, bool)),
              "w2c": gt_world}

    rounds_json = []
    for label, w2c, posed in rounds:
        entry = {"label": label, "n_posed": int(posed.sum()),
                 "frusta": _frusta_json(frustum_points(K, w2c, width, height, depth), posed)}
        if gt is not None:
            entry["errors"] = _errors(w2c, gt["w2c"], posed)
        rounds_json.append(entry)

    roles = ["held out" if held_out[i] else v["role"] for i, v in enumerate(schedule["views"])]
    mesh = meshing.load_mesh(versions["export"] / artifacts.MESH)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    colours = None
    if mesh.visual.kind == "vertex":
        colours = np.asarray(mesh.visual.vertex_colors)[:, :3]
    v, f, c = decimate(vertices, faces, colours, max_faces)
    return {
        "frame": {k: world_from_model[k] for k in ("frame", "units", "how")},
        "cameras": [{"view": i, "name": names[i], "role": roles[i], "round": int(schedule["views"][i]["round"])}
                    for i in range(n)],
        "counts": {"views": n, "optimised": int(final_posed.sum()), "held_out": int(held_out.sum()),
                   "held_out_drawn": int(held_out.sum()) if gt is not None else 0},
        "rounds": rounds_json,
        "gt": None if gt is None else {"frusta": gt["frusta"]},
        "reference": None if "reference" not in versions else reference_data(versions["reference"], final_w2c,
                                                                              final_posed, K, width, height, depth),
        "mesh": {"positions": _b64(v, "f4"), "indices": _b64(f, "u4"),
                 "colours": None if c is None else _b64(c, "u1"),
                 "n_vertices": int(len(v)), "n_faces": int(len(f)), "n_faces_full": int(len(faces))},
    }


def reference_data(reference_dir: Path, final_w2c: np.ndarray, final_posed: np.ndarray, K, width, height,
                   depth: float) -> dict | None:
    """The pycolmap reference's cameras and sparse points, mapped onto the final cameras by the
    Sim3 of the centres of the views both placed (None when fewer than 3)."""
    ref = artifacts.load_reference_poses(reference_dir, ["w2c", "registered", "points3d", "points3d_rgb"])
    both = ref["registered"].astype(bool) & final_posed
    if both.sum() < 3:
        return None
    s, R, t = cameras.align_centres(ref["w2c"], final_w2c, both)
    w2c = cameras.transform_w2c(ref["w2c"], s, R, t)
    points, rgb = ref["points3d"], ref["points3d_rgb"]
    if len(points) > MAX_POINTS:
        pick = np.random.default_rng(0).choice(len(points), MAX_POINTS, replace=False)
        points, rgb = points[pick], rgb[pick]
    points = s * points @ R.T + t
    return {"frusta": _frusta_json(frustum_points(K, w2c, width, height, depth), ref["registered"].astype(bool)),
            "n_registered": int(ref["registered"].sum()),
            "points": _b64(points, "f4"), "colours": _b64(rgb, "u1"), "n_points": int(len(points))}


# ---------------------------------------------------------------------------- the page


def _module_url(source: str) -> str:
    return "data:text/javascript;base64," + base64.b64encode(source.encode()).decode()


def build_page(data: dict, title: str) -> str:
    """The HTML text: the page template with three.js and OrbitControls as data: URLs in an import
    map (so the page needs no server and no network), the app's module and the data inlined."""
    import html

    imports = {"three": _module_url((ASSETS / "three.module.min.js").read_text()),
               "three/addons/controls/OrbitControls.js": _module_url((ASSETS / "OrbitControls.js").read_text())}
    # inside a <script> element "</script" ends it and "<!--<script" changes how it is parsed: the
    # JSON carries no "<" (nor ">", "&") at all, as \u003c-style escapes that JSON.parse reads back
    data_json = json.dumps(data, separators=(",", ":"))
    data_json = data_json.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")
    values = {"TITLE": html.escape(title), "IMPORTMAP": json.dumps({"imports": imports}), "DATA": data_json,
              "APP": (ASSETS / "viewer.js").read_text(),
              "LICENSE": html.escape((ASSETS / "LICENSE-three.txt").read_text())}
    # one pass over the template: a name holding "{{APP}}" is data, never a place to fill
    return re.sub(r"\{\{(" + "|".join(values) + r")\}\}", lambda m: values[m.group(1)],
                  (ASSETS / "viewer.html").read_text())


def write_page(versions: dict[str, Path], path: Path, title: str, max_faces: int = MAX_FACES) -> dict:
    """Write the viewer page of one run to ``path``; returns its data's counts and sizes."""
    data = {"title": title, **scene_data(versions, max_faces)}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    io.write_text_atomic(path, build_page(data, title))
    return {**data["counts"], "faces": data["mesh"]["n_faces"], "faces_full": data["mesh"]["n_faces_full"],
            "bytes": path.stat().st_size}


# ---------------------------------------------------------------------------- a real browser

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_browser() -> str | None:
    """A Chromium (or Chrome) executable on PATH, or None (the Debian package is ``chromium``)."""
    import shutil

    return next((path for path in map(shutil.which, BROWSERS) if path), None)


def render_in_browser(page: Path, screenshot: Path | None = None, size: tuple[int, int] = (1200, 800),
                      budget_ms: int = 20000, browser: str | None = None, fragment: str = "",
                      webgl: bool = True) -> dict:
    """Open ``page`` (+ ``fragment``, e.g. ``#view=object``) in headless Chromium with software WebGL
    (SwiftShader; none with ``webgl`` false), let it run, and return what it showed: ``attributes``
    (the ``data-*`` the page wrote on <html>: ``viewer-state``, ``cameras-drawn``, ``errors``, ...),
    ``console`` (every console message and uncaught error), ``dom`` (the page as it ended) and the
    screenshot's path. Raises RuntimeError when no browser is found or it fails."""
    import os
    import re
    import subprocess
    import tempfile

    browser = browser or find_browser()
    if browser is None:
        raise RuntimeError(f"no Chromium found (looked for {', '.join(BROWSERS)}); "
                           "install the Debian package: apt-get install chromium")
    with tempfile.TemporaryDirectory(prefix="manifoldneus_chromium_") as profile:
        gl = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"] if webgl else ["--disable-3d-apis"]
        args = [browser, "--headless", f"--user-data-dir={profile}", *gl, "--enable-logging=stderr", "--v=0",
                "--hide-scrollbars",
                f"--window-size={size[0]},{size[1]}", f"--virtual-time-budget={budget_ms}", "--dump-dom"]
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            args.append("--no-sandbox")  # Chromium refuses to run as root with its sandbox
        if screenshot is not None:
            args.append(f"--screenshot={Path(screenshot).resolve()}")
        done = subprocess.run([*args, Path(page).resolve().as_uri() + fragment], capture_output=True, text=True,
                              timeout=budget_ms / 1000 + 120)
    opening = re.search(r"<html[^>]*>", done.stdout)
    if done.returncode != 0 or opening is None:
        raise RuntimeError(f"{browser} failed (exit {done.returncode}): {done.stderr[-2000:]}")
    attributes = dict(re.findall(r'data-([a-z-]+)="([^"]*)"', opening.group(0)))
    console = re.findall(r":CONSOLE[^\]]*\] (.*)", done.stderr)
    return {"attributes": attributes, "console": console, "dom": done.stdout, "screenshot": screenshot}
