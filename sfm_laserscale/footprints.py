"""Image footprints on the mesh: area, ground sampling distance and range of every image.

For one image with a pose, the rays through the corners of a grid of ``grid_columns`` ×
``rows`` cells (rows from the aspect ratio; cell corners from pixel 0 to W and 0 to H, COLMAP's
convention) are cast into the mesh (:mod:`sfm_laserscale.raycast`). A cell whose four rays hit
the mesh is the quadrilateral of its four hits, split into two triangles; its area is theirs.
On a plane every cell is exactly such a quadrilateral (a pinhole camera maps straight lines to
straight lines), so the footprint's area is exact there, whatever the tilt; on relief it is the
surface area at the grid's resolution. A cell whose triangle is seen at more than
``max_incidence_deg`` from its normal spans a depth edge (a near and a far surface) or a
grazing slope; it is left out, as are cells cut by the mesh's border.

Per image (model units; ``Footprint.metric`` converts with the scale s: areas × s², lengths × s):

- ``area``: the summed area of the counted cells;
- ``gsd_centre``: √(area / pixels) of a ``centre_px`` square at the image centre — the side of
  the square a pixel covers there (on a facing plane at range D: D / √(fx·fy));
- ``gsd_median``: the median over the counted cells of √(cell area / pixels per cell);
- ``distance``: the median camera–hit distance of the grid's rays that hit;
- ``on_mesh_fraction``: the share of the image's cells counted in ``area``.

Large meshes (more than ``max_crop_triangles``): the rays of a group of images are cast on the
mesh cropped exactly to them (:func:`sfm_laserscale.raycast.crop_for_rays`), so no caster is
built on more than about that many triangles at once (images are grouped in the given order:
survey order keeps a group's footprints together); smaller meshes get one caster.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, Pose, SparseModel
from sfm_laserscale.raycast import MeshRaycaster, RaycastResult, crop_for_rays, pixel_rays

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
BATCH_IMAGES = 64  # images whose rays are cast in one call on a whole-mesh caster


@dataclass(frozen=True)
class FootprintOptions:
    """Options of :func:`footprints`."""

    enabled: bool = True
    grid_columns: int = 64  # cells across the image (rows: from the aspect ratio)
    centre_px: float = 8.0  # side of the centre square for gsd_centre, pixels
    max_incidence_deg: float = 85.0  # cells seen more obliquely are not counted
    max_crop_triangles: int = 4_000_000  # mesh triangles per cropped caster, about

    def __post_init__(self) -> None:
        if self.grid_columns < 1 or not self.centre_px > 0:
            raise InputError("footprints: grid_columns must be >= 1 and centre_px > 0")
        if not 0 < self.max_incidence_deg < 90:
            raise InputError("footprints: max_incidence_deg must be in (0, 90)")
        if self.max_crop_triangles < 1:
            raise InputError("footprints: max_crop_triangles must be >= 1")


@dataclass(frozen=True)
class FootprintView:
    """One image to measure: its name, kind (``laser`` or ``model``), camera and pose; a
    ``reason`` instead of a pose when it has none (an unregistered laser image)."""

    image: str
    kind: str
    camera: Camera | None
    cam_from_world: Pose | None
    reason: str | None = None


@dataclass(frozen=True)
class Footprint:
    """One image's footprint in model units (NaN where there is none; ``reason`` says why)."""

    image: str
    kind: str  # laser | model
    area: float  # model units²
    gsd_centre: float  # model units per pixel
    gsd_median: float  # model units per pixel
    distance: float  # model units
    on_mesh_fraction: float  # 0..1
    grid: tuple[int, int]  # (columns, rows)
    reason: str | None = None

    def metric(self, scale: float) -> dict[str, Any]:
        """The footprints.csv row at ``scale`` metres per model unit (NaN -> None)."""
        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None
        return {"image": self.image, "area_m2": num(self.area * scale ** 2),
                "gsd_mm_centre": num(self.gsd_centre * scale * 1e3),
                "gsd_mm_median": num(self.gsd_median * scale * 1e3),
                "distance_m": num(self.distance * scale),
                "footprint_on_mesh_fraction": num(self.on_mesh_fraction)}


def grid_shape(camera: Camera, columns: int) -> tuple[int, int]:
    """(columns, rows) of the grid: square-ish cells."""
    return columns, max(1, round(columns * camera.height / camera.width))


