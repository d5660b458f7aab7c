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

Large meshes (:func:`crop_for_rays`): the scale job casts a few dozen rays per image, so it does
not build Open3D's BVH over the whole mesh (~80 bytes per triangle, 15 s at 20M triangles).
The rays (spot rays and their edge-check rings) are known once the images are registered; the
mesh is cropped to the triangles that can lie within reach of them (exactly: every triangle
a ray can meet is kept, see :func:`crop_for_rays`), and the caster is built on that crop. A
cropped caster refuses rays it was not built for (``CropCoverage``), so a crop can never give a
wrong first hit silently.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy import ndimage

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
    """A mesh prepared once for many ray casts (optionally a crop that covers given rays)."""

    def __init__(self, vertices: NDArray[np.floating], triangles: NDArray[np.integer],
                 coverage: CropCoverage | None = None) -> None:
        verts = np.asarray(vertices, dtype=np.float64)
        # faces stay in their own integer type (a 20M-triangle mesh is 240 MB as int32, 480 MB
        # as int64); normals are computed in cast() for the triangles that are hit only
        tris = np.asarray(triangles)
        if tris.dtype.kind not in "iu":
            raise InputError("mesh triangle indices must be integers")
        if len(tris) == 0 and coverage is None:  # an empty crop is fine: its rays miss
            raise InputError("mesh has no triangles")
        self.vertices = verts
        self.triangles = tris
        self.coverage = coverage
        self.offset = verts.mean(axis=0) if len(verts) else np.zeros(3)
        self._scene = o3d.t.geometry.RaycastingScene()
        if len(tris) == 0:
            return
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
        if self.coverage is not None and not self.coverage.covers_rays(o, d).all():
            raise RuntimeError("ray outside the cropped mesh's coverage: crop for these rays")
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
        """Unsigned distance of (N, 3) points to the mesh surface (model units); on a crop,
        exact up to its ``coverage.point_radius`` and never less than the true distance."""
        pts = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
        if self.coverage is not None and not self.coverage.covers_points(pts).all():
            raise RuntimeError("point outside the cropped mesh's coverage: crop for it")
        pts = pts - self.offset
        out = self._scene.compute_distance(o3d.core.Tensor.from_numpy(pts.astype(np.float32)))
        return np.asarray(out.numpy(), dtype=np.float64)


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


def ring_pixels(xy_px: NDArray[np.float64], sigma_px: float,
                options: SpotCastOptions) -> NDArray[np.float64]:
    """(ring_rays, 2) pixels on the edge check's ring around a spot."""
    theta = np.linspace(0.0, 2 * np.pi, options.ring_rays, endpoint=False)
    radius_px = options.ring_sigma * sigma_px
    return np.asarray(xy_px)[None] + radius_px * np.column_stack([np.cos(theta), np.sin(theta)])


