"""Artifact I/O: arrays to zarr (v3), metadata to JSON, meshes to PLY, images to PNG."""
from __future__ import annotations

import contextlib
import json
import os
import sys
from pathlib import Path

import numpy as np


def save_arrays(path: Path, arrays: dict, attrs: dict | None = None, chunk_first: bool = True) -> None:
    """Write a zarr v3 group of numpy arrays. Arrays of per-view data are chunked one view each."""
    import zarr

    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    for name, value in arrays.items():
        value = np.asarray(value)
        chunks = (1,) + value.shape[1:] if (chunk_first and value.ndim >= 3) else value.shape
        chunks = tuple(max(c, 1) for c in chunks)
        arr = group.create_array(name, shape=value.shape, dtype=value.dtype, chunks=chunks)
        if value.size:
            arr[...] = value
    if attrs:
        group.attrs.update(attrs)


def load_arrays(path: Path, names: list[str] | None = None) -> dict:
    """Read a zarr group into a dict of numpy arrays (all arrays, or ``names``)."""
    import zarr

    group = zarr.open_group(str(path), mode="r")
    keys = names if names is not None else sorted(k for k, _ in group.arrays())
    return {k: np.asarray(group[k][...]) for k in keys}


def array_names(path: Path) -> list[str]:
    import zarr

    return sorted(k for k, _ in zarr.open_group(str(path), mode="r").arrays())


def load_attrs(path: Path) -> dict:
    import zarr

    return dict(zarr.open_group(str(path), mode="r").attrs)


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _finite(o):
    """Non-finite floats become null: strict JSON has no NaN or Infinity."""
    if isinstance(o, float):
        return o if np.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    if isinstance(o, (np.ndarray, np.floating)):
        return _finite(_jsonable(o))
    return o


def save_json(path: Path, obj) -> None:
    Path(path).write_text(json.dumps(_finite(obj), indent=2, default=_jsonable, allow_nan=False) + "\n")


def without_keys(value, keys):
    """``value`` (JSON-like: dicts, lists, scalars) without the dict keys ``keys`` at any depth."""
    if isinstance(value, dict):
        return {k: without_keys(v, keys) for k, v in value.items() if k not in keys}
    if isinstance(value, list):
        return [without_keys(v, keys) for v in value]
    return value


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``path`` whole or not at all: a full disk or a kill mid-write leaves the earlier file (if
    any) and no partial one (a temporary file beside it, renamed into place)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def load_json(path: Path):
    return json.loads(Path(path).read_text())


def save_png(path: Path, image: np.ndarray) -> None:
    """uint8 [H,W] or [H,W,3] RGB (floats in [0,1] are converted)."""
    import cv2

    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    if image.ndim == 3:
        image = image[..., ::-1]
    if not cv2.imwrite(str(path), image):
        raise OSError(f"could not write {path}")


def read_image(path: Path) -> np.ndarray:
    """RGB uint8 [H,W,3] as stored, EXIF orientation not applied (as COLMAP reads it: the pixels
    and the sensor's intrinsics, EXIF focal included, stay consistent). Raises a clear error
    naming an unreadable, corrupt or truncated file."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    corrupt = f"cannot decode image {path}: the file is unreadable, corrupt or truncated; replace or remove it"
    if path.suffix.lower() in (".jpg", ".jpeg"):
        # libjpeg decodes a truncated JPEG with a warning on stderr and grey rows; Pillow refuses it
        from PIL import Image

        try:
            with Image.open(path) as im:
                im.load()
        except OSError:
            raise ValueError(corrupt) from None
    image = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise ValueError(corrupt)
    return image[..., ::-1].copy()


def log_y(ax) -> None:
    """A matplotlib Axes' y axis on a log scale, its ticks labelled as plain numbers (0.3, 1, 20) where matplotlib's
    default writes 10^k in mathtext, whose parsing took a third of a small figure's time."""
    from matplotlib import ticker

    class PlainLogFormatter(ticker.LogFormatter):  # the default's choice of ticks to label, in plain text
        def _num_to_string(self, x, vmin, vmax):
            return f"{x:g}"

    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(PlainLogFormatter())
    ax.yaxis.set_minor_formatter(PlainLogFormatter(labelOnlyBase=False, minor_thresholds=(2, 0.5)))


def save_figure(path: Path, fig) -> None:
    import matplotlib.pyplot as plt

    fig.savefig(str(path), dpi=110, bbox_inches="tight")
    plt.close(fig)


@contextlib.contextmanager
def native_output_to(path: Path):
    """Send what native libraries write to the process's stdout and stderr (pycolmap's glog lines)
    to the end of ``path`` for the duration, then restore both. Python's own writes are flushed
    first so nothing is reordered across the switch."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with open(path, "ab") as target:
        try:
            os.dup2(target.fileno(), 1)
            os.dup2(target.fileno(), 2)
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)


# ---------------------------------------------------------------------------- content digests of inputs


def cache_root() -> Path:
    """Per-user cache of derived, re-creatable files (the compiled grid kernel, input digests)."""
    return Path(os.environ.get("MANIFOLDNEUS_CACHE", Path.home() / ".cache" / "manifoldneus"))


_DIGESTS: dict | None = None


def file_digests(paths) -> list[str]:
    """Hash of each file's bytes (blake2b, 16 hex digits). Remembered per file by size, mtime, ctime
    and inode (a file rewritten in place, even with its size and mtime restored, gets a new ctime),
    in one cache file written once per call."""
    import hashlib

    global _DIGESTS
    store = cache_root() / "file-digests.json"
    if _DIGESTS is None:
        try:
            _DIGESTS = json.loads(store.read_text())
        except (OSError, ValueError):
            _DIGESTS = {}
    out, changed = [], False
    for path in paths:
        path = Path(path).resolve()
        st = path.stat()
        key, stamp = str(path), [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]
        known = _DIGESTS.get(key)
        if known is None or known[:4] != stamp:
            h = hashlib.blake2b(digest_size=8)
            with open(path, "rb") as f:
                while chunk := f.read(1 << 22):
                    h.update(chunk)
            _DIGESTS[key] = known = [*stamp, h.hexdigest()]
            changed = True
        out.append(known[4])
    if changed:
        try:  # a cache: a read-only home or a race with another run only costs a re-hash later
            store.parent.mkdir(parents=True, exist_ok=True)
            write_text_atomic(store, json.dumps(_DIGESTS))
        except OSError:
            pass
    return out


def file_digest(path: Path) -> str:
    """:func:`file_digests` of one file."""
    return file_digests([path])[0]
