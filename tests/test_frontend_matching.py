"""Geometric front-end: stages features, matching, covisibility and the pycolmap reference.

Synthetic views are rendered here (a textured square floating above a textured ground plane,
so the scene is not planar); the stage modules run through a minimal stand-in for the
pipeline's ctx (docs/STAGES.md), so these tests do not depend on pipeline.py."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from manifoldneus.data import artifacts, io
from manifoldneus.scheduling import mavos
from manifoldneus.geometry.cameras import decompose_projection, look_at_w2c, rotation_angle_deg
from stages import covisibility, features, matching, reference
from tests.conftest import SHARED_DATA, needs_dtu

H = W = 256
K_SYN = np.array([[300.0, 0, 128], [0, 300.0, 128], [0, 0, 1]])


# --------------------------------------------------------------------------- helpers


def _texture(seed: int, size: int = 512) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    acc = np.zeros((size, size), np.float32)
    for sigma, w in [(1, 1.0), (2.5, 1.5), (6, 2.0), (15, 2.0)]:
        n = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), sigma)
        acc += w * n / n.std()
    return ((acc - acc.min()) / (acc.max() - acc.min()) * 255).astype(np.float32)


TEXTURES = None


def render(w2c: np.ndarray, K: np.ndarray = K_SYN) -> np.ndarray:
    """RGB uint8 [H,W,3]: ground plane z = 0 and a square |x|,|y| < 0.5 floating at z = 0.4,
    each with its own random texture (ray cast per pixel centre, bilinear texture lookup)."""
    import cv2

    global TEXTURES
    if TEXTURES is None:
        TEXTURES = [_texture(0), _texture(1)]
    R, t = w2c[:3, :3], w2c[:3, 3]
    C = -R.T @ t
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ R  # world ray directions

    def hit(h):
        return C + ((h - C[2]) / d[..., 2])[..., None] * d

    P1, P0 = hit(0.4), hit(0.0)
    on = (np.abs(P1[..., 0]) < 0.5) & (np.abs(P1[..., 1]) < 0.5)
    P = np.where(on[..., None], P1, P0)
    scale = TEXTURES[0].shape[0] / 3.0
    mx = ((P[..., 0] + 1.5) * scale).astype(np.float32)
    my = ((P[..., 1] + 1.5) * scale).astype(np.float32)
    a, b = (cv2.remap(T, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT) for T in TEXTURES)
    g = np.clip(np.where(on, b, a), 0, 255).astype(np.uint8)
    return np.repeat(g[..., None], 3, -1)


def cam(azimuth_deg: float, elevation_deg: float = 50.0, dist: float = 3.0) -> np.ndarray:
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = dist * np.array([np.cos(e) * np.sin(a), -np.cos(e) * np.cos(a), np.sin(e)])
    return look_at_w2c(eye, np.zeros(3), np.array([0, 0, 1.0]))


class FakeCtx:
    """The part of runner.Context that the stages use."""

    def __init__(self, module, out: Path, inputs: dict, params=None, scene="test"):
        self.params = params if params is not None else module.Params()
        self._inputs = inputs
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.log_path = self.out / "log.txt"
        self.scene = scene
        self.log = logging.getLogger(f"manifoldneus.test.{module.__name__}")
        self.metrics: dict = {}

    def input(self, name):
        return Path(self._inputs[name])

    def progress(self, iterable=None, **kw):
        return iterable

    def section(self, name):
        raise KeyError(name)


def make_ingest(root: Path, images: np.ndarray, K: np.ndarray, names: list[str], intrinsics_source="calibrated") -> Path:
    root.mkdir(parents=True, exist_ok=True)
    sizes = np.tile(np.asarray(images.shape[1:3], np.int64), (len(images), 1))  # one size, as ingest writes it
    io.save_arrays(root / "views.zarr", {"images": images, "sizes": sizes, "K": K})
    io.save_json(root / "views.json", {"names": names, "height": images.shape[1], "width": images.shape[2],
                                       "layout": "test", "intrinsics_source": intrinsics_source,
                                       "has_masks": False, "has_mono_depth": False,
                                       "has_mono_normal": False, "source": "test"})
    return root


def rel_pose(w2c_i, w2c_j):
    """(R, t unit) with x_j = R x_i + t."""
    M = w2c_j @ np.linalg.inv(w2c_i)
    return M[:3, :3], M[:3, 3] / np.linalg.norm(M[:3, 3])


def scan24_K(i: int) -> tuple[np.ndarray, np.ndarray]:
    cams = np.load(SHARED_DATA / "dtu" / "scan24" / "cameras.npz")
    K, w2c = decompose_projection(cams[f"world_mat_{i}"])
    K[0, 2] -= 200
    K[:2] *= 384 / 1200
    return K, w2c


# --------------------------------------------------------------------------- features


def test_sift_counts_and_rootsift_unit_norm():
    img = render(cam(0))
    f = features.extract_sift(img, root_sift=True)
    n = len(f["keypoints"])
    assert n > 200
    assert f["descriptors"].shape == (n, 128) and f["descriptors"].dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f["descriptors"], axis=1), 1.0, atol=1e-5)
    assert (f["descriptors"] >= 0).all()
    # keypoints in the project's pixel convention: inside [0, W] x [0, H]
    assert (f["keypoints"] >= 0).all() and (f["keypoints"][:, 0] <= W).all() and (f["keypoints"][:, 1] <= H).all()
    assert f["scales"].shape == f["orientations"].shape == (n,)
    assert (np.abs(f["orientations"]) <= 2 * np.pi + 1e-6).all()
    g = features.extract_sift(img, root_sift=False, max_features=100)
    assert len(g["keypoints"]) == 100
    np.testing.assert_allclose(np.linalg.norm(g["descriptors"], axis=1), 1.0, atol=1e-5)
    # the strongest 100 features are a subset of all of them (same detector)
    assert g["responses"].min() >= np.sort(f["responses"])[-100] - 1e-6
    # a mask restricts detection to its support (left half here)
    mask = np.zeros((H, W), bool)
    mask[:, : W // 2] = True
    fm = features.extract_sift(img, mask)
    assert 0 < len(fm["keypoints"]) < n and (fm["keypoints"][:, 0] <= W // 2 + 1).all()


def test_a_photo_larger_than_max_image_size_is_extracted_downscaled_in_its_own_pixels():
    """An image twice max_image_size: SIFT runs on its half-size copy (what bounds its memory) and the
    keypoints come back in the image's own pixels: those of the half-size image, doubled."""
    import cv2

    img = cv2.resize(render(cam(0)), (2 * W, 2 * H), interpolation=cv2.INTER_CUBIC)
    big = features.extract_sift(img, max_image_size=max(W, H))
    small = features.extract_sift(cv2.resize(features.to_gray(img), (W, H), interpolation=cv2.INTER_AREA))
    assert len(big["keypoints"]) == len(small["keypoints"]) > 100
    np.testing.assert_allclose(big["keypoints"], 2 * small["keypoints"], atol=1e-3)
    np.testing.assert_allclose(big["scales"], 2 * small["scales"], rtol=1e-5)
    assert np.array_equal(big["descriptors"], small["descriptors"])
    assert len(features.extract_sift(img, max_image_size=0)["keypoints"]) != len(big["keypoints"])  # 0: full size


