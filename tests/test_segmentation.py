"""Object masks from the photos and their tracks: the synthetic object on its textured floor, rendered with its
true masks, observed through tracks on its surface and on the floor around it."""
from __future__ import annotations

import numpy as np
import pytest

from manifoldneus.data import synthetic
from manifoldneus.geometry import cameras, segmentation
from manifoldneus.geometry.object_region import ObjectRegion

RES = 192
VIEWS = [0, 8, 16, 24, 32, 40, 48]
FLOOR = ObjectRegion(centre=[0.0, 0.0, 0.0], radius=0.9, plane=[0.0, 0.0, 1.0, -synthetic.FLOOR_Z])


@pytest.fixture(scope="module")
def scene():
    """Images [V,H,W,3], true masks [V,H,W], K [V,3,3], w2c [V,4,4] and the tracks: object surface points and floor
    points, each observed where a view sees it (its depth is the rendered depth)."""
    K = np.repeat(synthetic.intrinsics(RES, RES)[None], len(VIEWS), 0)
    w2c = synthetic.camera_poses(49)[VIEWS]
    renders = [synthetic.render_view(K[0], w, RES, RES, floor=True) for w in w2c]
    images, masks, depths = (np.stack([r[k] for r in renders]) for k in range(3))
    rng = np.random.default_rng(0)
    ang, rad = rng.uniform(0, 2 * np.pi, 600), rng.uniform(0.6, 1.1, 600)
    floor = np.stack([rad * np.cos(ang), rad * np.sin(ang), np.full(600, synthetic.FLOOR_Z)], 1)
    points = np.concatenate([synthetic.sample_surface(600, seed=1), floor])  # [P,3]
    obs_view, obs_point, obs_uv = [], [], []
    for i in range(len(VIEWS)):
        xc = cameras.transform_points(w2c[i], points)
        uv = cameras.project_points(K[i], xc)
        c, r = np.floor(uv).astype(int).T
        inside = (c >= 0) & (c < RES) & (r >= 0) & (r < RES)
        seen = np.zeros(len(points), bool)
        on_object = masks[i][r.clip(0, RES - 1), c.clip(0, RES - 1)]
        depth = depths[i][r.clip(0, RES - 1), c.clip(0, RES - 1)]
        seen[inside] = np.where(on_object[inside], np.abs(xc[inside, 2] - depth[inside]) < 0.03, True)
        seen[len(points) - len(floor):] &= ~on_object[len(points) - len(floor):]  # the object hides the floor
        obs_view += [np.full(seen.sum(), i)]
        obs_point += [np.flatnonzero(seen)]
        obs_uv += [uv[seen]]
    tracks = {"track_points": points, "track_obs_view": np.concatenate(obs_view),
              "track_obs_point": np.concatenate(obs_point), "track_obs_uv": np.concatenate(obs_uv)}
    return images, masks, K, w2c, tracks


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a & b).sum((1, 2)) / (a | b).sum((1, 2))


def test_points_on_the_support_and_outside_the_region_are_background():
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, synthetic.FLOOR_Z + 0.005], [0.0, 0.0, synthetic.FLOOR_Z - 0.1],
                       [2.0, 0.0, 0.0], [0.1, 0.1, 0.1]])
    seen = np.array([1.0, 1.0, 1.0, 1.0, 0.2])
    obj, background = segmentation.classify_points(points, seen, FLOOR, min_seen=0.5, support_margin=0.02)
    assert obj.tolist() == [True, False, False, False, False]  # the last one: too few views hold it
    assert background.tolist() == [False, True, True, True, False]
    obj, background = segmentation.classify_points(points, seen, None, 0.5, 0.02)
    assert obj.tolist() == [True, True, True, True, False] and not background.any()


def test_grabcut_from_the_tracks_finds_the_object_and_its_support_stays_out(scene):
    """With the floor's points as background seeds the masks are the object's; without a region every point
    the views' common frustum holds counts as the object's, and the floor between them comes in."""
    images, masks, K, w2c, tracks = scene
    ids = np.arange(len(VIEWS))
    sizes = np.tile([RES, RES], (len(VIEWS), 1))
    made = segmentation.object_masks(images, sizes, K, w2c, ids, tracks, FLOOR, min_seen=0.5, support_margin=0.02,
                                     band=6)
    assert made.shape == masks.shape and made.dtype == bool
    ours = iou(made, masks)
    assert ours.min() > 0.88, ours  # 0.91-0.96 at 192 px
    unplaced = iou(segmentation.object_masks(images, sizes, K, w2c, ids, tracks, None, 0.5, 0.02, band=6), masks)
    assert ours.mean() > unplaced.mean() + 0.2, (ours, unplaced)  # 0.93 against 0.53
    again = segmentation.object_masks(images, sizes, K, w2c, ids, tracks, FLOOR, 0.5, 0.02, band=6)
    assert np.array_equal(made, again)  # GrabCut's k-means is seeded


