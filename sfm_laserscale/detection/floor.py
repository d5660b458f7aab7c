"""Where the spots found in one image put a missing laser's spot: the floor through them.

A calibrated laser's spot at range r along its beam is the camera-frame point o + r·d (metres;
r read off the beam's image segment, :func:`.beams.range_along_beam`). The spots of two or
more lasers found on their own evidence give a plane for the floor they lit
(:func:`floor_plane`): the least-squares plane through three or more, and through two the
least tilted plane holding the chord between them (its second axis parallel to the image
plane). A missing laser's beam meets that plane at one range (:func:`beam_range_on_plane`), and
that point projected is where its spot should be (:func:`floor_predictions`), within the
floor's relief and the rig's calibration error (measured in docs/DETECTION.md: a median
2.3 px at 1920 × 1080). :func:`.detect.detect_spots` searches a few pixels around each such
point with :func:`.guided.search_near`, where the band's competition (scene blobs as
strong as a faint spot, hundreds of pixels of band) is gone, and the spots found give the size
to expect (their median half-max radius, :class:`.beams.SearchRegion`'s ``spot_radius_px``).
Where that search takes nothing, the same pixels are searched again with the weak-spot test at
``floor_weak_min_snr`` (2.5) instead of ``min_snr`` (5): the evidence must still reach
``min_score``, which at such an SNR takes a laser-coloured, round candidate only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.beams import SearchRegion, range_along_beam
from sfm_laserscale.detection.candidates import WEAK_SNR, Measure
from sfm_laserscale.detection.guided import GuidedOptions, search_near
from sfm_laserscale.detection.options import DetectionOptions
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import Rig

F64 = NDArray[np.float64]

_OPTICAL_AXIS = np.array([0.0, 0.0, 1.0])
#: the search radius by default, as a share of the image diagonal (3.1 px at 1920 × 1080)
RADIUS_PER_DIAGONAL = 0.0014
PLACE = "where the floor through the other lasers' spots puts it"
#: the same point, named again by the second search's reason
SAME_PLACE = "the same point"


def spot_points_m(spots_px: Mapping[str, tuple[float, float]], rig: Rig, region: SearchRegion
                  ) -> dict[str, F64]:
    """Laser -> (3,) camera-frame point (metres) of each calibrated laser's spot, at the range
    its image position reads on the beam's segment."""
    points = {}
    for name, xy in spots_px.items():
        las = rig.laser(name)
        line = region.polylines.get(name)
        if las.origin is None or las.direction is None or line is None or len(line) < 2:
            continue
        range_m = float(range_along_beam(np.array([xy], dtype=np.float64), line,
                                         region.ranges[name])[0])
        if np.isfinite(range_m):
            points[name] = np.asarray(las.origin, float) + range_m * np.asarray(las.direction,
                                                                                float)
    return points


def floor_plane(points_m: F64) -> tuple[F64, F64] | None:
    """(centre, unit normal) of the plane through (N, 3) points: least squares for N >= 3, the
    least tilted plane holding the chord for N = 2; None for fewer or degenerate points."""
    points_m = np.asarray(points_m, dtype=np.float64)
    if len(points_m) < 2:
        return None
    centre = points_m.mean(axis=0)
    if len(points_m) >= 3:
        _, sv, vt = np.linalg.svd(points_m - centre)
        if sv[1] < 1e-9:
            return None  # collinear: no plane
        normal = vt[-1]
    else:
        chord = points_m[1] - points_m[0]
        normal = np.cross(chord, np.cross(_OPTICAL_AXIS, chord))
        length = float(np.linalg.norm(normal))
        if length < 1e-12:
            return None  # chord along the optical axis
        normal = normal / length
    return centre, normal


def beam_range_on_plane(origin_m: F64, direction: F64, centre_m: F64, normal: F64
                        ) -> float | None:
    """Range (metres along the unit ``direction``) where the beam meets the plane, or None if
    it runs parallel to it or meets it behind its origin."""
    along = float(normal @ direction)
    if abs(along) < 1e-6:
        return None
    range_m = float(normal @ (centre_m - origin_m)) / along
    return range_m if range_m > 0 else None


