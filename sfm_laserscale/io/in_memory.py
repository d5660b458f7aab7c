"""Models and meshes already in memory (the Python API): a ``pycolmap.Reconstruction`` and an
``open3d.geometry.TriangleMesh`` read into the package's types, and written rescaled.

The readers take what the file readers take: cameras, registered images with their poses and
2D observations, 3D points (a ``SparseModel``); vertices and triangles (a ``TriangleMesh``).
The writers are used only when an output folder is given: the model rescaled as a COLMAP
binary folder (pycolmap's own writer: translations and points times the scale), the mesh as
``mesh.ply`` (Open3D's writer: vertices times the scale, every other attribute kept).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.meshes.mesh import TriangleMesh
from sfm_laserscale.model import INVALID_POINT3D_ID, Camera, Image, Pose, SparseModel

#: How an object given in memory is named where a path would be (report.json's ``inputs``).
RECONSTRUCTION_LABEL = "<in memory: pycolmap.Reconstruction>"
MESH_LABEL = "<in memory: open3d.geometry.TriangleMesh>"


@dataclass(frozen=True)
class InMemoryInputs:
    """A model and/or a mesh given as objects, and the objects themselves (for writing)."""

    model: SparseModel | None = None
    mesh: TriangleMesh | None = None
    reconstruction: Any = None  # the pycolmap.Reconstruction the model was read from
    open3d_mesh: Any = None  # the open3d.geometry.TriangleMesh the mesh was read from


def _pose(image: Any) -> Pose:
    rigid = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return Pose(np.asarray(rigid.rotation.matrix(), dtype=np.float64),
                np.asarray(rigid.translation, dtype=np.float64).reshape(3))


def model_from_reconstruction(rec: Any) -> SparseModel:
    """A ``SparseModel`` of a ``pycolmap.Reconstruction`` (its registered images only)."""
    if not all(hasattr(rec, a) for a in ("cameras", "images", "points3D")):
        raise InputError(f"model: expected a path or a pycolmap.Reconstruction, got "
                         f"{type(rec).__name__}")
    cameras = {int(cid): Camera(int(cid), c.model.name, int(c.width), int(c.height),
                                np.asarray(c.params, dtype=np.float64))
               for cid, c in rec.cameras.items()}
    images: dict[int, Image] = {}
    for iid, im in rec.images.items():
        if not getattr(im, "has_pose", True):
            continue
        pts = im.points2D
        xy = np.array([p.xy for p in pts], dtype=np.float64).reshape(-1, 2)
        ids = np.array([p.point3D_id for p in pts], dtype=np.uint64)
        images[int(iid)] = Image(int(iid), str(im.name), int(im.camera_id), _pose(im), xy, ids)
    point_ids = sorted(int(p) for p in rec.points3D)
    xyz = np.array([rec.points3D[p].xyz for p in point_ids], dtype=np.float64).reshape(-1, 3)
    if not images:
        raise InputError("model: the pycolmap.Reconstruction has no registered image")
    ids_arr = np.array(point_ids, dtype=np.uint64)
    if len(ids_arr) and np.any(ids_arr == INVALID_POINT3D_ID):
        raise InputError("model: a 3D point has the invalid id")
    return SparseModel(cameras, images, ids_arr, xyz, source_format="memory")


def mesh_from_open3d(mesh: Any) -> TriangleMesh:
    """A ``TriangleMesh`` of an ``open3d.geometry.TriangleMesh`` (float64 vertices, int32
    triangles); InputError when it has no triangles or vertices that are not finite."""
    if not (hasattr(mesh, "vertices") and hasattr(mesh, "triangles")):
        raise InputError(f"mesh: expected a path or an open3d.geometry.TriangleMesh, got "
                         f"{type(mesh).__name__}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    triangles = np.asarray(mesh.triangles).reshape(-1, 3)
    if len(triangles) == 0:
        raise InputError("mesh: the open3d mesh has no triangles")
    if not np.isfinite(vertices).all():
        raise InputError("mesh: the open3d mesh has vertices that are not finite")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise InputError("mesh: the open3d mesh has triangle indices out of range")
    return TriangleMesh(vertices=vertices.copy(), triangles=triangles.astype(np.int32))


def scaled_reconstruction(rec: Any, scale: float) -> Any:
    """A copy of the reconstruction with translations and points multiplied by ``scale``."""
    import pycolmap

    out = pycolmap.Reconstruction(rec)
    out.transform(pycolmap.Sim3d(float(scale), pycolmap.Rotation3d(), np.zeros(3)))
    return out


def scaled_open3d_mesh(mesh: Any, scale: float) -> Any:
    """A copy of the Open3D mesh with its vertices multiplied by ``scale`` (about the origin)."""
    import open3d as o3d

    out = o3d.geometry.TriangleMesh(mesh)
    out.scale(float(scale), center=np.zeros(3))
    return out


def write_scaled_reconstruction(rec: Any, folder: Path, scale: float) -> list[Path]:
    """The reconstruction rescaled, as a COLMAP binary model in ``folder``: its files."""
    folder.mkdir(parents=True, exist_ok=True)
    scaled_reconstruction(rec, scale).write_binary(str(folder))
    return sorted(folder.iterdir())


def write_scaled_open3d_mesh(mesh: Any, folder: Path, scale: float,
                             name: str = "mesh.ply") -> Path:
    """The Open3D mesh rescaled, written as ``folder/name`` (binary PLY)."""
    import open3d as o3d

    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    if not o3d.io.write_triangle_mesh(path, scaled_open3d_mesh(mesh, scale)):
        raise OSError(f"Open3D could not write {path}")
    return path
