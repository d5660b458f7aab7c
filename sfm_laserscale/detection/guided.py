"""A laser's spot searched where the model predicts it: a few pixels around one image point.

Once the model's scale is known from the spots found on their own evidence, the registered
pose, the mesh and the calibrated beam tell where every other laser's spot must be (the
prediction is made by :mod:`sfm_laserscale.guided_spots`). A band 10-20 px wide and hundreds
long holds the scene's own blobs — pale clutter, glints, texture as strong as a faint spot —
so :func:`.detect.detect_spots` holds maxima below the scene's clutter level back and weighs
every candidate against the rest of its band. Within ``radius_px`` of the predicted point
that competition is gone: a scene blob is no more likely there than at any other few pixels,
where the spot is certain to be if the laser lit the floor.

:func:`detect_near` measures the local maxima of the laser's responses in a small window with
the detector's own code (shape, sub-pixel centre, σ, colour), with no clutter gate and no
clutter term, listing them from ``maxima_sigmas`` robust σ of the window's DoG (the window's
spread is its scene's, not noise: a lamp's hot spot, clutter), and takes the best candidate
within ``radius_px`` of the prediction whose evidence (contrast × roundness × colour)
reaches ``min_score``. Colour counts at least ``colour_floor`` (0.5: a green spot in green
water adds light of the scene's own colour); a clipped core whose colour reads whitened
(:mod:`.joint`) takes colour term 1 there, as it does at the other spots' range.
Every hard test of the detector still applies (too large, not compact, SNR below ``min_snr``,
refinement failed). Given the radius of the image's other spots (the floor search), a maximum
that fails the shape tests against the far background is measured against its own
surroundings at that radius, and one whose refinement fails is refined again at it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.beams import (
    SearchRegion,
    default_max_spot_radius_px,
    distance_to_polyline,
)
from sfm_laserscale.detection.candidates import Measure, candidates_for_colour
from sfm_laserscale.detection.centre import centre_chosen
from sfm_laserscale.detection.inputs import check_image, group_rgb
from sfm_laserscale.detection.joint import CLIPPED_COLOUR
from sfm_laserscale.detection.options import DetectionOptions
from sfm_laserscale.detection.response import CHANNELS, crop_channels
from sfm_laserscale.detection.score import below
from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, Spot
from sfm_laserscale.rig import Rig

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GuidedOptions:
    """Options of :func:`detect_near`.

    - ``radius_px``: largest distance (px) of a spot from its predicted point.
    - ``min_score``: least evidence (contrast × roundness × colour, each 0–1) of a spot.
    - ``min_snr``: the weak-spot test's SNR (None: the detector's ``min_snr``).
    - ``colour_floor``: the colour term never counts below this: a green spot in green water
      adds light of the scene's own colour (colour term ~0.05 on the spot itself), and near its
      predicted point its position is the stronger evidence (docs/DETECTION.md).
    - ``maxima_sigmas``: local maxima are listed from this many robust σ of their response's
      DoG over the search's crop (the detector lists its bands' from 4). The crop's spread
      is its scene's (a lamp's hot spot, clutter), not noise; near the point the weak-spot
      test decides (docs/DETECTION_ROUNDS.md, the twenty-sixth round).
    """

    radius_px: float = 3.0
    min_score: float = 0.25
    min_snr: float | None = None
    colour_floor: float = 0.5
    maxima_sigmas: float = 2.0

    def __post_init__(self) -> None:
        if not self.radius_px > 0:
            raise InputError(f"guided radius_px must be positive, got {self.radius_px}")
        if not self.maxima_sigmas > 0:
            raise InputError(f"guided maxima_sigmas must be positive, got {self.maxima_sigmas}")
        for name in ("min_score", "colour_floor"):
            if not 0 <= getattr(self, name) <= 1:
                raise InputError(f"guided {name} must be in [0, 1], got {getattr(self, name)}")


@dataclass(frozen=True)
class GuidedResult:
    """Spots found near their predictions (``source`` "guided") and, for every other laser
    searched, why not."""

    spots: tuple[Spot, ...]
    missing: dict[str, str]


def _window(camera: Camera, where: F64, reach: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) array-index window ``reach`` px beyond the (K, 2) COLMAP points'
    bounding box."""
    lo, hi = np.floor(where.min(axis=0)).astype(int), np.floor(where.max(axis=0)).astype(int)
    return (max(0, int(lo[0]) - reach), max(0, int(lo[1]) - reach),
            min(camera.width, int(hi[0]) + reach + 1), min(camera.height, int(hi[1]) + reach + 1))


def _max_radius(camera: Camera, options: DetectionOptions) -> float:
    """The largest half-maximum radius (px) of a spot in this camera's images."""
    return options.max_spot_radius_px or default_max_spot_radius_px(camera.width, camera.height)


def _region(camera: Camera, where: F64, radius: float, max_radius: float,
            options: DetectionOptions, spot_radius_px: float | None) -> SearchRegion:
    """The image searched around a point or segment ((K, 2) COLMAP px): maxima within
    ``radius`` (+1 px) of it."""
    reach = int(math.ceil(radius + 2.0 * max_radius + 4.0 * max(options.spot_sigmas_px) + 8.0))
    roi = _window(camera, where, reach)
    x0, y0, x1, y1 = roi
    cols, rows = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
    pixels = np.stack([cols.ravel(), rows.ravel()], axis=1)
    near = distance_to_polyline(pixels, where).reshape(cols.shape) <= radius + 1.0
    return SearchRegion(roi, {}, {}, near, radius, max_radius, spot_radius_px)


