"""A lone spot's floor: where a floor through one spot puts the other beams' spots (closed form on
planes), and the search there (physical frames whose only spot was dropped as alone)."""

from __future__ import annotations

import math
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, detect_spots, lone
from sfm_laserscale.detection.beams import distance_to_polyline, search_region
from sfm_laserscale.detection.floor import default_floor_radius_px
from sfm_laserscale.detection.lone import (
    LONE_PLACE,
    LONE_REACH_RADII,
    LONE_TILT_DEG,
    lone_segments,
    tilted_range_interval,
)
from sfm_laserscale.errors import InputError
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.underwater import CONDITIONS, render_frame
from tests.test_detection_floor import _physical, _rig, _spots
from tests.test_detection_second_look import CAMERA

OFF = DetectionOptions(lone_floor_spots=0)
#: the brightness's DoG, on which the physical frames below were measured; with its ridge-free
#: response (the default) seed 2's ``turbid_brown`` 15 has its three spots on their own
#: evidence, and the laser-free frame a scene blob that scores 0.57 (docs/DETECTION_ROUNDS.md)
ON_DOG = DetectionOptions(ridge_free_brightness=False)


def test_a_beam_parallel_to_the_axis_meets_the_tilted_floors_over_b_tan_tilt() -> None:
    """Closed form: a beam along the optical axis b metres from a point at depth Z meets the
    planes through the point tilted up to θ at Z ± b·tan θ."""
    b, depth = 0.2, 3.0
    lo, hi = tilted_range_interval(np.array([0.0, 0.0, depth]), np.array([b, 0.0, 0.0]),
                                   np.array([0.0, 0.0, 1.0]))
    spread = b * math.tan(math.radians(LONE_TILT_DEG))
    assert lo == pytest.approx(depth - spread) and hi == pytest.approx(depth + spread)
    # a beam pointing away from every such plane meets none ahead of it
    assert tilted_range_interval(np.array([0.0, 0.0, depth]), np.zeros(3),
                                 np.array([0.0, 0.0, -1.0])) is None


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.15, -0.1, 1.0)])
def test_the_other_spots_lie_on_their_segments_within_the_reach(
        normal: tuple[float, float, float]) -> None:
    """A floor (facing the camera, or tilted 10°) through L1's spot: each other laser's true
    spot lies on its segment, and each segment stays within the reach of its centre."""
    rig, options = _rig(), DetectionOptions()
    truth = _spots(normal, 2.5)
    region = search_region(CAMERA, rig, options)
    segments = lone_segments(CAMERA, rig, region, "L1", truth["L1"], options)
    assert set(segments) == {"L2", "L3", "L4"}
    reach = LONE_REACH_RADII * default_floor_radius_px(CAMERA.width, CAMERA.height)
    for name, segment in segments.items():
        assert distance_to_polyline(np.array([truth[name]]), segment)[0] < 0.1
        assert math.dist(segment[0], segment[-1]) <= 2 * reach + 1e-6


def test_a_lone_spots_floor_finds_the_others() -> None:
    """Physical frame (seed 2, ``turbid_brown`` 15): L1's spot (score 0.42) is the only one
    taken on its own evidence, and it was dropped as alone in its image, with the frame's other
    spots missed. Where a floor through it puts L3 and L4 (segments 22–26 px long) they are
    found (evidence 0.84 and 0.70), and all three are taken."""
    frame, camera, rig, _ = _physical(2, "turbid_brown", 15, "L1")
    before = detect_spots(frame.image_rgb, camera, rig, replace(ON_DOG, lone_floor_spots=0))
    assert before.spots == () and "alone in its image" in before.missing["L1"]
    res = detect_spots(frame.image_rgb, camera, rig, ON_DOG)
    got = {s.laser: s for s in res.spots}
    assert set(got) >= {"L1", "L3", "L4"}, res.missing
    for name, spot in got.items():
        truth = frame.truth[name]
        assert truth is not None and math.dist((spot.x, spot.y), truth) < 0.5
    place = LONE_PLACE.format(laser="L1")
    reasons = {c.laser: c.reason for c in res.candidates if c.laser}
    assert place in reasons["L3"] and place in reasons["L4"]


def test_a_lone_spot_whose_floor_holds_too_few_says_so() -> None:
    """Physical frame (seed 4, ``blue_beams`` 5): L2's lone spot is dropped, and its reason
    says how many spots a floor through it held."""
    frame, camera, rig, _ = _physical(4, "blue_beams", 5, "L2")
    res = detect_spots(frame.image_rgb, camera, rig)
    assert res.spots == ()
    assert ("alone in its image" in res.missing["L2"]
            and "a floor through it, tilted up to 40°, holds 0 of the 2 other lasers' spots it "
                "needs" in res.missing["L2"])
    assert "holds" not in detect_spots(frame.image_rgb, camera, rig, OFF).missing["L2"]


def test_the_lone_floor_options_are_checked() -> None:
    with pytest.raises(InputError, match="lone_floor_spots"):
        DetectionOptions(lone_floor_spots=-1)
    with pytest.raises(InputError, match="lone_floor_reach_px"):
        DetectionOptions(lone_floor_reach_px=0.0)


def test_a_laser_free_frame_takes_no_scene_blobs_along_the_segments(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Physical laser-free frame (the 4000 × 3000 table's ``no_lasers`` 14): a scene blob is
    taken as a lone spot (score 0.48) and dropped. With the colour term counted at least 0.5
    along the segments, as at the floor's point, three scene-coloured blobs (colour 0.02–0.04)
    would stand with it; counted as measured, one passes, too few."""
    ci = list(CONDITIONS).index("no_lasers")
    frame = render_frame("no_lasers", 4000, 3000, np.random.default_rng([0, ci, 1, 14]))
    camera, rig = parse_camera(frame.camera_spec), rig_from_dict(tomllib.loads(frame.rig_toml))
    res = detect_spots(frame.image_rgb, camera, rig, ON_DOG)
    assert res.spots == () and "holds 1 of the 2" in res.missing["L1"]
    monkeypatch.setattr(lone, "LONE_COLOUR_FLOOR", 0.5)
    assert len(detect_spots(frame.image_rgb, camera, rig, ON_DOG).spots) == 4
