"""A red or blue laser's clipped core centred on the channels other than its laser's (the
sensor's crosstalk), where its own channel clips over the core and its halo
(``DetectionOptions.crosstalk_max_noise_px``, :func:`.centre.crosstalk_centre`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sfm_laserscale.detection import DetectionOptions, detect_spots
from sfm_laserscale.detection.centre import crosstalk_centre
from sfm_laserscale.detection.refine import SpotGuess, refine_spot
from sfm_laserscale.detection.response import crop_channels, make_planes
from sfm_laserscale.errors import InputError
from tests.test_detection_floor import _physical

OFF = DetectionOptions(crosstalk_max_noise_px=0.0)
RED = (1.0, 0.06, 0.03)  # a 638 nm laser's expected linear camera response
SIZE = 48
CORE = (24.3, 23.6)  # the core's centre (crop COLMAP px)


def _core_in_a_clipped_halo(noise: float, seed: int = 0) -> np.ndarray:
    """(SIZE, SIZE, 3) uint8: a red core (σ 1.2 px) whose crosstalk lifts green and blue by up
    to 120 levels, inside a red halo clipped over a disc of radius 7 px centred 3 px to its
    lower left, on a grey floor; Gaussian noise of ``noise`` levels."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    core = np.exp(-0.5 * ((xx - CORE[0]) ** 2 + (yy - CORE[1]) ** 2) / 1.2**2)
    halo = np.hypot(xx - CORE[0] + 2.1, yy - CORE[1] - 2.1)
    img = np.full((SIZE, SIZE, 3), 90.0)
    img[..., 0] = np.where(halo <= 7.0, 255.0, 90.0 + 150.0 * np.exp(-0.5 * (halo - 7.0) ** 2))
    img[..., 1] += 120.0 * core
    img[..., 2] += 110.0 * core
    img += rng.normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _centres(noise: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """(the texture-free light's centre, the crosstalk centre) of the synthetic core, both
    started 1.5 px off it."""
    opts = DetectionOptions()
    planes = make_planes(crop_channels(_core_in_a_clipped_halo(noise), (0, 0, SIZE, SIZE),
                                       opts.input_gamma), "red", opts, 8.0, RED)
    guess = SpotGuess(CORE[0] - 1.2, CORE[1] + 0.9, 2.5, 6.0, bright=True)
    light = refine_spot(planes, guess, "centroid", sigma_model=opts.sigma_model, signal="light")
    start = (guess.x, guess.y, 0.4)
    return light, crosstalk_centre(planes, guess, opts.sigma_model, start,
                                   opts.crosstalk_max_noise_px)


def test_a_core_in_a_clipped_halo_is_centred_on_its_crosstalk() -> None:
    """The red channel clips over the core and the halo beside it, so the texture-free light has
    no shape there and stays off the core; green and blue hold the core alone."""
    light, cross = _centres(noise=1.0)
    assert math.dist(light[:2], CORE) > 1.0
    assert math.dist(cross[:2], CORE) < 0.1
    assert 0.1 <= cross[2] < 0.2  # noise, structure and the 0.1 px floor


def test_a_noisy_crosstalk_centre_is_not_taken() -> None:
    """With noise of 25 levels the crosstalk centre's noise σ is above 0.05 px: the centre
    so far is kept, unchanged."""
    _, cross = _centres(noise=25.0)
    assert cross == (CORE[0] - 1.2, CORE[1] + 0.9, 0.4)


def test_a_red_core_in_turbid_water_is_centred_on_its_crosstalk() -> None:
    """Seed 6, ``turbid_brown`` 17, L2: a red core 16 × white whose halo clips the red channel
    around it. Without the rule it is reported 3.4 px off (a false spot and a miss); on its
    crosstalk, within 0.2 px. The frame's other spots stay where they were."""
    frame, camera, rig, truth = _physical(6, "turbid_brown", 17, "L2")
    before = {s.laser: s for s in detect_spots(frame.image_rgb, camera, rig, OFF).spots}
    assert math.dist((before["L2"].x, before["L2"].y), truth) > 3.0
    after = {s.laser: s for s in detect_spots(frame.image_rgb, camera, rig).spots}
    assert math.dist((after["L2"].x, after["L2"].y), truth) < 0.2
    assert after["L2"].sigma_px < before["L2"].sigma_px
    for name in set(before) - {"L2"}:
        other = frame.truth[name]
        assert other is not None
        assert math.dist((after[name].x, after[name].y), other) <= math.dist(
            (before[name].x, before[name].y), other) + 0.05


def test_the_crosstalk_noise_limit_is_checked() -> None:
    """0 switches the rule off; a negative limit is an input error."""
    with pytest.raises(InputError, match="crosstalk_max_noise_px"):
        DetectionOptions(crosstalk_max_noise_px=-0.1)
    assert OFF.crosstalk_max_noise_px == 0.0
