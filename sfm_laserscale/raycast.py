"""Rays through pixels -> first hit on the mesh (Open3D RaycastingScene, refined in float64).

Open3D casts in float32. Model coordinates can sit far from the origin and a
0.1 % scale needs better than float32 there, so the scene is built around the
mesh centroid and every hit is re-intersected in float64 with the plane of the
triangle Open3D reports.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, Pose

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RaycastResult:
    """Per ray: hit flag, first hit (world, model units), unit normal facing the ray, distance."""

    hit: NDArray[np.bool_]  # (N,)
    xyz: NDArray[np.float64]  # (N, 3), NaN where no hit
    normal: NDArray[np.float64]  # (N, 3), NaN where no hit; n·d < 0
    distance: NDArray[np.float64]  # (N,) along the unit ray, NaN where no hit
    primitive_id: NDArray[np.int64]  # (N,), -1 where no hit


class MeshRaycaster:
    """A mesh prepared once for many ray casts."""

    def __init__(self, vertices: NDArray[np.float64], triangles: NDArray[np.integer]) -> None:
        verts = np.asarray(vertices, dtype=np.float64)
        tris = np.asarray(triangles, dtype=np.int64)
        if len(tris) == 0:
            raise InputError("mesh has no triangles")
        self.vertices = verts
        self.triangles = tris
        self.offset = verts.mean(axis=0)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor.from_numpy((verts - self.offset).astype(np.float32)),
            o3d.core.Tensor.from_numpy(tris.astype(np.uint32)),
        )
        a, b, c = (verts[tris[:, k]] for k in range(3))
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        self._normals = np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)

    def cast(self, origins: NDArray[np.float64], directions: NDArray[np.float64]) -> RaycastResult:
        """First hits of (N, 3) rays (world, model units); directions need not be unit."""
        o = np.atleast_2d(np.asarray(origins, dtype=np.float64))
        d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        rays = np.hstack([o - self.offset, d]).astype(np.float32)
        ans = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        t32 = ans["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t32) & (prim != int(self._scene.INVALID_ID))
        prim = np.where(hit, prim, -1)
        n = np.full_like(o, np.nan)
        t = np.full(len(o), np.nan)
        if hit.any():
            normals = self._normals[prim[hit]]
            p0 = self.vertices[self.triangles[prim[hit], 0]]
            denom = np.einsum("ij,ij->i", normals, d[hit])
            t_ref = np.einsum("ij,ij->i", normals, p0 - o[hit]) / np.where(denom == 0, 1, denom)
            ok = np.abs(denom) > 1e-12
            t[hit] = np.where(
                ok, t_ref, t32[hit]
            )  # float64 re-intersection with the triangle plane
            n[hit] = np.where((denom > 0)[:, None], -normals, normals)
        xyz = o + t[:, None] * d
        return RaycastResult(hit=hit, xyz=xyz, normal=n, distance=t, primitive_id=prim)

    def distances(self, xyz: NDArray[np.float64]) -> NDArray[np.float64]:
        """Unsigned distance of (N, 3) points to the mesh surface (model units)."""
        pts = np.atleast_2d(np.asarray(xyz, dtype=np.float64)) - self.offset
        out = self._scene.compute_distance(o3d.core.Tensor.from_numpy(pts.astype(np.float32)))
        return np.asarray(out.numpy(), dtype=np.float64)

    def median_distance(self, xyz: NDArray[np.float64]) -> float:
        """Median distance of points to the mesh (NaN for no points)."""
        return float(np.median(self.distances(xyz))) if len(xyz) else float("nan")


def pixel_rays(
    camera: Camera, world_from_cam_pose: Pose, xy_px: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """World-frame rays (origins (N,3), unit directions (N,3)) through (N, 2) pixels."""
    d_cam = camera.unproject(xy_px)
    d_world = d_cam @ world_from_cam_pose.R.T
    d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
    origins = np.repeat(world_from_cam_pose.t[None, :], len(d_world), axis=0)
    return origins, d_world
