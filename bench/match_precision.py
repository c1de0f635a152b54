#!/usr/bin/env python
"""How precisely do our matches locate a point? Verified SIFT matches against the exact correspondence.

    python -m bench.match_precision [--resolution 192] [--views 49] [--neighbours 3] [--out-dir DIR]

On the synthetic scene (exact cameras and rendered depth), with the features and matching stages'
defaults on each view and its nearest views: view a's keypoint of a verified match is lifted with a's
depth and projected into view b, and its distance to b's keypoint is the match's error in pixels
(keypoints whose 3x3 depth neighbourhood leaves the object or jumps are left out). The same for b's
keypoint refined against a's patch: translation-only Lucas-Kanade (OpenCV, 11 and 21 px windows) and an
affine ECC alignment of a 17x17 patch (OpenCV's findTransformECC). What a keypoint refinement would have
to beat (docs/REFINEMENT.md, "What our matches and our field can see of the poses"). Prints a table and
writes ``<out-dir>/observability/match-precision-<date>.json``.
"""
from __future__ import annotations

import argparse
import datetime as dt
from pathlib import Path

import numpy as np
from scipy.ndimage import map_coordinates

from bench import bench
from manifoldneus.data import synthetic
from manifoldneus.geometry.cameras import camera_centers, lift_points, project_points
from stages import features, matching


