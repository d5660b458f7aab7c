"""A coarse surface from a sparse model's 3D points, for users without a dense (MVS) mesh
(``sfm-laserscale mesh``, the COLMAP pipeline command).

The points seen by at least ``min_track_length`` images, statistical outliers removed (Open3D),
are meshed either by a 2.5D Delaunay triangulation in their best-fitting plane seen from the
cameras' side (``delaunay25d``: exact for a height field such as a surveyed seafloor; triangles
with an edge over ``max_edge_factor`` × the median are dropped: gaps, the concave outline), or by
Open3D's screened Poisson reconstruction (``poisson``: normals turned towards the cameras, the
least supported vertices removed, cropped to the points' box). Either surface only interpolates
the sparse points: a laser hit between them is as good as the surface is smooth there, so
:class:`CoarseMesh` says how far apart they are (``median_edge``, ``max_edge``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import INVALID_POINT3D_ID, SparseModel

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
MESH_METHODS = ("delaunay25d", "poisson")


@dataclass(frozen=True)
class CoarseMeshOptions:
    """How the coarse mesh is built from the sparse points."""

    method: str = "delaunay25d"  # delaunay25d (surveys: a height field) | poisson (Open3D)
    min_track_length: int = 3  # points seen by fewer images are dropped
    outlier_neighbours: int = 16  # statistical outlier removal (Open3D)
    outlier_std_ratio: float = 2.5
    max_edge_factor: float = 4.0  # delaunay25d: drop triangles with an edge > factor x median
    poisson_depth: int = 7
    poisson_density_quantile: float = 0.05  # poisson: drop the least supported vertices


@dataclass(frozen=True)
class CoarseMesh:
    """The surface (model units) and what it interpolates."""

    vertices: F64  # (V, 3)
    triangles: I64  # (F, 3)
    method: str
    points_total: int  # 3D points of the model
    points_used: int  # the points meshed (track length, outliers)
    median_edge: float  # triangle edge lengths, model units: how far apart the interpolated
    max_edge: float  # points are


def track_lengths(model: SparseModel) -> I64:
    """(M,) number of images observing each 3D point (rows of ``model.points_xyz``)."""
    obs = np.concatenate([im.point3D_ids for im in model.images.values()]
                         or [np.zeros(0, np.uint64)])
    uniq, counts = np.unique(obs[obs != INVALID_POINT3D_ID], return_counts=True)
    pos = np.searchsorted(uniq, model.point3D_ids)
    found = pos < len(uniq)
    found[found] = uniq[pos[found]] == model.point3D_ids[found]
    out = np.zeros(len(model.point3D_ids), np.int64)
    out[found] = counts[pos[found]]
    return out


def mesh_points(model: SparseModel, options: CoarseMeshOptions) -> F64:
    """(N, 3) sparse points fit for meshing: long enough tracks, statistical outliers removed."""
    import open3d as o3d

    xyz = model.points_xyz[track_lengths(model) >= options.min_track_length]
    if len(xyz) < 4:
        raise InputError(f"only {len(xyz)} sparse points with track length >= "
                         f"{options.min_track_length}: too few for a mesh")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    _, keep = pcd.remove_statistical_outlier(options.outlier_neighbours, options.outlier_std_ratio)
    return np.asarray(xyz[np.asarray(keep, dtype=np.int64)], dtype=np.float64)


def view_axis(model: SparseModel, xyz: F64) -> F64:
    """(3,) unit normal of the points' best plane, pointing towards the cameras."""
    centred = xyz - xyz.mean(0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    centres = np.array([im.cam_from_world.center for im in model.images.values()])
    return normal if float((centres.mean(0) - xyz.mean(0)) @ normal) >= 0 else -normal


def delaunay_25d(xyz: F64, axis: F64, max_edge_factor: float) -> I64:
    """(F, 3) triangles of a 2.5D Delaunay triangulation of the points seen along ``axis``
    (scipy's Qhull in the plane normal to it); triangles with an edge longer than
    ``max_edge_factor`` × the median edge are dropped. Exact for a height field."""
    from scipy.spatial import Delaunay

    u = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    tri = Delaunay(np.column_stack([xyz @ u, xyz @ v])).simplices.astype(np.int64)
    edges = _edge_lengths(xyz, tri)
    keep = edges.max(1) <= max_edge_factor * float(np.median(edges))
    return tri[keep]


def _edge_lengths(xyz: F64, tri: I64) -> F64:
    """(F, 3) the three edge lengths of each triangle."""
    return np.stack([np.linalg.norm(xyz[tri[:, a]] - xyz[tri[:, b]], axis=1)
                     for a, b in ((0, 1), (1, 2), (2, 0))], axis=1)


def poisson_mesh(xyz: F64, axis: F64, options: CoarseMeshOptions) -> tuple[F64, I64]:
    """Open3D screened Poisson surface of the points, normals turned towards the cameras."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=20))
    normals = np.asarray(pcd.normals)
    normals[normals @ axis < 0] *= -1
    pcd.normals = o3d.utility.Vector3dVector(normals)
    mesh, o3d_density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        pcd, depth=options.poisson_depth)
    density = np.asarray(o3d_density, dtype=np.float64)
    low = density < float(np.quantile(density, options.poisson_density_quantile))
    mesh.remove_vertices_by_mask(low.tolist())
    box = o3d.geometry.AxisAlignedBoundingBox(xyz.min(0), xyz.max(0))
    mesh = mesh.crop(box)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int64)


def coarse_mesh(model: SparseModel, options: CoarseMeshOptions = CoarseMeshOptions()  # noqa: B008
                ) -> CoarseMesh:
    """A coarse mesh from the sparse points (InputError when the model cannot give one)."""
    if options.method not in MESH_METHODS:
        raise InputError(f"unknown mesh method {options.method!r} "
                         f"(known: {', '.join(MESH_METHODS)})")
    if not model.images:
        raise InputError("the model has no registered image: no side to see the points from")
    xyz = mesh_points(model, options)
    axis = view_axis(model, xyz)
    if options.method == "poisson":
        vertices, triangles = poisson_mesh(xyz, axis, options)
    else:
        vertices, triangles = xyz, delaunay_25d(xyz, axis, options.max_edge_factor)
    if len(triangles) == 0:
        raise InputError("the coarse mesh has no triangles (points too few or degenerate)")
    edges = _edge_lengths(vertices, triangles)
    logger.info("coarse mesh (%s): %d triangles over %d of %d sparse points, median edge %.4g",
                options.method, len(triangles), len(xyz), len(model.points_xyz),
                float(np.median(edges)))
    return CoarseMesh(vertices, triangles, options.method, len(model.points_xyz), len(xyz),
                      float(np.median(edges)), float(edges.max()))
