"""matching: pairwise descriptor matching + geometric verification.

For each pair (i, j), i < j: mutual nearest neighbours of the unit descriptors (cosine
similarity, one batched torch matmul per pair) that pass Lowe's ratio test on L2 distances;
then geometric verification with ``cv2.findEssentialMat`` on K-normalised points when both
views have intrinsics (always, for the canonical ingest), ``cv2.findFundamentalMat`` otherwise;
``cv2.recoverPose`` gives the relative pose, and the stored inliers are the essential-matrix
inliers that also pass its cheirality check.

A pair only counts downstream with ``min_inliers`` verified inliers: pairs with fewer raw matches
are not verified (logged), and with ``adaptive_iters`` the robust estimator's iterations are capped
at what finds a model with ``min_inliers`` inliers with probability ``confidence``
(:func:`ransac_iterations`). Hopeless pairs (few raw matches, low inlier ratio) otherwise run
thousands of iterations each: on scan24, 4/5 of the verification time. Pairs that can pass
mostly stop earlier by USAC's own adaptive criterion (scan24: the same inlier sets for all 429 pairs
with >= 15 inliers, and one more pair reaching 15).

Relative pose convention: (R, t) of pair (i, j) maps camera-i coordinates to camera-j
coordinates, ``x_j = R @ x_i + t`` (so ``w2c_j = [R | t] @ w2c_i`` with the unknown scale of
``t``); ``|t| = 1``. Fundamental-only pairs have ``pose_valid = False`` and R = I, t = 0.

Output ``matches.zarr`` (zarr v3 group), P pairs:

- ``pairs``          int32   [P,2]   view indices (i, j), i < j
- ``n_raw``          int32   [P]     mutual-NN + ratio matches
- ``n_inliers``      int32   [P]     verified inliers (0 when verification failed or was impossible)
- ``raw_offsets``    int64   [P+1]   pair p owns ``raw_matches[raw_offsets[p]:raw_offsets[p+1]]``
- ``raw_matches``    int32   [M,2]   (keypoint index in view i, keypoint index in view j), per-view indices
- ``inlier_offsets`` int64   [P+1]
- ``inlier_matches`` int32   [Mi,2]  subset of the raw matches, same layout
- ``R``              float64 [P,3,3]
- ``t``              float64 [P,3]
- ``model``          float64 [P,3,3] essential matrix (pixel-free, K-normalised) or fundamental matrix
- ``pose_valid``     bool    [P]

Attributes: ``names``, ``n_views``, ``geometry`` ("essential" | "fundamental"),
``pose_convention``. Read back with :func:`manifoldneus.data.artifacts.load_matches`.
"""
from __future__ import annotations

import hashlib
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manifoldneus.geometry.cameras import pixels_to_normalised
from manifoldneus.config import param
from manifoldneus.data import artifacts
from manifoldneus.data.io import array_names, file_digest, load_arrays, save_arrays

METHODS = {
    "magsac": "USAC_MAGSAC",
    "usac_accurate": "USAC_ACCURATE",
    "usac_default": "USAC_DEFAULT",
    "usac_prosac": "USAC_PROSAC",
    "ransac": "RANSAC",
    "lmeds": "LMEDS",
}