def grid_pixels(camera: Camera, options: FootprintOptions) -> F64:
    """((rows+1)·(cols+1) + 4, 2) pixels: the grid's cell corners row by row, then the centre
    square's corners (counter-clockwise in the image)."""
    cols, rows = grid_shape(camera, options.grid_columns)
    xs = np.linspace(0.0, camera.width, cols + 1)
    ys = np.linspace(0.0, camera.height, rows + 1)
    gx, gy = np.meshgrid(xs, ys)
    h = 0.5 * options.centre_px
    cx, cy = 0.5 * camera.width, 0.5 * camera.height
    centre = np.array([[cx - h, cy - h], [cx + h, cy - h], [cx + h, cy + h], [cx - h, cy + h]])
    return np.vstack([np.column_stack([gx.ravel(), gy.ravel()]), centre])


def _quad_areas(a: F64, b: F64, c: F64, d: F64, eye: F64,
                cos_min: float) -> tuple[F64, NDArray[np.bool_]]:
    """Areas of quads a-b-c-d ((K, 3) corners each) as triangles abc + acd, and whether both
    triangles are seen within the incidence limit from ``eye``."""
    n1 = np.cross(b - a, c - a)
    n2 = np.cross(c - a, d - a)
    area = 0.5 * (np.linalg.norm(n1, axis=1) + np.linalg.norm(n2, axis=1))
    ok = np.ones(len(a), dtype=bool)
    for n, centroid in ((n1, (a + b + c) / 3), (n2, (a + c + d) / 3)):
        view = centroid - eye
        denom = np.linalg.norm(n, axis=1) * np.linalg.norm(view, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos = np.abs(np.einsum("ij,ij->i", n, view)) / denom
        ok &= np.nan_to_num(cos, nan=0.0) >= cos_min
    return area, ok


def view_rays(camera: Camera, cam_from_world: Pose, options: FootprintOptions) -> tuple[F64, F64]:
    """The rays of one image's grid and centre square: origins (N, 3), unit directions (N, 3)."""
    return pixel_rays(camera, cam_from_world.inverse(), grid_pixels(camera, options))


def measure(view: FootprintView, res: RaycastResult, options: FootprintOptions) -> Footprint:
    """The footprint of one image from the cast of its :func:`view_rays`."""
    if view.camera is None or view.cam_from_world is None:
        return _none(view, options)
    camera = view.camera
    cols, rows = grid_shape(camera, options.grid_columns)
    xyz, hit, eye = res.xyz, res.hit, view.cam_from_world.center
    n_grid = (rows + 1) * (cols + 1)
    cos_min = math.cos(math.radians(options.max_incidence_deg))
    idx = np.arange(n_grid).reshape(rows + 1, cols + 1)
    a, b, c, d = (idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(),
                  idx[1:, :-1].ravel())
    area, seen = _quad_areas(xyz[a], xyz[b], xyz[c], xyz[d], eye, cos_min)
    counted = hit[a] & hit[b] & hit[c] & hit[d] & seen
    pixels_per_cell = (camera.width / cols) * (camera.height / rows)
    centre = n_grid + np.arange(4)
    q = xyz[centre]
    c_area, c_seen = _quad_areas(q[0:1], q[1:2], q[2:3], q[3:4], eye, cos_min)
    centre_ok = bool(hit[centre].all() and c_seen[0])
    dist = res.distance[:n_grid][hit[:n_grid]]
    return Footprint(
        image=view.image, kind=view.kind,
        area=float(area[counted].sum()),
        gsd_centre=float(np.sqrt(c_area[0] / options.centre_px ** 2)) if centre_ok else math.nan,
        gsd_median=(float(np.median(np.sqrt(area[counted] / pixels_per_cell)))
                    if counted.any() else math.nan),
        distance=float(np.median(dist)) if len(dist) else math.nan,
        on_mesh_fraction=float(counted.mean()),
        grid=(cols, rows),
        reason=None if counted.any() else "the image's footprint is not on the mesh")


def _measure_batch(views: Sequence[FootprintView], caster: MeshRaycaster | None,
                   vertices: NDArray[np.floating], triangles: NDArray[np.integer],
                   options: FootprintOptions) -> list[Footprint]:
    """Footprints of posed views, their rays cast at once: on ``caster``, or (None) on the
    mesh cropped exactly to these rays."""
    rays = [view_rays(v.camera, v.cam_from_world, options)  # type: ignore[arg-type]
            for v in views]
    origins = np.concatenate([o for o, _ in rays])
    dirs = np.concatenate([d for _, d in rays])
    if caster is None:
        caster = crop_for_rays(vertices, triangles, origins, dirs).raycaster()
    res = caster.cast(origins, dirs)
    bounds = np.cumsum([0] + [len(o) for o, _ in rays])
    return [measure(v, _rows(res, bounds[k], bounds[k + 1]), options)
            for k, v in enumerate(views)]


def _rows(res: RaycastResult, a: int, b: int) -> RaycastResult:
    return RaycastResult(res.hit[a:b], res.xyz[a:b], res.normal[a:b], res.distance[a:b],
                         res.primitive_id[a:b])


def _none(view: FootprintView, options: FootprintOptions) -> Footprint:
    grid = ((0, 0) if view.camera is None else grid_shape(view.camera, options.grid_columns))
    return Footprint(view.image, view.kind, math.nan, math.nan, math.nan, math.nan, math.nan,
                     grid, view.reason or "no pose")


def _groups(n_views: int, n_triangles: int, options: FootprintOptions) -> int:
    """Images per cropped caster."""
    return max(1, math.ceil(n_views * options.max_crop_triangles / max(n_triangles, 1)))


def footprints(views: Sequence[FootprintView], vertices: NDArray[np.floating],
               triangles: NDArray[np.integer],
               options: FootprintOptions = FootprintOptions(),  # noqa: B008 (frozen)
               progress: Callable[[list[list[int]]], Iterable[list[int]]] | None = None
               ) -> tuple[Footprint, ...]:
    """Every view's footprint on the mesh (model units), in the views' order."""
    posed = [i for i, v in enumerate(views)
             if v.camera is not None and v.cam_from_world is not None]
    out = {i: _none(v, options) for i, v in enumerate(views) if i not in set(posed)}
    whole = len(triangles) <= options.max_crop_triangles  # one caster on the whole mesh
    caster = MeshRaycaster(vertices, triangles) if whole and posed else None
    size = BATCH_IMAGES if whole else _groups(len(posed), len(triangles), options)
    batches = [posed[k:k + size] for k in range(0, len(posed), size)]
    for batch in (progress(batches) if progress is not None else batches):
        found = _measure_batch([views[i] for i in batch], caster, vertices, triangles, options)
        out.update(zip(batch, found, strict=True))
    return tuple(out[i] for i in range(len(views)))


def model_views(model: SparseModel) -> list[FootprintView]:
    """The model's images as views (sorted by name)."""
    images = sorted(model.images.values(), key=lambda im: im.name)
    return [FootprintView(im.name, "model", model.cameras.get(im.camera_id), im.cam_from_world,
                          None if im.camera_id in model.cameras else "camera missing")
            for im in images]


def _stats(values: Sequence[float]) -> dict[str, float] | None:
    v = np.asarray([x for x in values if math.isfinite(x)], dtype=np.float64)
    if len(v) == 0:
        return None
    q = np.percentile(v, [0, 25, 50, 75, 100])
    return {"n": int(len(v)), "min": float(q[0]), "p25": float(q[1]), "median": float(q[2]),
            "p75": float(q[3]), "max": float(q[4])}


def _histogram(rows: Sequence[dict[str, Any]], kinds: Sequence[str],
               bins: int = 12) -> dict[str, Any] | None:
    areas = [r["area_m2"] for r in rows if r["area_m2"] is not None]
    if not areas:
        return None
    lo, hi = min(areas), max(areas)
    edges = np.linspace(lo, hi if hi > lo else lo + 1e-9, bins + 1)
    out: dict[str, Any] = {"edges": [float(e) for e in edges]}
    for kind in ("laser", "model"):
        vals = [r["area_m2"] for r, k in zip(rows, kinds, strict=True)
                if k == kind and r["area_m2"] is not None]
        out[kind] = [int(c) for c in np.histogram(vals, bins=edges)[0]]
    return out


def footprint_summary(found: Sequence[Footprint], scale: float) -> dict[str, Any]:
    """report.json's ``footprints`` block: counts and the distribution (metric) of each column
    over the images whose footprint is on the mesh."""
    every = [f.metric(scale) for f in found]
    on = [i for i, r in enumerate(every) if r["area_m2"] is not None and r["area_m2"] > 0]
    rows = [every[i] for i in on]
    kinds = [found[i].kind for i in on]
    summary: dict[str, Any] = {
        "file": "footprints.csv", "n_images": len(found),
        "n_laser_images": sum(f.kind == "laser" for f in found),
        "n_model_images": sum(f.kind == "model" for f in found), "n_on_mesh": len(on),
        "grid": list(next((f.grid for f in found if f.grid != (0, 0)), (0, 0))) or None,
    }
    for key in ("area_m2", "gsd_mm_centre", "gsd_mm_median", "distance_m",
                "footprint_on_mesh_fraction"):
        summary[key] = _stats([r[key] for r in rows if r[key] is not None])
    areas = [r["area_m2"] for r in rows if r["area_m2"] is not None]
    if summary["area_m2"] is not None:
        summary["area_m2"]["total"] = float(sum(areas))
    summary["histogram_area_m2"] = _histogram(rows, kinds)
    if summary["grid"] == [0, 0]:
        del summary["grid"]
    if summary["histogram_area_m2"] is None:
        del summary["histogram_area_m2"]
    return summary