def spot_cast_rays(spots: Sequence[Spot], camera: Camera, cam_from_world: Pose,
                   options: SpotCastOptions) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Every ray :func:`cast_spots` may cast for these spots (spot rays and edge-check rings):
    origins (N, 3) and unit directions (N, 3), world frame; what a crop must cover."""
    xy = [np.array([[s.x, s.y] for s in spots], dtype=np.float64).reshape(-1, 2)]
    if options.edge_check and options.ring_rays >= 3:
        xy += [ring_pixels(xy[0][i], s.sigma_px, options) for i, s in enumerate(spots)
               if s.sigma_px > 0]
    return pixel_rays(camera, cam_from_world.inverse(), np.concatenate(xy))


def on_depth_edge(caster: MeshRaycaster, camera: Camera, cam_from_world: Pose, hit: SpotHit,
                  options: SpotCastOptions) -> bool:
    """True when the spot's tangent-plane σ cannot hold.

    Rays on a ring of ``ring_sigma`` σ around the spot meet the mesh off the hit's tangent plane
    by more than ``tolerance`` × the range change the plane predicts and more than the ring's
    radius at the hit's range (or miss the mesh).
    """
    if not hit.sigma_px > 0 or options.ring_rays < 3:
        return False
    radius_px = options.ring_sigma * hit.sigma_px
    ring = ring_pixels(hit.xy_px, hit.sigma_px, options)
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


# --------------------------------------------------------------------------- mesh crop


@dataclass(frozen=True)
class CropOptions:
    """Options of :func:`crop_for_rays`."""

    grid_cells: int = 256  # at most this many cells along the mesh box's longest side
    # cells are at least this quantile of the triangles' sizes (ρ, estimated on a seeded
    # sample): larger triangles are kept whatever the rays, so they must be few
    size_quantile: float = 0.999
    size_sample: int = 100_000
    # triangles tested at a time: 2^16 holds the crop's working memory at 1M triangles to
    # 21 MiB (29 MiB with 2^18, at the same speed: 0.08 s at 1M, 0.52-0.56 s at 20M)
    chunk_triangles: int = 1 << 16
    point_radius: float = 0.0  # distances up to this (model units) are exact for given points
    threads: int = 0  # chunks tested at once (numpy releases the GIL); 0: one per CPU

    def __post_init__(self) -> None:
        if self.grid_cells < 1 or self.chunk_triangles < 1 or self.size_sample < 1:
            raise InputError("grid_cells, chunk_triangles and size_sample must be >= 1")
        if self.threads < 0:
            raise InputError(f"threads must be >= 0, got {self.threads}")
        if not 0 < self.size_quantile <= 1:
            raise InputError(f"size_quantile must be in (0, 1], got {self.size_quantile}")
        if not self.point_radius >= 0:
            raise InputError(f"point_radius must be >= 0, got {self.point_radius}")


RAY_DILATION = 2  # cells: see crop_for_rays
RAY_SLACK = 1  # cells: a ray is covered when its samples lie within this of the crop's rays


@dataclass(frozen=True)
class CropCoverage:
    """The voxel grid a crop was made for: cells within ``RAY_SLACK`` of the cells the rays pass
    (``ray_cells``; the slack absorbs rounding in rays recomputed in another batch) and the
    cells of the given points (``point_cells``), whose distances are exact up to
    ``point_radius``."""

    lo: NDArray[np.float64]  # (3,) grid origin, model units
    cell: float  # cell size, model units
    ray_cells: NDArray[np.bool_] = field(repr=False)  # (X, Y, Z)
    point_cells: NDArray[np.bool_] = field(repr=False)  # (X, Y, Z)
    point_radius: float = 0.0

    @property
    def shape(self) -> tuple[int, int, int]:
        """Grid cells per axis."""
        return tuple(int(v) for v in self.ray_cells.shape)  # type: ignore[return-value]

    def cells_of(self, xyz: NDArray[np.floating]) -> NDArray[np.int64]:
        """(N, 3) cell indices of (N, 3) points, clamped to the grid."""
        return _cells(self.lo, self.cell, self.shape, xyz)

    def covers_rays(self, origins: NDArray[np.float64],
                    unit_dirs: NDArray[np.float64]) -> NDArray[np.bool_]:
        """(N,) True where every sample of the ray falls in a cell the crop was made for."""
        samples, ray = ray_samples(self.lo, self.cell, self.shape, origins, unit_dirs)
        c = self.cells_of(samples)
        inside = self.ray_cells[c[:, 0], c[:, 1], c[:, 2]]
        return np.bincount(ray[~inside], minlength=len(origins)) == 0

    def covers_points(self, xyz: NDArray[np.float64]) -> NDArray[np.bool_]:
        """(N,) True for points the crop was made for (distance exact up to point_radius)."""
        c = self.cells_of(np.atleast_2d(xyz))
        return self.point_cells[c[:, 0], c[:, 1], c[:, 2]]


@dataclass(frozen=True)
class MeshCrop:
    """The triangles within reach of some rays (and points), as their own small mesh."""

    vertices: NDArray[np.float64]  # (V', 3) model units
    triangles: NDArray[np.int32]  # (F', 3) indices into ``vertices``
    coverage: CropCoverage
    source_triangles: int  # F of the whole mesh

    @property
    def kept_fraction(self) -> float:
        """Share of the mesh's triangles kept."""
        return len(self.triangles) / max(self.source_triangles, 1)

    def raycaster(self) -> MeshRaycaster:
        """A caster over the crop that refuses rays and points it was not made for."""
        return MeshRaycaster(self.vertices, self.triangles, coverage=self.coverage)


def _cells(lo: NDArray[np.float64], cell: float, shape: tuple[int, int, int],
           xyz: NDArray[np.floating]) -> NDArray[np.int64]:
    """(N, 3) cell indices of (N, 3) points, clamped to the grid (float32 points are binned in
    float32: an error ~1e-7 of the coordinates, far inside the dilation's 0.75-cell margin)."""
    ftype = np.dtype(np.float32 if xyz.dtype == np.float32 else np.float64)
    rel = (xyz - lo.astype(ftype)) * ftype.type(1.0 / cell)
    return np.clip(np.floor(rel).astype(np.int64), 0, np.array(shape) - 1)


