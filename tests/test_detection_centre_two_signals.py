"""A green laser's chosen spot centred on both of its signals (texture-free light and luma).

Painted patches (a clipped core's two centres agree: their weighted mean; an unclipped spot
keeps its centre), the combination rule on given centres, and physical frames of the
independent generator (clipped cores whose texture-free light was read from the crosstalk of
the unclipped channels, 0.7 px off; a disagreement that widens the σ).
"""

from __future__ import annotations

import functools
import math
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, centre, detect_spots
from sfm_laserscale.detection.candidates import Measure
from sfm_laserscale.detection.centre import centre_on_both, two_signal_centre
from sfm_laserscale.detection.options import SigmaModel
from sfm_laserscale.detection.refine import SpotGuess, refine_spot, spot_patch
from sfm_laserscale.errors import InputError
from sfm_laserscale.laser_color import DEFAULT_RGB
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.underwater import CONDITIONS, Frame, render_frame
from tests.painted_spots import GREEN, SIZE, TRUE_XY, gaussian, green_planes


def _image(grey_blob: float, peak: float = 3.0, seed: int = 0) -> np.ndarray:
    """A green spot (σ 1.2 px, ``peak`` × white: 3 clips its core in green) on a dull
    grey-green floor with mild noise, and optionally a grey blob 2.5 px to its right;
    encoded with gamma 2.2."""
    rng = np.random.default_rng(seed)
    floor = np.array([0.10, 0.14, 0.10])
    lin = np.broadcast_to(floor, (SIZE, SIZE, 3)).copy()
    lin += peak * gaussian(TRUE_XY, 1.2)[..., None] * np.asarray(GREEN)
    blob = gaussian((TRUE_XY[0] + 2.5, TRUE_XY[1]), 1.2)[..., None]
    lin += grey_blob * blob * floor / floor.max()
    lin += rng.normal(0.0, 0.002, lin.shape)
    return np.round(255.0 * np.clip(lin, 0.0, 1.0) ** (1 / 2.2)).astype(np.uint8)


GUESS = SpotGuess(20.5, 19.5, 1.4, 4.0, bright=True)  # a clipped core


def test_agreeing_signals_give_their_weighted_mean() -> None:
    planes = green_planes(_image(0.0))
    light = refine_spot(planes, GUESS, "centroid", signal="light")
    luma = refine_spot(planes, GUESS, "centroid", signal="luma")
    x, y, sigma = two_signal_centre(planes, GUESS, "centroid", SigmaModel(), light)
    assert math.dist((x, y), TRUE_XY) < 0.1  # a clipped core: both signals 0.05-0.06 px off
    # the weighted mean lies between the two centres, its σ is the smaller one's with the
    # disagreement term
    assert min(light[0], luma[0]) - 1e-9 <= x <= max(light[0], luma[0]) + 1e-9
    d = math.dist(light[:2], luma[:2])
    assert sigma == pytest.approx(math.hypot(min(light[2], luma[2]), 0.354 * d))


def test_an_unclipped_spot_keeps_its_centre_and_gains_the_disagreement_term() -> None:
    planes = green_planes(_image(0.0, peak=0.5))
    guess = replace(GUESS, bright=False)
    light = refine_spot(planes, guess, "centroid", signal="light")
    luma = refine_spot(planes, guess, "centroid", signal="luma")
    d = math.dist(light[:2], luma[:2])
    assert 0.0 < d < 0.5
    x, y, sigma = two_signal_centre(planes, guess, "centroid", SigmaModel(), luma)
    assert (x, y) == luma[:2]
    assert sigma == pytest.approx(math.hypot(luma[2], 0.354 * d))


def test_only_the_texture_free_light_holds_the_colour_term() -> None:
    """Luma is kept at full resolution: a green spot refined on it has no colour term; on its
    texture-free light (a colour difference) σ² gains (chroma_px / radius)²."""
    planes = green_planes(_image(0.0))
    plain, colour = SigmaModel(chroma_px=0.0), SigmaModel()
    for signal in ("light", "luma"):
        a = refine_spot(planes, GUESS, "centroid", sigma_model=plain, signal=signal)
        b = refine_spot(planes, GUESS, "centroid", sigma_model=colour, signal=signal)
        assert a[:2] == b[:2]
        term = colour.chroma(GUESS.radius_px) if signal == "light" else 0.0
        assert b[2] == pytest.approx(math.hypot(a[2], term))
    assert colour.chroma(0.5) == colour.chroma(1.0) == 0.3
    assert colour.chroma(3.0) == pytest.approx(0.1)


CHOSEN = (20.0, 20.0, 0.2)