@needs_dtu
def test_sift_on_scan24_view():
    import cv2

    img = cv2.imread(str(SHARED_DATA / "dtu" / "scan24" / "000024_rgb.png"))[..., ::-1]
    f = features.extract_sift(img)
    assert len(f["keypoints"]) > 300
    np.testing.assert_allclose(np.linalg.norm(f["descriptors"], axis=1), 1.0, atol=1e-5)


def test_match_descriptors_mutual_and_ratio():
    rng = np.random.default_rng(0)
    a = features.normalize_descriptors(rng.random((50, 128)) ** 4)
    b = features.normalize_descriptors(a[:30] + 0.01 * rng.random((30, 128)))
    m = matching.match_descriptors(a, b, ratio=0.8)
    assert len(m) == 30 and (m[:, 0] == m[:, 1]).all()
    # two identical rows in b: ambiguous under the ratio test, kept without it
    b2 = np.concatenate([b, b[:1]])
    m2 = matching.match_descriptors(a, b2, ratio=0.8)
    assert 0 not in m2[:, 0]
    m3 = matching.match_descriptors(a, b2, ratio=1.0, mutual=True)
    assert 0 in m3[:, 0]
    # empty sides
    assert matching.match_descriptors(a, np.zeros((0, 128), np.float32)).shape == (0, 2)
    assert matching.match_descriptors(a, b[:1]).shape[1] == 2


# --------------------------------------------------------------------------- matching