def test_a_view_of_a_smaller_size_is_segmented_within_its_own_pixels(scene):
    images, masks, K, w2c, tracks = scene
    sizes = np.tile([RES, RES], (len(VIEWS), 1))
    sizes[1] = [RES - 16, RES]  # its last 16 rows are the canvas's padding
    made = segmentation.object_masks(images, sizes, K, w2c, np.array([0, 1]), tracks, FLOOR, 0.5, 0.02, band=6)
    assert not made[1, RES - 16:].any()
    assert iou(made[1:, :RES - 16], masks[1:2, :RES - 16])[0] > 0.85


def test_the_vote_leaves_a_views_wrong_mask_undecided_and_decides_the_rest(scene):
    """One view's mask misses part of the object, another's takes in a patch of background: the vote across the
    views keeps the part and drops the patch, so the labels neither carve the part nor fill the patch; elsewhere
    they agree with the true masks."""
    images, masks, K, w2c, tracks = scene
    sizes = np.tile([RES, RES], (len(VIEWS), 1))
    wrong = masks.copy()
    rows, cols = np.nonzero(masks[0])
    missed = np.zeros_like(masks[0])
    missed[rows.min():rows.min() + 20] = True
    missed &= masks[0]  # the object's top 20 rows in view 0
    wrong[0] &= ~missed
    patch = np.zeros_like(masks[1])
    patch[:20, :20] = True  # a corner of view 1's background
    assert not (patch & masks[1]).any()
    wrong[1] |= patch
    points = tracks["track_points"][:600]  # the object's
    voted = segmentation.vote_masks(wrong, K, w2c, sizes, points, resolution=96, agree=0.8)  # 1 of 7 views may err
    assert voted[0][missed].mean() > 0.9 and not voted[1][patch].any()
    labels = segmentation.object_labels(wrong, voted, erode=2, fill=True)
    assert labels.dtype == np.float32 and set(np.unique(labels)) <= {0.0, 0.5, 1.0}
    carve_only = segmentation.object_labels(wrong, voted, erode=2)
    assert not (carve_only == 1).any() and np.array_equal(carve_only == 0, labels == 0)
    assert (labels[0][missed] == 0.5).mean() > 0.9 and (labels[1][patch] == 0.5).all()
    decided = labels != 0.5
    agree = (labels == 1) == masks
    assert agree[decided].mean() > 0.99 and decided.mean() > 0.8
    picture = segmentation.labels_picture(images, labels, n=3, size=64)
    assert picture.dtype == np.uint8 and picture.shape == (64, 3 * 66, 3)


def test_filled_pixels_coloured_as_the_carved_background_are_left_to_the_photos():
    """A ring on a dark background, its texture sprinkled with dark dots, and the hole in its middle kept inside
    the mask (as GrabCut keeps it): filling would grow surface across the hole. The filled pixels of the
    background's colour go back to undecided; the ring stays filled but for its dark dots, the carving stays."""
    rng = np.random.default_rng(0)
    H = W = 96
    yy, xx = np.mgrid[:H, :W]
    r = np.hypot(yy - 48, xx - 48)
    ring, hole = (r >= 14) & (r < 36), r < 14
    background = np.clip(rng.normal(40, 2, (2, H, W, 3)), 0, 255)  # dark grey with sensor noise
    dots = ring & (rng.random((2, H, W)) < 0.1)  # [2,H,W] 10 % of the ring as dark as the background
    images = np.where((ring & ~dots)[..., None], rng.integers(90, 255, (2, H, W, 3)), background).astype(np.uint8)
    masks = np.broadcast_to(r < 36, (2, H, W))  # the hole inside
    labels = segmentation.object_labels(masks, masks, erode=1, fill=True)
    sizes = np.array([[H, W], [H, W - 16]])  # the second view's own part is narrower
    out = segmentation.unfill_background_colours(labels, images, sizes, margin=8.0)
    own = np.zeros_like(masks)
    own[0], own[1, :, : W - 16] = True, True
    assert (labels[:, hole] == 1).all() and (out[own & hole[None]] == 0.5).mean() > 0.98
    bright = (labels == 1) & ring & ~dots
    assert (out[bright] == 1).all()  # the ring's own colours stay filled
    assert (out[own & dots & (labels == 1)] == 0.5).mean() > 0.98  # its dark dots are left to the photos too
    assert np.array_equal(out == 0, labels == 0) and (out[labels == 0.5] == 0.5).all()
    assert np.array_equal(out[1, :, W - 16:], labels[1, :, W - 16:])  # beyond a view's own part: as it was
    assert np.array_equal(segmentation.unfill_background_colours(labels, images, sizes, margin=8.0), out)