@pytest.mark.parametrize(("light", "luma", "expected"), [
    # the texture-free light's σ holds the colour term (refine_spot: hypot(σ, 0.3 / 1.5) for
    # a spot of radius 1.5 px), luma's does not
    # agree: inverse-variance weighted mean, the smaller σ with the disagreement term
    ((20.0, 20.0, math.hypot(0.1, 0.2)), (20.3, 20.0, 0.2),
     (20.0 + 0.3 * 25 / 45, 20.0, math.hypot(0.2, 0.354 * 0.3))),
    # 0.8 px apart, but within 4σ combined: agree
    ((20.0, 20.0, math.hypot(0.5, 0.2)), (20.8, 20.0, 0.5),
     (20.0 + 0.8 * 4 / (4 + 1 / 0.29), 20.0, math.hypot(0.5, 0.354 * 0.8))),
    # 1.5 px apart, within 4σ combined but more than 1 px: the chosen centre is kept
    ((20.0, 20.0, 0.5), (21.5, 20.0, 0.5), (20.0, 20.0, math.hypot(0.2, 0.354 * 1.5))),
    # 0.95 px apart, beyond 4σ combined (0.85 px), σ 0.21 and 0.05 (more than 3× apart):
    # the sharper centre (luma) is taken
    ((20.0, 20.0, math.hypot(0.05, 0.2)), (20.95, 20.0, 0.05),
     (20.95, 20.0, math.hypot(0.05, 0.354 * 0.95))),
    # ... and so is the texture-free light's when it is the sharper one
    ((20.0, 20.0, 0.1), (21.2, 20.0, 0.6), (20.0, 20.0, math.hypot(0.1, 0.354 * 1.2))),
    # 1.2 px apart, σ less than 3× apart: the chosen centre is kept
    ((20.0, 20.0, 0.3), (21.2, 20.0, 0.15), (20.0, 20.0, math.hypot(0.2, 0.354 * 1.2))),
    # a signal that cannot be refined, or wanders beyond max(2, radius): nothing changes
    ((20.0, 20.0, math.nan), (20.1, 20.0, 0.1), CHOSEN),
    ((20.0, 20.0, 0.1), (22.5, 20.0, 0.1), CHOSEN),
])
def test_two_centres_are_combined_only_when_they_agree(
        monkeypatch: pytest.MonkeyPatch, light: tuple[float, float, float],
        luma: tuple[float, float, float], expected: tuple[float, float, float]) -> None:
    results = {"light": light, "luma": luma}
    monkeypatch.setattr(centre, "refine_spot",
                        lambda *args, signal, **kw: results[signal])
    got = centre.two_signal_centre(green_planes(_image(0.0)),
                                   SpotGuess(20.0, 20.0, 1.5, 4.0, bright=True),
                                   "centroid", SigmaModel(), CHOSEN)
    assert got == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize(("light", "luma", "clipped", "expected"), [
    # a red or blue clipped core whose luma centre disagrees and is 3× sharper: luma's
    ((20.0, 20.0, 0.9), (21.5, 20.0, 0.2), True, (21.5, 20.0, math.hypot(0.2, 0.354 * 1.5))),
    # its texture-free light the sharper: the chosen centre and σ, untouched
    ((20.0, 20.0, 0.1), (21.5, 20.0, 0.9), True, CHOSEN),
    # the two agree, or luma is not 3× sharper: untouched (luma holds the scene's texture)
    ((20.0, 20.0, 0.3), (20.2, 20.0, 0.1), True, CHOSEN),
    ((20.0, 20.0, 0.5), (21.5, 20.0, 0.2), True, CHOSEN),
    # an unclipped spot: untouched
    ((20.0, 20.0, 0.9), (21.5, 20.0, 0.2), False, CHOSEN),
])
def test_a_red_or_blue_clipped_core_takes_luma_only_where_it_is_much_sharper(
        light: tuple[float, float, float], luma: tuple[float, float, float], clipped: bool,
        expected: tuple[float, float, float]) -> None:
    got = centre.combine_centres(light, luma, CHOSEN, clipped, green=False,
                                 disagreement_gain=0.354)
    assert got == pytest.approx(expected, abs=1e-9)


def test_unclipped_red_spots_and_spots_beside_a_neighbour_keep_their_centre() -> None:
    image = _image(0.0)
    options = DetectionOptions()
    for m, rgb in ((Measure(20.6, 19.6, "red", "colour", 1.0, radius_px=1.4, support_px=4.0,
                            sigma_px=0.2), DEFAULT_RGB["red"]),
                   (Measure(20.6, 19.6, "green", "colour", 1.0, radius_px=1.4, support_px=4.0,
                            sigma_px=0.2, beside=True), GREEN)):
        centre_on_both(image, m, rgb, options, 10.0)
        assert (m.x, m.y, m.sigma_px) == (20.6, 19.6, 0.2)
    m = Measure(20.6, 19.6, "green", "colour", 1.0, radius_px=1.4, support_px=4.0, sigma_px=0.2,
                bright=True)
    centre_on_both(image, m, GREEN, replace(options, two_signal_centre=False), 10.0)
    assert (m.x, m.y, m.sigma_px) == (20.6, 19.6, 0.2)
    centre_on_both(image, m, GREEN, options, 10.0)
    assert math.dist((m.x, m.y), TRUE_XY) < 0.1