@dataclass
class Params:
    """Section `matching` of params.yaml."""

    pairs: str = param("exhaustive", "Which pairs to match: all pairs, or those in pair_list", choices=["exhaustive", "list"])
    pair_list: str = param(
        "",
        "Pair-list file for pairs=list: one pair per line, 'name_i name_j' or 'index_i index_j' ('#' comments)",
    )
    ratio: float = param(0.8, "Lowe ratio test: keep a match if d1 < ratio * d2 (L2 distances)", lo=0.0, hi=1.0)
    mutual: bool = param(True, "Keep only mutual nearest neighbours (cross check)")
    method: str = param("usac_accurate", "Robust estimator for E / F (OpenCV USAC variants, RANSAC, LMedS)", choices=list(METHODS))
    threshold_px: float = param(1.0, "Inlier threshold of the robust estimator, in pixels", lo=0.0)
    confidence: float = param(0.999, "RANSAC confidence", lo=0.0, hi=1.0)
    max_iters: int = param(10000, "Maximum RANSAC iterations", lo=1)
    min_inliers: int = param(
        15,
        "Verified inliers a pair needs to count (15 = COLMAP's min_num_inliers = covisibility.min_inliers): pairs with "
        "fewer raw matches are not verified (stored with 0 inliers)",
        lo=5,
    )
    adaptive_iters: bool = param(
        True,
        "Cap RANSAC iterations per pair at those that find a model with min_inliers inliers with probability "
        "`confidence` (ransac_iterations); false: max_iters only",
    )
    use_intrinsics: bool = param(True, "Essential matrix with the ingest's K; false forces the fundamental matrix")
    workers: int = param(2, "Threads over pairs (OpenCV and torch release the GIL; each runs single-threaded)", lo=1)


UPSTREAM = ("ingest", "features")
SECTIONS = ("matching",)
OUTPUTS = (artifacts.MATCHES,)


def input_signature(scene, p: Params) -> str | None:
    """The pair list's content: a file named by a parameter, so an edit must reach the fingerprint."""
    if p.pairs != "list" or not p.pair_list:
        return None
    path = Path(p.pair_list)
    return file_digest(path) if path.is_file() else f"missing {path}"


# --------------------------------------------------------------------------- plain functions


def exhaustive_pairs(n: int) -> np.ndarray:
    """All (i, j), i < j, in row-major order; [n(n-1)/2, 2] int32."""
    i, j = np.triu_indices(n, k=1)
    return np.stack([i, j], 1).astype(np.int32)