def exact_correspondence(scene: synthetic.SyntheticScene, a: int, b: int, ka: np.ndarray):
    """Where view a's keypoints ka [M,2] (project pixel convention) lie in view b, from a's rendered
    depth: (pb [M,2], valid [M]); invalid where a's 3x3 depth neighbourhood leaves the object or jumps."""
    depth = scene.depth[a]
    h, w = depth.shape
    ij = np.floor(ka).astype(int)  # pixel (i, j) covers [i, i+1) x [j, j+1)
    valid = (ij[:, 0] >= 1) & (ij[:, 1] >= 1) & (ij[:, 0] < w - 1) & (ij[:, 1] < h - 1)
    ij = np.where(valid[:, None], ij, 1)
    near = np.stack([depth[ij[:, 1] + dy, ij[:, 0] + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 1)
    valid &= (near > 0).all(1) & (near.max(1) - near.min(1) < 0.05 * near.mean(1))
    z = map_coordinates(depth, [ka[:, 1] - 0.5, ka[:, 0] - 0.5], order=1, mode="nearest")  # bilinear, centres at +0.5
    world = lift_points(scene.K[a], scene.w2c[a], ka, z)  # [M,3]
    wb = scene.w2c[b]
    return project_points(scene.K[b], world @ wb[:3, :3].T + wb[:3, 3]), valid


def refine_lk(gray_a, gray_b, ka, kb, window: int) -> np.ndarray:
    """b's keypoints tracked from a's by translation-only Lucas-Kanade, starting at kb; kept where it
    converged within 2 px."""
    import cv2

    p0 = np.ascontiguousarray((ka - 0.5).astype(np.float32).reshape(-1, 1, 2))
    p1 = np.ascontiguousarray((kb - 0.5).astype(np.float32).reshape(-1, 1, 2))
    moved, ok, _ = cv2.calcOpticalFlowPyrLK(gray_a, gray_b, p0, p1, winSize=(window, window), maxLevel=0,
                                           flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                           criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-3))
    out = moved.reshape(-1, 2) + 0.5
    keep = (ok.ravel() == 1) & (np.linalg.norm(out - kb, axis=1) < 2)
    return np.where(keep[:, None], out, kb)


def refine_affine(gray_a, gray_b, ka, kb, half: int = 8) -> np.ndarray:
    """b's keypoints by an affine ECC alignment of a's (2 half + 1)^2 patch around ka into b, starting at
    the translation to kb; kept where it converged within 2 px."""
    import cv2

    fa, fb = gray_a.astype(np.float32), gray_b.astype(np.float32)
    h, w = fa.shape
    gx, gy = np.meshgrid(np.arange(-half, half + 1, dtype=np.float32), np.arange(-half, half + 1, dtype=np.float32))
    out = kb.copy()
    for i, ((xa, ya), (xb, yb)) in enumerate(zip(ka - 0.5, kb - 0.5)):
        if not (half + 2 <= xa < w - half - 2 and half + 2 <= ya < h - half - 2):
            continue
        patch = cv2.remap(fa, gx + np.float32(xa), gy + np.float32(ya), cv2.INTER_LINEAR)
        warp = np.array([[1, 0, xb - half], [0, 1, yb - half]], np.float32)  # patch (u, v) -> b
        try:
            _, warp = cv2.findTransformECC(patch, fb, warp, cv2.MOTION_AFFINE,
                                           (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-4), None, 1)
        except cv2.error:  # did not converge
            continue
        centre = warp @ np.array([half, half, 1.0], np.float32)
        if np.linalg.norm(centre - (xb, yb)) < 2:
            out[i] = centre + 0.5
    return out


REFINEMENTS = {
    "SIFT (as matched)": None,
    "+ Lucas-Kanade 11 px": lambda ga, gb, ka, kb: refine_lk(ga, gb, ka, kb, 11),
    "+ Lucas-Kanade 21 px": lambda ga, gb, ka, kb: refine_lk(ga, gb, ka, kb, 21),
    "+ affine ECC 17 px": refine_affine,
}


def near_pairs(w2c: np.ndarray, neighbours: int) -> np.ndarray:
    """Each view with its `neighbours` nearest views by camera centre, as pairs i < j [P,2]."""
    centres = camera_centers(w2c)
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    pairs = {tuple(sorted((i, int(j)))) for i in range(len(w2c)) for j in np.argsort(dist[i])[:neighbours]}
    return np.array(sorted(pairs), np.int64).reshape(-1, 2)


def match_errors(scene: synthetic.SyntheticScene, neighbours: int = 3, offset=(0.0, 0.0)) -> dict:
    """Per refinement (REFINEMENTS' names): the errors [M] in pixels of every verified match with an
    exact correspondence. ``offset`` is added to b's keypoints before anything (a test's control)."""
    fp, mp = features.Params(), matching.Params()
    feats = [features.extract_sift(im, max_features=fp.max_features, root_sift=fp.root_sift,
                                   contrast_threshold=fp.contrast_threshold, edge_threshold=fp.edge_threshold,
                                   n_octave_layers=fp.n_octave_layers) for im in scene.images]
    m = matching.match_pairs(feats, near_pairs(scene.w2c, neighbours), scene.K, ratio=mp.ratio,
                             threshold_px=mp.threshold_px, workers=1)
    gray = [features.to_gray(im) for im in scene.images]
    errors = {name: [] for name in REFINEMENTS}
    for p, (a, b) in enumerate(m["pairs"]):
        pair_matches = m["inlier_matches"][m["inlier_offsets"][p]:m["inlier_offsets"][p + 1]]
        ka = feats[a]["keypoints"][pair_matches[:, 0]].astype(np.float64)
        kb = feats[b]["keypoints"][pair_matches[:, 1]].astype(np.float64) + np.asarray(offset)
        truth, valid = exact_correspondence(scene, a, b, ka)
        if not valid.any():
            continue
        ka, kb, truth = ka[valid], kb[valid], truth[valid]
        for name, refine in REFINEMENTS.items():
            refined = kb if refine is None else refine(gray[a], gray[b], ka, kb)
            errors[name].append(np.linalg.norm(refined - truth, axis=1))
    return {name: np.concatenate(e) if e else np.zeros(0) for name, e in errors.items()}


def summary(errors: np.ndarray) -> dict:
    return {"matches": int(len(errors)), "mean_px": float(errors.mean()), "median_px": float(np.median(errors)),
            "p90_px": float(np.percentile(errors, 90))}


def markdown(result: dict) -> str:
    lines = ["| keypoints in view b | matches | mean px | median px | 90th percentile px |", "|---|---:|---:|---:|---:|"]
    for name, s in result["rows"].items():
        lines.append(f"| {name} | {s['matches']} | {s['mean_px']:.3f} | {s['median_px']:.3f} | {s['p90_px']:.3f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--resolution", type=int, default=192, help="the synthetic scene's image side (ingest's default)")
    ap.add_argument("--views", type=int, default=49)
    ap.add_argument("--neighbours", type=int, default=3, help="nearest views matched with each view")
    ap.add_argument("--out-dir", type=Path, default=bench.DEFAULT_OUT_DIR)
    args = ap.parse_args(argv)
    scene = synthetic.make_scene(seed=0, n_views=args.views, resolution=args.resolution)
    rows = {name: summary(e) for name, e in match_errors(scene, args.neighbours).items()}
    result = {"date": dt.datetime.now().isoformat(timespec="seconds"), "commit": bench.git_commit(),
              "resolution": args.resolution, "views": args.views, "neighbours": args.neighbours, "rows": rows}
    bench.write_report(args.out_dir / "observability" / f"match-precision-{dt.date.today().isoformat()}.json",
                       result, markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
