"""Synthetic DTU-like scene: a textured analytic object with exactly known surface and poses.

The object (fixed shape, independent of the seed) is the union (``min``) of three primitives,
in the object-normalised world frame (z up, everything within radius 0.6 of the origin,
see :func:`bounding_box`):

* a rounded box (the "base"), centre (0, 0, -0.17), half extents (0.42, 0.3, 0.18), rounding 0.06;
* a sphere, centre (-0.2, 0.02, 0.15), radius 0.24, sunk into the top of the box;
* a torus (a ring standing on the box, its hole facing the cameras), centre (0.25, -0.02, 0.15),
  axis ~ world y (tilted 14 deg towards x), major radius 0.19, tube radius 0.065; it sinks into
  the box and touches the sphere slightly.

:func:`sdf` is the ``min`` of the three exact primitive SDFs. It is **exact outside the
object** (and exactly 0 on the surface); inside, where primitives overlap, ``|sdf|`` is a lower
bound of the true distance to the surface (exact inside any single primitive away from the
junctions). So ``mean(|sdf(p)|)`` is the exact accuracy of points on/outside the object and
a (slight) underestimate for points inside near the junctions.

The **seed only changes the texture** (a view-independent procedural albedo defined in 3D:
smooth coloured value noise plus four scales of random coloured dots). Shading is Lambertian with
two lights fixed in the world, baked into the colour, so the images are photometrically
consistent across views. Background: a mild dark-grey vertical gradient, untextured; optionally
(``floor``) the object stands on a textured floor disc (z = FLOOR_Z), as objects on a table do.

Cameras (:func:`camera_poses`): three arcs of the upper hemisphere in front of the object
(the -y side): elevations 20/40/60 deg, azimuth spans +-70/+-55/+-45 deg, 24/16/9 views for
N = 49 (other N: split by arc length, evenly spaced along each arc); distance 3.0, looking at
the origin with world +z up in the images, ordered serpentine (consecutive indices are
neighbours, like the DTU robot path). The whole object is in every view (>= 5 px margin).
Intrinsics: fx = fy = 2.4 W, principal point at the image centre (W/2, H/2); optionally a lens with
radial distortion k1 (OpenCV's model, :func:`render_view`), to test its estimation. Conventions are
those of :mod:`manifoldneus.geometry.cameras` (OpenCV, w2c, pixel centres at +0.5).
As in DTU, the back and the bottom of the object are never observed: :func:`points_visible`
restricts ground-truth surface samples to the observed part.
"""
from __future__ import annotations

import copy
import functools
from dataclasses import dataclass, field

import numpy as np

from manifoldneus.geometry.cameras import look_at_w2c

# --------------------------------------------------------------------------- shape

BOX_CENTER = np.array([0.0, 0.0, -0.17])
BOX_HALF = np.array([0.42, 0.3, 0.18])
BOX_ROUND = 0.06
SPHERE_CENTER = np.array([-0.2, 0.02, 0.15])
SPHERE_RADIUS = 0.24
TORUS_CENTER = np.array([0.25, -0.02, 0.15])
_a = np.array([0.25, 1.0, 0.0])
TORUS_AXIS = _a / np.linalg.norm(_a)
TORUS_R = 0.19  # major radius
TORUS_r = 0.065  # tube radius


def _torus_frame() -> np.ndarray:
    """Rotation [3,3] whose columns are the torus local axes (x, y = TORUS_AXIS, z) in world."""
    y = TORUS_AXIS
    z = np.array([0.0, 0.0, 1.0])
    z = z - y * (y @ z)
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    return np.stack([x, y, z], 1)


TORUS_FRAME = _torus_frame()

_BOX_INNER = BOX_HALF - BOX_ROUND


def _box3(x, y, z):
    qx = np.abs(x - BOX_CENTER[0]) - _BOX_INNER[0]
    qy = np.abs(y - BOX_CENTER[1]) - _BOX_INNER[1]
    qz = np.abs(z - BOX_CENTER[2]) - _BOX_INNER[2]
    inside = np.minimum(np.maximum(np.maximum(qx, qy), qz), 0.0)
    np.maximum(qx, 0.0, out=qx)
    np.maximum(qy, 0.0, out=qy)
    np.maximum(qz, 0.0, out=qz)
    return np.sqrt(qx * qx + qy * qy + qz * qz) + inside - BOX_ROUND


