"""Surface extraction: SDF on a grid inside the sphere (everywhere, or only in a narrow band around
its zero level, refined from a coarse grid) -> marching cubes -> largest component(s),
optional culling (the sphere's closure, the training views' dilated masks or, without masks, the
silhouettes of the object's SfM points, surface no view sees, what lies outside the object's region),
PLY writing and a PNG preview.

Outside the sphere the SDF is unconstrained, so the grid values are intersected with the sphere:
f' = max(f, |x| - radius) (the mesh is closed by the sphere where the SDF leaks out).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from manifoldneus.data.views import canvas_sizes


def sdf_grid(sdf_fn, resolution: int = 256, radius: float = 1.0, chunk: int = 262144,
             lo=None, hi=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evaluate ``sdf_fn`` (numpy [P,3] -> [P]) on a resolution^3 grid spanning [lo, hi]
    (default the sphere's cube). Returns (values [r,r,r] indexed x,y,z, lo, hi)."""
    lo = np.full(3, -radius) if lo is None else np.asarray(lo, float)
    hi = np.full(3, radius) if hi is None else np.asarray(hi, float)
    axes = [np.linspace(lo[k], hi[k], resolution) for k in range(3)]
    out = np.empty((resolution,) * 3, np.float32)
    # evaluate slab by slab (x), to bound memory
    yz = np.stack(np.meshgrid(axes[1], axes[2], indexing="ij"), -1).reshape(-1, 2)
    slabs = max(1, chunk // len(yz))
    for i in range(0, resolution, slabs):
        xs = axes[0][i:i + slabs]
        P = np.concatenate([np.repeat(xs, len(yz))[:, None], np.tile(yz, (len(xs), 1))], 1)
        out[i:i + len(xs)] = np.asarray(sdf_fn(P), np.float32).reshape(len(xs), resolution, resolution)
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    out = np.maximum(out, np.linalg.norm(g, axis=-1) - radius).astype(np.float32)
    return out, lo, hi


def narrow_band_sdf_grid(sdf_fn, resolution: int = 512, radius: float = 1.0, lo=None, hi=None, coarse_step: int = 8,
                         band: float = 2.0, chunk: int = 262144):
    """The SDF on a resolution^3 grid over [lo, hi] (default the sphere's cube), evaluated only near its
    zero level: a dense grid every ``coarse_step`` nodes first, then level by level each cell that may hold
    surface (its corners change sign, or one lies within ``band`` cell diagonals of it: a distance
    field's surface is no nearer) is split in eight and the new nodes evaluated. Returns (values [r,r,r]
    indexed x,y,z, with 4 * radius where not evaluated; cells bool [r,r,r], True at the lowest corner of
    every finest cell near the surface, all its corners evaluated; lo; hi; number of SDF evaluations).
    Intersected with the sphere like :func:`sdf_grid`."""
    if coarse_step < 1 or coarse_step & (coarse_step - 1):
        raise ValueError(f"coarse_step must be a power of two, got {coarse_step}")
    lo = np.full(3, -radius) if lo is None else np.asarray(lo, float)
    hi = np.full(3, radius) if hi is None else np.asarray(hi, float)
    r, last = resolution, resolution - 1
    spacing = (hi - lo) / last  # [3]
    ticks = np.arange(0, last, coarse_step)  # the coarse cells' lowest corners, per axis
    n = int(ticks[-1]) + coarse_step + 1  # padded so that no cell is cut: nodes past `hi` are evaluated like others
    values = np.full(n**3, 4.0 * radius, np.float32)  # flat, index x * n * n + y * n + z
    evaluated = np.zeros(n**3, bool)
    queued = np.zeros(n**3, bool)  # scratch: each node once per level

    def evaluate(nodes: np.ndarray) -> None:  # flat node indices, repeats allowed
        queued[nodes[~evaluated[nodes]]] = True
        flat = np.flatnonzero(queued)
        queued[flat] = False
        for a in range(0, len(flat), chunk):
            f = flat[a:a + chunk]
            x = lo + np.stack(np.unravel_index(f, (n, n, n)), 1) * spacing  # [C,3]
            values[f] = np.maximum(np.asarray(sdf_fn(x), np.float32).reshape(-1), np.linalg.norm(x, axis=1) - radius)
        evaluated[flat] = True

    def offsets(steps) -> np.ndarray:  # flat offsets of every combination of per-axis steps
        d = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), -1).reshape(-1, 3)
        return d @ np.array([n * n, n, 1])

    def near_surface(cells: np.ndarray, step: int) -> np.ndarray:  # cells [M]: flat lowest corners
        v = values[cells[:, None] + offsets([0, step])[None]]  # [M,8]
        crosses = (v.min(1) <= 0) & (v.max(1) >= 0)
        return crosses | (np.abs(v).min(1) <= band * step * np.linalg.norm(spacing))

    cells = offsets(ticks)
    evaluate(offsets(np.append(ticks, ticks[-1] + coarse_step)))
    step = coarse_step
    while True:
        cells = cells[near_surface(cells, step)]
        if step == 1 or not len(cells):
            break
        step //= 2
        evaluate((cells[:, None] + offsets([0, step, 2 * step])[None]).reshape(-1))
        cells = (cells[:, None] + offsets([0, step])[None]).reshape(-1)
    ijk = np.stack(np.unravel_index(cells, (n, n, n)), 1)  # [M,3]
    ijk = ijk[(ijk < last).all(1)]  # cells inside the requested grid
    mask = np.zeros((r, r, r), bool)
    mask[tuple(ijk.T)] = True
    values = values.reshape(n, n, n)[:r, :r, :r]
    return np.ascontiguousarray(values), mask, lo, hi, int(evaluated.sum())


