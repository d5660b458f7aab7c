"""A clipped core's centre beside a glow line, the centroid's fixed point, and a colour read
around the centre.

A thresholded centroid (the light above a fraction of the white plateau) keeps a glow line or
texture beside a green laser's clipped core from pulling its centre; closed-form scene. The
windowed centroid reaches its fixed point in few steps (closed-form spots). A small
spot's colour reading can flip with a centre moved by a tenth of a pixel; the median of five
readings around the centre does not hinge on one of them (a frame of the independent physical
generator).
"""

from __future__ import annotations

import math
import tomllib
from typing import Any

import numpy as np
import pytest

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, detect_spots
from sfm_laserscale.detection import refine as refine_module
from sfm_laserscale.detection import score as score_module
from sfm_laserscale.detection.refine import SpotGuess, SpotPatch, refine_centroid, refine_spot
from sfm_laserscale.detection.response import crop_channels, make_planes
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.underwater import CONDITIONS, render_frame

TRUTH = (50.3, 40.6)  # COLMAP px


def _clipped_core(glow: float, below_px: float = 4.0) -> np.ndarray:
    """(80, 100, 3) uint8, linear: a green spot 20 × white (σ 0.8 px, crosstalk 0.08 / 0.11 in
    red / blue) on grey, and a horizontal green glow line ``glow`` × white (σ 1 px) ``below_px``
    below it."""
    yy, xx = np.mgrid[0:80, 0:100] + 0.5
    spot = 20.0 * np.exp(-0.5 * ((xx - TRUTH[0]) ** 2 + (yy - TRUTH[1]) ** 2) / 0.8**2)
    line = glow * np.exp(-0.5 * (yy - TRUTH[1] - below_px) ** 2) * (xx > 20.0)
    rgb = np.stack([0.25 + 0.08 * spot + 0.05 * line, 0.25 + spot + line,
                    0.25 + 0.11 * spot + 0.05 * line], axis=2)
    return np.asarray(np.round(255.0 * np.clip(rgb, 0.0, 1.0)), dtype=np.uint8)


def _centre_error(image: np.ndarray) -> float:
    options = DetectionOptions(input_gamma=1.0)
    channels = crop_channels(image, (0, 0, image.shape[1], image.shape[0]), options.input_gamma)
    planes = make_planes(channels, "green", options, 10.0, (0.08, 1.0, 0.11))
    x, y, _ = refine_spot(planes, SpotGuess(50.5, 40.5, 2.0, 5.0, True), "centroid")
    return math.hypot(x - TRUTH[0], y - TRUTH[1])


def test_a_glow_line_beside_a_clipped_core_barely_pulls_its_centre(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Measured: 0.14 px with the line 4 px away at 0.2 × white (0.30 px with the whole light,
    the cut at 0), 0.11 px without the line (0.09 px): the plateau's pixels set the centre."""
    assert _centre_error(_clipped_core(0.0)) < 0.15
    assert _centre_error(_clipped_core(0.2)) < 0.2
    monkeypatch.setattr(refine_module, "CLIPPED_CUT", 0.0)
    assert _centre_error(_clipped_core(0.2)) > 0.25


def _patch(signal_of: str) -> SpotPatch:
    """A noise-free 100 × 100 patch holding a spot centred on TRUTH: a Gaussian (σ 1.2 px) or a
    flat-topped disc (radius 5 px, a clipped core's plateau, anti-aliased)."""
    gy, gx = (np.mgrid[0:100, 0:100] + 0.5).astype(np.float64)
    if signal_of == "gaussian":
        signal = np.exp(-0.5 * ((gx - TRUTH[0]) ** 2 + (gy - TRUTH[1]) ** 2) / 1.2**2)
    else:
        sub = (np.arange(8) + 0.5) / 8 - 0.5
        signal = sum((np.hypot(gx + dx - TRUTH[0], gy + dy - TRUTH[1]) <= 5.0).astype(float)
                     for dx in sub for dy in sub) / 64.0
    return SpotPatch(gx=gx, gy=gy, signal=signal, usable=np.ones(signal.shape, dtype=bool),
                     noise=0.01, support_px=15.0, cut=False)


def test_the_centroid_reaches_its_fixed_point_in_few_steps(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A window creeping towards the centre by a steady ratio jumps to where its steps end: a
    Gaussian spot started 1.8 px off is found in 7 centroid steps (20 one step at a time), the
    same point; a flat plateau under a narrow window (steps shrinking by ~0.9) ends 0.07 px off
    after the 50 steps allowed, where one step at a time ended 0.19 px off."""
    steps = [0]
    step = refine_module._centroid_step

    def counted(*args: Any) -> tuple[float, float, float]:
        steps[0] += 1
        return step(*args)

    monkeypatch.setattr(refine_module, "_centroid_step", counted)
    x, y, sigma = refine_centroid(_patch("gaussian"), 51.8, 39.6, 1.2)
    assert math.hypot(x - TRUTH[0], y - TRUTH[1]) < 1e-4 and math.isfinite(sigma)
    assert steps[0] <= 10  # the two last are the gain's displaced windows
    x, y, _ = refine_centroid(_patch("disc"), 52.3, 39.6, 1.6)
    assert math.hypot(x - TRUTH[0], y - TRUTH[1]) < 0.1


def _found(condition: str, index: int, seed: int,
           options: DetectionOptions = DetectionOptions()) -> int:  # noqa: B008
    ci = list(CONDITIONS).index(condition)
    frame = render_frame(condition, 1920, 1080, np.random.default_rng([seed, ci, 0, index]))
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    res = detect_spots(frame.image_rgb, parse_camera(frame.camera_spec), rig, options)
    return sum(1 for s in res.spots if (t := frame.truth.get(s.laser)) is not None
               and math.dist((s.x, s.y), t) < 1.5)


def test_colour_read_around_the_centre_does_not_hinge_on_one_reading(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """green_all, seed 5, frame 1: L1's clipped core (13 × white) reads the scene's colour at
    its refined centre (term 0.05) and laser light at three of the four points 0.3 px away; with
    the single reading the frame had no spot, with the median three of its four are found
    (the third by the range of the first). On the brightness's DoG, as the frame was measured,
    and without centring a maximum whose refinement failed at its peak (the forty-sixth round,
    which finds all four with the single reading too): with its ridge-free response three are
    found either way."""
    on_dog = DetectionOptions(ridge_free_brightness=False, peak_when_refinement_fails=False)
    assert _found("green_all", 1, seed=5, options=on_dog) >= 3
    assert _found("green_all", 1, seed=5) >= 3
    monkeypatch.setattr(score_module, "COLOUR_JITTER_PX", 0.0)
    assert _found("green_all", 1, seed=5, options=on_dog) == 0
    at_peak = DetectionOptions(ridge_free_brightness=False)
    assert _found("green_all", 1, seed=5, options=at_peak) == 4