def evidence_terms(m: Measure, colour_floor: float) -> dict[str, float]:
    """A candidate's evidence terms without the clutter term, its colour term at least
    ``colour_floor`` (whitened clipped cores: colour 1)."""
    terms = {k: v for k, v in m.terms.items() if k != "clutter"}
    if not terms:
        return {}
    return terms | {"colour": CLIPPED_COLOUR if m.whitened else max(m.colour.term, colour_floor)}


def evidence(m: Measure, colour_floor: float) -> float:
    """The product of :func:`evidence_terms` (0 without terms)."""
    terms = evidence_terms(m, colour_floor)
    return float(np.prod(list(terms.values()))) if terms else 0.0


MODEL_PLACE = "where the model puts its spot"


def _best(measures: list[Measure], where: F64, guided: GuidedOptions, place: str
          ) -> tuple[Measure | None, str]:
    """The highest-evidence valid candidate within ``guided.radius_px`` of the point or segment
    ``where`` ((K, 2) COLMAP px), or why there is none (``place`` names it, e.g. "where the
    model puts its spot")."""
    radius = guided.radius_px
    dist = distance_to_polyline(np.array([[m.x, m.y] for m in measures]).reshape(-1, 2), where)
    near = [(d, m) for d, m in zip(dist, measures, strict=True) if d <= radius]
    valid = [m for _, m in near if m.rejected is None]
    if valid:
        return max(valid, key=lambda m: evidence(m, guided.colour_floor)), ""
    if not near:
        return None, (f"no local maximum of its light within {radius:.1f} px of "
                      f"{_named(where)}, {place}")
    closest = min(near, key=lambda dm: dm[0])[1]
    return None, (f"the maximum at ({closest.x:.1f}, {closest.y:.1f}), near {place}, is "
                  f"{closest.rejected}")


def _named(where: F64) -> str:
    """A point, or a segment by its ends, in words (COLMAP px)."""
    ends = [f"({x:.1f}, {y:.1f})" for x, y in (where[0], where[-1])]
    return ends[0] if len(where) == 1 else f"the segment from {ends[0]} to {ends[1]}"


def search_near(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig, laser: str,
                xy: tuple[float, float], options: DetectionOptions, guided: GuidedOptions,
                place: str = MODEL_PLACE, spot_radius_px: float | None = None
                ) -> tuple[Measure | None, float, str]:
    """The candidate taken for ``laser`` within ``guided.radius_px`` of the COLMAP point ``xy``
    and its evidence, or (None, 0, why not); ``place`` names the point in the reasons,
    ``spot_radius_px`` the half-max radius of the image's other spots when known (a maximum
    whose refinement fails at its own radius is refined again at it, :mod:`.candidates`)."""
    if not (0 <= xy[0] <= camera.width and 0 <= xy[1] <= camera.height):
        return None, 0.0, f"({xy[0]:.1f}, {xy[1]:.1f}), {place}, is outside the image"
    return search_along(image_rgb, camera, rig, laser, np.array([xy], dtype=np.float64),
                        options, guided, place, spot_radius_px)


def search_along(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig, laser: str,
                 where: F64, options: DetectionOptions, guided: GuidedOptions, place: str,
                 spot_radius_px: float | None = None) -> tuple[Measure | None, float, str]:
    """As :func:`search_near`, within ``guided.radius_px`` of a point or segment ``where``
    ((K, 2) COLMAP px inside the image)."""
    las = rig.laser(laser)
    max_radius = _max_radius(camera, options)
    region = _region(camera, where, guided.radius_px, max_radius, options, spot_radius_px)
    ungated = replace(options, min_clutter_ratio=0.0, second_look_clutter_ratio=0.0,
                      min_snr=options.min_snr if guided.min_snr is None else guided.min_snr)
    channels = crop_channels(image_rgb, region.roi, options.input_gamma)
    colours = list(CHANNELS) if las.color == "any" else [las.color]
    measures = [m for c in colours
                for m in candidates_for_colour(channels, c, ungated, region, group_rgb(rig, c),
                                               guided.maxima_sigmas)]
    best, why = _best(measures, where, guided, place)
    if best is None:
        return None, 0.0, why
    score = evidence(best, guided.colour_floor)
    if score < guided.min_score:
        return None, 0.0, (f"the best candidate near {place}, at ({best.x:.1f}, {best.y:.1f}), "
                           f"scores {below(score, guided.min_score)} < {guided.min_score:g}")
    best.evidence = evidence_terms(best, guided.colour_floor)
    return best, score, ""


def detect_near_one(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig, laser: str,
                    xy: tuple[float, float], options: DetectionOptions,
                    guided: GuidedOptions) -> tuple[Spot | None, str]:
    """One laser's spot within ``guided.radius_px`` of the COLMAP point ``xy``, or why not."""
    best, score, why = search_near(image_rgb, camera, rig, laser, xy, options, guided)
    if best is None:
        return None, why
    centre_chosen(image_rgb, best, group_rgb(rig, best.color), options,
                  _max_radius(camera, options))
    return Spot(laser=laser, x=best.x, y=best.y, score=float(min(score, 1.0)),
                sigma_px=best.sigma_px, source="guided"), ""


def detect_near(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig,
                predicted: Mapping[str, tuple[float, float]],
                options: DetectionOptions = DetectionOptions(),  # noqa: B008
                guided: GuidedOptions = GuidedOptions()) -> GuidedResult:  # noqa: B008
    """Each laser's spot near its predicted point (laser -> COLMAP (x, y)), or why not."""
    check_image(image_rgb, camera)
    spots, missing = [], {}
    for laser, xy in predicted.items():
        spot, why = detect_near_one(image_rgb, camera, rig, laser, (float(xy[0]), float(xy[1])),
                                    options, guided)
        if spot is None:
            missing[laser] = why
        else:
            spots.append(spot)
    return GuidedResult(tuple(spots), missing)
