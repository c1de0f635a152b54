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


def test_a_log_axis_labels_the_defaults_ticks_in_plain_numbers():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labelled = {}
    for plain in (False, True):  # less than a decade (minor ticks labelled) and four decades (decades only)
        fig, axes = plt.subplots(1, 2)
        for ax, y in zip(axes, ([0.17, 0.45, 1.2], [2e-4, 0.3, 5.0])):
            ax.plot(y)
            io.log_y(ax) if plain else ax.set_yscale("log")
        fig.canvas.draw()
        labelled[plain] = [[(round(t.get_position()[1], 9), t.get_text()) for t in ax.get_yticklabels(minor=minor)
                            if t.get_text() and ax.get_ylim()[0] <= t.get_position()[1] <= ax.get_ylim()[1]]
                           for ax in axes for minor in (False, True)]
        plt.close(fig)
    for default, plain in zip(labelled[False], labelled[True]):
        assert [p for p, _ in plain] == [p for p, _ in default]  # the same ticks carry a label
        assert all("$" in text for _, text in default) and all(float(text) == p for p, text in plain)
    assert [text for _, text in labelled[True][1]] == ["0.2", "0.3", "0.4", "0.6"]
    assert [text for _, text in labelled[True][2]] == ["0.001", "0.01", "0.1", "1"]
