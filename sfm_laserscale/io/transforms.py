"""Transform files of the metric rescale: COLMAP Sim3d text and a 4×4 matrix for OpenMVS."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray


def metric_from_model_matrix(scale: float) -> NDArray[np.float64]:
    """4×4 homogeneous similarity metric_from_model = diag(s, s, s, 1)."""
    m = np.eye(4)
    m[:3, :3] *= scale
    return m


def write_sim3(path: Path, scale: float) -> None:
    """COLMAP Sim3d file: one line "scale qw qx qy qz tx ty tz" (metric_from_model)."""
    path.write_text(f"{scale!r} 1 0 0 0 0 0 0\n", encoding="utf-8")


def write_matrix_4x4(path: Path, scale: float) -> None:
    """Row-major 4×4 matrix, one row per line (OpenMVS TransformScene --transform-file)."""
    rows = metric_from_model_matrix(scale)
    text = "\n".join(" ".join(repr(float(x)) for x in row) for row in rows)
    path.write_text(text + "\n", encoding="utf-8")


def read_sim3(path: Path) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """Parse a Sim3d file -> (scale, qvec wxyz, translation)."""
    vals = [float(x) for x in path.read_text(encoding="utf-8").split()]
    if len(vals) != 8:
        raise ValueError(f"{path}: expected 8 numbers, got {len(vals)}")
    return vals[0], np.array(vals[1:5]), np.array(vals[5:8])
