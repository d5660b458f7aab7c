"""A chosen spot refined again under narrower centroid windows, taking the centre whose stated σ
is much smaller (:func:`sfm_laserscale.detection.centre.narrow_window_centre`).

Closed-form patches: a small red spot (σ 0.6 px) beside a broad red patch of the scene (σ 4 px,
6 px away), refined with a window of the half-maximum radius the candidate search measures on
its smoothed response (3 px, five times the spot). That window weights the patch's flank,
which pulls the centroid 1 px off the spot, and its σ says the light is not point-symmetric
about it; a window on the spot's own scale reads the spot, with a σ less than half as large.
Then the guards: a clean spot keeps its centre, the option off, a spot refined beside another.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sfm_laserscale.detection import DetectionOptions
from sfm_laserscale.detection.candidates import Measure
from sfm_laserscale.detection.centre import centre_chosen, narrow_window_centre
from sfm_laserscale.detection.options import SigmaModel
from sfm_laserscale.detection.refine import SpotGuess, refine_spot
from sfm_laserscale.detection.response import Planes, crop_channels, make_planes
from sfm_laserscale.errors import InputError
from sfm_laserscale.laser_color import DEFAULT_RGB

SIZE = 41
TRUE_XY = (20.3, 19.8)  # COLMAP px
RED = DEFAULT_RGB["red"]
FLOOR = np.array([0.12, 0.15, 0.13])  # linear RGB of the floor
WIDE = SpotGuess(20.5, 19.5, 3.0, 8.0)  # a half-maximum radius of 3 px: the response's


def _image(blob_peak: float, seed: int = 0) -> np.ndarray:
    """The spot (σ 0.6 px, 0.8 × white) and a red patch of the scene (σ 4 px, ``blob_peak``
    × white) centred 6 px to its right, camera noise 0.005, gamma 2.2 encoded."""
    c = np.arange(SIZE) + 0.5
    gx, gy = np.meshgrid(c, c)
    spot = 0.8 * np.exp(-0.5 * ((gx - TRUE_XY[0]) ** 2 + (gy - TRUE_XY[1]) ** 2) / 0.36)
    blob = blob_peak * np.exp(-0.5 * ((gx - TRUE_XY[0] - 6.0) ** 2 + (gy - TRUE_XY[1]) ** 2)
                              / 16.0)
    lin = FLOOR + (spot + blob)[..., None] * np.asarray(RED)
    lin = lin + np.random.default_rng(seed).normal(0.0, 0.005, lin.shape)
    return np.round(255.0 * np.clip(lin, 0.0, 1.0) ** (1 / 2.2)).astype(np.uint8)


def _planes(image: np.ndarray) -> Planes:
    options = DetectionOptions()
    return make_planes(crop_channels(image, (0, 0, SIZE, SIZE), options.input_gamma), "red",
                       options, 10.0, RED)


def test_a_patch_beside_a_small_spot_pulls_the_wide_window_not_the_narrow_one() -> None:
    planes = _planes(_image(0.05))
    wide = refine_spot(planes, WIDE, "centroid")
    assert wide[0] - TRUE_XY[0] > 0.8  # pulled towards the patch (measured 1.08 px)
    got = narrow_window_centre(planes, WIDE, "centroid", SigmaModel(), wide, 2.0)
    assert math.dist(got[:2], TRUE_XY) < 0.15
    # its σ: the narrow window's (less than half the wide one's, or it was not taken) with
    # the disagreement term of the distance moved, and at least half the wide one's
    moved = math.dist(got[:2], wide[:2])
    assert got[2] >= max(SigmaModel().disagreement_gain * moved, wide[2] / 2.0)
    assert got[2] < math.hypot(wide[2] / 2.0, SigmaModel().disagreement_gain * moved)
    # asked for a σ ratio no window reaches: the wide window's centre stays
    assert narrow_window_centre(planes, WIDE, "centroid", SigmaModel(), wide, 1e6) == wide


def test_a_clean_spot_keeps_its_centre() -> None:
    """Without the blob every window reads the same spot: no σ is twice as small, or the
    centre taken is as close to the truth."""
    for seed in range(5):
        planes = _planes(_image(0.0, seed))
        wide = refine_spot(planes, WIDE, "centroid")
        got = narrow_window_centre(planes, WIDE, "centroid", SigmaModel(), wide, 2.0)
        assert math.dist(got[:2], TRUE_XY) <= math.dist(wide[:2], TRUE_XY) + 0.05
    # a window no wider than the narrow ones: nothing is refined again
    narrow = replace(WIDE, radius_px=1.0)
    chosen = refine_spot(planes, narrow, "centroid")
    assert narrow_window_centre(planes, narrow, "centroid", SigmaModel(), chosen, 2.0) == chosen


def test_centre_chosen_takes_it_only_when_switched_on() -> None:
    image = _image(0.05)
    options = DetectionOptions(fit_agree_sigmas=0.0)

    def spot(**kw: object) -> Measure:
        x, y, sigma = refine_spot(_planes(image), WIDE, "centroid")
        return Measure(x, y, "red", "colour", 1.0, radius_px=3.0, support_px=8.0,
                       sigma_px=sigma, **kw)  # type: ignore[arg-type]

    for m, opts in ((spot(), replace(options, narrow_window_ratio=0.0)),
                    (spot(beside=True), options)):
        before = (m.x, m.y, m.sigma_px)
        centre_chosen(image, m, RED, opts, 10.0)
        assert (m.x, m.y, m.sigma_px) == before
    m = spot()
    centre_chosen(image, m, RED, options, 10.0)
    assert math.dist((m.x, m.y), TRUE_XY) < 0.15


def test_the_ratio_is_checked() -> None:
    for bad in (-1.0, 0.5):  # a ratio below 1 would take a centre of a larger σ
        with pytest.raises(InputError, match="narrow_window_ratio"):
            DetectionOptions(narrow_window_ratio=bad)
    assert DetectionOptions(narrow_window_ratio=0.0).narrow_window_ratio == 0.0