def test_match_descriptors_equals_brute_force():
    """Mutual NN + Lowe ratio against a per-descriptor loop (the vectorised reductions must not change it)."""
    rng = np.random.default_rng(3)
    a = features.normalize_descriptors(rng.random((60, 128)) ** 3)
    b = features.normalize_descriptors(np.concatenate([a[:40] + 0.05 * rng.random((40, 128)), rng.random((25, 128)) ** 3]))
    for ratio, mutual in [(0.8, True), (0.95, False), (1.0, True)]:
        expected = []
        dist = np.sqrt(np.maximum(2 - 2 * a @ b.T, 0))
        for i in range(len(a)):
            order = np.argsort(dist[i])
            j = order[0]
            if ratio < 1.0 and not dist[i, j] < ratio * dist[i, order[1]]:
                continue
            if mutual and np.argmin(dist[:, j]) != i:
                continue
            expected.append((i, j))
        got = matching.match_descriptors(a, b, ratio=ratio, mutual=mutual)
        assert got.dtype == np.int32
        np.testing.assert_array_equal(got, np.array(expected, np.int32).reshape(-1, 2))


def test_ransac_iterations_budget():
    # P(5 of the 15 inliers among 20 matches) = C(15,5) / C(20,5) = 0.194: 33 draws for 0.999
    assert matching.ransac_iterations(20, 15, 0.999, 10000) == 33
    assert matching.ransac_iterations(15, 15, 0.999, 10000) == 1  # every sample is all-inlier
    assert matching.ransac_iterations(100, 15, 0.999, 10000) == 10000  # capped
    assert matching.ransac_iterations(40, 15, 1.0, 500) == 500  # certainty: no cap
    budgets = [matching.ransac_iterations(n, 15, 0.999, 10**9) for n in range(15, 80)]
    assert all(x <= y for x, y in zip(budgets, budgets[1:]))
    assert matching.ransac_iterations(30, 15, 0.99, 10**9) < matching.ransac_iterations(30, 15, 0.999, 10**9)


def test_capped_verification_finds_min_inlier_model():
    """20 matches, exactly 15 consistent with the true pose: the capped budget (33 iterations)
    still finds them, like the full 10000 iterations."""
    import cv2

    rng = np.random.default_rng(1)
    w1, w2 = cam(0), cam(15, elevation_deg=55)
    X = rng.uniform(-0.6, 0.6, (20, 3)) * [1, 1, 0.5]

    def project(w2c):
        x = (K_SYN @ (X @ w2c[:3, :3].T + w2c[:3, 3]).T).T
        return x[:, :2] / x[:, 2:]

    x1, x2 = project(w1), project(w2)
    x2[15:] = rng.uniform(20, 236, (5, 2))  # 5 outliers
    results = []
    for iters in (matching.ransac_iterations(20, 15, 0.999, 10000), 10000):
        cv2.setRNGSeed(7)
        results.append(matching.verify_pair(x1, x2, K_SYN, K_SYN, max_iters=iters))
    capped, full = results
    np.testing.assert_array_equal(capped["inliers"], np.arange(20) < 15)
    np.testing.assert_array_equal(capped["inliers"], full["inliers"])
    np.testing.assert_allclose(capped["R"], full["R"], atol=1e-9)
    R_gt, _ = rel_pose(w1, w2)
    assert rotation_angle_deg(capped["R"].T @ R_gt) < 2.0  # 15 exact points spanning a small box


def test_matching_recovers_known_relative_pose():
    w1, w2 = cam(0), cam(12, elevation_deg=55)
    f1, f2 = features.extract_sift(render(w1)), features.extract_sift(render(w2))
    res = matching.match_pairs([f1, f2], matching.exhaustive_pairs(2), np.stack([K_SYN, K_SYN]), workers=1)
    R_gt, t_gt = rel_pose(w1, w2)
    assert res["n_inliers"][0] > 200
    assert res["pose_valid"][0]
    assert rotation_angle_deg(res["R"][0].T @ R_gt) < 0.5, "convention: x_j = R x_i + t"
    assert np.degrees(np.arccos(np.clip(res["t"][0] @ t_gt, -1, 1))) < 3.0
    # inliers are a subset of the raw matches, and geometrically consistent
    raw = res["raw_matches"]
    inl = res["inlier_matches"]
    assert set(map(tuple, inl)) <= set(map(tuple, raw))
    # without intrinsics: fundamental matrix, inliers but no pose
    resF = matching.match_pairs([f1, f2], matching.exhaustive_pairs(2), None, workers=1)
    assert resF["n_inliers"][0] > 200 and not resF["pose_valid"][0]


def test_matching_deterministic_across_workers():
    feats = [features.extract_sift(render(cam(a))) for a in (0, 10, 20)]
    K = np.stack([K_SYN] * 3)
    r1 = matching.match_pairs(feats, matching.exhaustive_pairs(3), K, workers=1)
    r2 = matching.match_pairs(feats, matching.exhaustive_pairs(3), K, workers=2)
    for k in ("n_raw", "n_inliers", "inlier_matches"):
        np.testing.assert_array_equal(r1[k], r2[k])
    np.testing.assert_allclose(r1["R"], r2["R"])