def _sphere3(x, y, z):
    dx, dy, dz = x - SPHERE_CENTER[0], y - SPHERE_CENTER[1], z - SPHERE_CENTER[2]
    return np.sqrt(dx * dx + dy * dy + dz * dz) - SPHERE_RADIUS


def _torus3(x, y, z):
    dx, dy, dz = x - TORUS_CENTER[0], y - TORUS_CENTER[1], z - TORUS_CENTER[2]
    F = TORUS_FRAME  # local coordinates q_j = sum_i d_i F[i, j]; torus axis = local y
    qx = F[0, 0] * dx + F[1, 0] * dy + F[2, 0] * dz
    qy = F[0, 1] * dx + F[1, 1] * dy + F[2, 1] * dz
    qz = F[0, 2] * dx + F[1, 2] * dy + F[2, 2] * dz
    ring = np.sqrt(qx * qx + qz * qz) - TORUS_R
    return np.sqrt(ring * ring + qy * qy) - TORUS_r


def _sdf3(x, y, z):
    """Union SDF on separate coordinate arrays (the tracer's layout)."""
    return np.minimum(np.minimum(_box3(x, y, z), _sphere3(x, y, z)), _torus3(x, y, z))


def _split(p: np.ndarray):
    p = np.asarray(p, dtype=np.float64)
    return p[..., 0], p[..., 1], p[..., 2]


def _sdf_box(p: np.ndarray) -> np.ndarray:
    return _box3(*_split(p))


def _sdf_sphere(p: np.ndarray) -> np.ndarray:
    return _sphere3(*_split(p))


def _sdf_torus(p: np.ndarray) -> np.ndarray:
    return _torus3(*_split(p))


def sdf(points: np.ndarray) -> np.ndarray:
    """Signed distance of the object, [P,3] (or [...,3]) -> [P] (negative inside).

    Exact outside the object and on it; inside it is a lower bound of the distance (min of
    exact primitive SDFs). The shape does not depend on any seed."""
    return _sdf3(*_split(points))


def sdf_normals(points: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    """Unit outward normals (normalised central-difference gradient of :func:`sdf`), [P,3]."""
    p = np.asarray(points, dtype=np.float64)
    g = np.empty_like(p)
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        g[:, k] = sdf(p + d) - sdf(p - d)
    return g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)


def bounding_box() -> tuple[np.ndarray, np.ndarray]:
    """Exact min / max corners [3], [3] of the object (union of the primitives' exact boxes)."""
    lo = [BOX_CENTER - BOX_HALF, SPHERE_CENTER - SPHERE_RADIUS]
    hi = [BOX_CENTER + BOX_HALF, SPHERE_CENTER + SPHERE_RADIUS]
    # torus: extent along world axis k is R * sqrt(1 - a_k^2) + r
    ext = TORUS_R * np.sqrt(np.clip(1.0 - TORUS_AXIS**2, 0.0, None)) + TORUS_r
    lo.append(TORUS_CENTER - ext)
    hi.append(TORUS_CENTER + ext)
    return np.min(lo, 0), np.max(hi, 0)


# --------------------------------------------------------------------------- surface samples


