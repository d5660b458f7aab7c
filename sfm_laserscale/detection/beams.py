"""Where to look: each calibrated beam's image segment, the band around it, the crop searched.

A beam between ``min_range_m`` and ``max_range_m`` is projected with the camera model (lens
distortion included) to an image polyline; a spot of that laser must lie within ``band_px`` of
it. When every laser is calibrated only the bands' bounding box is searched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.options import DetectionOptions
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import Laser, Rig

F64 = NDArray[np.float64]


def default_band_px(width: int, height: int) -> float:
    """Default beam band half-width: 3 px + 0.5 % of the image diagonal."""
    return 3.0 + 0.005 * math.hypot(width, height)


def default_max_spot_radius_px(width: int, height: int) -> float:
    """Default largest spot half-maximum radius: 1.5 % of the image diagonal (at least 6 px)."""
    return max(6.0, 0.015 * math.hypot(width, height))


def _normalised_bounds(camera: Camera, margin: float = 0.15) -> F64:
    """(2, 2) [[xmin, ymin], [xmax, ymax]] of the image in normalised (z = 1) coordinates.

    Border pixels that the camera model cannot undistort (NaN, beyond the fold of a strong
    radial distortion) are skipped; if too few remain, the pinhole bounds are used.
    """
    w, h = float(camera.width), float(camera.height)
    t = np.linspace(0.0, 1.0, 9)
    border = np.concatenate([
        np.column_stack([t * w, np.zeros_like(t)]), np.column_stack([t * w, np.full_like(t, h)]),
        np.column_stack([np.zeros_like(t), t * h]), np.column_stack([np.full_like(t, w), t * h]),
    ])
    xy = camera.unproject(border)[:, :2]
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if len(xy) < 8:
        f = camera.focal_px
        c = camera.unproject(np.array([[w / 2, h / 2]]))[0, :2]
        xy = np.array([[c[0] - w / (2 * f), c[1] - h / (2 * f)],
                       [c[0] + w / (2 * f), c[1] + h / (2 * f)]])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    pad = margin * (hi - lo)
    return np.stack([lo - pad, hi + pad])


def beam_polyline_px(
    camera: Camera, laser: Laser, min_range_m: float, max_range_m: float, samples: int = 64
) -> F64:
    """(K, 2) projection of a calibrated beam's [min, max] range part (pixels); K = 0 if unseen.

    Beam points are sampled uniformly in 1 / range (uniform in the image for a pinhole) and
    only those whose normalised coordinates lie within the (padded) field of view are projected,
    so lens-distortion polynomials are never evaluated far outside their valid domain.
    """
    return beam_samples(camera, laser, min_range_m, max_range_m, samples)[0]


def beam_samples(
    camera: Camera, laser: Laser, min_range_m: float, max_range_m: float, samples: int = 64
) -> tuple[F64, F64]:
    """(K, 2) image polyline of a calibrated beam (see :func:`beam_polyline_px`) and the (K,)
    range along the beam (metres from its origin) of each vertex."""
    empty = (np.zeros((0, 2)), np.zeros(0))
    if laser.origin is None or laser.direction is None:
        return empty
    ranges = 1.0 / np.linspace(1.0 / max_range_m, 1.0 / min_range_m, samples)
    pts = laser.origin[None, :] + ranges[:, None] * laser.direction[None, :]
    front = pts[:, 2] > 1e-6
    pts, ranges = pts[front], ranges[front]
    if len(pts) == 0:
        return empty
    xy_n = pts[:, :2] / pts[:, 2:3]
    bounds = _normalised_bounds(camera)
    inside = np.all((xy_n >= bounds[0]) & (xy_n <= bounds[1]), axis=1)
    if not np.any(inside):
        return empty
    xy = camera.project(pts[inside])
    ok = np.all(np.isfinite(xy), axis=1)
    return np.asarray(xy[ok], dtype=np.float64), np.asarray(ranges[inside][ok])


def range_along_beam(xy: F64, polyline: F64, ranges: F64) -> F64:
    """(N,) range (metres along the beam) of the polyline point nearest each of (N, 2) points,
    interpolated in inverse range (linear in the image for a pinhole); NaN if K < 2."""
    xy = np.atleast_2d(xy)
    if len(polyline) < 2:
        return np.full(len(xy), np.nan)
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    ap = xy[:, None, :] - a[None, :, :]
    t = np.clip(np.sum(ap * ab[None], axis=2) / np.maximum(np.sum(ab * ab, axis=1), 1e-12),
                0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    seg = np.argmin(np.linalg.norm(xy[:, None, :] - closest, axis=2), axis=1)
    tt = t[np.arange(len(xy)), seg]
    inv = (1.0 - tt) / ranges[seg] + tt / ranges[seg + 1]
    return np.asarray(1.0 / inv)


def distance_to_polyline(xy: F64, polyline: F64) -> F64:
    """(N,) Euclidean distance of (N, 2) points to a (K, 2) polyline (inf if K = 0)."""
    xy = np.atleast_2d(xy)
    if len(polyline) == 0:
        return np.full(len(xy), np.inf)
    if len(polyline) == 1:
        return np.asarray(np.linalg.norm(xy - polyline[0], axis=1), dtype=np.float64)
    a, b = polyline[:-1], polyline[1:]  # (S, 2)
    ab = b - a
    ap = xy[:, None, :] - a[None, :, :]  # (N, S, 2)
    denom = np.maximum(np.sum(ab * ab, axis=1), 1e-12)
    t = np.clip(np.sum(ap * ab[None], axis=2) / denom[None], 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.asarray(np.linalg.norm(xy[:, None, :] - closest, axis=2).min(axis=1))



@dataclass(frozen=True)
class SearchRegion:
    """Where to look: crop of the image, beam polylines and the near-band mask (crop pixels).

    ``spot_radius_px``: the half-maximum radius of the spots already found in the image, when
    known (a search near one point, :mod:`.floor`): a maximum that fails a shape test against
    the far background is measured against its own surroundings for a spot of this radius, and
    one whose sub-pixel refinement fails at its own measured radius is refined again at this
    one (:mod:`.candidates`).
    """

    roi: tuple[int, int, int, int]  # x0, y0, x1, y1 (array indices, end exclusive)
    polylines: dict[str, F64]  # calibrated laser -> (K, 2) beam segment, image COLMAP px
    ranges: dict[str, F64]  # calibrated laser -> (K,) range along the beam of each vertex, m
    near: NDArray[np.bool_] | None  # (y1-y0, x1-x0) within reach of a band; None = everywhere
    band_px: float
    max_radius: float
    spot_radius_px: float | None = None


def search_region(camera: Camera, rig: Rig, options: DetectionOptions) -> SearchRegion:
    """Whole image if a laser is uncalibrated, else the beam bands' bounding box plus margins."""
    band = options.band_px or default_band_px(camera.width, camera.height)
    max_radius = options.max_spot_radius_px or default_max_spot_radius_px(
        camera.width, camera.height)
    samples = {las.name: beam_samples(camera, las, options.min_range_m, options.max_range_m)
               for las in rig.lasers if las.calibrated}
    polylines = {name: xy for name, (xy, _) in samples.items()}
    ranges = {name: r for name, (_, r) in samples.items()}
    full = (0, 0, camera.width, camera.height)
    if not all(las.calibrated for las in rig.lasers):
        return SearchRegion(full, polylines, ranges, None, band, max_radius)
    pts = [p for p in polylines.values() if len(p)]
    if not pts:
        return SearchRegion((0, 0, 0, 0), polylines, ranges, None, band, max_radius)
    allp = np.concatenate(pts)
    margin = band + 2.0 * max_radius + 4.0 * max(options.spot_sigmas_px) + 4.0
    lo = np.floor(allp.min(axis=0) - margin).astype(int)
    hi = np.ceil(allp.max(axis=0) + margin).astype(int)
    x0, y0 = max(0, int(lo[0])), max(0, int(lo[1]))
    x1, y1 = min(camera.width, int(hi[0])), min(camera.height, int(hi[1]))
    if x1 - x0 < 8 or y1 - y0 < 8:
        return SearchRegion((0, 0, 0, 0), polylines, ranges, None, band, max_radius)
    near = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
    for line in pts:
        # COLMAP px -> array index coordinates of the crop: subtract 0.5 and the crop origin
        idx = np.round((line - 0.5 - [x0, y0]) * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(near, [idx], False, 255, thickness=2 * int(math.ceil(band)) + 5,
                      shift=4)
    return SearchRegion((x0, y0, x1, y1), polylines, ranges, near > 0, band, max_radius)


def scene_mask(region: SearchRegion) -> NDArray[np.bool_] | None:
    """Pixels of the crop away from every band (the lasers' own light: spots, beam glow), where
    the scene's clutter is measured; None when the whole image is searched."""
    if region.near is None:
        return None
    grow = 2 * int(math.ceil(region.max_radius)) + 1
    wide = cv2.dilate(region.near.astype(np.uint8), np.ones((grow, grow), np.uint8))
    return np.asarray(wide == 0)
