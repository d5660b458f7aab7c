"""Transform files of the metric rescale: COLMAP Sim3d text and a 4×4 matrix for OpenMVS.

What the tools that read them actually parse (their sources, read for this):

- ``transform.sim3`` — COLMAP's ``Sim3d::FromFile`` (COLMAP >= 3.9, ``colmap/geometry/sim3.cc``)
  reads eight whitespace-separated numbers ``scale qw qx qy qz tx ty tz`` with ``operator>>``
  (``Sim3d::ToFile`` writes them on one line, 17 digits). pycolmap 4.x has no file reader:
  build ``pycolmap.Sim3d(scale, Rotation3d([qx, qy, qz, qw]), t)`` from :func:`read_sim3`.
- COLMAP **3.8** (Debian bookworm's package) is different: its ``model_transformer
  --transform_path`` calls ``SimilarityTransform3::FromFile`` (``base/similarity_transform.cc``),
  which reads a row-major **4×4 matrix**, 16 numbers with ``operator>>`` (any whitespace). Given
  the 8-number Sim3d file it would silently read a garbage matrix, so for COLMAP 3.8 use
  ``transform_4x4.txt``; COLMAP 3.9's ``Sim3d::FromFile`` read a 3×4 matrix (the first 12
  numbers of the same file).
- ``transform_4x4.txt`` — OpenMVS ``TransformScene --transform-file``
  (``apps/TransformScene/TransformScene.cpp``) needs 12 or 16 numbers, row-major (the first 12
  fill its ``Matrix3x4``; with 16 the last row must be exactly ``0 0 0 1``). OpenMVS releases
  before v2.3.0 read the file LINE BY LINE and take only the FIRST number of each line
  (``std::getline`` + ``std::strtod``; a line that does not start with a number is skipped),
  so a "4 numbers per row" file gives them 4 values and "error: invalid transform". Since
  openMVS PR #1025/#1026 (July 2023, in v2.3.0) it reads whitespace-separated tokens.
  Writing ONE NUMBER PER LINE, 16 lines, row-major, satisfies every version of OpenMVS and
  COLMAP 3.8.
"""

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
    """The 4×4 metric_from_model matrix, row-major, ONE NUMBER PER LINE (16 lines).

    One number per line is what ``TransformScene`` before OpenMVS v2.3.0 needs (it reads only
    the first number of each line); newer OpenMVS and COLMAP 3.8's ``model_transformer`` read
    whitespace-separated tokens and accept it too (see the module docstring).
    """
    values = metric_from_model_matrix(scale).ravel()  # row-major
    path.write_text("".join(f"{float(x)!r}\n" for x in values), encoding="utf-8")


def read_matrix_4x4(path: Path) -> NDArray[np.float64]:
    """Parse a 4×4 (16 numbers) or 3×4 (12 numbers) row-major matrix in any layout -> (4, 4)."""
    vals = [float(x) for x in path.read_text(encoding="utf-8").split()]
    if len(vals) not in (12, 16):
        raise ValueError(f"{path}: expected 12 or 16 numbers, got {len(vals)}")
    m = np.eye(4)
    m.ravel()[: len(vals)] = vals
    return m


def read_sim3(path: Path) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """Parse a Sim3d file -> (scale, qvec wxyz, translation)."""
    vals = [float(x) for x in path.read_text(encoding="utf-8").split()]
    if len(vals) != 8:
        raise ValueError(f"{path}: expected 8 numbers, got {len(vals)}")
    return vals[0], np.array(vals[1:5]), np.array(vals[5:8])
