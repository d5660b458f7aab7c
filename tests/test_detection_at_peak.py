"""A round brightness maximum whose sub-pixel refinement fails, centred at its sub-pixel peak
(:func:`sfm_laserscale.detection.candidates._at_peak`).

Closed form: the parabola's vertex (exact on a parabola); a blob response holding a Gaussian
peak at a known sub-pixel point, read back within 0.02 px, with the stated σ (the radius it
counts clipped to 1–4 px); the guards (a colour maximum, an elongated one, the option off, a
response with no vertex there). Then two
frames of the physical benchmark whose spots' centroids ran off them: with the rule, every
spot is found within 0.5 px, its reason says how it was centred; without it, fewer.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import replace

import numpy as np
import pytest
from benchmark_frames import fitted_frame

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, detect_spots
from sfm_laserscale.detection.candidates import PEAK_MIN_ROUNDNESS, Measure, _at_peak, _Source
from sfm_laserscale.detection.detect import AT_PEAK_FAILED
from sfm_laserscale.detection.refine import parabola_vertex
from sfm_laserscale.rig import rig_from_dict

SIZE = 41
TRUE_XY = (20.3, 19.8)  # crop COLMAP px of the response's peak


def test_the_vertex_of_a_parabola_is_exact() -> None:
    xs = np.array([-1.0, 0.0, 1.0])
    for vertex in (-0.45, 0.0, 0.3):
        three = (1.0 - (xs - vertex) ** 2).astype(np.float32)
        assert parabola_vertex(three) == pytest.approx(vertex)
    assert parabola_vertex(np.array([1.0, 0.5, 2.0], np.float32)) is None  # not a maximum
    assert parabola_vertex(np.array([1.0, 1.0, 1.0], np.float32)) is None  # flat


def _source(name: str, flat: bool = False) -> _Source:
    """A response whose blobs peak at TRUE_XY: log of a Gaussian (a parabola along each axis,
    so the vertex is exact), or flat."""
    c = np.arange(SIZE) + 0.5
    gx, gy = np.meshgrid(c, c)
    blobs = -((gx - TRUE_XY[0]) ** 2 + (gy - TRUE_XY[1]) ** 2) / 4.0
    if flat:
        blobs = np.zeros_like(blobs)
    plane = blobs.astype(np.float32)
    return _Source(name, plane, plane, 0.0, 1.0, None)


def _maximum(roundness: float = 0.9, radius_px: float = 1.6) -> Measure:
    """A maximum measured at the pixel holding TRUE_XY."""
    peak = (math.floor(TRUE_XY[0]) + 0.5, math.floor(TRUE_XY[1]) + 0.5)
    return Measure(*peak, "green", "bright", 1.0, radius_px=radius_px, roundness=roundness,
                   peak=peak)


MAX_RADIUS = 32.0  # the largest spot radius (px): σ counts at most 4 px of a radius


@pytest.mark.parametrize(("radius_px", "counted_px"), [(0.6, 1.0), (1.6, 1.6), (3.0, 3.0),
                                                       (12.0, 4.0)])
def test_a_round_brightness_maximum_is_centred_at_its_peak(radius_px: float,
                                                           counted_px: float) -> None:
    m, options = _maximum(radius_px=radius_px), DetectionOptions()
    got = _at_peak(m, _source("bright"), options, MAX_RADIUS)
    assert got is not None and m.at_peak
    x, y, sigma = got
    assert math.dist((x, y), TRUE_XY) < 0.02
    model = options.sigma_model
    assert sigma == pytest.approx(math.hypot(model.floor_px,
                                             model.disagreement_gain * counted_px))


@pytest.mark.parametrize("case", ["colour", "elongated", "switched off", "no vertex"])
def test_other_maxima_stay_rejected(case: str) -> None:
    m, options = _maximum(), DetectionOptions()
    source = _source("colour" if case == "colour" else "bright", flat=case == "no vertex")
    if case == "elongated":
        m.roundness = PEAK_MIN_ROUNDNESS - 0.05
    elif case == "switched off":
        options = replace(options, peak_when_refinement_fails=False)
    assert _at_peak(m, source, options, MAX_RADIUS) is None
    assert not m.at_peak


@pytest.mark.parametrize(("draw", "without"), [
    # a strobe's frame: four clipped cores read white; two of them refined off their maxima
    # (beside a hot spot's rim), the other two then had no spot to agree with
    (("strobe_hotspots", 3, 6), set()),
    # green on green water: L3's centroid ran off beside a pale speck
    (("green_all", 2, 1), {"L1", "L2", "L4"}),
])
def test_spots_whose_centroid_ran_off_are_found(draw: tuple[str, int, int],
                                                without: set[str]) -> None:
    frame, scene = fitted_frame(*draw)
    camera, rig = parse_camera(frame.camera_spec), rig_from_dict(tomllib.loads(frame.rig_toml))

    def spots(on: bool) -> dict[str, tuple[float, float]]:
        options = DetectionOptions(peak_when_refinement_fails=on)
        res = detect_spots(frame.image_rgb, camera, rig, options, scene_rgb=scene)
        errors = {s.laser: (math.dist((s.x, s.y), frame.truth[s.laser] or (0.0, 0.0)),
                            s.sigma_px) for s in res.spots}
        if on:
            at_peak = [c for c in res.candidates if c.taken_by and AT_PEAK_FAILED in c.reason]
            assert at_peak, "no spot was centred at its peak"
            for c in at_peak:  # its σ per axis covers its error
                assert errors[c.laser or ""][0] < 2.0 * errors[c.laser or ""][1]
        return errors

    got = spots(True)
    assert sorted(got) == ["L1", "L2", "L3", "L4"]
    assert max(e for e, _ in got.values()) < 0.5, got
    assert set(spots(False)) == without
