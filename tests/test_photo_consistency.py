"""The colour spread tells a surface in the right place from the same surface moved off it."""
import numpy as np
import pytest
import trimesh
from skimage import measure

from manifoldneus.data import synthetic
from manifoldneus.output import photo_consistency


@pytest.fixture(scope="module")
def scene():
    return synthetic.make_scene(n_views=16, resolution=128)


def level_set(level: float, n: int = 96) -> trimesh.Trimesh:
    """The synthetic shape's surface moved ``level`` along its normals (marching cubes of its exact SDF)."""
    lo, hi = synthetic.bounding_box()
    lo, hi = lo - 0.05, hi + 0.05
    grid = np.stack(np.meshgrid(*[np.linspace(a, b, n) for a, b in zip(lo, hi)], indexing="ij"), -1)  # [n,n,n,3]
    values = synthetic.sdf(grid.reshape(-1, 3)).reshape(n, n, n)
    vertices, faces, _, _ = measure.marching_cubes(values, level, spacing=tuple((hi - lo) / (n - 1)))
    return trimesh.Trimesh(vertices + lo, faces)


def spread(mesh, scene):
    return photo_consistency.colour_spread(mesh, photo_consistency.grey_levels(scene.images), scene.K, scene.w2c,
                                           depth_tolerance=0.005, n_points=20000, splat_points=500000)


def test_the_true_surface_is_the_most_consistent(scene):
    true = spread(level_set(0.0), scene)
    assert 0.3 < true["share_scored"] <= 1.0  # the views are on one side: the underside is never scored
    outward, inward, far = (spread(level_set(level), scene) for level in (0.01, -0.01, 0.03))
    # 1 % of the object's radius off the surface already reads other texels in each view
    assert true["median"] < 0.75 * min(outward["median"], inward["median"])
    assert max(outward["median"], inward["median"]) < far["median"]


def test_nothing_to_score(scene):
    assert spread(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)), scene) is None
    beyond = level_set(0.0)
    beyond.apply_translation([0.0, 0.0, 100.0])  # far outside every view
    assert spread(beyond, scene) is None


def test_splats_scaled_to_the_images_score_as_a_denser_z_buffer_does(scene):
    """16 samples per pixel of the largest image (262 k here instead of the 2 M cap) fill each view's z-buffer:
    four times as many change what is scored by less than a percent."""
    grey, mesh = photo_consistency.grey_levels(scene.images), level_set(0.0)
    default, dense = (photo_consistency.colour_spread(mesh, grey, scene.K, scene.w2c, depth_tolerance=0.005,
                                                      n_points=20000, splats_per_pixel=n) for n in (16, 64))
    assert default["median"] == pytest.approx(dense["median"], rel=0.01)
    assert default["share_scored"] == pytest.approx(dense["share_scored"], abs=0.01)
    sparse = photo_consistency.colour_spread(mesh, grey, scene.K, scene.w2c, depth_tolerance=0.005, n_points=20000,
                                             splats_per_pixel=0.25)
    # too few: holes in the z-buffers let hidden points through, each reading another surface's texture
    assert sparse["median"] > 1.05 * default["median"] and sparse["share_scored"] > default["share_scored"]
