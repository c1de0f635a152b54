"""Cameras and poses: the one module that owns the project's conventions.

Conventions (used everywhere else, restated nowhere else):

* Camera frame: OpenCV. x right, y down, z forward (the camera looks along +z).
* Pixel coordinates: (u, v) with the centre of the top-left pixel at (0.5, 0.5);
  a ray through pixel (col, row) passes through (col + 0.5, row + 0.5).
* Intrinsics ``K``: 3x3, ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
* A pose is stored **world-to-camera** unless its name says otherwise:
  ``w2c`` is ``[R | t]`` (3x4, or 4x4 with last row 0 0 0 1) and maps
  ``x_cam = R @ x_world + t``. ``c2w`` is its inverse; the camera centre is
  ``C = -R.T @ t`` (= ``c2w[:3, 3]``). Arrays of poses are ``[N,3,4]`` or ``[N,4,4]``.
* A similarity ``(s, R, t)`` maps points ``y = s * R @ x + t``; as a 4x4 matrix
  ``[[s R, t], [0, 1]]``.
* Exports for other tools (nerfstudio's ``transforms.json``, three.js, Blender) use camera-to-world
  poses with **OpenGL camera axes** (x right, y up, the camera looks along -z):
  :func:`opengl_c2w` and :func:`w2c_from_opengl_c2w` convert; COLMAP's ``cam_from_world`` is ours.
* glTF files are **+Y up** (its specification; Blender's importer turns that into its +Z up): a
  mesh written as glTF is first turned by :func:`gltf_from_world`, which takes the scene's
  vertical (:func:`vertical_from_cameras`) to +Y.
* Lens distortion is OpenCV's model, ``[k1, k2, p1, p2]`` (radial and tangential terms on normalised
  camera coordinates; COLMAP's SIMPLE_RADIAL is ``[k1, 0, 0, 0]``). Everything after the front-end
  works with pinhole cameras: a lens's distortion is removed from keypoints
  (:func:`undistort_points`) and images (:func:`undistort_image`), keeping K.
* Learnable pose corrections are se(3) vectors ``xi = (rho, omega)`` (translation part
  first, then the rotation vector), applied on the left of the world-to-camera pose:
  ``w2c' = exp(xi) @ w2c`` (a perturbation in the camera frame, as in BARF).

Numpy functions are used by the geometric front-end and evaluation; torch functions
(suffix-free, in the second half of the file) by the neural stages, differentiably.
"""
from __future__ import annotations

import numpy as np
import torch

# --------------------------------------------------------------------------- numpy


def to_4x4(pose: np.ndarray) -> np.ndarray:
    """[...,3,4] or [...,4,4] -> [...,4,4]."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape[-2:] == (4, 4):
        return pose.copy()
    out = np.zeros(pose.shape[:-2] + (4, 4))
    out[..., :3, :] = pose
    out[..., 3, 3] = 1.0
    return out


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid pose ([...,3,4] or [...,4,4]); returns [...,4,4]. w2c <-> c2w."""
    pose = to_4x4(pose)
    R, t = pose[..., :3, :3], pose[..., :3, 3:]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(pose)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def camera_centers(w2c: np.ndarray) -> np.ndarray:
    """Camera centres C = -R^T t; [N,3]."""
    w2c = np.asarray(w2c, dtype=np.float64)
    R, t = w2c[..., :3, :3], w2c[..., :3, 3]
    return -np.einsum("...ji,...j->...i", R, t)


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 projection ``K [R|t]`` into K (K[2,2] = 1) and w2c [4,4]."""
    import cv2

    K, R, C_h = cv2.decomposeProjectionMatrix(np.asarray(P[:3, :4], dtype=np.float64))[:3]
    K = K / K[2, 2]
    C = (C_h[:3] / C_h[3]).ravel()
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ C
    return K, w2c


def look_at_w2c(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera pose [4,4] of an OpenCV camera at ``eye`` looking at ``target``.
    ``up`` is the world direction that should appear up in the image (-y of the camera)."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows are camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ np.asarray(eye, float)
    return w2c


def umeyama_sim3(src: np.ndarray, dst: np.ndarray, with_scale: bool = True):
    """Least-squares similarity with ``dst ~ s * R @ src + t`` (Umeyama 1991).

    src, dst: [N,3] corresponding points (N >= 3, not collinear). Returns (s, R [3,3], t [3]).
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def align_centres(w2c_src: np.ndarray, w2c_dst: np.ndarray, valid=None, with_scale: bool = True):
    """The similarity (s, R [3,3], t [3]) that takes the camera centres of ``w2c_src`` [N,4,4] onto
    those of ``w2c_dst`` [N,4,4] (Umeyama), over the ``valid`` views (bool [N]; default all, >= 3)."""
    valid = np.ones(len(w2c_src), bool) if valid is None else np.asarray(valid, bool)
    return umeyama_sim3(camera_centers(w2c_src[valid]), camera_centers(w2c_dst[valid]), with_scale)