def test_signal_and_gain_are_checked() -> None:
    with pytest.raises(ValueError, match="signal"):
        spot_patch(green_planes(_image(0.0)), GUESS, 4.0, signal="red")
    with pytest.raises(InputError, match="sigma_disagreement_gain"):
        DetectionOptions(sigma_disagreement_gain=-0.1)


def _detect(condition: str, index: int, two_signals: bool,
            size: tuple[int, int] = (1920, 1080), crosstalk: bool = False
            ) -> tuple[dict, dict]:
    frame = _render(condition, index, size)
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    # the narrower windows (centre.narrow_window_centre), the brightness maximum's sub-pixel
    # peak (wandered.back_to_peak; candidates._at_peak, whose spots skip the centring steps)
    # and, unless asked, the crosstalk centre (centre.crosstalk_centre) off: these frames test
    # the two signals and the clipped pixels alone; the σ term of the rule that took a spot is
    # off too (the blob's σ is tested)
    opts = DetectionOptions(two_signal_centre=two_signals, narrow_window_ratio=0.0,
                            peak_apart_px=0.0, peak_when_refinement_fails=False,
                            crosstalk_max_noise_px=DetectionOptions().crosstalk_max_noise_px
                            if crosstalk else 0.0, sigma_floor_choice=0.0,
                            sigma_second_look_choice=0.0)
    res = detect_spots(frame.image_rgb, parse_camera(frame.camera_spec), rig, opts)
    return {s.laser: s for s in res.spots}, frame.truth


@functools.lru_cache(maxsize=1)
def _render(condition: str, index: int, size: tuple[int, int]) -> Frame:
    """A frame of the physical benchmark (seed 0; its first size's generator draws)."""
    ci = list(CONDITIONS).index(condition)
    return render_frame(condition, *size, np.random.default_rng([0, ci, 0, index]))


def test_clipped_cores_are_centred_on_luma_where_the_light_was_crosstalk() -> None:
    """``clipped_cores`` frame 0: L1 and L2 (10x and 37x white) clip in green; their
    texture-free light was read from red and blue, the crosstalk alone (measured 0.69 and
    0.75 px off); luma sees the cores whole (0.18 and 0.15 px)."""
    before, truth = _detect("clipped_cores", 0, two_signals=False)
    after, _ = _detect("clipped_cores", 0, two_signals=True)
    for name in ("L1", "L2"):
        t = truth[name]
        assert t is not None
        assert math.dist((before[name].x, before[name].y), t) > 0.6
        assert math.dist((after[name].x, after[name].y), t) < 0.3


def test_a_disagreement_widens_the_sigma_of_the_centre_kept() -> None:
    """``turbid_brown`` frame 17, L3: luma's centre lies on the texture beside the spot, the
    chosen centre (0.41 px off, 2.8σ per axis before) is kept and its σ now holds its error."""
    before, truth = _detect("turbid_brown", 17, two_signals=False)
    after, _ = _detect("turbid_brown", 17, two_signals=True)
    t = truth["L3"]
    assert t is not None
    assert (after["L3"].x, after["L3"].y) == (before["L3"].x, before["L3"].y)
    err = max(abs(after["L3"].x - t[0]), abs(after["L3"].y - t[1]))
    assert err > 1.96 * before["L3"].sigma_px
    assert err < 1.96 * after["L3"].sigma_px


def test_a_red_clipped_core_is_centred_on_luma_where_its_light_is_not_symmetric() -> None:
    """``turbid_brown`` frame 8 at 4000 × 3000, L2: a red core 3.8× white in yellow-brown
    water whose red channel is near full scale around it. Its texture-free light, read from
    the unclipped green and blue, centres it 4.2 px off with σ 1.6 px; luma sees the core
    whole (0.4 px off, σ 0.2 px)."""
    before, truth = _detect("turbid_brown", 8, two_signals=False, size=(4000, 3000))
    after, _ = _detect("turbid_brown", 8, two_signals=True, size=(4000, 3000))
    t = truth["L2"]
    assert t is not None
    assert math.dist((before["L2"].x, before["L2"].y), t) > 3.0
    assert before["L2"].sigma_px > 1.0
    assert math.dist((after["L2"].x, after["L2"].y), t) < 0.6
    # the two centres disagree by ~4 px: the σ says so
    assert after["L2"].sigma_px > 1.0
    for name in ("L3", "L4"):  # cores whose two signals agree keep their centre
        assert (after[name].x, after[name].y) == (before[name].x, before[name].y)
    # read on its crosstalk (green and blue, where the core stands far above the noise), the
    # core is centred as well as on luma, with a σ no longer inflated by the disagreement
    # (measured 0.36 px off, σ 0.25 px)
    cross, _ = _detect("turbid_brown", 8, two_signals=True, size=(4000, 3000), crosstalk=True)
    assert math.dist((cross["L2"].x, cross["L2"].y), t) < 0.4
    assert cross["L2"].sigma_px < 0.3