def marching_cubes(values: np.ndarray, lo, hi, level: float = 0.0, mask: np.ndarray | None = None):
    """skimage marching cubes of a grid over [lo, hi] -> trimesh.Trimesh, in the cells whose lowest corner
    ``mask`` holds (None: every cell). skimage winds the faces so their normals point towards increasing
    values: outwards for an SDF (outside positive)."""
    import trimesh
    from skimage import measure

    inside = values if mask is None else values[mask]
    if not len(inside) or not (inside.min() < level < values.max()):
        lo_v = inside.min() if len(inside) else float("nan")
        raise ValueError(f"the SDF does not cross {level} on the grid (min {lo_v:.3g}, max {values.max():.3g})")
    r = np.array(values.shape) - 1
    spacing = (np.asarray(hi) - np.asarray(lo)) / r
    verts, faces, _, _ = measure.marching_cubes(values, level=level, spacing=tuple(spacing), mask=mask)
    verts = verts + np.asarray(lo)
    return trimesh.Trimesh(verts, faces, process=False)


def largest_components(mesh, keep: int = 1, min_faces: int = 0):
    """Keep the ``keep`` connected components with the most faces."""
    import trimesh

    if len(mesh.faces) == 0:
        return mesh
    parts = mesh.split(only_watertight=False)
    if len(parts) <= 1:
        return mesh
    parts = sorted(parts, key=lambda m: len(m.faces), reverse=True)
    parts = [m for m in parts[:keep] if len(m.faces) >= min_faces] or parts[:1]
    return trimesh.util.concatenate(parts)


def keep_vertices(mesh, keep):
    """The mesh with only the faces whose vertices all have ``keep`` (bool [V]) set."""
    out = mesh.copy()
    out.update_faces(np.asarray(keep, bool)[mesh.faces].all(1))
    out.remove_unreferenced_vertices()
    return out


