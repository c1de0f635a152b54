"""Artifact I/O: zarr round trips and strict JSON."""
import json

import numpy as np

from manifoldneus.data import io


def test_zarr_roundtrip_with_scalars_and_empty_arrays(tmp_path):
    arrays = {"images": np.arange(2 * 4 * 4 * 3, dtype=np.uint8).reshape(2, 4, 4, 3), "K": np.eye(3),
              "empty": np.zeros((0, 2), np.int32), "scalar": np.float32(2.5)}
    io.save_arrays(tmp_path / "a.zarr", arrays, attrs={"n": 2})
    back = io.load_arrays(tmp_path / "a.zarr")
    for k, v in arrays.items():
        np.testing.assert_array_equal(back[k], v)
        assert back[k].dtype == np.asarray(v).dtype
    assert io.load_attrs(tmp_path / "a.zarr") == {"n": 2}


def test_json_is_strict_nan_becomes_null(tmp_path):
    io.save_json(tmp_path / "m.json", {"loss": float("nan"), "per_view": np.array([1.0, np.inf]), "n": np.int64(3)})
    text = (tmp_path / "m.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"loss": None, "per_view": [1.0, None], "n": 3}