def test_pair_list(tmp_path):
    names = ["a", "b", "c", "d"]
    f = tmp_path / "pairs.txt"
    f.write_text("# comment\na b\n2 3\nb a\nc c\nd a  # names or indices\n")
    np.testing.assert_array_equal(matching.read_pair_list(f, names), [[0, 1], [0, 3], [2, 3]])
    f.write_text("a zzz\n")
    with pytest.raises(ValueError, match="unknown view"):
        matching.read_pair_list(f, names)


def test_stage_chain_with_featureless_view(tmp_path, caplog):
    """features -> matching -> covisibility through the stage wrappers; view 'blank' is constant."""
    poses = [cam(0), cam(12), cam(24)]
    images = np.stack([render(w) for w in poses] + [np.full((H, W, 3), 128, np.uint8)])
    names = ["v0", "v1", "v2", "blank"]
    ingest = make_ingest(tmp_path / "ingest", images, np.stack([K_SYN] * 4), names)

    caplog.set_level(logging.INFO)
    ctx = FakeCtx(features, tmp_path / "features", {"ingest": ingest})
    features.run(ctx)
    assert any("blank" in r.message and "featureless" in r.message for r in caplog.records if r.levelno == logging.WARNING)
    feats, attrs = artifacts.load_features(ctx.out)
    assert attrs["names"] == names and list(attrs["featureless"]) == [False, False, False, True]
    assert len(feats[3]["keypoints"]) == 0 and all(len(f["keypoints"]) > 200 for f in feats[:3])
    assert ctx.metrics["n_featureless"] == 1

    mctx = FakeCtx(matching, tmp_path / "matching", {"ingest": ingest, "features": ctx.out})
    matching.run(mctx)
    arrays, mattrs = artifacts.load_matches(mctx.out)
    assert mattrs["geometry"] == "essential" and len(arrays["pairs"]) == 6
    with_blank = (arrays["pairs"] == 3).any(1)
    assert (arrays["n_inliers"][with_blank] == 0).all() and (arrays["n_raw"][with_blank] == 0).all()
    assert (arrays["n_inliers"][~with_blank] >= 15).all()
    for p in np.flatnonzero(~with_blank):
        i, j = arrays["pairs"][p]
        R_gt, _ = rel_pose(poses[i], poses[j])
        assert rotation_angle_deg(arrays["R"][p].T @ R_gt) < 1.0
        assert len(artifacts.inliers_of(arrays, p)) == arrays["n_inliers"][p]
    assert np.isfinite(arrays["R"]).all() and np.isfinite(arrays["t"]).all()
    assert mctx.metrics["pairs_ge_min_inliers"] == 3
    # pairs with the blank view have no raw matches: not verified, and logged as such
    assert mctx.metrics["pairs_not_verified"] == 3
    assert any("3 of 6 pairs" in r.message and "not verified" in r.message for r in caplog.records)

    caplog.clear()
    cctx = FakeCtx(covisibility, tmp_path / "covisibility", {"matching": mctx.out})
    covisibility.run(cctx)
    cov = io.load_arrays(cctx.out / "covisibility.zarr")
    Wm = cov["W"]
    np.testing.assert_array_equal(Wm, Wm.T)
    assert (np.diag(Wm) == 0).all() and (Wm[3] == 0).all()
    np.testing.assert_allclose(cov["c"], Wm.sum(1))
    comps = io.load_json(cctx.out / "components.json")
    assert comps["components"] == [[0, 1, 2], [3]] and comps["outside_largest"] == ["blank"]
    assert any("disconnected" in r.message and "blank" in r.message for r in caplog.records if r.levelno == logging.WARNING)
    for png in ("covisibility.png", "graph.png"):
        assert (cctx.out / png).stat().st_size > 1000


def test_all_featureless_is_an_error(tmp_path):
    images = np.full((2, 64, 64, 3), 7, np.uint8)
    ingest = make_ingest(tmp_path / "ingest", images, np.stack([K_SYN] * 2), ["a", "b"])
    with pytest.raises(RuntimeError, match="all 2 views are featureless"):
        features.run(FakeCtx(features, tmp_path / "features", {"ingest": ingest}))


# --------------------------------------------------------------------------- covisibility


