"""Spots cut by the image border: the window mirrored inside the image and the σ term."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sfm_laserscale.detection.options import SigmaModel
from sfm_laserscale.detection.refine import (
    SpotPatch,
    cut_sigma,
    mirrored_inside,
    refine_centroid,
    refine_gaussian,
)

WIDTH, HEIGHT = 64.0, 48.0


def _cut_patch(x: float, y: float, extra: float = 0.0) -> SpotPatch:
    """A Gaussian spot (σ 1.2 px) at (x, y) near the left edge, in a window cut at x = 0;
    ``extra``: the peak of a second, smaller blob 2.5 px to its right (light the spot's
    symmetric model does not hold)."""
    xs = np.arange(0, 14) + 0.5
    ys = np.arange(int(y) - 10, int(y) + 11) + 0.5
    gx, gy = np.meshgrid(xs, ys)
    sig = np.exp(-0.5 * ((gx - x) ** 2 + (gy - y) ** 2) / 1.2**2)
    sig += extra * np.exp(-0.5 * ((gx - x - 2.5) ** 2 + (gy - y) ** 2) / 0.8**2)
    return SpotPatch(gx=gx, gy=gy, signal=sig, usable=np.ones(gx.shape, dtype=bool),
                     noise=1e-3, support_px=5.0, cut=True, bounds=(WIDTH, HEIGHT))


def test_mirrored_inside_is_the_interval_symmetric_about_the_centre() -> None:
    centres = np.arange(8, dtype=np.float64) + 0.5
    # c = 2.25: [0, 4.5] is inside with its reflection; pixel 4 is half in it
    assert np.allclose(mirrored_inside(centres, 2.25, WIDTH), [1, 1, 1, 1, 0.5, 0, 0, 0])
    # near the far edge: [2 c - size, size]
    assert np.allclose(mirrored_inside(WIDTH - 8 + centres, WIDTH - 1.5, WIDTH),
                       [0, 0, 0, 0, 0, 1, 1, 1])
    # far from both edges every pixel counts; a centre outside the image keeps none
    assert np.allclose(mirrored_inside(centres + 20, 24.0, WIDTH), 1.0)
    assert np.allclose(mirrored_inside(centres, -0.5, WIDTH), 0.0)


@pytest.mark.parametrize("x", [2.0, 2.6, 3.7])
def test_a_cut_symmetric_spot_needs_no_cut_term(x: float) -> None:
    patch = _cut_patch(x, 20.4)
    xf, yf, _ = refine_gaussian(patch, x + 0.4, 20.0, 1.2)
    assert math.hypot(xf - x, yf - 20.4) < 0.02
    # the mirrored window's centroid agrees: for a symmetric spot the term vanishes
    xc, yc, _ = refine_centroid(patch, x + 0.4, 20.0, 1.2)
    assert math.hypot(xc - x, yc - 20.4) < 0.02
    assert cut_sigma(patch, xf, yf, 1.2, SigmaModel()) < 0.01


def test_light_beside_a_cut_spot_raises_its_sigma() -> None:
    """The fit and the mirrored window's centroid are pulled by different amounts (0.17 and
    0.09 px for a blob of 0.3 the spot's peak): the term grows with the extra light, but it
    shows it rather than bounds it (0.04 px here)."""
    terms = []
    for extra in (0.3, 0.5):
        patch = _cut_patch(2.0, 20.4, extra=extra)
        xf, yf, _ = refine_gaussian(patch, 2.0, 20.4, 1.2)
        assert xf - 2.0 > 0.1  # the symmetric model is pulled towards the extra light
        terms.append(cut_sigma(patch, xf, yf, 1.2, SigmaModel()))
        assert cut_sigma(patch, xf, yf, 1.2, SigmaModel(window_gain=1.0)) == pytest.approx(
            2 * terms[-1])
    assert 0.03 < terms[0] < terms[1]


def test_an_uncut_spot_has_no_cut_term() -> None:
    uncut = replace(_cut_patch(2.0, 20.4, extra=0.3), cut=False)
    assert cut_sigma(uncut, 2.0, 20.4, 1.2, SigmaModel()) == 0.0