def cut_by_plane(mesh, plane, offset: float = 0.0):
    """The part of the mesh where n.x + d >= ``offset`` (``plane`` = n [3] unit + [d]), its triangles split
    along the plane, so the cut is a straight edge on it."""
    import trimesh

    n = np.asarray(plane[:3], np.float64)
    # the faces' slicer, not Trimesh.slice_plane: that one imports shapely (for caps) even when not capping
    vertices, faces = trimesh.intersections.slice_faces_plane(np.asarray(mesh.vertices), np.asarray(mesh.faces), n,
                                                              (offset - float(plane[3])) * n)[:2]
    out = trimesh.Trimesh(vertices, faces, process=False)
    out.merge_vertices()  # the split faces' new vertices, shared between neighbours
    out.remove_unreferenced_vertices()
    return out


def point_silhouettes(points: np.ndarray, K: np.ndarray, w2c: np.ndarray, hw) -> np.ndarray:
    """bool [N,H,W]: in each view (K [N,3,3], w2c [N,4,4], image size hw = (H, W)) the convex hull of the
    points [P,3] in front of it, projected: the silhouette a mask would give, from SfM points alone. Convex, so
    it also covers the object's concavities and its textureless parts between points."""
    from manifoldneus.geometry.segmentation import convex_hull_mask

    return np.array([convex_hull_mask(points, K[i], w2c[i], hw) for i in range(len(w2c))], bool).reshape(len(w2c), *hw)


def off_sphere_closure(vertices: np.ndarray, radius: float, resolution: int) -> np.ndarray:
    """bool [V]: vertices [V,3] away from the sphere that closes the grid (:func:`sdf_grid`): where the SDF
    is still negative at the sphere, marching cubes puts surface on the sphere itself, which no view saw
    as surface (an unmasked capture's background, the far side of a cropped field)."""
    cell = 2 * radius / (resolution - 1)
    return np.linalg.norm(vertices, axis=1) < radius - 0.75 * cell


def cull_by_masks(mesh, K, w2c, masks, dilation: int = 12, rule: str = "all", min_fraction: float = 1.0, sizes=None):
    """Remove vertices outside the training views' dilated masks.

    rule 'all' (DTU evaluation scripts of IDR / NeuS / MonoSDF at ``min_fraction`` 1): keep a vertex when
    it projects inside the dilated mask in at least ``min_fraction`` of the views whose image it falls in
    (a visual hull; below 1 it tolerates views whose mask misses a part).
    rule 'any': keep a vertex that projects inside the dilated mask of at least one view.
    K [N,3,3], w2c [N,4,4], masks [N,H,W] bool; ``sizes`` [N,2] (H, W) each view's own part of the masks'
    canvas (:mod:`manifoldneus.data.views`; None: all of it). Faces keep only when all their vertices stay."""
    import cv2

    V = np.asarray(mesh.vertices, np.float64)
    N = len(masks)
    ker = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilation + 1, 2 * dilation + 1)) if dilation > 0 else None
    n_inside = np.zeros(len(V))
    n_in_image = np.zeros(len(V))
    for i, (H, W) in enumerate(canvas_sizes(sizes, N, masks.shape[1:3])):
        m = masks[i].astype(np.uint8)
        if ker is not None:
            m = cv2.dilate(m, ker)
        xc = V @ w2c[i][:3, :3].T + w2c[i][:3, 3]
        z = xc[:, 2]
        uvw = xc @ K[i].T
        uv = uvw[:, :2] / np.clip(z, 1e-9, None)[:, None]
        in_img = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        c = np.clip(uv[:, 0].astype(int), 0, W - 1)
        r = np.clip(uv[:, 1].astype(int), 0, H - 1)
        in_mask = in_img & (m[r, c] > 0)
        n_inside += in_mask
        n_in_image += in_img
    keep = n_inside >= min_fraction * n_in_image - 1e-9 if rule == "all" else n_inside > 0
    return keep_vertices(mesh, keep)