def _sample_sphere_dirs(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _box_pieces():
    """Areas of the rounded box pieces: 3 face pairs, 3 edge groups, corners."""
    a = BOX_HALF - BOX_ROUND
    r = BOX_ROUND
    faces = [2 * 4 * a[(i + 1) % 3] * a[(i + 2) % 3] for i in range(3)]  # pair of faces normal to i
    edges = [4 * (np.pi * r / 2) * 2 * a[i] for i in range(3)]  # 4 quarter cylinders along i
    corners = 4 * np.pi * r**2
    return a, r, np.array(faces + edges + [corners])


def _sample_box(rng: np.random.Generator, n: int) -> np.ndarray:
    a, r, areas = _box_pieces()
    piece = rng.choice(len(areas), size=n, p=areas / areas.sum())
    out = np.zeros((n, 3))
    for k in range(7):
        idx = np.nonzero(piece == k)[0]
        m = len(idx)
        if m == 0:
            continue
        s = rng.choice([-1.0, 1.0], size=(m, 3))
        if k < 3:  # faces normal to axis i
            i, j, l = k, (k + 1) % 3, (k + 2) % 3
            out[idx, i] = s[:, 0] * (a[i] + r)
            out[idx, j] = rng.uniform(-a[j], a[j], m)
            out[idx, l] = rng.uniform(-a[l], a[l], m)
        elif k < 6:  # quarter cylinders along axis i
            i = k - 3
            j, l = (i + 1) % 3, (i + 2) % 3
            th = rng.uniform(0.0, np.pi / 2, m)
            out[idx, i] = rng.uniform(-a[i], a[i], m)
            out[idx, j] = s[:, 1] * (a[j] + r * np.cos(th))
            out[idx, l] = s[:, 2] * (a[l] + r * np.sin(th))
        else:  # eighth spheres at the corners
            u = _sample_sphere_dirs(rng, m)
            out[idx] = np.sign(u) * a + r * u
    return out + BOX_CENTER


def _sample_torus(rng: np.random.Generator, n: int) -> np.ndarray:
    pts = []
    got = 0
    while got < n:
        m = 2 * (n - got) + 16
        phi = rng.uniform(0, 2 * np.pi, m)
        keep = rng.uniform(0, 1, m) < (TORUS_R + TORUS_r * np.cos(phi)) / (TORUS_R + TORUS_r)
        phi = phi[keep]
        th = rng.uniform(0, 2 * np.pi, len(phi))
        rho = TORUS_R + TORUS_r * np.cos(phi)
        local = np.stack([rho * np.cos(th), TORUS_r * np.sin(phi), rho * np.sin(th)], 1)
        pts.append(local)
        got += len(local)
    local = np.concatenate(pts)[:n]
    return local @ TORUS_FRAME.T + TORUS_CENTER


def _areas() -> np.ndarray:
    box = _box_pieces()[2].sum()
    sphere = 4 * np.pi * SPHERE_RADIUS**2
    torus = 4 * np.pi**2 * TORUS_R * TORUS_r
    return np.array([box, sphere, torus])


def sample_surface(n: int, seed: int = 0) -> np.ndarray:
    """[n,3] points exactly on the object's surface (|sdf| < 1e-6; float64 round-off only),
    uniform by area: each primitive's surface is sampled uniformly at a common density and
    the parts inside another primitive are discarded."""
    rng = np.random.default_rng(seed)
    areas = _areas()
    samplers = (_sample_box, lambda r, m: SPHERE_CENTER + SPHERE_RADIUS * _sample_sphere_dirs(r, m), _sample_torus)
    others = ((_sdf_sphere, _sdf_torus), (_sdf_box, _sdf_torus), (_sdf_box, _sdf_sphere))
    chunks, total = [], 0
    density = 1.3 * n / areas.sum()
    while total < n:
        for k in range(3):
            m = int(np.ceil(density * areas[k]))
            p = samplers[k](rng, m)
            keep = np.ones(m, bool)
            for f in others[k]:
                keep &= f(p) > 0.0
            chunks.append(p[keep])
            total += int(keep.sum())
    pts = np.concatenate(chunks)
    return pts[rng.choice(len(pts), size=n, replace=False)]


# --------------------------------------------------------------------------- texture

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_PX, _PY, _PZ = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xC2B2AE3D27D4EB4F), np.uint64(0x165667B19E3779F9)
_S16 = 1.0 / 65536.0


def _hash(hx: np.ndarray, hy: np.ndarray, hz: np.ndarray, salt: int) -> np.ndarray:
    """64-bit hash (splitmix64 finaliser) of pre-multiplied lattice coordinates, uint64 [P]."""
    with np.errstate(over="ignore"):
        h = hx ^ hy ^ hz ^ np.uint64(salt)
        h ^= h >> np.uint64(30)
        h *= _M1
        h ^= h >> np.uint64(27)
        h *= _M2
        h ^= h >> np.uint64(31)
    return h


