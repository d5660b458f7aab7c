"""A maximum near the floor's point whose half-maximum region runs into its surroundings, and
whose centroid window that wide wanders off it, is refined at the image's other spots' radius
(``DetectionOptions.wide_maximum_ratio``; physical frames the rule was not written on)."""

from __future__ import annotations

import math

import pytest

from sfm_laserscale.detection import DetectionOptions, detect_spots
from sfm_laserscale.detection.floor import PLACE
from sfm_laserscale.errors import InputError
from tests.test_detection_floor import _physical

OFF = DetectionOptions(wide_maximum_ratio=0.0)


def test_a_spot_beside_a_wide_patch_is_centred_at_the_other_spots_radius() -> None:
    """Seed 7, ``red_blue_water`` 12, L1: a red spot 1.4 × white 0.6 px from the floor's point.
    Its maximum's half-maximum region (25 px) takes in a red patch, and a window that wide
    centres 10 px off; without the rule the spot was missed ("no local maximum of its light"
    near the floor's point). At the other spots' radius it is centred within 0.2 px."""
    frame, camera, rig, truth = _physical(7, "red_blue_water", 12, "L1")
    before = detect_spots(frame.image_rgb, camera, rig, OFF)
    assert "L1" not in {s.laser for s in before.spots}
    assert PLACE in before.missing["L1"]
    res = detect_spots(frame.image_rgb, camera, rig)
    got = {s.laser: s for s in res.spots}
    assert "L1" in got, res.missing.get("L1")
    assert math.dist((got["L1"].x, got["L1"].y), truth) < 0.2
    assert PLACE in next(c.reason for c in res.candidates if c.laser == "L1")
    assert {s.laser: (s.x, s.y) for s in res.spots if s.laser != "L1"} == {
        s.laser: (s.x, s.y) for s in before.spots}


def test_a_bright_green_water_frame_keeps_all_its_spots() -> None:
    """Seed 5, ``green_water`` 15: a green core in water near full scale measured 5.2 px wide
    and centred 4.1 px off its maximum; refined at the other spots' radius it is found, and with
    it the frame's other spots, which its floor then holds (none was reported before)."""
    frame, camera, rig, _ = _physical(5, "green_water", 15, "L1")
    assert detect_spots(frame.image_rgb, camera, rig, OFF).spots == ()
    res = detect_spots(frame.image_rgb, camera, rig)
    for spot in res.spots:
        truth = frame.truth[spot.laser]
        assert truth is not None and math.dist((spot.x, spot.y), truth) < 0.5
    assert {s.laser for s in res.spots} == {"L1", "L2", "L3", "L4"}, res.missing


def test_the_wide_maximum_ratio_is_checked() -> None:
    """0 switches the rule off; a ratio below 1 would refine a maximum narrower than the spots."""
    for bad in (0.5, -1.0):
        with pytest.raises(InputError, match="wide_maximum_ratio"):
            DetectionOptions(wide_maximum_ratio=bad)
    assert OFF.wide_maximum_ratio == 0.0
