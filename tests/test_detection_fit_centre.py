"""An unclipped chosen spot's centre from a 2D Gaussian fit where the centroid's window was too
wide and the two agree.

Closed-form patches: a faint red spot (σ 1 px, half-maximum radius 1.18 px) on a flat floor
with camera noise, over many noise draws. With the centroid's window the spot's size, the fit
is taken about half the time and changes nothing; with a window 1.7 × the spot (a half-maximum
radius measured 2 px), the fit is taken and is the more precise. Then the rule's guards (a fit
beyond ``fit_agree_sigmas`` · σ, a clipped core, the option off).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sfm_laserscale.detection import DetectionOptions, centre
from sfm_laserscale.detection.candidates import Measure
from sfm_laserscale.detection.centre import fit_centre, polish_with_fit
from sfm_laserscale.detection.refine import SpotGuess, refine_spot
from sfm_laserscale.detection.response import Planes, crop_channels, make_planes
from sfm_laserscale.errors import InputError
from sfm_laserscale.laser_color import DEFAULT_RGB

SIZE = 41
TRUE_XY = (20.3, 19.8)  # COLMAP px
RED = DEFAULT_RGB["red"]
FLOOR = np.array([0.12, 0.15, 0.13])  # linear RGB of the floor


def _image(seed: int, peak: float, noise: float = 0.01) -> np.ndarray:
    """A red spot (σ 1 px, ``peak`` × white) on a flat floor with Gaussian noise of ``noise``
    (linear) per channel, gamma 2.2 encoded."""
    rng = np.random.default_rng(seed)
    c = np.arange(SIZE) + 0.5
    gx, gy = np.meshgrid(c, c)
    spot = np.exp(-0.5 * ((gx - TRUE_XY[0]) ** 2 + (gy - TRUE_XY[1]) ** 2))
    lin = FLOOR + peak * spot[..., None] * np.asarray(RED)
    lin = lin + rng.normal(0.0, noise, lin.shape)
    return np.round(255.0 * np.clip(lin, 0.0, 1.0) ** (1 / 2.2)).astype(np.uint8)


def _planes(image: np.ndarray) -> Planes:
    options = DetectionOptions()
    return make_planes(crop_channels(image, (0, 0, SIZE, SIZE), options.input_gamma), "red",
                       options, 10.0, RED)


GUESS = SpotGuess(20.5, 19.5, 2.0, 4.0)  # a half-maximum radius measured too wide


def _errors(radius_px: float, peak: float, noise: float, draws: int = 40
            ) -> tuple[float, float, int]:
    """RMS distance to the truth of the centroid and of :func:`fit_centre` over ``draws``
    noise draws, and how many draws took the fit."""
    guess = replace(GUESS, radius_px=radius_px)
    centroid_err, fitted_err, taken = [], [], 0
    for seed in range(draws):
        planes = _planes(_image(seed, peak, noise))
        chosen = refine_spot(planes, guess, "centroid")
        got = fit_centre(planes, replace(guess, x=chosen[0], y=chosen[1]), chosen, 3.0)
        assert got[2] == chosen[2]  # the σ stays the centroid's
        taken += got[:2] != chosen[:2]
        centroid_err.append(math.dist(chosen[:2], TRUE_XY))
        fitted_err.append(math.dist(got[:2], TRUE_XY))
    rms = [math.sqrt(float(np.mean(np.square(e)))) for e in (centroid_err, fitted_err)]
    return rms[0], rms[1], taken


def test_a_too_wide_window_gives_way_to_the_fit() -> None:
    centroid, fitted, taken = _errors(2.0, 0.1, 0.01)
    assert taken == 40
    assert fitted < 0.75 * centroid  # measured 0.140 against 0.211 px


def test_with_a_window_of_the_spot_s_size_the_fit_changes_nothing() -> None:
    """A faint spot (0.1 × white, noise 0.02): where the fit is taken the two are as precise."""
    centroid, fitted, taken = _errors(1.2, 0.1, 0.02)
    assert 5 <= taken <= 35
    assert fitted == pytest.approx(centroid, rel=0.05)


def test_a_fit_beyond_its_agreement_or_on_a_clipped_core_is_not_taken() -> None:
    planes = _planes(_image(0, 0.1))
    chosen = refine_spot(planes, GUESS, "centroid")
    fitted = fit_centre(planes, GUESS, chosen, 3.0)
    apart = math.dist(fitted[:2], chosen[:2])
    assert apart > 0
    # the same fit, allowed just less than its distance from the centroid: not taken
    tight = (chosen[0], chosen[1], 0.99 * apart)
    assert fit_centre(planes, GUESS, tight, 1.0) == tight
    assert fit_centre(planes, replace(GUESS, bright=True), chosen, 3.0) == chosen


def test_polish_moves_a_chosen_spot_only_when_switched_on(monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    image = _image(3, 0.1)
    options = DetectionOptions()

    def spot(**kw: object) -> Measure:
        return Measure(20.6, 19.6, "red", "colour", 1.0, radius_px=2.0, support_px=4.0,
                       sigma_px=0.3, **kw)  # type: ignore[arg-type]

    for m, opts in ((spot(), replace(options, fit_agree_sigmas=0.0)),
                    (spot(), replace(options, refine="gaussian")),
                    (spot(bright=True), options), (spot(beside=True), options)):
        polish_with_fit(image, m, RED, opts, 10.0)
        assert (m.x, m.y, m.sigma_px) == (20.6, 19.6, 0.3)
    m = spot()
    polish_with_fit(image, m, RED, options, 10.0)
    assert (m.x, m.y) != (20.6, 19.6) and m.sigma_px == 0.3
    assert math.dist((m.x, m.y), TRUE_XY) < 0.3
    # the crop's corner is added back: the same fit as on the whole patch
    monkeypatch.setattr(centre, "MARGIN_PX", 30)
    m2 = spot()
    polish_with_fit(image, m2, RED, options, 10.0)
    assert (m2.x, m2.y) == pytest.approx((m.x, m.y), abs=0.02)


def test_the_agreement_is_checked() -> None:
    with pytest.raises(InputError, match="fit_agree_sigmas"):
        DetectionOptions(fit_agree_sigmas=-1.0)
