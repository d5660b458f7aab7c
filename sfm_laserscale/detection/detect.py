"""Laser spots in one image: sub-pixel centres (COLMAP pixel convention) assigned to lasers.

:func:`detect_spots` chains the stages of this package: where to look (:mod:`.beams`), the
responses (:mod:`.response`), candidates measured, refined and scored (:mod:`.candidates`,
:mod:`.shape`, :mod:`.refine`, :mod:`.score`), the assignment to lasers (:mod:`.assign`) and
the reasons for lasers without a spot (:mod:`.explain`). Every candidate is returned with what
became of it.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.assign import (
    assign_calibrated,
    assign_uncalibrated,
    explain_unused,
    second_look,
)
from sfm_laserscale.detection.beams import SearchRegion, search_region
from sfm_laserscale.detection.candidates import Measure, candidates_for_colour
from sfm_laserscale.detection.explain import explain_missing
from sfm_laserscale.detection.options import Candidate, DetectionOptions, DetectionResult
from sfm_laserscale.detection.response import CHANNELS, crop_channels
from sfm_laserscale.errors import InputError
from sfm_laserscale.laser_color import DEFAULT_RGB
from sfm_laserscale.memory import trim_heap
from sfm_laserscale.model import Camera, Spot
from sfm_laserscale.rig import Rig

logger = logging.getLogger(__name__)


def check_image(image_rgb: NDArray[np.uint8], camera: Camera) -> None:
    """Validate the image against its camera (shape, size, dtype)."""
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
        raise InputError(f"laser image must be RGB (H, W, 3), got shape {image_rgb.shape}")
    if image_rgb.shape[:2] != (camera.height, camera.width):
        raise InputError(
            f"laser image is {image_rgb.shape[1]}x{image_rgb.shape[0]} px but its camera is "
            f"{camera.width}x{camera.height} px")
    if image_rgb.dtype != np.uint8:
        raise InputError(f"laser image must be 8-bit (uint8), got {image_rgb.dtype}")


def colours_needed(rig: Rig) -> list[str]:
    """Laser channels to search, in channel order ("any" needs all three)."""
    wanted = {las.color for las in rig.lasers}
    if "any" in wanted:
        return list(CHANNELS)
    return [c for c in CHANNELS if c in wanted]


def group_rgb(rig: Rig, color: str) -> tuple[float, float, float]:
    """Expected colour of a channel's lasers: the mean of theirs, or the channel's default."""
    rgbs = [las.expected_rgb for las in rig.lasers if las.color == color and las.expected_rgb]
    if not rgbs:
        return DEFAULT_RGB[color]
    mean = np.mean(np.asarray(rgbs), axis=0)
    return (float(mean[0]), float(mean[1]), float(mean[2]))


def _measure_candidates(image_rgb: NDArray[np.uint8], rig: Rig, region: SearchRegion,
                        options: DetectionOptions) -> list[Measure]:
    """Every candidate spot of every colour the rig needs, within the search region."""
    measures: list[Measure] = []
    x0, y0, x1, y1 = region.roi
    if x1 > x0 and y1 > y0:
        channels = crop_channels(image_rgb, region.roi, options.input_gamma)
        for color in colours_needed(rig):
            measures += candidates_for_colour(channels, color, options, region,
                                              group_rgb(rig, color))
    return measures


def _candidate(m: Measure) -> Candidate:
    return Candidate(x=m.x, y=m.y, color=m.color, response=m.response, snr=m.snr,
                     radius_px=m.radius_px, roundness=m.roundness,
                     score=0.0 if m.rejected else float(m.score), laser=m.laser,
                     reason=m.rejected or m.reason, source=m.source,
                     evidence=tuple(m.evidence.items()), clutter_ratio=m.clutter_ratio)


def detect_spots(
    image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig,
    options: DetectionOptions = DetectionOptions(),  # noqa: B008 (frozen dataclass)
) -> DetectionResult:
    """Detect laser spots in one image and assign them to the rig's lasers."""
    check_image(image_rgb, camera)
    region = search_region(camera, rig, options)
    measures = _measure_candidates(image_rgb, rig, region, options)
    trim_heap()  # the detection planes (~16 bytes per pixel) go back to the OS
    valid = [m for m in measures if m.rejected is None]
    chosen, missing, dist = assign_calibrated(rig, region, valid, options)
    for name, k in second_look(rig, region, measures, valid, chosen, options).items():
        chosen[name] = k  # appended to valid: dist keeps the first choice's columns
        missing.pop(name, None)
    chosen_u, missing_u = assign_uncalibrated(rig, valid, set(chosen.values()), options)
    chosen.update(chosen_u)
    missing.update(missing_u)
    explain_unused(rig, valid, dist, region.band_px, options)
    shown = explain_missing(rig, measures, region, set(chosen), missing, options)
    spots = tuple(
        Spot(laser=name, x=valid[j].x, y=valid[j].y, score=float(np.clip(valid[j].score, 0, 1)),
             sigma_px=valid[j].sigma_px, source="detected")
        for name in rig.names if (j := chosen.get(name)) is not None
    )
    candidates = tuple(_candidate(m) for m in measures)
    index = {id(m): i for i, m in enumerate(measures)}
    near = {name: tuple(candidates[index[id(m)]] for m in ms) for name, ms in shown.items()}
    logger.debug("%d candidates, %d spots, missing: %s", len(candidates), len(spots), missing)
    return DetectionResult(spots=spots, candidates=candidates, missing=missing, near_misses=near)
