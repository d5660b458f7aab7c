"""What else lies along a beam, on frames of the independent physical generator.

A far spot beside its beam's in-water glow: a maximum of its own within a too-large blob's
radius is measured, not dropped as part of that blob. Of two laser lights on one beam the nearer
is a particle lit in the water, unless the other beams' spots sit at its range: then the
farther one is a laser-coloured speck of the scene. Reasons name positions
in image pixels.
"""

from __future__ import annotations

import math
import re
import tomllib

import numpy as np
import pytest

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionResult, candidates, detect_spots
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.underwater import CONDITIONS, Frame, render_frame


def _frame(condition: str, index: int, seed: int = 0) -> tuple[Frame, DetectionResult]:
    ci = list(CONDITIONS).index(condition)
    frame = render_frame(condition, 1920, 1080, np.random.default_rng([seed, ci, 0, index]))
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    return frame, detect_spots(frame.image_rgb, parse_camera(frame.camera_spec), rig)


@pytest.fixture(scope="module")
def faint_far_2() -> tuple[Frame, DetectionResult]:
    """L3's spot (0.42 x white) 2 px from a maximum of a glow line whose half-max region,
    against the background two largest spots out, is too large (12 px): it used to be dropped
    as 'part of the too-large blob'."""
    return _frame("faint_far", 2)


def _l3_found(frame: Frame, res: DetectionResult) -> None:
    truth = frame.truth["L3"]
    assert truth is not None
    got = {s.laser: s for s in res.spots}
    assert "L3" in got, res.missing.get("L3")
    assert math.dist((got["L3"].x, got["L3"].y), truth) < 1.0


def test_a_spot_beside_a_too_large_glow_is_measured_and_found(
        faint_far_2: tuple[Frame, DetectionResult], monkeypatch: pytest.MonkeyPatch) -> None:
    """Measured against its own surroundings (``candidates.LOCAL_RADII``), the glow's maximum
    is the spot; measured against the far background alone, it is too large, and the spot's
    own maximum within its radius is measured, not dropped as a repeat of it."""
    frame, res = faint_far_2
    _l3_found(frame, res)
    monkeypatch.setattr(candidates, "LOCAL_RADII", ())
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    res = detect_spots(frame.image_rgb, parse_camera(frame.camera_spec), rig)
    truth = frame.truth["L3"]
    assert truth is not None
    glow = [c for c in res.candidates if c.reason.startswith("too large")
            and math.dist((c.x, c.y), truth) < c.radius_px]
    assert glow  # the spot lies within a too-large blob's radius
    _l3_found(frame, res)


def test_reasons_name_positions_in_image_pixels() -> None:
    """Each 'duplicate of the stronger maximum at (x, y)' names a listed candidate, and so do
    the explanations of missing lasers (they used to name positions in the searched crop)."""
    _, res = _frame("red_blue_water", 7)
    texts = [c.reason for c in res.candidates] + list(res.missing.values())
    named = [tuple(map(float, m)) for t in texts
             for m in re.findall(r"maximum at \(([-\d.]+), ([-\d.]+)\)", t)]
    assert len(named) >= 3
    for x, y in named:
        # (a separate refinement of overlapping spots may move it afterwards, measured 0.6 px;
        # the searched crop's corner was hundreds of px off)
        assert min(math.hypot(c.x - x, c.y - y) for c in res.candidates) < 1.0, (x, y)


def _all_four_found(frame: Frame, res: DetectionResult) -> None:
    got = {s.laser: s for s in res.spots}
    assert set(got) == {"L1", "L2", "L3", "L4"}, res.missing
    for name, s in got.items():
        truth = frame.truth[name]
        assert truth is not None and math.dist((s.x, s.y), truth) < 0.5, name


def test_a_speck_farther_along_the_beam_does_not_veto_the_spot_at_the_others_range() -> None:
    """blue_beams, seed 1, frame 4: a laser-coloured speck 90 px farther along L1's band used
    to mark L1's spot (SNR 347, at the other three spots' range) as light nearer than the
    laser's own on its beam (depth 0.1), and L1 had no spot."""
    frame, res = _frame("blue_beams", 4, seed=1)
    _all_four_found(frame, res)
    spot = [c for c in res.candidates if c.laser == "L1"][0]
    assert dict(spot.evidence)["depth"] == 1.0


def test_a_particle_lit_nearer_on_the_beam_is_still_vetoed_by_the_spot_behind_it() -> None:
    """marine_snow, seed 0, frame 9: a particle lit by L2's beam has more evidence than L2's
    spot on the floor behind it (more than twice: a rule that let weaker far light not count
    took the particle, 180 px from the spot); the spot's range agrees with the other spots'."""
    frame, res = _frame("marine_snow", 9)
    _all_four_found(frame, res)
    assert any(c.evidence and dict(c.evidence)["depth"] < 1.0 and c.laser is None
               for c in res.candidates)
