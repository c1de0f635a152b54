"""COLMAP text export (manifoldneus/export.py) read back by pycolmap."""
import numpy as np
import pytest

from manifoldneus import cameras, export


def test_colmap_text_model_reads_back_with_the_same_cameras(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    rng = np.random.default_rng(0)
    eyes = rng.normal(size=(3, 3)) * 3
    w2c = np.stack([cameras.look_at_w2c(e, np.zeros(3), np.array([0.0, 0.0, 1.0])) for e in eyes])
    K = np.stack([np.array([[300.0 + i, 0, 96.5], [0, 310.0, 64.25], [0, 0, 1]]) for i in range(3)])
    export.write_colmap_text(tmp_path, ["a", "b", "c"], K, w2c, 192, 128, valid=[True, False, True])
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert sorted(im.name for im in rec.images.values()) == ["a.png", "c.png"]
    for im in rec.images.values():
        i = im.image_id - 1
        np.testing.assert_allclose(cameras.to_4x4(np.asarray(im.cam_from_world().matrix())), w2c[i], atol=1e-9)
        cam = rec.cameras[im.camera_id]
        assert (cam.width, cam.height) == (192, 128)
        np.testing.assert_allclose(cam.calibration_matrix(), K[i], atol=1e-9)
