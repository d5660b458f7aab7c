"""A new triangle mesh as a binary PLY (float64 x y z, int32 faces), written atomically: a
temporary file beside the target renamed over it, so a killed run leaves no partial mesh."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import plyfile
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError


def write_new_ply(path: Path, vertices: NDArray[np.float64], triangles: NDArray[np.integer],
                  comments: Sequence[str] = ()) -> Path:
    """Write (V, 3) vertices and (F, 3) triangles to ``path`` (binary little-endian PLY); each
    comment becomes a ``comment`` line of the header."""
    vert = np.empty(len(vertices), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    for k, name in enumerate("xyz"):
        vert[name] = vertices[:, k]
    faces = np.empty(len(triangles), dtype=[("vertex_indices", "<i4", (3,))])
    faces["vertex_indices"] = triangles
    ply = plyfile.PlyData([plyfile.PlyElement.describe(vert, "vertex"),
                           plyfile.PlyElement.describe(faces, "face",
                                                       len_types={"vertex_indices": "u1"})],
                          text=False, byte_order="<",
                          comments=[c.replace("\n", " ") for c in comments])
    parent = path.resolve().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=parent)
    except OSError as exc:
        raise InputError(f"cannot write the mesh ({exc.strerror})", path) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            ply.write(fh)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