def splat_depth(uv: np.ndarray, z: np.ndarray, hw) -> np.ndarray:
    """[H,W] z-buffer of points splatted one pixel each: per pixel the least depth z [P] of the points whose
    pixel coordinates uv [P,2] fall in it, inf where none does (points outside the image ``hw`` = (H, W) left out)."""
    H, W = hw
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    buffer = np.full(H * W, np.inf, z.dtype)
    np.minimum.at(buffer, uv[inside, 1].astype(int) * W + uv[inside, 0].astype(int), z[inside])
    return buffer.reshape(H, W)


def cull_unseen(mesh, K, w2c, hw, size: int = 128, depth_tol_px: float = 4.0, sizes=None):
    """Remove vertices that no view sees: surface the training never observed (e.g. the underside,
    where a grid SDF keeps its initial sphere) has no image evidence, and DTU's evaluation crops it too.

    Per view, a z-buffer of the mesh's own vertices at ``size`` px (longest side; min-filtered 3x3 to
    close gaps between splatted vertices); a vertex is seen when it lies in the image, in front of the
    camera, and no deeper than the z-buffer by ``depth_tol_px`` pixel footprints (a slanted surface
    changes depth across the 3x3 filter by about its slope times a footprint).
    K [N,3,3] and w2c [N,4,4] at image size ``hw`` = (H, W), or each view's own ``sizes`` [N,2] (H, W).
    Faces keep only when all their vertices stay."""
    from scipy.ndimage import minimum_filter

    V = np.asarray(mesh.vertices, np.float64)  # [P,3]
    seen = np.zeros(len(V), bool)
    for Ki, T, (H, W) in zip(K, w2c, canvas_sizes(sizes, len(K), hw)):
        scale = size / max(H, W)
        h, w = max(int(round(H * scale)), 1), max(int(round(W * scale)), 1)
        xc = V @ T[:3, :3].T + T[:3, 3]  # [P,3] camera frame
        z = xc[:, 2]
        uv = (xc @ Ki.T)[:, :2] / np.clip(z, 1e-9, None)[:, None] * scale
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        idx = np.flatnonzero(ok)
        pix = uv[idx, 1].astype(int) * w + uv[idx, 0].astype(int)
        zbuf = minimum_filter(splat_depth(uv[idx], z[idx], (h, w)), size=3, mode="nearest").reshape(-1)
        footprint = z[idx] / (0.5 * (Ki[0, 0] + Ki[1, 1]) * scale)  # world size of a z-buffer pixel
        seen[idx[z[idx] <= zbuf[pix] + depth_tol_px * footprint]] = True
    return keep_vertices(mesh, seen)


def extract_mesh(sdf_fn, resolution: int = 256, radius: float = 1.0, keep_components: int = 1,
                 level: float = 0.0, lo=None, hi=None, coarse_step: int = 0, band: float = 2.0):
    """SDF -> grid -> marching cubes -> largest component(s). Returns trimesh.Trimesh. coarse_step > 0
    evaluates the grid only near the surface (:func:`narrow_band_sdf_grid`), 0 everywhere."""
    mask = None
    if coarse_step > 0:
        vals, mask, lo, hi, _ = narrow_band_sdf_grid(sdf_fn, resolution, radius, lo, hi, coarse_step, band)
    else:
        vals, lo, hi = sdf_grid(sdf_fn, resolution, radius, lo=lo, hi=hi)
    mesh = marching_cubes(vals, lo, hi, level, mask)
    if keep_components > 0:
        mesh = largest_components(mesh, keep_components)
    return mesh


def load_mesh(path):
    """A PLY this package wrote, as a Trimesh: an empty one too (trimesh reads a file without faces
    as an empty Scene, which has no ``faces``)."""
    import trimesh

    return trimesh.load(str(path), process=False, force="mesh")


def save_ply(mesh, path) -> None:
    """Binary PLY."""
    Path(path).write_bytes(mesh.export(file_type="ply"))