def sim3_matrix(s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = s * R
    M[:3, 3] = t
    return M


def sim3_inverse(s: float, R: np.ndarray, t: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Inverse of the similarity y = s R x + t: (1/s, R^T, -R^T t / s)."""
    return 1.0 / s, R.T, -R.T @ t / s


def transform_w2c(w2c: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Express world-to-camera poses in a new world frame ``y = s R x + t``.

    The camera frame keeps its orientation and is scaled with the world, so that
    projections are unchanged: ``w2c_new = [R_c R^T | s t_c - R_c R^T t]``. Returns [N,4,4].
    """
    w2c = to_4x4(w2c)
    Rc, tc = w2c[..., :3, :3], w2c[..., :3, 3]
    out = np.zeros_like(w2c)
    out[..., :3, :3] = Rc @ R.T
    out[..., :3, 3] = s * tc - np.einsum("...ij,j->...i", Rc @ R.T, t)
    out[..., 3, 3] = 1.0
    return out


def sim3_from_matrix(M: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) of a 4x4 similarity ``[[s R, t], [0, 1]]`` (s > 0, R a rotation)."""
    M = np.asarray(M, np.float64)
    s = float(abs(np.linalg.det(M[:3, :3])) ** (1 / 3))
    return s, M[:3, :3] / s, M[:3, 3].copy()


def transform_points(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Points [P,3] mapped by a 4x4 affine matrix (a similarity ``y = s R x + t``); [P,3]."""
    M = np.asarray(M, np.float64)
    return np.asarray(x, np.float64) @ M[:3, :3].T + M[:3, 3]


# Flips a camera's y and z axes: OpenCV camera axes <-> OpenGL camera axes (it is its own inverse).
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_c2w(w2c: np.ndarray) -> np.ndarray:
    """World-to-camera poses (OpenCV axes) [...,3|4,4] -> camera-to-world with OpenGL camera axes
    [...,4,4]: nerfstudio's ``transform_matrix``, a three.js camera's ``matrixWorld``."""
    return invert_pose(w2c) @ OPENGL_FROM_OPENCV


def w2c_from_opengl_c2w(c2w: np.ndarray) -> np.ndarray:
    """Inverse of :func:`opengl_c2w`: OpenGL camera-to-world [...,3|4,4] -> our w2c [...,4,4]."""
    return invert_pose(to_4x4(c2w) @ OPENGL_FROM_OPENCV)


def vertical_from_cameras(w2c: np.ndarray) -> np.ndarray:
    """The scene's up direction [3] (unit, world frame) from the cameras [N,3|4,4]: the direction
    most nearly perpendicular to every camera's x axis (photos are taken with the camera level, not
    rolled: nerfstudio's 'vertical' orientation), signed to agree with the cameras' mean up (-y).
    Where the x axes barely vary (one camera, or cameras all facing one way) the mean up itself."""
    R = to_4x4(w2c)[:, :3, :3]
    x_axes, up_mean = R[:, 0, :], -R[:, 1, :].mean(0)  # camera axes in the world: the rows of R
    evals, evecs = np.linalg.eigh(x_axes.T @ x_axes / len(R))  # ascending
    up = evecs[:, 0] if evals[1] > 0.05 else up_mean
    up = up / max(np.linalg.norm(up), 1e-12)
    return up if up @ up_mean >= 0 else -up


def gltf_from_world(w2c: np.ndarray) -> np.ndarray:
    """4x4 rotation taking the world to a glTF file's frame: the smallest turn that takes the
    cameras' vertical (:func:`vertical_from_cameras`) to +Y."""
    from scipy.spatial.transform import Rotation

    up, y = vertical_from_cameras(w2c), np.array([0.0, 1.0, 0.0])
    axis, cos = np.cross(up, y), float(np.clip(up @ y, -1.0, 1.0))
    if np.linalg.norm(axis) < 1e-9:  # already +Y, or exactly -Y: half a turn about x
        R = np.eye(3) if cos > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.arccos(cos)).as_matrix()
    M = np.eye(4)
    M[:3, :3] = R
    return M


def perturb_w2c(w2c: np.ndarray, rot_deg: tuple[float, float], centre_offset: float,
                rng: np.random.Generator) -> np.ndarray:
    """Poses with each camera turned by an angle drawn uniformly from ``rot_deg`` (lo, hi) about a
    random axis (in its own frame) and its centre moved by ``centre_offset`` in a random direction:
    BARF's synthetic pose noise, for experiments from a perturbed start. Returns [N,4,4]."""
    w2c = to_4x4(w2c)
    n = len(w2c)
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.radians(rng.uniform(rot_deg[0], rot_deg[1], size=n))
    shifts = rng.normal(size=(n, 3))
    shifts *= centre_offset / np.linalg.norm(shifts, axis=1, keepdims=True)
    R = rotvec_to_matrix(axes * angles[:, None]) @ w2c[:, :3, :3]  # [N,3,3]
    C = camera_centers(w2c) + shifts  # [N,3]
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = R
    out[:, :3, 3] = -np.einsum("nij,nj->ni", R, C)
    return out


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Geodesic angle of rotation matrices [...,3,3] in degrees: atan2 of its sine (the skew part) and its
    cosine (the trace); the arccos of the trace alone is off by ~1e-6 deg near 0 (float64 rounding)."""
    R = np.asarray(R, dtype=np.float64)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.degrees(np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), cos))


def intrinsics_scaled(K: np.ndarray, sx: float, sy: float | None = None) -> np.ndarray:
    """K of an image resized by (sx, sy) (pixel-centre convention above: no half-pixel shift)."""
    sy = sx if sy is None else sy
    K = np.array(K, dtype=np.float64)
    K[..., 0, :] *= sx
    K[..., 1, :] *= sy
    return K


def pixels_to_normalised(K: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixels [M,2] -> normalised camera coordinates [M,2] (``K^-1 [u, v, 1]``, dehomogenised), with
    one K [3,3] or one per point [M,3,3]."""
    K = np.asarray(K, np.float64)
    h = np.c_[np.asarray(uv, np.float64).reshape(-1, 2), np.ones(len(uv))]
    h = np.linalg.solve(K, h.T).T if K.ndim == 2 else np.linalg.solve(K, h[..., None])[..., 0]
    return h[:, :2] / h[:, 2:]


def has_distortion(distortion) -> bool:
    """Whether a distortion vector (or any of an array of them) is non-zero."""
    return distortion is not None and bool(np.any(np.asarray(distortion) != 0))


def undistort_points(uv: np.ndarray, K: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    """Pixels [M,2] of a camera with K [3,3] and lens ``distortion`` -> where a pinhole camera with the
    same K sees them (OpenCV's iterative inversion, run to 1e-10 in normalised coordinates)."""
    import cv2

    uv = np.asarray(uv, np.float64).reshape(-1, 1, 2)
    if len(uv) == 0:
        return uv.reshape(0, 2)
    K = np.asarray(K, np.float64)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    return cv2.undistortPoints(uv, K, np.asarray(distortion, np.float64), R=None, P=K, criteria=criteria).reshape(-1, 2)


def undistort_image(image: np.ndarray, K: np.ndarray, distortion: np.ndarray, nearest: bool = False) -> np.ndarray:
    """An image [H,W(,C)] taken through a lens with ``distortion`` resampled as a pinhole camera with the
    same K sees it (bilinear, or ``nearest`` for masks); pixels the lens did not cover are 0."""
    import cv2

    h, w = image.shape[:2]
    K_cv = np.array(K, np.float64)
    K_cv[:2, 2] -= 0.5  # OpenCV's maps put pixel centres at integers
    maps = cv2.initUndistortRectifyMap(K_cv, np.asarray(distortion, np.float64), None, K_cv, (w, h), cv2.CV_32FC1)
    src = image.astype(np.uint8) if image.dtype == bool else image
    out = cv2.remap(src, *maps, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR)
    return out.astype(image.dtype).reshape(image.shape)


def project_points(K: np.ndarray, Xc: np.ndarray) -> np.ndarray:
    """Camera-frame points [M,3] -> pixels [M,2], with one K [3,3] or one per point [M,3,3]."""
    K = np.asarray(K, np.float64)
    z = Xc[:, 2]
    x, y = Xc[:, 0] / z, Xc[:, 1] / z
    return np.stack([K[..., 0, 0] * x + K[..., 0, 1] * y + K[..., 0, 2], K[..., 1, 1] * y + K[..., 1, 2]], 1)


def lift_points(
    K: np.ndarray, w2c: np.ndarray, uv: np.ndarray, depth: np.ndarray, ray_distance: bool = False
) -> np.ndarray:
    """Back-project pixels uv [M,2] of a view with depth [M] to world points [M,3].
    depth is the z-depth (along the optical axis) unless ``ray_distance`` (distance along the
    unit ray from the camera centre). Non-positive / non-finite depths give NaN points."""
    xn = pixels_to_normalised(K, uv)
    d = np.concatenate([xn, np.ones((len(xn), 1))], 1)
    depth = np.asarray(depth, np.float64).reshape(-1)
    if ray_distance:
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
    Xc = d * depth[:, None]
    w2c = to_4x4(w2c)
    R, t = w2c[:3, :3], w2c[:3, 3]
    X = (Xc - t) @ R
    X[~(np.isfinite(depth) & (depth > 0))] = np.nan
    return X


def gauge_from_points(points: np.ndarray, radius: float = 0.8, percentile: float = 99.0,
                      centre: str = "box") -> tuple[float, np.ndarray]:
    """Scale s and centre c of the gauge y = s (x - c): s maps the half diagonal of the points' robust box (per
    axis, the ``100 - percentile``-th to ``percentile``-th percentiles) to ``radius``. A box, not a percentile
    distance, for the scale: the views that triangulate the points see some parts of an object more than
    others, and a median-centred radius left the rest outside the unit sphere (the synthetic scene's anchors:
    14 % of its surface; docs/REFINEMENT.md).

    centre="box": c is the box's middle (the whole box within ``radius``). centre="median": c is the points'
    median, where the views see most, moved towards the box's middle only as far as it takes to keep the whole
    box inside the unit sphere: held-out PSNR 0.3-0.8 dB higher on DTU, Chamfer worse on scan24 and the
    photos-alone surfaces worse (three seeds, docs/REFINEMENT.md, "The gauge's centre")."""
    pts = np.asarray(points, np.float64)
    lo, hi = np.percentile(pts, [100.0 - percentile, percentile], axis=0)  # [3], [3]
    s = radius / max(0.5 * float(np.linalg.norm(hi - lo)), 1e-12)
    middle = 0.5 * (lo + hi)
    if centre == "box":
        return s, middle
    if centre != "median":
        raise ValueError(f"gauge centre {centre!r}: 'median' or 'box'")
    median = np.median(pts, axis=0)
    # c(t) = median + t d keeps corner a inside the sphere of radius 1/s where |a - median - t d| <= 1/s: t at
    # least the quadratic's smaller root; t = 1 (the middle) keeps every corner in, as radius <= 1.
    d = middle - median
    corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), -1).reshape(-1, 3) - median  # [8,3]
    a, b, c = d @ d, corners @ d, (corners ** 2).sum(1) - s ** -2.0
    if a < 1e-24:
        return s, median
    t = (b - np.sqrt(np.maximum(b * b - a * c, 0.0))) / a  # [8] smaller roots
    return s, median + float(np.clip(t.max(), 0.0, 1.0)) * d


def rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation vectors [M,3] (or one [3]) -> rotation matrices [M,3,3]."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(w, np.float64).reshape(-1, 3)).as_matrix()


def skew(v):
    """[...,3] -> [...,3,3] cross-product matrices (``skew(a) @ b = a x b``); numpy or torch."""
    xp = torch if isinstance(v, torch.Tensor) else np
    v = v if xp is torch else np.asarray(v, np.float64)
    zero = xp.zeros_like(v[..., 0])
    return xp.stack(
        [zero, -v[..., 2], v[..., 1], v[..., 2], zero, -v[..., 0], -v[..., 1], v[..., 0], zero], -1
    ).reshape(v.shape[:-1] + (3, 3))


# --------------------------------------------------------------------------- torch


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """se(3) -> SE(3). xi: [...,6] = (rho, omega). Returns [...,3,4]. Differentiable at 0."""
    import roma  # here, not at the top: roma imports torch._dynamo, a second of every command's start-up

    rho, omega = xi[..., :3], xi[..., 3:]
    R = roma.rotvec_to_rotmat(omega)  # [...,3,3]
    theta2 = (omega**2).sum(-1, keepdim=True)[..., None]  # [...,1,1]
    theta = theta2.clamp_min(1e-12).sqrt()
    small = theta2 < 1e-8
    # V = I + B W + C W^2 with Taylor expansions near theta = 0
    B = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-12))
    C = torch.where(small, 1 / 6 - theta2 / 120, (theta - torch.sin(theta)) / (theta2 * theta).clamp_min(1e-12))
    W = skew(omega)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(W)
    V = eye + B * W + C * (W @ W)
    t = (V @ rho[..., None])[..., 0]
    return torch.cat([R, t[..., None]], -1)


