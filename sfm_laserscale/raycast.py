"""Rays through pixels -> first hit on the mesh (Open3D RaycastingScene, refined in float64).

Open3D casts in float32. Model coordinates can sit far from the origin and a
0.1 % scale needs better than float32 there, so the scene is built around the
mesh centroid and every hit is re-intersected in float64 with the plane of the
triangle Open3D reports.

Laser spots (:func:`cast_spots`): the ray through each spot with the registered pose gives the
spot's 3D hit and the mesh normal there. The estimators propagate the spot's σ through the
tangent plane at the hit; that first-order model breaks where the surface within a few σ of the
spot is not a plane (a crest seen edge-on, a depth edge, an occlusion boundary), where a spot's
σ can be 100× too small and its scale biased by percents. :func:`on_depth_edge` casts a ring of
rays around the spot and rejects such spots with a reason, so every estimate that reaches the
fusion has a σ that holds.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, Pose, Spot

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
        # faces stay in their own integer type (a 20M-triangle mesh is 240 MB as int32, 480 MB
        # as int64); normals are computed in cast() for the triangles that are hit only
        tris = np.asarray(triangles)
        if tris.dtype.kind not in "iu":
            raise InputError("mesh triangle indices must be integers")
        if len(tris) == 0:
            raise InputError("mesh has no triangles")
        self.vertices = verts
        self.triangles = tris
        self.offset = verts.mean(axis=0)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor.from_numpy((verts - self.offset).astype(np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(tris, dtype=np.uint32)),
        )

    def _normals(self, prim: NDArray[np.int64]) -> NDArray[np.float64]:
        """(K, 3) unit normals (float64, right-hand winding) of triangles ``prim``."""
        a, b, c = (self.vertices[self.triangles[prim, k]] for k in range(3))
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)

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
            normals = self._normals(prim[hit])
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

    def median_distance(self, xyz: NDArray[np.float64], max_points: int = 20000,
                        seed: int = 0) -> float:
        """Median distance of points to the mesh (NaN for no points); above ``max_points``
        points, of a seeded random subset (the median's error is ~1/√max_points of the spread:
        a 1M-point model took 36 s in full)."""
        pts = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
        if len(xyz) == 0:
            return float("nan")
        if len(pts) > max_points:
            rng = np.random.default_rng(seed)
            pts = pts[rng.choice(len(pts), size=max_points, replace=False)]
        return float(np.median(self.distances(pts)))


def pixel_rays(
    camera: Camera, world_from_cam_pose: Pose, xy_px: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """World-frame rays (origins (N,3), unit directions (N,3)) through (N, 2) pixels."""
    d_cam = camera.unproject(xy_px)
    d_world = d_cam @ world_from_cam_pose.R.T
    d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
    origins = np.repeat(world_from_cam_pose.t[None, :], len(d_world), axis=0)
    return origins, d_world


@dataclass(frozen=True)
class SpotHit:
    """One laser spot of an image and its first mesh hit (world frame, model units)."""

    laser: str
    xy_px: NDArray[np.float64]  # (2,) COLMAP pixel convention
    sigma_px: float  # 1-σ per axis, pixels
    hit_world: NDArray[np.float64]  # (3,) model units
    normal_world: NDArray[np.float64]  # (3,) unit mesh normal at the hit


@dataclass(frozen=True)
class SpotCastOptions:
    """Options of :func:`cast_spots` and :func:`on_depth_edge`."""

    edge_check: bool = True  # reject spots where the mesh is not locally planar
    ring_sigma: float = 3.0  # ring radius around the spot, in the spot's σ
    ring_rays: int = 8
    # a ring ray may leave the hit's tangent plane by this fraction of the range change the
    # plane predicts (creases between facets stay well below; crests seen edge-on go far above)
    tolerance: float = 0.5


@dataclass(frozen=True)
class SpotCastResult:
    """Spots with a usable mesh hit, spots rejected by the edge check, and why others have none."""

    hits: tuple[SpotHit, ...]
    edge_hits: tuple[SpotHit, ...]  # hit, but on a depth edge: not used by the estimators
    reasons: dict[str, str]  # laser -> why it has no usable hit


EDGE_REASON = ("the mesh is not locally planar around the spot (a crest seen edge-on or a depth "
               "edge): its uncertainty cannot be propagated")


def cast_spots(spots: Sequence[Spot], camera: Camera, cam_from_world: Pose,
               caster: MeshRaycaster, options: SpotCastOptions) -> SpotCastResult:
    """Cast the ray through each spot into the mesh; reject misses and depth-edge spots."""
    if not spots:
        return SpotCastResult((), (), {})
    xy = np.array([[s.x, s.y] for s in spots], dtype=np.float64)
    res = caster.cast(*pixel_rays(camera, cam_from_world.inverse(), xy))
    hits: list[SpotHit] = []
    edges: list[SpotHit] = []
    reasons: dict[str, str] = {}
    for i, spot in enumerate(spots):
        if not res.hit[i]:
            reasons[spot.laser] = "ray through the spot misses the mesh"
            continue
        hit = SpotHit(laser=spot.laser, xy_px=xy[i], sigma_px=spot.sigma_px,
                      hit_world=res.xyz[i], normal_world=res.normal[i])
        if options.edge_check and on_depth_edge(caster, camera, cam_from_world, hit, options):
            edges.append(hit)
            reasons[spot.laser] = EDGE_REASON
        else:
            hits.append(hit)
    return SpotCastResult(tuple(hits), tuple(edges), reasons)


def on_depth_edge(caster: MeshRaycaster, camera: Camera, cam_from_world: Pose, hit: SpotHit,
                  options: SpotCastOptions) -> bool:
    """True when the spot's tangent-plane σ cannot hold.

    Rays on a ring of ``ring_sigma`` σ around the spot meet the mesh off the hit's tangent plane
    by more than ``tolerance`` × the range change the plane predicts and more than the ring's
    radius at the hit's range (or miss the mesh).
    """
    if not hit.sigma_px > 0 or options.ring_rays < 3:
        return False
    theta = np.linspace(0.0, 2 * np.pi, options.ring_rays, endpoint=False)
    radius_px = options.ring_sigma * hit.sigma_px
    ring = hit.xy_px[None] + radius_px * np.column_stack([np.cos(theta), np.sin(theta)])
    origins, dirs = pixel_rays(camera, cam_from_world.inverse(), ring)
    res = caster.cast(origins, dirs)
    centre = cam_from_world.center
    t0 = float(np.linalg.norm(hit.hit_world - centre))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = ((hit.hit_world - centre) @ hit.normal_world) / (dirs @ hit.normal_world)
    t_mesh = np.where(res.hit, res.distance, np.inf)
    nonlinear = float(np.max(np.abs(t_mesh - t_plane)))
    linear = float(np.max(np.abs(t_plane - t0)))
    radius = radius_px * t0 / camera.focal_px  # the ring's radius on a facing plane
    return not nonlinear <= max(options.tolerance * linear, radius)
