"""Exports of the method's result in other tools' formats."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_colmap_text(folder: Path, names, K: np.ndarray, w2c: np.ndarray, width: int, height: int, valid=None) -> None:
    """COLMAP text model (PINHOLE camera per view, poses world-to-camera; no 3D points)."""
    from scipy.spatial.transform import Rotation

    folder.mkdir(parents=True, exist_ok=True)
    valid = np.ones(len(names), bool) if valid is None else np.asarray(valid, bool)
    cams = ["# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    imgs = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "# POINTS2D[] (empty)"]
    for i, name in enumerate(names):
        if not valid[i]:
            continue
        k = K[i]
        cams.append(f"{i + 1} PINHOLE {width} {height} {k[0, 0]:.9g} {k[1, 1]:.9g} {k[0, 2]:.9g} {k[1, 2]:.9g}")
        x, y, z, w = Rotation.from_matrix(w2c[i][:3, :3]).as_quat()
        t = w2c[i][:3, 3]
        imgs.append(f"{i + 1} {w:.12g} {x:.12g} {y:.12g} {z:.12g} {t[0]:.12g} {t[1]:.12g} {t[2]:.12g} {i + 1} {name}.png")
        imgs.append("")
    (folder / "cameras.txt").write_text("\n".join(cams) + "\n")
    (folder / "images.txt").write_text("\n".join(imgs) + "\n")
    (folder / "points3D.txt").write_text("# no points: poses only\n")