def _look_rotation(forward: np.ndarray, up=np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    z = forward / np.linalg.norm(forward)
    if abs(np.dot(z, up)) > 0.99:
        up = np.array([0.0, 1.0, 0.0])
    x = np.cross(-up, z)  # OpenCV-like: x right, y down the image
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def preview_directions(w2c, n: int = 3) -> tuple[list, np.ndarray]:
    """Viewing directions of ``n`` of the cameras ``w2c`` [N,4,4] spread across their azimuths, and
    their mean image-up vector: previews then show the surface the cameras saw, upright."""
    R = np.asarray(w2c, np.float64)[:, :3, :3]
    forward = R[:, 2, :]  # camera +z in world, [N,3]
    up = -R[:, 1, :].mean(0)  # OpenCV y points down the image
    up /= np.linalg.norm(up) + 1e-12
    flat = forward - np.outer(forward @ up, up)
    ref = flat.mean(0)
    side = np.cross(up, ref)
    azimuth = np.arctan2(flat @ side, flat @ ref)
    order = np.argsort(azimuth)
    picks = order[np.round(np.linspace(0.1, 0.9, n) * (len(order) - 1)).astype(int)]
    return [forward[i] for i in picks], up


def render_preview(mesh, size: int = 320, directions=None, up=None) -> np.ndarray:
    """Shaded orthographic views of a mesh side by side (a numpy z-buffer rasteriser of the
    triangles' sample points). Returns uint8 [size, size * n_views, 3]."""
    V = np.asarray(mesh.vertices, np.float64)
    F_ = np.asarray(mesh.faces)
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float)
    if directions is None:
        directions = [np.array([1.0, 1.0, -0.6]), np.array([-1.0, 0.3, -0.4]), np.array([0.0, -1.0, -1.0])]
    centre = 0.5 * (V.min(0) + V.max(0))
    ext = np.linalg.norm(V.max(0) - V.min(0)) / 2 + 1e-9
    fn = np.asarray(mesh.face_normals)
    # sample points on faces: barycentric grid (more where faces are big relative to pixels)
    bary = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1 / 3, 1 / 3, 1 / 3], [0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5]])
    tri = V[F_]  # [F,3,3]
    pts = np.einsum("bk,fkd->fbd", bary, tri).reshape(-1, 3)
    pn = np.repeat(fn, len(bary), 0)
    panels = []
    for dvec in directions:
        Rm = _look_rotation(np.asarray(dvec, float), up)
        pc = (pts - centre) @ Rm.T / ext  # in [-1,1]
        u = ((pc[:, 0] * 0.95 + 1) * 0.5 * (size - 1)).round().astype(int)
        v = ((pc[:, 1] * 0.95 + 1) * 0.5 * (size - 1)).round().astype(int)
        z = pc[:, 2]
        ok = (u >= 0) & (u < size) & (v >= 0) & (v < size)
        u, v, z = u[ok], v[ok], z[ok]
        ncam = pn[ok] @ Rm.T
        shade = np.clip(-ncam[:, 2], 0, 1) * 0.75 + 0.2 * np.clip(-ncam[:, 1], 0, 1) + 0.05
        pix = v * size + u
        order = np.lexsort((z, pix))  # by pixel, then nearest first
        pix_s = pix[order]
        first = np.ones(len(pix_s), bool)
        first[1:] = pix_s[1:] != pix_s[:-1]
        img = np.full(size * size, 1.0)
        img[pix_s[first]] = shade[order][first]
        img = img.reshape(size, size)
        panels.append(np.stack([img * 0.85, img * 0.9, img], -1))
    return (np.concatenate(panels, 1).clip(0, 1) * 255).astype(np.uint8)


def save_preview(mesh, path, size: int = 320, **kw) -> None:
    from manifoldneus.data.io import save_png

    save_png(Path(path), render_preview(mesh, size, **kw))
