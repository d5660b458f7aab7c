"""Chosen spots whose centre wandered off the maximum they were measured from.

A candidate is a local maximum of a blob response (:mod:`.candidates`), whose centre is then
refined by a centroid in a window of its measured half-maximum radius (:mod:`.refine`,
:mod:`.centre`). Where the spot's surroundings are not flat (a pale patch, a lit slope, green
water near full scale, a beam's glow, a particle beside it), that window can centre them,
pixels off the maximum that was the spot. Two steps put such a spot back:

- **A wide spot, at the other spots' radius** (:func:`narrow_wide_spots`). The spots of one
  scaler on one floor are footprints of like beams at like ranges, so their half-maximum
  radii are alike; a maximum on bright surroundings can measure a half-maximum region that
  runs into them (10-20 px for a 2 px spot). The candidate search cannot know the spots'
  radius; once three spots or more are chosen it can. A chosen spot
  ``options.wide_maximum_ratio`` times the other chosen spots' median radius wide or more
  (NARROW_OTHER_SPOTS of them at least) whose centre lies beyond max(2 px, that radius) of
  its maximum is refined again at that maximum with the others' radius for its window, as
  the floor search does (:mod:`.candidates`), and takes that centre, radius and σ where the
  refinement holds (a finite centre within max(2 px, the radius) of the maximum). A wide spot
  centred near its maximum keeps its centre: there the wide window read the spot, and a
  narrower one can follow the scene beside it.
- **A brightness maximum, at its sub-pixel peak** (:func:`back_to_peak`). A spot found on
  the brightness response (a clipped core, a green laser's spot) whose reported centre lies
  beyond max(``options.peak_apart_px``, PEAK_APART_RADII half-maximum radii) of its maximum
  takes that maximum's sub-pixel position: the response's peak, interpolated by a parabola
  through it and its neighbours along each axis (:func:`.refine.subpixel_peak`). The brightness
  response is a band-pass curvature at the spot's own scales, which the surroundings' slope
  and a neighbour's flank move far less than a centroid. Its σ gains (disagreement_gain ·
  d)², d the distance between the two (:class:`~.options.SigmaModel`). Spots of the colour
  response keep their centre: a clipped core's colour peaks on its halo beside the core, and
  a streaked or glowing spot's response peak lies anywhere along it, where the centroid reads
  the spot. So do elongated spots (roundness below PEAK_MIN_ROUNDNESS: a streak of motion
  blur is flat along itself, and its response peaks anywhere along it) and spots the floor
  search took (:mod:`.floor`): near a predicted point it takes a maximum beside the spot and
  refines it onto the spot at the other spots' radius.

Measured in docs/DETECTION_ROUNDS.md (the forty-fifth round).
"""

from __future__ import annotations

import logging
import math
import statistics
from collections.abc import Mapping
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.candidates import (
    PEAK_MIN_ROUNDNESS,
    Measure,
    refine_within,
    source_blobs,
)
from sfm_laserscale.detection.centre import local_planes
from sfm_laserscale.detection.inputs import group_rgb
from sfm_laserscale.detection.options import TAKEN_ON_FLOOR, DetectionOptions
from sfm_laserscale.detection.refine import subpixel_peak
from sfm_laserscale.detection.response import brightness, crop_channels
from sfm_laserscale.detection.shape import expected_support_px
from sfm_laserscale.rig import Rig

logger = logging.getLogger(__name__)

F32 = NDArray[np.float32]
#: how many other chosen spots give the radius a wide spot is measured again at
NARROW_OTHER_SPOTS = 2
#: a brightness maximum's spot centred farther than ``options.peak_apart_px`` from it, and
#: than this share of its half-maximum radius, takes its sub-pixel peak
PEAK_APART_RADII = 0.5
#: what the reason of a spot measured again adds
NARROWED = ("; measured again at its maximum ({x:.1f}, {y:.1f}) at the other spots' radius "
            "{radius:.1f} px (its own, {wide:.1f} px, ran into its surroundings)")
AT_PEAK = ("; centred at its brightness maximum's sub-pixel peak: its window's centre lay "
           "{apart:.1f} px from it")


def others_radius(valid: list[Measure], chosen: Mapping[str, int], name: str) -> float | None:
    """Median half-max radius (px) of the chosen spots other than ``name``'s, or None with
    fewer than NARROW_OTHER_SPOTS of them."""
    radii = [valid[j].radius_px for other, j in chosen.items() if other != name]
    return statistics.median(radii) if len(radii) >= NARROW_OTHER_SPOTS else None


def _apart(m: Measure) -> float:
    """Distance (px) from a spot's centre to the maximum it was measured from."""
    return math.hypot(m.x - m.peak[0], m.y - m.peak[1])


