"""Overlapping candidates re-refined with each other's light removed stay near their centres.

:func:`~sfm_laserscale.detection.candidates.separate_overlapping` alternates rounds; each
round used to allow a move of max(2, radius) px from the previous one, so three rounds could
walk a spot three times that far (a clipped core beside the beam's glow in the water ended
8 px off on a physical frame). The rounds together now stay within that distance of the
measured centre.
"""

from __future__ import annotations

import math

import pytest

from sfm_laserscale.detection import DetectionOptions, candidates
from sfm_laserscale.detection.candidates import Measure, separate_overlapping


def _pair() -> list[Measure]:
    """Two spots of half-max radius 2 px, 5 px apart: their supports overlap."""
    return [Measure(50.0, 50.0, "green", "colour", 1.0, radius_px=2.0, support_px=6.0),
            Measure(55.0, 50.0, "green", "colour", 1.0, radius_px=2.0, support_px=6.0)]


@pytest.mark.parametrize(("step_px", "expected_px"), [
    (1.5, 1.5),  # a second step would end 3 px from the measured centre: only one is taken
    (0.5, 1.5),  # three small steps, 1.5 px in all
    (2.5, 0.0),  # one step beyond max(2, radius): none is taken
])
def test_the_rounds_together_stay_within_the_spots_radius(
        monkeypatch: pytest.MonkeyPatch, step_px: float, expected_px: float) -> None:
    # every re-refinement moves the spot step_px farther from its neighbour
    monkeypatch.setattr(candidates, "spot_patch", lambda *a, **k: object())
    monkeypatch.setattr(candidates, "neighbour_model", lambda *a, **k: object())

    def refine(planes: object, guess, refine: str, mine: tuple, model: object
               ) -> tuple[float, float, float]:
        away = -1.0 if guess.x < 52.5 else 1.0
        return guess.x + away * step_px, guess.y, 0.1

    monkeypatch.setattr(candidates, "refine_spot", refine)
    pair = _pair()
    separate_overlapping(object(), pair, DetectionOptions())  # type: ignore[arg-type]
    assert pair[0].x == pytest.approx(50.0 - expected_px)
    assert pair[1].x == pytest.approx(55.0 + expected_px)
    assert all(m.beside == (expected_px > 0) for m in pair)
    for m, x in zip(pair, (50.0, 55.0), strict=True):
        assert math.dist((m.x, m.y), (x, 50.0)) <= 2.0
