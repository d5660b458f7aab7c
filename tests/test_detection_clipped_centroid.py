"""A clipped core whose centre the two signals left uncertain takes its clipped pixels' centroid.

Closed-form masks (the region chosen, its centroid and size), the rule on given centres (σ,
distance and compactness gates; the σ taken), and physical frames of the independent generator
where the scene under a clipped core pulled both of its signals 1.4-1.5 px off.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sfm_laserscale.detection import centre
from sfm_laserscale.detection.centre import clipped_centroid, clipped_core_centre
from sfm_laserscale.detection.options import SigmaModel
from sfm_laserscale.detection.refine import SpotGuess
from tests.test_detection_centre_two_signals import _detect

GAIN = SigmaModel().disagreement_gain


def _disc(cx: float, cy: float, r: float, shape: tuple[int, int] = (40, 40)) -> np.ndarray:
    """(H, W) mask of the pixels whose centres (COLMAP: index + 0.5) lie within r of (cx, cy)."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    return np.hypot(cols + 0.5 - cx, rows + 0.5 - cy) <= r


def test_the_centroid_is_the_region_next_to_the_centre() -> None:
    mask = _disc(20.0, 20.0, 2.2) | _disc(30.0, 20.0, 3.0)  # the spot, and a glint 10 px away
    found = clipped_centroid(mask, 21.0, 20.4)
    assert found is not None
    x, y, n = found
    assert (x, y) == pytest.approx((20.0, 20.0))
    assert n == int(_disc(20.0, 20.0, 2.2).sum())
    assert clipped_centroid(mask, 29.4, 21.0)[:2] == pytest.approx((30.0, 20.0))  # type: ignore[index]
    # nothing clipped within reach (1.5 px) of the centre, or nothing clipped at all
    assert clipped_centroid(mask, 20.0, 25.0) is None
    assert clipped_centroid(np.zeros((40, 40), dtype=bool), 20.0, 20.0) is None


def test_an_uncertain_centre_moves_to_the_clipped_centroid() -> None:
    mask = _disc(20.0, 20.0, 2.2)  # 16 px, within one half-maximum disc of radius 2.5 px
    guess = SpotGuess(21.0, 20.5, 2.5, 6.0, bright=True)
    x, y, sigma = clipped_core_centre(mask, guess, (21.0, 20.5, 0.7), GAIN)
    assert (x, y) == pytest.approx((20.0, 20.0))
    assert sigma == pytest.approx(math.hypot(0.3, 0.354 * math.hypot(1.0, 0.5)), abs=1e-3)


@pytest.mark.parametrize(
    ("mask", "start", "radius"),
    [
        (_disc(20.0, 20.0, 2.2), (21.0, 20.5, 0.5), 2.5),  # a centre sure of itself
        (_disc(20.0, 20.0, 2.2), (20.5, 20.4, 0.9), 2.5),  # the centroid 0.64 px away
        (_disc(20.0, 19.5, 0.6), (21.0, 20.0, 0.9), 2.5),  # two pixels: the rim, not a core
        (_disc(20.0, 20.0, 4.0), (21.0, 20.5, 0.9), 2.0),  # wider than the spot's disc
        (_disc(20.0, 20.0, 4.6), (21.0, 20.5, 0.9), 6.0),  # 69 px: core and clipped halo
        (_disc(20.0, 20.0, 2.2), (23.5, 20.0, 0.9), 2.5),  # no clipped pixel within reach
    ],
)
def test_the_centre_is_kept(mask: np.ndarray, start: tuple[float, float, float],
                            radius: float) -> None:
    guess = SpotGuess(start[0], start[1], radius, 6.0, bright=True)
    assert clipped_core_centre(mask, guess, start, GAIN) == start


@pytest.mark.parametrize(("condition", "index", "laser"),
                         [("strobe_hotspots", 13, "L3"), ("green_all", 14, "L1")])
def test_clipped_cores_pulled_by_the_scene_are_found(
        condition: str, index: int, laser: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """``strobe_hotspots`` 13 L3 (13× white under a lamp's hot spot) and ``green_all`` 14 L1:
    both signals of the core hold the scene beside it; the centre chosen was 1.4-1.5 px off
    with σ 0.6-0.7 px, its clipped pixels' centroid lies within 0.6 px."""
    monkeypatch.setattr(centre, "CLIPPED_CENTROID_WHEN_SIGMA_PX", math.inf)
    before, truth = _detect(condition, index, two_signals=True)
    monkeypatch.undo()
    after, _ = _detect(condition, index, two_signals=True)
    t = truth[laser]
    assert t is not None
    assert math.dist((before[laser].x, before[laser].y), t) > 1.3
    assert before[laser].sigma_px >= 0.6
    assert math.dist((after[laser].x, after[laser].y), t) < 0.6
    assert math.dist((after[laser].x, after[laser].y), t) < 2.0 * after[laser].sigma_px
    for name, spot in after.items():  # the frame's other spots keep their centres
        if name != laser:
            assert (spot.x, spot.y) == (before[name].x, before[name].y)