def _wide_and_wandered(m: Measure, ratio: float, radius: float) -> bool:
    """Whether ``m`` is ``ratio`` × ``radius`` wide or more and centred beyond max(2 px,
    ``radius``) of its maximum."""
    return m.radius_px >= ratio * radius and _apart(m) > max(2.0, radius)


def narrow_wide_spots(image_rgb: NDArray[np.uint8], rig: Rig, valid: list[Measure],
                      chosen: Mapping[str, int], options: DetectionOptions,
                      max_radius: float) -> list[str]:
    """In place (``valid``): each chosen spot ``options.wide_maximum_ratio`` × the other
    chosen spots' median radius wide or more and centred beyond max(2 px, that radius) of its
    maximum, refined again at its maximum at that radius (``max_radius``: the largest spot
    radius, px); returns the lasers whose spot took it."""
    ratio = options.wide_maximum_ratio
    wide = {}
    for name, j in chosen.items():
        radius = others_radius(valid, chosen, name)
        if ratio > 0 and radius is not None and _wide_and_wandered(valid[j], ratio, radius):
            wide[name] = radius
    moved = []
    for name, radius in wide.items():
        m = valid[chosen[name]]
        probe = replace(m, x=m.peak[0], y=m.peak[1], radius_px=radius,
                        support_px=expected_support_px(radius))
        centre = narrow_centre(image_rgb, probe, group_rgb(rig, m.color), options, max_radius)
        if centre is None:
            logger.debug("%s: refinement at its maximum failed, wide spot kept", name)
            continue
        m.reason += NARROWED.format(x=m.peak[0], y=m.peak[1], radius=radius, wide=m.radius_px)
        m.x, m.y, m.sigma_px = centre
        m.radius_px, m.support_px = probe.radius_px, probe.support_px
        moved.append(name)
    return moved


def narrow_centre(image_rgb: NDArray[np.uint8], probe: Measure,
                  laser_rgb: tuple[float, float, float], options: DetectionOptions,
                  max_radius: float) -> tuple[float, float, float] | None:
    """(x, y, σ) (image COLMAP px) of ``probe`` refined at its own position and radius, or
    None when the refinement gives no finite centre within max(2, radius) px of it."""
    planes, guess, x0, y0 = local_planes(image_rgb, probe, laser_rgb, options, max_radius)
    centre = refine_within(planes, guess, options)
    return None if centre is None else (centre[0] + x0, centre[1] + y0, centre[2])


def back_to_peak(image_rgb: NDArray[np.uint8], valid: list[Measure],
                 chosen: Mapping[str, int], options: DetectionOptions) -> list[str]:
    """In place (``valid``): each round chosen spot of a brightness maximum (not one the floor
    search took) centred beyond max(``options.peak_apart_px``, PEAK_APART_RADII radii) of it
    takes the maximum's sub-pixel peak (image COLMAP px); returns the lasers whose spot took
    it."""
    moved: list[str] = []
    if options.peak_apart_px <= 0:
        return moved
    for name, j in chosen.items():
        m = valid[j]
        apart = _apart(m)
        if (m.source != "bright" or m.taken_by == TAKEN_ON_FLOOR or not math.isfinite(apart)
                or m.roundness < PEAK_MIN_ROUNDNESS
                or apart <= max(options.peak_apart_px, PEAK_APART_RADII * m.radius_px)):
            continue
        response, corner = _brightness_blobs(image_rgb, m.peak, options)
        peak = subpixel_peak(response, corner, m.peak)
        if peak is None:
            logger.debug("%s: no sub-pixel peak at its maximum, centre kept", name)
            continue
        m.reason += AT_PEAK.format(apart=apart)
        m.sigma_px = math.hypot(m.sigma_px, options.sigma_model.disagreement_gain
                                * math.hypot(peak[0] - m.x, peak[1] - m.y))
        m.x, m.y = peak
        moved.append(name)
    return moved


def _brightness_blobs(image_rgb: NDArray[np.uint8], peak: tuple[float, float],
                      options: DetectionOptions) -> tuple[F32, tuple[int, int]]:
    """The brightness blob response (as the candidate search computes it) of a crop around
    ``peak`` (image COLMAP px), and the crop's corner (x0, y0)."""
    reach = int(math.ceil(4.0 * max(options.spot_sigmas_px))) + 8
    height, width = image_rgb.shape[:2]
    col, row = int(math.floor(peak[0])), int(math.floor(peak[1]))
    roi = (max(0, col - reach), max(0, row - reach), min(width, col + reach + 1),
           min(height, row + reach + 1))
    plane = brightness(crop_channels(image_rgb, roi, options.input_gamma))
    return source_blobs("bright", plane, options), (roi[0], roi[1])