def _lattice(i: np.ndarray, prime: np.uint64) -> np.ndarray:
    with np.errstate(over="ignore"):
        return i.astype(np.int64).view(np.uint64) * prime


def _fields(h: np.ndarray, k: int) -> list[np.ndarray]:
    """k (<= 4) independent uniform [0,1) values from the 16-bit fields of a hash."""
    return [((h >> np.uint64(16 * j)) & np.uint64(0xFFFF)).astype(np.float64) * _S16 for j in range(k)]


def _value_noise(p: np.ndarray, salt: int, k: int) -> np.ndarray:
    """k (<= 4) channels of smooth 3D value noise in [0,1], p [3,P] (lattice spacing 1) -> [k,P]."""
    i0 = np.floor(p)
    f = p - i0
    f = f * f * (3.0 - 2.0 * f)
    i0 = i0.astype(np.int64)
    lx = (_lattice(i0[0], _PX), _lattice(i0[0] + 1, _PX))
    ly = (_lattice(i0[1], _PY), _lattice(i0[1] + 1, _PY))
    lz = (_lattice(i0[2], _PZ), _lattice(i0[2] + 1, _PZ))
    wx, wy, wz = (1.0 - f[0], f[0]), (1.0 - f[1], f[1]), (1.0 - f[2], f[2])
    out = np.zeros((k, p.shape[1]))
    for dx in (0, 1):
        for dy in (0, 1):
            wxy = wx[dx] * wy[dy]
            for dz in (0, 1):
                w = wxy * wz[dz]
                for c, v in enumerate(_fields(_hash(lx[dx], ly[dy], lz[dz], salt), k)):
                    out[c] += w * v
    return out


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """[P] each -> [3,P]."""
    k = np.stack([(5 + h * 6) % 6, (3 + h * 6) % 6, (1 + h * 6) % 6])
    return v - v * s * np.clip(np.minimum(k, 4 - k), 0, 1)


# Dot layers: (lattice frequency per unit, min / max radius in cells, probability, edge width
# in world units ~ one pixel at 192 px, so the texture is band-limited at that resolution).
DOT_LAYERS = ((7.0, 0.2, 0.4, 1.0), (12.0, 0.18, 0.4, 1.0), (20.0, 0.18, 0.4, 1.0), (34.0, 0.2, 0.4, 1.0))
DOT_EDGE = 0.0065


def albedo(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """View-independent procedural albedo in [0,1], [P,3] -> [P,3]; the seed picks the texture
    (lattice orientation / offset and all random values), not the shape."""
    p = np.asarray(points, dtype=np.float64)
    rng = np.random.default_rng([int(seed), 0x5EED])
    salts = [int(s) for s in rng.integers(0, 2**63, size=16, dtype=np.uint64)]
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]  # random lattice orientation per seed
    q = np.ascontiguousarray((p @ rot + rng.uniform(-10, 10, 3)).T)  # [3,P]
    # smooth coloured base: two octaves of 3-channel value noise, then a finer brightness noise
    col = 0.25 + 0.6 * (0.65 * _value_noise(q * 2.5, salts[0], 3) + 0.35 * _value_noise(q * 6.0, salts[1], 3))
    col *= 0.7 + 0.6 * _value_noise(q * 18.0, salts[2], 1)
    # random coloured dots at four scales (each dot's ball lies inside its lattice cell)
    for layer, (freq, rmin, rmax, prob) in enumerate(DOT_LAYERS):
        qq = q * freq
        cell = np.floor(qq)
        lx, ly, lz = _lattice(cell[0], _PX), _lattice(cell[1], _PY), _lattice(cell[2], _PZ)
        h = _fields(_hash(lx, ly, lz, salts[3 + layer]), 4) + _fields(_hash(lx, ly, lz, salts[3 + layer] ^ 0x55), 4)
        rad = rmin + (rmax - rmin) * h[0]
        off = 0.5 + (np.stack(h[1:4]) - 0.5) * (1.0 - 2.0 * rad)
        dist = np.sqrt(((qq - cell - off) ** 2).sum(0))
        alpha = np.clip((rad - dist) / (DOT_EDGE * freq) + 0.5, 0.0, 1.0) * (h[4] < prob)
        dark = h[6] < 0.45  # dark dots or bright saturated dots, for luminance contrast
        v = np.where(dark, 0.05 + 0.2 * h[7], 0.75 + 0.25 * h[7])
        dot = _hsv_to_rgb(h[5], 0.55 + 0.45 * h[7], v)
        col += alpha * (dot - col)
    return np.clip(col.T, 0.0, 1.0)