def _projected(camera: Camera, point_m: F64) -> tuple[float, float] | None:
    """COLMAP (x, y) of a camera-frame point, or None outside the image."""
    xy = camera.project(point_m[None])[0]
    if np.all(np.isfinite(xy)) and 0 <= xy[0] <= camera.width and 0 <= xy[1] <= camera.height:
        return float(xy[0]), float(xy[1])
    return None


def floor_predictions(camera: Camera, rig: Rig, region: SearchRegion,
                      spots_px: Mapping[str, tuple[float, float]], min_spots: int,
                      range_m: tuple[float, float]) -> dict[str, tuple[float, float]]:
    """Laser -> COLMAP (x, y) where the floor through the found spots puts each other calibrated
    laser's spot (within ``range_m`` along its beam, inside the image); empty with fewer than
    ``min_spots`` (>= 2) calibrated spots."""
    points = spot_points_m(spots_px, rig, region)
    if len(points) < max(2, min_spots):
        return {}
    plane = floor_plane(np.array(list(points.values())))
    if plane is None:
        return {}
    predicted = {}
    for las in rig.lasers:
        if las.name in spots_px or las.origin is None or las.direction is None:
            continue
        origin, direction = np.asarray(las.origin, float), np.asarray(las.direction, float)
        r = beam_range_on_plane(origin, direction, *plane)
        if r is None or not range_m[0] <= r <= range_m[1]:
            continue
        if (xy := _projected(camera, origin + r * direction)) is not None:
            predicted[las.name] = xy
    return predicted


@dataclass(frozen=True)
class FloorFind:
    """One laser's search on the floor through the other spots: the candidate taken and its
    evidence, or (None, 0) and why not."""

    measure: Measure | None
    score: float
    why: str


def default_floor_radius_px(width: int, height: int) -> float:
    """The floor search's radius by default: 0.14 % of the image diagonal (px)."""
    return RADIUS_PER_DIAGONAL * math.hypot(width, height)


def floor_radius_px(camera: Camera, options: DetectionOptions) -> float:
    """The floor search's radius (px) in this camera's images: ``options.floor_radius_px`` or
    the default."""
    return options.floor_radius_px or default_floor_radius_px(camera.width, camera.height)


def floor_search(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig, region: SearchRegion,
                 spots_px: Mapping[str, tuple[float, float]], options: DetectionOptions,
                 spot_radius_px: float | None = None) -> dict[str, FloorFind]:
    """Laser -> what the search found where the floor through ``spots_px`` (laser -> COLMAP
    (x, y), the spots found so far; ``spot_radius_px``: their median half-max radius) puts
    each other calibrated laser's spot."""
    if not options.floor_search:
        return {}
    predicted = floor_predictions(camera, rig, region, spots_px, options.floor_min_spots,
                                  (options.min_range_m, options.max_range_m))
    radius = floor_radius_px(camera, options)
    return {name: _search(image_rgb, camera, rig, name, xy, options, radius, spot_radius_px)
            for name, xy in predicted.items()}


def _search(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig, name: str,
            xy: tuple[float, float], options: DetectionOptions, radius_px: float,
            spot_radius_px: float | None) -> FloorFind:
    """One laser's search near the floor's point: with the weak-spot test at ``min_snr``, then,
    where that takes nothing, at ``floor_weak_min_snr`` (the reason adds what that one saw)."""
    first = FloorFind(*search_near(image_rgb, camera, rig, name, xy, options,
                                   GuidedOptions(radius_px=radius_px), PLACE, spot_radius_px))
    weak_snr = options.floor_weak_min_snr
    if first.measure is not None or weak_snr is None or weak_snr >= options.min_snr:
        return first
    again = FloorFind(*search_near(image_rgb, camera, rig, name, xy, options,
                                   GuidedOptions(radius_px=radius_px, min_snr=weak_snr),
                                   SAME_PLACE, spot_radius_px))
    if again.measure is not None:
        return again
    if WEAK_SNR in again.why or again.why.replace(SAME_PLACE, PLACE) == first.why:
        return first  # nothing the first reason does not say
    return FloorFind(None, 0.0, f"{first.why}; with SNR {weak_snr:g} allowed, {again.why}")