def se3_log(pose: torch.Tensor) -> torch.Tensor:
    """SE(3) -> se(3). pose: [...,3,4] or [...,4,4]. Returns [...,6] = (rho, omega)."""
    import roma

    R, t = pose[..., :3, :3], pose[..., :3, 3]
    omega = roma.rotmat_to_rotvec(R)
    theta2 = (omega**2).sum(-1, keepdim=True)[..., None]
    theta = theta2.clamp_min(1e-12).sqrt()
    small = theta2 < 1e-8
    W = skew(omega)
    # V^-1 = I - W/2 + D W^2
    D = torch.where(
        small,
        1 / 12 + theta2 / 720,
        (1 - theta * torch.sin(theta) / (2 * (1 - torch.cos(theta))).clamp_min(1e-12)) / theta2.clamp_min(1e-12),
    )
    eye = torch.eye(3, dtype=pose.dtype, device=pose.device).expand_as(W)
    V_inv = eye - 0.5 * W + D * (W @ W)
    rho = (V_inv @ t[..., None])[..., 0]
    return torch.cat([rho, omega], -1)


def compose(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a @ b for rigid poses [...,3,4] -> [...,3,4]."""
    R = a[..., :3, :3] @ b[..., :3, :3]
    t = (a[..., :3, :3] @ b[..., :3, 3:])[..., 0] + a[..., :3, 3]
    return torch.cat([R, t[..., None]], -1)


def apply_correction(xi: torch.Tensor, w2c: torch.Tensor) -> torch.Tensor:
    """Corrected world-to-camera pose exp(xi) @ w2c; [...,6] x [...,3|4,4] -> [...,3,4]."""
    return compose(se3_exp(xi), w2c[..., :3, :4])


def invert(pose: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid poses [...,3,4] -> [...,3,4] (w2c <-> c2w)."""
    Rt = pose[..., :3, :3].transpose(-1, -2)
    return torch.cat([Rt, -(Rt @ pose[..., :3, 3:])], -1)