def read_pair_list(path: Path, names: list[str]) -> np.ndarray:
    """Parse a pair-list file (names or indices; '#' comments). Returns unique sorted (i<j) pairs."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"matching.pair_list: file not found: {path}")
    index = {n: k for k, n in enumerate(names)}
    stems = {Path(n).stem: k for k, n in enumerate(names)}
    out = set()
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        toks = line.replace(",", " ").split()
        if len(toks) < 2:
            raise ValueError(f"{path}:{lineno}: expected two views per line, got {line!r}")
        ids = []
        for tok in toks[:2]:
            if tok in index:
                ids.append(index[tok])
            elif tok in stems:
                ids.append(stems[tok])
            elif tok.lstrip("-").isdigit() and 0 <= int(tok) < len(names):
                ids.append(int(tok))
            else:
                raise ValueError(f"{path}:{lineno}: unknown view {tok!r} (not a view name nor an index < {len(names)})")
        a, b = ids
        if a == b:
            continue
        out.add((min(a, b), max(a, b)))
    if not out:
        raise ValueError(f"{path}: no pairs found")
    return np.array(sorted(out), np.int32).reshape(-1, 2)


def match_descriptors(d1, d2, ratio: float = 0.8, mutual: bool = True) -> np.ndarray:
    """Mutual-NN + Lowe ratio matching of unit-norm descriptors. Returns [M,2] int32 (idx1, idx2).

    One matmul for the similarity matrix; no Python loop over descriptors.
    """
    import torch

    n1, n2 = len(d1), len(d2)
    if n1 == 0 or n2 == 0:
        return np.zeros((0, 2), np.int32)
    a = torch.as_tensor(np.asarray(d1, np.float32))
    b = torch.as_tensor(np.asarray(d2, np.float32))
    with torch.no_grad():
        sim = (a @ b.T).numpy()  # [n1,n2] cosine similarity; torch's GEMM is several times numpy's here
    # The reductions in numpy: torch's CPU argmax / topk along rows are ~10x slower than np.argmax
    # and cost as much as the matmul itself.
    rows = np.arange(n1)
    nn = sim.argmax(1)
    best = sim[rows, nn]
    keep = np.ones(n1, bool)
    if mutual:
        # i -> nn[i] is mutual iff sim[i, nn[i]] is also the maximum of column nn[i]
        keep &= best >= sim.max(0)[nn]
    if n2 >= 2 and ratio < 1.0:
        sim[rows, nn] = -np.inf  # the row maxima are now the second nearest neighbours
        dist1 = np.sqrt(np.maximum(2.0 - 2.0 * best, 0))
        dist2 = np.sqrt(np.maximum(2.0 - 2.0 * sim.max(1), 0))
        keep &= dist1 < ratio * dist2
    i1 = np.flatnonzero(keep)
    return np.stack([i1, nn[i1]], 1).astype(np.int32)


def ransac_iterations(n: int, min_inliers: int, confidence: float, max_iters: int, sample: int = 5) -> int:
    """RANSAC iterations after which, if a model with ``min_inliers`` inliers among ``n`` matches
    exists, one of its all-inlier minimal samples (``sample`` points, drawn without replacement) has
    been drawn with probability ``confidence``; capped at ``max_iters``.

    A pair whose best model has fewer inliers cannot count downstream, so iterating longer than
    this only costs time: 20 raw matches need 33 iterations for 15 inliers at 0.999, where USAC's
    own criterion keeps going for ~1300 when the best model it finds has 7 inliers."""
    if n < sample or min_inliers < sample or confidence >= 1.0:
        return int(max_iters)
    if min_inliers >= n:
        return 1
    q = math.comb(min_inliers, sample) / math.comb(n, sample)  # P(a random sample is all-inlier)
    k = math.ceil(math.log1p(-confidence) / math.log1p(-q))
    return int(min(max(k, 1), max_iters))


def verify_pair(
    x1: np.ndarray,
    x2: np.ndarray,
    K1: np.ndarray | None = None,
    K2: np.ndarray | None = None,
    *,
    method: str = "usac_accurate",
    threshold_px: float = 1.0,
    confidence: float = 0.999,
    max_iters: int = 10000,
) -> dict:
    """Geometric verification of putative correspondences x1 <-> x2 ([M,2] pixels, same convention as K).

    With K1, K2: essential matrix on K-normalised points (threshold scaled by the mean focal),
    then recoverPose; inliers = RANSAC inliers passing cheirality. Without: fundamental matrix.
    Returns dict(inliers bool [M], R [3,3], t [3], model [3,3], pose_valid bool).
    """
    import cv2

    m = len(x1)
    out = {"inliers": np.zeros(m, bool), "R": np.eye(3), "t": np.zeros(3), "model": np.zeros((3, 3)), "pose_valid": False}
    flag = getattr(cv2, METHODS[method])
    if K1 is not None and K2 is not None:
        if m < 5:
            return out
        n1, n2 = pixels_to_normalised(K1, x1), pixels_to_normalised(K2, x2)
        f = float(np.mean([K1[0, 0], K1[1, 1], K2[0, 0], K2[1, 1]]))
        E, mask = cv2.findEssentialMat(
            n1, n2, cameraMatrix=np.eye(3), method=flag, prob=confidence, threshold=threshold_px / f, maxIters=max_iters
        )
        if E is None or mask is None or E.shape[0] < 3:
            return out
        E = E[:3]  # the 5-point solver may return several stacked solutions
        mask = mask.ravel().astype(bool)
        if mask.sum() < 5:
            return out
        ninl, R, t, pmask = cv2.recoverPose(E, n1, n2, np.eye(3), mask=mask.astype(np.uint8).copy())
        inl = mask & (pmask.ravel() > 0)
        out.update(inliers=inl, R=R, t=t.ravel() / max(np.linalg.norm(t), 1e-12), model=E, pose_valid=bool(inl.sum() >= 5))
        return out
    if m < 8:
        return out
    F, mask = cv2.findFundamentalMat(
        np.asarray(x1, np.float64), np.asarray(x2, np.float64), method=flag, ransacReprojThreshold=threshold_px,
        confidence=confidence, maxIters=max_iters,
    )
    if F is None or mask is None or F.shape[0] < 3:
        return out
    out.update(inliers=mask.ravel().astype(bool), model=F[:3])
    return out


def match_pairs(
    feats: list[dict],
    pairs: np.ndarray,
    K: np.ndarray | None = None,
    *,
    ratio: float = 0.8,
    mutual: bool = True,
    method: str = "usac_accurate",
    threshold_px: float = 1.0,
    confidence: float = 0.999,
    max_iters: int = 10000,
    min_inliers: int = Params.min_inliers,
    adaptive_iters: bool = True,
    workers: int = 2,
    progress=None,
) -> dict:
    """Match and verify every pair. feats: per-view dicts with keypoints [K,2], descriptors [K,128]
    (unit rows); K: [N,3,3] or None. Returns the arrays of ``matches.zarr`` (see module doc)."""
    import cv2

    pairs = np.asarray(pairs, np.int32).reshape(-1, 2)

    def one(p):
        i, j = int(pairs[p, 0]), int(pairs[p, 1])
        raw = match_descriptors(feats[i]["descriptors"], feats[j]["descriptors"], ratio, mutual)
        if len(raw) < min_inliers:  # cannot reach min_inliers: not verified
            return raw, np.zeros(len(raw), bool), np.eye(3), np.zeros(3), np.zeros((3, 3)), False
        iters = max_iters
        if adaptive_iters:  # minimal samples: 5 points for E, 7 for F
            iters = ransac_iterations(len(raw), min_inliers, confidence, max_iters, 5 if K is not None else 7)
        cv2.setRNGSeed(int(i * 100003 + j))  # deterministic RANSAC per pair
        res = verify_pair(
            feats[i]["keypoints"][raw[:, 0]],
            feats[j]["keypoints"][raw[:, 1]],
            None if K is None else K[i],
            None if K is None else K[j],
            method=method,
            threshold_px=threshold_px,
            confidence=confidence,
            max_iters=iters,
        )
        return raw, res["inliers"], res["R"], res["t"], res["model"], res["pose_valid"]

    import torch

    # One level of parallelism: `workers` threads over pairs, each single-threaded inside
    # OpenCV and torch (restored afterwards). workers=1 leaves both libraries' own threading on.
    prev_cv, prev_torch = cv2.getNumThreads(), torch.get_num_threads()
    try:
        if workers > 1:
            cv2.setNumThreads(1)
            torch.set_num_threads(1)
            with ThreadPoolExecutor(max_workers=workers) as pool:
                it = pool.map(one, range(len(pairs)))
                results = list(progress(it, total=len(pairs)) if progress else it)
        else:
            it = map(one, range(len(pairs)))
            results = list(progress(it, total=len(pairs)) if progress else it)
    finally:
        cv2.setNumThreads(prev_cv)
        torch.set_num_threads(prev_torch)

    raws = [r[0] for r in results]
    inls = [r[0][r[1]] for r in results]
    n_raw = np.array([len(r) for r in raws], np.int32)
    n_inl = np.array([len(r) for r in inls], np.int32)
    return {
        "pairs": pairs,
        "n_raw": n_raw,
        "n_inliers": n_inl,
        "raw_offsets": np.concatenate([[0], np.cumsum(n_raw)]).astype(np.int64),
        "raw_matches": np.concatenate(raws, 0).astype(np.int32) if raws else np.zeros((0, 2), np.int32),
        "inlier_offsets": np.concatenate([[0], np.cumsum(n_inl)]).astype(np.int64),
        "inlier_matches": np.concatenate(inls, 0).astype(np.int32) if inls else np.zeros((0, 2), np.int32),
        "R": np.array([r[2] for r in results], np.float64).reshape(-1, 3, 3),
        "t": np.array([r[3] for r in results], np.float64).reshape(-1, 3),
        "model": np.array([r[4] for r in results], np.float64).reshape(-1, 3, 3),
        "pose_valid": np.array([r[5] for r in results], bool),
    }


# --------------------------------------------------------------------------- stage


def run(ctx) -> None:
    p: Params = ctx.params
    src = Path(ctx.input("ingest"))
    meta = artifacts.load_views_meta(src)
    names = list(meta["names"])
    fa = load_arrays(Path(ctx.input("features")) / artifacts.FEATURES, ["offsets", "keypoints", "descriptors"])
    off = fa["offsets"]
    feats = [
        {"keypoints": fa["keypoints"][off[v] : off[v + 1]], "descriptors": fa["descriptors"][off[v] : off[v + 1]]}
        for v in range(len(off) - 1)
    ]
    if len(feats) != len(names):
        raise RuntimeError(f"features has {len(feats)} views but ingest has {len(names)}: rerun features")
    K = None
    if p.use_intrinsics:
        if "K" in array_names(src / artifacts.VIEWS):
            K = artifacts.load_views_arrays(src, ["K"])["K"].astype(np.float64)
        else:
            ctx.log.warning("ingest has no intrinsics K: verifying with the fundamental matrix (no relative poses)")
    geometry = "essential" if K is not None else "fundamental"

    if p.pairs == "exhaustive":
        pairs = exhaustive_pairs(len(names))
        pair_src = "exhaustive"
    else:
        if not p.pair_list:
            raise ValueError("matching.pairs=list needs matching.pair_list (path of a pair-list file)")
        pairs = read_pair_list(Path(p.pair_list), names)
        pair_src = f"{p.pair_list} (sha256 {hashlib.sha256(Path(p.pair_list).read_bytes()).hexdigest()[:16]})"
        ctx.log.info(f"{len(pairs)} pairs from {pair_src}")

    t0 = time.perf_counter()
    res = match_pairs(
        feats,
        pairs,
        K,
        ratio=p.ratio,
        mutual=p.mutual,
        method=p.method,
        threshold_px=p.threshold_px,
        confidence=p.confidence,
        max_iters=p.max_iters,
        min_inliers=p.min_inliers,
        adaptive_iters=p.adaptive_iters,
        workers=p.workers,
        progress=lambda it, total: ctx.progress(it, total=total, desc="match pairs"),
    )
    seconds = time.perf_counter() - t0

    save_arrays(
        Path(ctx.out) / artifacts.MATCHES,
        res,
        attrs={
            "names": names,
            "n_views": len(names),
            "geometry": geometry,
            "pose_convention": "x_j = R @ x_i + t (camera i -> camera j), |t| = 1",
            "pair_source": pair_src,
        },
        chunk_first=False,
    )
    n_inl = res["n_inliers"]
    counted = n_inl >= p.min_inliers
    good = int(counted.sum())
    not_verified = int((res["n_raw"] < p.min_inliers).sum())
    if not_verified:
        ctx.log.info(
            f"{not_verified} of {len(pairs)} pairs have fewer than matching.min_inliers={p.min_inliers} raw matches: "
            "not verified (they cannot reach min_inliers), stored with 0 inliers"
        )
    ctx.log.info(
        f"{len(pairs)} pairs matched in {seconds:.2f} s ({geometry}, {p.method}): {good} with >= {p.min_inliers} inliers, "
        f"mean {n_inl.mean():.1f} inliers, mean {res['n_raw'].mean():.1f} raw matches"
    )
    ctx.metrics["n_pairs"] = int(len(pairs))
    ctx.metrics["pairs_ge_min_inliers"] = good
    ctx.metrics["pairs_not_verified"] = not_verified
    ctx.metrics["mean_inliers"] = float(n_inl.mean()) if len(n_inl) else 0.0
    ctx.metrics["mean_inliers_ge_min_inliers"] = float(n_inl[counted].mean()) if good else 0.0
    ctx.metrics["mean_raw_matches"] = float(res["n_raw"].mean()) if len(n_inl) else 0.0
    ctx.metrics["geometry"] = geometry
    ctx.metrics["seconds"] = float(seconds)
