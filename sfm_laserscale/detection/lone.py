"""A lone spot's floor: the other beams searched where a floor through that one spot puts them.

With one laser's spot found on its own evidence, the floor search (:mod:`.floor`) has no plane:
it needs two spots. One spot gives a point of the floor (metres, camera frame) but not its
tilt. A floor through that point, tilted up to ``LONE_TILT_DEG`` from facing the camera, puts
each other calibrated beam's spot on a segment of its image (:func:`lone_segments`); the part
searched is the one within ``lone_floor_reach_px`` of where the floor facing the camera puts
it, because the chance that a scene blob passes the search's tests grows with the length
searched. Each segment is searched as the floor's point is (:func:`.guided.search_along`: no
clutter gate, the lone spot's radius to expect), but with the colour term as measured, and
:func:`.detect.detect_spots` takes the spots found when ``lone_floor_spots`` or more beams hold
one: a scene blob alone rarely has partners on two other beams' segments at the lone spot's
range, a laser's spot does.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.beams import SearchRegion
from sfm_laserscale.detection.candidates import Measure
from sfm_laserscale.detection.floor import floor_radius_px, spot_points_m
from sfm_laserscale.detection.guided import GuidedOptions, search_along
from sfm_laserscale.detection.options import DetectionOptions
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import Rig

F64 = NDArray[np.float64]

#: the steepest floor (degrees from facing the camera) through a lone spot
LONE_TILT_DEG = 40.0
#: the part of a segment searched by default: this many floor-search radii each side of the
#: point where the floor facing the camera puts the spot (15.5 px at 1920 × 1080)
LONE_REACH_RADII = 5.0
#: ranges sampled along a beam's segment, and the vertices kept of its part searched (the
#: image of a beam is nearly straight over tens of pixels; fewer vertices keep the distance
#: map of the search window small)
_SAMPLES = 400
_VERTICES = 16
#: the colour term counts as measured along a segment (the floor's point counts it at least
#: 0.5): tens of pixels of a beam's image hold the scene's own pale blobs
LONE_COLOUR_FLOOR = 0.0
#: names the segment in the reasons
LONE_PLACE = "where a floor through the lone {laser} spot puts it"


def tilted_range_interval(point_m: F64, origin_m: F64, direction: F64,
                          tilt_deg: float = LONE_TILT_DEG) -> tuple[float, float] | None:
    """(least, largest) range (metres along the unit ``direction``) where the beam meets a plane
    through ``point_m`` whose normal lies within ``tilt_deg`` of the optical axis; None when
    none meets it ahead of its origin."""
    tilt = np.radians(np.linspace(0.0, tilt_deg, 9))[:, None]
    azimuth = np.linspace(0.0, 2.0 * np.pi, 36, endpoint=False)[None, :]
    normals = np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth),
                        np.cos(tilt) * np.ones_like(azimuth)], axis=-1).reshape(-1, 3)
    along = normals @ direction
    ok = np.abs(along) > 1e-6
    ranges = (normals[ok] @ (point_m - origin_m)) / along[ok]
    ranges = ranges[ranges > 0]
    return (float(ranges.min()), float(ranges.max())) if len(ranges) else None


def lone_segments(camera: Camera, rig: Rig, region: SearchRegion, name: str,
                  xy: tuple[float, float], options: DetectionOptions) -> dict[str, F64]:
    """Laser -> (K, 2) COLMAP px part of each other calibrated beam's image where a floor
    through laser ``name``'s spot at ``xy`` puts its spot (within the options' ranges, inside
    the image, within the reach of the point where the floor facing the camera puts it)."""
    point = spot_points_m({name: xy}, rig, region).get(name)
    if point is None:
        return {}
    reach = options.lone_floor_reach_px or LONE_REACH_RADII * floor_radius_px(camera, options)
    out = {}
    for las in rig.lasers:
        if las.name == name or las.origin is None or las.direction is None:
            continue
        segment = _segment(camera, point, np.asarray(las.origin, float),
                           np.asarray(las.direction, float), options, reach)
        if segment is not None:
            out[las.name] = segment
    return out


def _segment(camera: Camera, point_m: F64, origin_m: F64, direction: F64,
             options: DetectionOptions, reach_px: float) -> F64 | None:
    """One beam's segment for :func:`lone_segments`, or None (fewer than 2 samples)."""
    interval = tilted_range_interval(point_m, origin_m, direction)
    if interval is None or abs(direction[2]) < 1e-9:
        return None
    lo, hi = max(interval[0], options.min_range_m), min(interval[1], options.max_range_m)
    facing = (point_m[2] - origin_m[2]) / direction[2]  # the floor facing the camera
    if not lo < hi or not lo <= facing <= hi:
        return None
    ranges = np.linspace(lo, hi, _SAMPLES)
    xy = camera.project(origin_m[None] + ranges[:, None] * direction[None])
    centre = camera.project((origin_m + facing * direction)[None])[0]
    inside = (np.all(np.isfinite(xy), axis=1) & (xy[:, 0] >= 0) & (xy[:, 0] <= camera.width)
              & (xy[:, 1] >= 0) & (xy[:, 1] <= camera.height)
              & (np.hypot(*(xy - centre).T) <= reach_px))
    if inside.sum() < 2:
        return None
    kept = xy[inside]
    vertices = np.unique(np.linspace(0, len(kept) - 1, min(len(kept), _VERTICES)).round())
    return np.asarray(kept[vertices.astype(int)], dtype=np.float64)


def lone_floor_search(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig,
                      region: SearchRegion, name: str, lone: Measure,
                      options: DetectionOptions) -> dict[str, tuple[Measure, float]]:
    """Laser -> (candidate, evidence) found on each other beam's segment where a floor through
    the lone spot ``lone`` (laser ``name``) puts its spot (:func:`lone_segments`)."""
    guided = GuidedOptions(radius_px=floor_radius_px(camera, options),
                           colour_floor=LONE_COLOUR_FLOOR)
    place = LONE_PLACE.format(laser=name)
    found = {}
    for laser, segment in lone_segments(camera, rig, region, name, (lone.x, lone.y),
                                        options).items():
        m, score, _ = search_along(image_rgb, camera, rig, laser, segment, options, guided,
                                   place, lone.radius_px)
        if m is not None:
            found[laser] = (m, score)
    return found

