"""A whitened clipped core near the floor's point: with three spots chosen, a laser still
without one takes the whitened core nearest where the floor through them puts its spot, within
WHITENED_FLOOR_REACH floor search radii of that point and WHITENED_FLOOR_BEAM band_px of its
beam's image, when it scores min_score with its clutter term waived and colour CLIPPED_COLOUR."""

from __future__ import annotations

import math
import tomllib
from dataclasses import replace

import numpy as np
import pytest

import sfm_laserscale.detection.assign as assign
import sfm_laserscale.detection.detect as detect_module
from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, DetectionResult, detect_spots
from sfm_laserscale.detection.floor import default_floor_radius_px
from sfm_laserscale.detection.joint import CLIPPED_COLOUR
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.underwater import CONDITIONS, Frame, render_frame


def _frame(seed: int, condition: str, index: int) -> Frame:
    ci = list(CONDITIONS).index(condition)
    return render_frame(condition, 1920, 1080, np.random.default_rng([seed, ci, 0, index]))


@pytest.fixture(scope="module", params=[(2, "strobe_hotspots", 16, "L4"),
                                        (3, "blue_beams", 13, "L1")])
def case(request: pytest.FixtureRequest) -> tuple[Frame, str]:
    """Physical frames (independent generator) whose spot is a clipped core read white, lying
    3.2 and 4.0 px from the floor's point (beyond the floor search's 3.1 px) and 0.20-0.23
    band_px from its beam's image (beyond the second look's 0.1); the other three are found
    (measured on the brightness's DoG: with its ridge-free response seed 3's ``blue_beams`` 13
    keeps its other three spots, but its whitened core is no longer a maximum of its own)."""
    seed, condition, index, name = request.param
    return _frame(seed, condition, index), name


ON_DOG = DetectionOptions(ridge_free_brightness=False)


def _detect(frame: Frame, options: DetectionOptions = ON_DOG) -> DetectionResult:
    return detect_spots(frame.image_rgb, parse_camera(frame.camera_spec),
                        rig_from_dict(tomllib.loads(frame.rig_toml)), options)


def test_a_whitened_core_near_the_floors_point_is_taken(case: tuple[Frame, str]) -> None:
    frame, name = case
    truth = frame.truth[name]
    assert truth is not None
    res = _detect(frame)
    got = {s.laser: s for s in res.spots}
    assert len(got) == 4
    assert math.dist((got[name].x, got[name].y), truth) < 0.6
    taken = next(c for c in res.candidates if c.laser == name)
    assert "px from where the floor through the other lasers' spots puts it" in taken.reason
    assert dict(taken.evidence)["colour"] == CLIPPED_COLOUR
    assert dict(taken.evidence)["clutter"] == 1.0


@pytest.mark.parametrize(("module", "constant", "value"), [
    (detect_module, "WHITENED_FLOOR_REACH", 2.5 / default_floor_radius_px(1920, 1080)),
    (detect_module, "WHITENED_FLOOR_SPOTS", 4),
    (assign, "WHITENED_FLOOR_BEAM", 0.15),
])
def test_each_limit_of_the_rule_holds(case: tuple[Frame, str], module: object, constant: str,
                                      value: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """Closer than 2.5 px to the floor's point, on a floor of four spots, or within 0.15
    band_px of its beam's image, the same core is not taken and the laser is explained."""
    frame, name = case
    monkeypatch.setattr(module, constant, value)
    res = _detect(frame)
    assert name not in {s.laser for s in res.spots}
    assert name in res.missing


def test_no_core_is_taken_without_a_floor_search(case: tuple[Frame, str]) -> None:
    frame, _ = case
    res = _detect(frame, replace(ON_DOG, floor_search=False))
    assert not any("from where the floor" in c.reason for c in res.candidates)
