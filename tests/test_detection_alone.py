"""A spot alone in its image (no other laser's spot while other beams are in view) needs
``alone_min_score``: nothing corroborates it, and laser-free photographs hold such blobs."""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, detect_spots
from sfm_laserscale.detection.score import below
from sfm_laserscale.errors import InputError
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.underwater import CONDITIONS, render_frame
from tests.test_detection_floor import CAMERA, _image, _rig, _spots


def test_a_clear_spot_alone_is_kept_and_a_weaker_one_is_dropped_with_its_reason() -> None:
    truth = _spots((0.1, -0.1, 1.0), 2.5)
    image = _image(truth, {"L2": 0.0, "L3": 0.0, "L4": 0.0}, np.random.default_rng(3))
    rig = _rig()
    res = detect_spots(image, CAMERA, rig)
    assert [s.laser for s in res.spots] == ["L1"]  # four beams in view, one spot
    assert math.dist((res.spots[0].x, res.spots[0].y), truth["L1"]) < 0.3
    score = res.spots[0].score
    assert score >= DetectionOptions().alone_min_score
    strict = detect_spots(image, CAMERA, rig, DetectionOptions(alone_min_score=score + 0.01))
    assert strict.spots == ()
    assert "alone in its image" in strict.missing["L1"]
    dropped = [c for c in strict.candidates if c.reason.startswith("alone in its image")]
    assert len(dropped) == 1 and dropped[0].laser is None


def test_a_reason_reads_a_score_below_its_limit() -> None:
    """A score just under alone_min_score is written with the digits that show it below."""
    truth = _spots((0.1, -0.1, 1.0), 2.5)
    image = _image(truth, {"L2": 0.0, "L3": 0.0, "L4": 0.0}, np.random.default_rng(3))
    score = detect_spots(image, CAMERA, _rig()).spots[0].score
    limit = score + 1e-4
    strict = detect_spots(image, CAMERA, _rig(), DetectionOptions(alone_min_score=limit))
    found = re.search(r"alone in its image: score ([\d.]+) < alone_min_score ([\d.]+)",
                      strict.missing["L1"])
    assert found is not None
    assert float(found.group(1)) < float(found.group(2))
    assert float(found.group(1)) == pytest.approx(score, abs=0.005)


@pytest.mark.parametrize(("value", "limit", "text"), [
    (0.598, 0.6, "0.598"), (0.12, 0.25, "0.12"), (0.24996, 0.25, "0.24996"),
    (0.2499999, 0.25, "0.250000")])
def test_below_keeps_the_digits_a_comparison_needs(value: float, limit: float,
                                                   text: str) -> None:
    assert below(value, limit) == text


def test_a_two_laser_rig_keeps_its_lone_spot() -> None:
    """With one other beam in view a lone spot is judged as any spot."""
    truth = _spots((0.1, -0.1, 1.0), 2.5)
    image = _image(truth, {"L2": 0.0, "L3": 0.0, "L4": 0.0}, np.random.default_rng(3))
    full = _rig()
    two = replace(full, lasers=full.lasers[:2])
    res = detect_spots(image, CAMERA, two, DetectionOptions(alone_min_score=1.0))
    assert [s.laser for s in res.spots] == ["L1"]


def test_a_laser_free_photograph_keeps_no_lone_blob() -> None:
    """A laser-free frame of the physical benchmark (1920 x 1080, seed 0, image 10) whose
    L1 band holds a blob that scores 0.36 on its own."""
    ci = list(CONDITIONS).index("no_lasers")
    frame = render_frame("no_lasers", 1920, 1080, np.random.default_rng([0, ci, 0, 10]))
    camera = parse_camera(frame.camera_spec)
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    assert detect_spots(frame.image_rgb, camera, rig).spots == ()
    lax = detect_spots(frame.image_rgb, camera, rig, DetectionOptions(alone_min_score=0.0))
    assert len(lax.spots) == 1 and lax.spots[0].score < 0.6


def test_alone_min_score_must_not_be_negative() -> None:
    with pytest.raises(InputError, match="alone_min_score"):
        DetectionOptions(alone_min_score=-0.1)