def ray_samples(lo: NDArray[np.float64], cell: float, shape: tuple[int, int, int],
                origins: NDArray[np.float64], unit_dirs: NDArray[np.float64]
                ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Points every ``cell / 2`` along each ray inside the grid box grown by one cell, and the
    ray each belongs to: (K, 3) model units, (K,). A ray missing the box has none."""
    box_lo = lo - cell
    box_hi = lo + (np.array(shape) + 1) * cell
    with np.errstate(divide="ignore", invalid="ignore"):
        t_a = (box_lo - origins) / unit_dirs
        t_b = (box_hi - origins) / unit_dirs
    t_lo = np.where(unit_dirs == 0, np.where((origins >= box_lo) & (origins <= box_hi),
                                             -np.inf, np.inf), np.minimum(t_a, t_b))
    t_hi = np.where(unit_dirs == 0, np.where((origins >= box_lo) & (origins <= box_hi),
                                             np.inf, -np.inf), np.maximum(t_a, t_b))
    t0 = np.maximum(t_lo.max(axis=1), 0.0)
    t1 = t_hi.min(axis=1)
    step = cell / 2
    span = np.where(t1 >= t0, t1 - t0, -1.0)  # -1: the ray misses the box
    n = np.where(span >= 0, np.floor(np.maximum(span, 0) / step).astype(np.int64) + 2, 0)
    ray = np.repeat(np.arange(len(origins)), n)
    k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    t = np.minimum(t0[ray] + k * step, t1[ray])
    return origins[ray] + t[:, None] * unit_dirs[ray], ray


def _mark(shape: tuple[int, int, int], cells: NDArray[np.int64]) -> NDArray[np.bool_]:
    grid = np.zeros(shape, dtype=bool)
    grid[cells[:, 0], cells[:, 1], cells[:, 2]] = True
    return grid


def _dilate(grid: NDArray[np.bool_], cells: int) -> NDArray[np.bool_]:
    """Cells within ``cells`` (Chebyshev) of a marked cell (separable maximum filter)."""
    if cells <= 0 or not grid.any():
        return grid
    return np.asarray(ndimage.maximum_filter(grid, size=2 * cells + 1, mode="constant"),
                      dtype=bool)


def _triangle_size(vertices: NDArray[np.floating], tris: NDArray[np.integer],
                   options: CropOptions) -> float:
    """The ``size_quantile`` of the triangles' largest axis extent, over a seeded sample
    (0 for no triangles)."""
    if len(tris) == 0:
        return 0.0
    rng = np.random.default_rng(0)
    pick = rng.choice(len(tris), size=min(len(tris), options.size_sample), replace=False)
    # (n, 3 corners, 3 axes) in the vertices' own type: the differences of a triangle's
    # nearby coordinates are exact in it, and float32 halves this sample's 7 MB
    corners = vertices[tris[np.sort(pick)]]
    extent = (corners.max(axis=1) - corners.min(axis=1)).max(axis=1).astype(np.float64)
    return float(np.quantile(extent, options.size_quantile))


def _in_chunks(fn: Callable[[int, int], NDArray[Any]], n: int, chunk: int,
               threads: int) -> NDArray[Any]:
    """``fn(start, stop)`` over consecutive chunks of ``range(n)``, concatenated in order; on
    ``threads`` threads (0: one per CPU): the numpy work inside releases the GIL, so two
    cores halve the crop's passes over a large mesh."""
    bounds = [(s, min(s + chunk, n)) for s in range(0, n, chunk)]
    if not bounds:
        return fn(0, 0)
    workers = min(len(bounds), threads or os.cpu_count() or 1)
    if workers == 1:
        return np.concatenate([fn(a, b) for a, b in bounds])
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return np.concatenate(list(pool.map(lambda ab: fn(*ab), bounds)))


def _vertex_cells(vertices: NDArray[np.floating], coverage: CropCoverage,
                  chunk: int, threads: int = 1) -> NDArray[np.int32]:
    """(V,) grid cell of each vertex, its axis indices packed 10 bits each (i << 20 | j << 10 |
    k; the grid has at most 257 cells per axis); a sequential pass, chunk by chunk."""
    def pack(a: int, b: int) -> NDArray[np.int32]:
        c = coverage.cells_of(vertices[a:b]).astype(np.int32)
        return (c[:, 0] << 20) | (c[:, 1] << 10) | c[:, 2]
    return _in_chunks(pack, len(vertices), chunk, threads).astype(np.int32, copy=False)


def _kept_triangles(vertex_cells: NDArray[np.int32], tris: NDArray[np.integer],
                    shape: tuple[int, int, int], hot: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(F,) True for triangles spanning more than 2 cells on an axis, or whose first
    vertex's cell is hot (see crop_for_rays)."""
    ids = vertex_cells[tris]  # (F, 3): one gather of 4-byte cells, not of 3 coordinates
    compact = np.ones(len(ids), dtype=bool)
    for shift in (20, 10, 0):  # axis i, j, k of each corner
        axis = (ids >> shift) & 1023
        a, b, c = axis[:, 0], axis[:, 1], axis[:, 2]  # columns: reducing 3-long rows is slow
        compact &= (np.abs(a - b) <= 1) & (np.abs(a - c) <= 1) & (np.abs(b - c) <= 1)
    first = ids[:, 0]
    _, ny, nz = shape
    linear = (((first >> 20) * ny + ((first >> 10) & 1023)) * nz + (first & 1023))
    return ~compact | hot.reshape(-1)[linear]


def crop_for_rays(vertices: NDArray[np.floating], triangles: NDArray[np.integer],
                  origins: NDArray[np.float64], directions: NDArray[np.float64],
                  points: NDArray[np.float64] | None = None,
                  options: CropOptions = CropOptions()) -> MeshCrop:  # noqa: B008
    """The mesh's triangles that any of the (N, 3) rays can meet, and those within
    ``options.point_radius`` of the (M, 3) points: first hits and distances up to that radius
    are the whole mesh's.

    Why it is exact: a voxel grid of cell h (at least the 99.9 % quantile of the triangles'
    axis extents, so almost all are "compact") covers the mesh's box. A compact triangle's
    vertex cells differ by at most 1 on each axis, so the triangle lies in their box of cells
    and each of its points is at most 1 cell from each vertex's cell. A point x where a ray
    meets it is within h/4 of a ray sample (samples every h/2), i.e. at most 1 cell from a
    sampled cell: its vertices' cells are at most 2 cells from a sampled cell, which is why
    ray cells are dilated by 2 (after the slack of ``RAY_SLACK`` cells that covered rays may
    take). Likewise a triangle within r of a point has its vertices' cells at most ⌈r/h⌉ + 1
    cells from the point's cell (dilated by ⌈r/h⌉ + 2). Other triangles are always kept.
    Cost: one sequential pass over the vertices and one gather of 4-byte cell ids per
    triangle (1.8 s instead of 4.5 s for 20M triangles when coordinates were gathered).
    """
    verts = np.asarray(vertices)  # float32 or float64 as read: converted chunk by chunk
    if verts.dtype.kind != "f":
        verts = verts.astype(np.float64)
    tris = np.asarray(triangles)
    # per column: numpy's axis-0 reduction of an (N, 3) array is ~15x slower (0.4 s at 10M)
    lo = np.array([verts[:, j].min() for j in range(3)], dtype=np.float64)
    hi = np.array([verts[:, j].max() for j in range(3)], dtype=np.float64)
    cell = max(float(np.max(hi - lo)) / options.grid_cells, _triangle_size(verts, tris, options),
               1e-12)
    shape = tuple(int(v) for v in np.floor((hi - lo) / cell).astype(np.int64) + 1)
    o = np.atleast_2d(np.asarray(origins, dtype=np.float64)).reshape(-1, 3)
    d = np.atleast_2d(np.asarray(directions, dtype=np.float64)).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    samples, _ = ray_samples(lo, cell, shape, o, d)  # type: ignore[arg-type]
    ray_cells = _dilate(_mark(shape, _cells(lo, cell, shape, samples)),  # type: ignore[arg-type]
                        RAY_SLACK)
    pts = np.zeros((0, 3)) if points is None else np.atleast_2d(np.asarray(points, np.float64))
    pt_cells = _mark(shape, _cells(lo, cell, shape, pts))  # type: ignore[arg-type]
    cov = CropCoverage(lo, cell, ray_cells, pt_cells, options.point_radius)
    hot = _dilate(ray_cells, RAY_DILATION) | _dilate(
        pt_cells, int(np.ceil(options.point_radius / cell)) + RAY_DILATION)
    vcells = _vertex_cells(verts, cov, options.chunk_triangles, options.threads)
    keep = _in_chunks(lambda a, b: _kept_triangles(vcells, tris[a:b], cov.shape, hot),
                      len(tris), options.chunk_triangles, options.threads)
    return _submesh(verts, tris[keep], cov, len(tris))


def _submesh(verts: NDArray[np.floating], kept: NDArray[np.integer], coverage: CropCoverage,
             source_triangles: int) -> MeshCrop:
    """The kept triangles with their own compact vertex array."""
    used = np.zeros(len(verts), dtype=bool)  # a mask, not np.unique: O(V) instead of a sort
    used[kept.reshape(-1)] = True
    new_index = np.cumsum(used, dtype=np.int64) - 1
    return MeshCrop(vertices=verts[used].astype(np.float64),
                    triangles=new_index[kept].astype(np.int32),
                    coverage=coverage, source_triangles=source_triangles)
