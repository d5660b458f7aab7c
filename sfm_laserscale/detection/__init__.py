"""Laser spot detection: sub-pixel spot centres in an image, assigned to the rig's lasers.

The stages, in data-flow order: :mod:`.beams` (where to look), :mod:`.response` (colour and
brightness responses), :mod:`.candidates` with :mod:`.shape`, :mod:`.refine` and :mod:`.score`
(candidates measured, refined, scored), :mod:`.assign` (spots to lasers) and :mod:`.explain`
(why a laser has no spot); :mod:`.detect` chains them, first removing the texture of a scene
reference when one is given (:mod:`.scene`). docs/DETECTION.md has the benchmark.
"""

from sfm_laserscale.detection.assign import UNCALIBRATED_REASON
from sfm_laserscale.detection.beams import (
    beam_polyline_px,
    default_band_px,
    default_max_spot_radius_px,
    distance_to_polyline,
)
from sfm_laserscale.detection.detect import detect_spots
from sfm_laserscale.detection.options import Candidate, DetectionOptions, DetectionResult
from sfm_laserscale.detection.response import CHANNELS, blob_response, clutter_level

__all__ = [
    "CHANNELS",
    "UNCALIBRATED_REASON",
    "Candidate",
    "DetectionOptions",
    "DetectionResult",
    "beam_polyline_px",
    "blob_response",
    "clutter_level",
    "default_band_px",
    "default_max_spot_radius_px",
    "detect_spots",
    "distance_to_polyline",
]
