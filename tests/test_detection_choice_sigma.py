"""The σ term of the rule that took a spot: the floor search and the second look take a maximum
beside the spot more often than the first pass, and a spot's σ says so."""

from __future__ import annotations

import math
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, detect_spots
from sfm_laserscale.detection.floor import floor_radius_px
from sfm_laserscale.detection.options import (
    FLOOR_CHOICE,
    SECOND_LOOK_CHOICE,
    TAKEN_ON_FLOOR,
    TAKEN_ON_OWN,
    TAKEN_ON_SECOND_LOOK,
    SigmaModel,
)
from sfm_laserscale.errors import InputError
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.underwater import CONDITIONS, render_frame

NO_CHOICE = DetectionOptions(sigma_floor_choice=0.0, sigma_second_look_choice=0.0)


def test_the_term_is_the_rules_share_of_the_floor_search_radius() -> None:
    model = SigmaModel(floor_choice=0.2, second_look_choice=0.5)
    assert model.choice(TAKEN_ON_FLOOR, 3.0) == pytest.approx(0.6)
    assert model.choice(TAKEN_ON_SECOND_LOOK, 3.0) == pytest.approx(1.5)
    assert model.choice(TAKEN_ON_OWN, 3.0) == 0.0
    assert model.choice("", 3.0) == 0.0
    opts = DetectionOptions()
    assert (opts.sigma_model.floor_choice, opts.sigma_model.second_look_choice) == (
        FLOOR_CHOICE, SECOND_LOOK_CHOICE)
    for name in ("sigma_floor_choice", "sigma_second_look_choice"):
        with pytest.raises(InputError, match=name):
            DetectionOptions(**{name: -0.1})  # type: ignore[arg-type]


def test_spots_of_the_floor_search_and_the_second_look_state_their_rules_sigma() -> None:
    """``green_all`` 15 of seed 5 (the independent generator, 1920 × 1080): L4 is taken on its
    own evidence, L1 by the floor search, L2 and L3 by the second look. L2 is the right spot
    1.4 px off along x, with a blob σ of 0.51 px: 2.7σ. With its rule's term it is within
    1.96σ. The centres do not move, and L4's σ is its blob's. (Measured with the brightness
    maximum's sub-pixel peak off: L2's centroid lies 1.6 px from that maximum, and at its
    peak, on by default, L2 is found 0.41 px off.)"""
    ci = list(CONDITIONS).index("green_all")
    frame = render_frame("green_all", 1920, 1080, np.random.default_rng([5, ci, 0, 15]))
    camera = parse_camera(frame.camera_spec)
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    blob = detect_spots(frame.image_rgb, camera, rig, replace(NO_CHOICE, peak_apart_px=0.0))
    result = detect_spots(frame.image_rgb, camera, rig, DetectionOptions(peak_apart_px=0.0))
    rules = {c.laser: c.taken_by for c in result.candidates if c.taken_by}
    assert rules == {"L1": TAKEN_ON_FLOOR, "L2": TAKEN_ON_SECOND_LOOK,
                     "L3": TAKEN_ON_SECOND_LOOK, "L4": TAKEN_ON_OWN}
    reach = floor_radius_px(camera, DetectionOptions())
    share = {TAKEN_ON_FLOOR: FLOOR_CHOICE, TAKEN_ON_SECOND_LOOK: SECOND_LOOK_CHOICE,
             TAKEN_ON_OWN: 0.0}
    for before, after in zip(blob.spots, result.spots, strict=True):
        assert (after.laser, after.x, after.y) == (before.laser, before.x, before.y)
        assert after.sigma_px == pytest.approx(
            math.hypot(before.sigma_px, share[rules[after.laser]] * reach))
    spots = {s.laser: s for s in result.spots}
    before_l2 = next(s for s in blob.spots if s.laser == "L2")
    truth = frame.truth["L2"]
    assert truth is not None
    dx = abs(spots["L2"].x - truth[0])
    assert dx > max(1.3, 1.96 * before_l2.sigma_px)
    assert dx < 1.96 * spots["L2"].sigma_px
    assert spots["L4"].sigma_px == next(s for s in blob.spots if s.laser == "L4").sigma_px
    at_peak = {s.laser: s for s in detect_spots(frame.image_rgb, camera, rig).spots}["L2"]
    assert math.dist((at_peak.x, at_peak.y), truth) < 0.5