LIGHTS = (  # (direction towards the light in world, intensity)
    (np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82]), 0.7),
    (np.array([-0.6, -0.3, 0.3]) / np.linalg.norm([-0.6, -0.3, 0.3]), 0.25),
)
AMBIENT = 0.3


def shade(points: np.ndarray, normals_world: np.ndarray, seed: int = 0) -> np.ndarray:
    """Linear RGB in [0,1] of surface points: albedo x (ambient + Lambert, lights fixed in world)."""
    s = np.full(len(points), AMBIENT)
    for d, w in LIGHTS:
        s = s + w * np.clip(normals_world @ d, 0.0, None)
    return np.clip(albedo(points, seed) * s[:, None], 0.0, 1.0)


FLOOR_Z = -0.35  # the base's bottom: the object stands on the floor
FLOOR_RADIUS = 2.0


def floor_hit(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Ray parameter t [R] where rays (origins, unit dirs [R,3]) meet the floor, a textured disc of radius
    FLOOR_RADIUS at z = FLOOR_Z under the object (inf where they miss it)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (FLOOR_Z - origins[:, 2]) / dirs[:, 2]
    t = np.where((dirs[:, 2] < 0) & (t > 0), t, np.inf)
    on = np.isfinite(t)
    xy = origins[on, :2] + t[on, None] * dirs[on, :2]
    t[np.flatnonzero(on)[np.linalg.norm(xy, axis=1) > FLOOR_RADIUS]] = np.inf
    return t


def floor_colour(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """Linear RGB [P,3] of floor points: a texture of its own (the albedo of another seed, darker), lit
    like the object from straight above."""
    return shade(points, np.tile([0.0, 0.0, 1.0], (len(points), 1)), seed + 7919) * 0.8


def background(height: int, width: int) -> np.ndarray:
    """Background colour [H,W,3] in [0,1]: a mild dark-grey vertical gradient."""
    v = np.linspace(0.2, 0.12, height)[:, None, None]
    return np.broadcast_to(v * np.array([1.0, 1.0, 1.05]), (height, width, 3)).copy()


# --------------------------------------------------------------------------- tracing


def trace(
    origins: np.ndarray,
    dirs: np.ndarray,
    t_max: np.ndarray | float = np.inf,
    eps: float = 1e-6,
    min_step: float = 1e-4,
    max_steps: int = 300,
) -> np.ndarray:
    """Sphere-trace rays against :func:`sdf`. origins, dirs: [R,3] (dirs unit); t_max: scalar
    or [R], the ray length searched. Returns the ray parameter t [R] of the first hit (inf on a
    miss), accurate to ~eps along the normal.

    Steps are ``max(sdf, min_step)`` so that rays grazing a surface do not stall (a graze
    closer than ``min_step`` may be passed; an overshoot into the object is walked back with
    interior SDF steps, which never cross the entry point). Vectorised over rays, with the
    still-marching set compacted as rays finish."""
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(dirs, np.float64).reshape(-1, 3)
    t_hit = np.full(len(o), np.inf)
    # entry / exit of the (slightly padded) bounding box: slab test
    lo, hi = bounding_box()
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (lo - 1e-3 - o) * inv
        t1 = (hi + 1e-3 - o) * inv
    t_near = np.nan_to_num(np.minimum(t0, t1), nan=-np.inf).max(1)
    t_exit = np.nan_to_num(np.maximum(t0, t1), nan=np.inf).min(1)
    t_near = np.maximum(t_near, 0.0)
    t_exit = np.minimum(t_exit, np.broadcast_to(np.asarray(t_max, np.float64), t_exit.shape))
    act = np.nonzero(t_near < t_exit)[0]
    t, t_far = t_near[act], t_exit[act]
    ox, oy, oz = (np.ascontiguousarray(o[act, k]) for k in range(3))
    dx, dy, dz = (np.ascontiguousarray(d[act, k]) for k in range(3))
    hits = []  # (ray index, t) of rays that reached or crossed the surface
    for _ in range(max_steps):
        if len(act) == 0:
            break
        dist = _sdf3(ox + t * dx, oy + t * dy, oz + t * dz)
        hit = dist < eps
        if hit.any():
            hits.append((act[hit], t[hit]))
        t += np.maximum(dist, min_step)
        live = ~hit & (t <= t_far)
        if not live.all():
            act, t, t_far = act[live], t[live], t_far[live]
            ox, oy, oz, dx, dy, dz = ox[live], oy[live], oz[live], dx[live], dy[live], dz[live]
    if len(act):  # out of steps (should not happen): accept those essentially on the surface
        dist = _sdf3(ox + t * dx, oy + t * dy, oz + t * dz)
        ok = dist < 1e-4
        hits.append((act[ok], t[ok]))
    if hits:
        idx = np.concatenate([h[0] for h in hits])
        th = np.concatenate([h[1] for h in hits])
        oh, dh = o[idx], d[idx]
        for _ in range(100):  # walk overshoots back to the surface (sdf < 0 -> step backwards)
            dist = sdf(oh + th[:, None] * dh)
            back = dist < -eps
            if not back.any():
                break
            th[back] += dist[back]
        t_hit[idx] = th
    return t_hit


def camera_dirs(K: np.ndarray, uv: np.ndarray, k1: float = 0.0) -> np.ndarray:
    """Unit camera-frame directions [M,3] of the rays through pixels uv [M,2] of a camera with K and a
    lens of radial distortion k1 (OpenCV's [k1, 0, 0, 0])."""
    from manifoldneus.geometry.cameras import undistort_points

    if k1:
        uv = undistort_points(uv, K, np.array([k1, 0.0, 0.0, 0.0]))
    dc = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T
    return dc / np.linalg.norm(dc, axis=1, keepdims=True)


def pixel_rays(K: np.ndarray, w2c: np.ndarray, height: int, width: int, offsets=((0.5, 0.5),), k1: float = 0.0):
    """World rays through pixel points (col + ox, row + oy) for each offset (lens distortion k1).

    Returns origins [S,H*W,3], unit dirs [S,H*W,3] (world) and the z component of the unit
    camera-frame direction [S,H*W] (z-depth = t * dz)."""
    R, tvec = w2c[:3, :3], w2c[:3, 3]
    C = -R.T @ tvec
    rows, cols = np.mgrid[0:height, 0:width]
    dirs, dzs = [], []
    for ox, oy in offsets:
        dc = camera_dirs(K, np.stack([cols.ravel() + ox, rows.ravel() + oy], 1), k1)
        dirs.append(dc @ R)  # R^T dc, row-wise
        dzs.append(dc[:, 2])
    dirs = np.stack(dirs)
    return np.broadcast_to(C, dirs.shape).copy(), dirs, np.stack(dzs)


def _edge_pixels(mask: np.ndarray, depth: np.ndarray, rel: float = 0.01) -> np.ndarray:
    """bool [H,W]: pixels whose 3x3 neighbourhood mixes object / background or jumps in depth."""
    H, W = mask.shape
    m = np.pad(mask, 1, mode="edge")
    d = np.pad(np.where(mask, depth, 0.0), 1, mode="edge")
    out = np.zeros_like(mask)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            mn, dn = m[dy : dy + H, dx : dx + W], d[dy : dy + H, dx : dx + W]
            out |= mn != mask
            out |= mask & mn & (np.abs(dn - depth) > rel * depth)
    return out


def render_view(K: np.ndarray, w2c: np.ndarray, height: int, width: int, seed: int = 0, supersample: int = 2,
                floor: bool = False, k1: float = 0.0):
    """Render one view. Returns (image uint8 [H,W,3], mask bool [H,W], depth float32 [H,W],
    normals float32 [H,W,3] in the camera frame, 0 on background). ``floor``: the object stands on a
    textured floor (:func:`floor_hit`), a support as in most captures; it is background (outside the
    mask, no depth or normal). ``k1``: the lens's radial distortion (OpenCV's model): each pixel
    sees along the ray a pinhole camera with K would see at its undistorted position.

    Mask / depth / normals come from the ray through the pixel centre (mask = the centre ray
    hits). Colour: the centre ray's, except on silhouettes and depth discontinuities where it
    averages ``supersample**2`` traced sub-pixel rays (the texture itself is band-limited)."""
    K = np.asarray(K, np.float64)
    w2c = np.asarray(w2c, np.float64)
    o, d, dz = pixel_rays(K, w2c, height, width, k1=k1)
    o, d, dz = o[0], d[0], dz[0]
    t = trace(o, d)
    hit = np.isfinite(t)
    pts = o[hit] + t[hit][:, None] * d[hit]
    n_world = sdf_normals(pts)
    bg = background(height, width).reshape(-1, 3)
    if floor:
        tf = floor_hit(o, d)
        on = ~hit & np.isfinite(tf)
        bg[on] = floor_colour(o[on] + tf[on, None] * d[on], seed)
    rgb = bg.copy()
    rgb[hit] = shade(pts, n_world, seed)
    depth = np.zeros(height * width)
    depth[hit] = t[hit] * dz[hit]
    mask = hit.reshape(height, width)
    ss = max(int(supersample), 1)
    if ss > 1:
        edge = np.nonzero(_edge_pixels(mask, depth.reshape(height, width)).ravel())[0]
        if len(edge):
            sub = [((i + 0.5) / ss, (j + 0.5) / ss) for j in range(ss) for i in range(ss)]
            rows, cols = np.divmod(edge, width)
            R = w2c[:3, :3]
            C = -R.T @ w2c[:3, 3]
            pix = np.concatenate([np.stack([cols + ox, rows + oy], 1) for ox, oy in sub])
            dw = camera_dirs(K, pix, k1) @ R  # world directions, R^T d row-wise
            ts = trace(np.broadcast_to(C, dw.shape), dw)
            hs = np.isfinite(ts)
            c = np.tile(bg[edge], (len(sub), 1))
            ps = C + ts[hs][:, None] * dw[hs]
            c[hs] = shade(ps, sdf_normals(ps), seed)
            acc = c.reshape(len(sub), len(edge), 3).sum(0)
            rgb[edge] = acc / len(sub)
    image = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8).reshape(height, width, 3)
    normals = np.zeros((height * width, 3), np.float32)
    normals[hit] = (n_world @ w2c[:3, :3].T).astype(np.float32)
    return image, mask, depth.astype(np.float32).reshape(height, width), normals.reshape(height, width, 3)


# --------------------------------------------------------------------------- cameras

DISTANCE = 3.0
FOCAL_FACTOR = 2.4  # fx = 2.4 W: a narrow, DTU-like field of view (23.5 deg)
ARCS = ((20.0, 70.0), (40.0, 55.0), (60.0, 45.0))  # (elevation, half azimuth span) in degrees


def _arc_counts(n_views: int) -> list[int]:
    lengths = np.array([np.cos(np.radians(e)) * 2 * s for e, s in ARCS])
    if n_views < len(ARCS):
        return [n_views] + [0] * (len(ARCS) - 1)
    raw = 1 + (n_views - len(ARCS)) * lengths / lengths.sum()
    counts = np.floor(raw).astype(int)
    for k in np.argsort(-(raw - counts))[: n_views - counts.sum()]:
        counts[k] += 1
    return counts.tolist()


def intrinsics(height: int, width: int) -> np.ndarray:
    f = FOCAL_FACTOR * width
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def camera_positions(n_views: int = 49) -> np.ndarray:
    """Camera centres [N,3] on the arcs, serpentine order."""
    out = []
    for a, (count, (elev, span)) in enumerate(zip(_arc_counts(n_views), ARCS)):
        if count == 0:
            continue
        az = np.linspace(-span, span, count) if count > 1 else np.zeros(1)
        if a % 2 == 1:
            az = az[::-1]
        e, az = np.radians(elev), np.radians(az)
        out.append(DISTANCE * np.stack([np.cos(e) * np.sin(az), -np.cos(e) * np.cos(az), np.full_like(az, np.sin(e))], 1))
    return np.concatenate(out)


UP = np.array([0.0, 0.0, 1.0])


def camera_poses(n_views: int = 49) -> np.ndarray:
    """World-to-camera poses [N,4,4] looking at the origin, world +z up in the images."""
    return np.stack([look_at_w2c(c, np.zeros(3), UP) for c in camera_positions(n_views)])


def points_visible(
    points: np.ndarray, K: np.ndarray, w2c: np.ndarray, height: int, width: int, tol: float = 1e-3
) -> np.ndarray:
    """bool [P]: surface point is inside the image, front-facing and unoccluded in at least one
    view (e.g. to keep the observed part of :func:`sample_surface` for completeness).
    K [N,3,3] or [3,3], w2c [N,4,4]."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    w2c = np.asarray(w2c, np.float64).reshape(-1, 4, 4)
    K = np.broadcast_to(np.asarray(K, np.float64), (len(w2c), 3, 3))
    normals = sdf_normals(p)
    seen = np.zeros(len(p), bool)
    cand = np.arange(len(p))  # not seen yet
    for Ki, T in zip(K, w2c):
        if len(cand) == 0:
            break
        C = -T[:3, :3].T @ T[:3, 3]
        q = p[cand]
        vec = q - C
        front = np.einsum("ij,ij->i", normals[cand], vec) < 0  # back faces are hidden (closed surface)
        uvw = q @ (Ki @ T[:3, :3]).T + Ki @ T[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
        ok = front & (uvw[:, 2] > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        idx = np.nonzero(ok)[0]
        if len(idx) == 0:
            continue
        dist = np.linalg.norm(vec[idx], axis=1)
        blocked = np.isfinite(trace(np.broadcast_to(C, (len(idx), 3)), vec[idx] / dist[:, None], t_max=dist - tol))
        vis = idx[~blocked]
        seen[cand[vis]] = True
        keep = np.ones(len(cand), bool)
        keep[vis] = False
        cand = cand[keep]
    return seen


# --------------------------------------------------------------------------- scene


@dataclass
class SyntheticScene:
    images: np.ndarray  # uint8 [N,H,W,3] RGB
    masks: np.ndarray  # bool [N,H,W] foreground = object
    K: np.ndarray  # float64 [N,3,3]
    w2c: np.ndarray  # float64 [N,4,4] world-to-camera, object inside the unit sphere
    depth: np.ndarray  # float32 [N,H,W] z-depth in camera frame (0 on background)
    normals: np.ndarray  # float32 [N,H,W,3] unit normals, OpenCV camera frame (0 on background)
    names: list[str] = field(default_factory=list)


def make_scene(seed: int = 0, n_views: int = 49, resolution: int = 192, floor: bool = False,
               k1: float = 0.0) -> SyntheticScene:
    """Render the synthetic scene: ``n_views`` views of ``resolution`` x ``resolution`` pixels, the object
    on a textured floor when ``floor``, through a lens of radial distortion ``k1`` (K stays the
    pinhole part). The seed changes the texture only (the shape and the cameras are fixed).
    The caller's own copy of a rendering kept for the process: the ingest and the ground truth of a run
    render the same views, and so do the runs of a sweep or a test suite."""
    return copy.deepcopy(_rendered(int(seed), int(n_views), int(resolution), bool(floor), float(k1)))


@functools.lru_cache(maxsize=4)
def _rendered(seed: int, n_views: int, resolution: int, floor: bool, k1: float) -> SyntheticScene:
    H = W = resolution
    w2c = camera_poses(n_views)
    K = np.broadcast_to(intrinsics(H, W), (len(w2c), 3, 3)).copy()
    out = [render_view(K[i], w2c[i], H, W, seed, floor=floor, k1=k1) for i in range(len(w2c))]
    images, masks, depth, normals = (np.stack(x) for x in zip(*out))
    return SyntheticScene(images, masks, K, w2c, depth, normals, [f"view_{i:03d}" for i in range(len(w2c))])