def test_covisibility_handmade_disconnected():
    pairs = np.array([[0, 1], [1, 2], [3, 4], [4, 3], [2, 2], [0, 5], [5, 6]])
    counts = np.array([50, 30, 20, 25, 99, 10, 0])
    Wm = mavos.covisibility_matrix(7, pairs, counts, min_inliers=15)
    np.testing.assert_array_equal(Wm, Wm.T)
    assert (np.diag(Wm) == 0).all()
    assert Wm[0, 1] == 50 and Wm[3, 4] == 25 and Wm[0, 5] == 0
    assert list(mavos.component_labels(Wm)) == [0, 0, 0, 1, 1, 2, 3]  # largest first, ties by smallest view index
    W0 = mavos.covisibility_matrix(7, pairs, counts, min_inliers=0)
    assert list(mavos.component_labels(W0)) == [0, 0, 0, 1, 1, 0, 2]  # the zero-count pair (5, 6) is no edge
    pos = covisibility.spectral_layout(Wm)
    assert pos.shape == (7, 2) and np.isfinite(pos).all()


# --------------------------------------------------------------------------- pycolmap reference


@needs_dtu
def test_reference_pycolmap_registers_scan24_views(tmp_path, caplog):
    import cv2

    ids = [12, 13, 14, 24, 25]  # two neighbouring rows of the DTU path: a well-conditioned small set
    images = np.stack([cv2.imread(str(SHARED_DATA / "dtu" / "scan24" / f"{i:06d}_rgb.png"))[..., ::-1] for i in ids])
    Ks, gt = zip(*(scan24_K(i) for i in ids))
    names = [f"{i:06d}" for i in ids]
    ingest = make_ingest(tmp_path / "ingest", images, np.stack(Ks), names)
    caplog.set_level(logging.INFO)
    ctx = FakeCtx(reference, tmp_path / "reference", {"ingest": ingest})
    reference.run(ctx)
    poses = io.load_arrays(ctx.out / "poses.zarr")
    assert poses["registered"].all() and ctx.metrics["n_registered"] == 5
    assert np.isfinite(poses["w2c"]).all() and poses["w2c"].shape == (5, 4, 4)
    np.testing.assert_allclose(poses["K"], np.stack(Ks), atol=2e-3)  # held fixed (PINHOLE: no skew, shared K)
    assert ctx.metrics["extract_match_seconds"] > 0 and ctx.metrics["mapping_seconds"] > 0
    for f in ("cameras.txt", "images.txt", "points3D.txt"):
        assert (ctx.out / "sparse" / f).is_file()
    assert "PINHOLE" in (ctx.out / "sparse" / "cameras.txt").read_text()
    # relative rotations agree with the ground truth (gauge-free check)
    for a in range(5):
        for b in range(a + 1, 5):
            R_est = poses["w2c"][b, :3, :3] @ poses["w2c"][a, :3, :3].T
            R_gt = gt[b][:3, :3] @ gt[a][:3, :3].T
            assert rotation_angle_deg(R_est.T @ R_gt) < 1.0  # measured 0.35 deg max here; all 49 views give 0.16 deg mean


@needs_dtu
def test_reference_refines_a_guessed_focal_length(tmp_path):
    """A folder without calibration: the ingest's K is a guess (here the true focal length x 1.3);
    `intrinsics: auto` makes pycolmap refine it from there, towards the truth."""
    import cv2

    ids = list(range(0, 49, 3))
    images = np.stack([cv2.imread(str(SHARED_DATA / "dtu" / "scan24" / f"{i:06d}_rgb.png"))[..., ::-1] for i in ids])
    K_true = np.stack([scan24_K(i)[0] for i in ids])
    K_guess = K_true.copy()
    K_guess[:, :2, :2] = K_true[0, [0, 1], [0, 1]].mean() * 1.3 * np.eye(2)
    ingest = make_ingest(tmp_path / "ingest", images, K_guess, [f"{i:06d}" for i in ids], intrinsics_source="default")
    ctx = FakeCtx(reference, tmp_path / "reference", {"ingest": ingest})
    reference.run(ctx)
    assert ctx.metrics["intrinsics"] == "refine"
    f_true = K_true[:, [0, 1], [0, 1]].mean()
    assert abs(ctx.metrics["focal_px_ingest"] / f_true - 1.3) < 0.01
    assert abs(ctx.metrics["focal_px"] / f_true - 1) < 0.05, (ctx.metrics["focal_px"], f_true)
    # the principal point started right: freed or not (the likelihood-ratio test), it stays near
    assert isinstance(ctx.metrics["principal_point_freed"], bool)
    K_out = io.load_arrays(tmp_path / "reference" / "poses.zarr", ["K"])["K"]
    assert np.abs(K_out[:, :2, 2] - K_true[:, :2, 2]).max() < 0.02 * images.shape[2], K_out[0]
