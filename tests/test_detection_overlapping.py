"""Overlapping candidates re-refined with each other's light removed: which overlap, and how
far the separation may move them.

:func:`~sfm_laserscale.detection.candidates.separate_overlapping` alternates rounds; each
round used to allow a move of max(2, radius) px from the previous one, so three rounds could
walk a spot three times that far (a clipped core beside the beam's glow in the water ended
8 px off on a physical frame). The rounds together now stay within that distance of the
measured centre.

Which candidates overlap (:func:`~sfm_laserscale.detection.candidates.overlap_reach`): red and
blue spots whose refinement windows overlap; a green (luma-dominant) laser's spots only when
their cores are within ``luma_separation_radii`` half-maximum radii, since a spot refined
beside a neighbour loses luma. Physical frames of the independent generator: clipped green
cores 40–180 px apart, whose supports hold their forward-scatter halos, were refined beside
each other and ended ~1 px off. A spot keeps a neighbour whose half-maximum radius exceeds
its own reach (its light is smooth across the spot's window); the broad one still has the
compact one removed.
"""

from __future__ import annotations

import math
import tomllib
from types import SimpleNamespace

import numpy as np
import pytest

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, candidates, detect_spots
from sfm_laserscale.detection.candidates import Measure, overlap_reach, separate_overlapping
from sfm_laserscale.errors import InputError
from sfm_laserscale.laser_color import DEFAULT_RGB
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.underwater import CONDITIONS, render_frame

GREEN_PLANES = SimpleNamespace(laser_rgb=np.asarray(DEFAULT_RGB["green"]))
RED_PLANES = SimpleNamespace(laser_rgb=np.asarray(DEFAULT_RGB["red"]))


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
    separate_overlapping(GREEN_PLANES, pair, DetectionOptions())  # type: ignore[arg-type]
    assert pair[0].x == pytest.approx(50.0 - expected_px)
    assert pair[1].x == pytest.approx(55.0 + expected_px)
    assert all(m.beside == (expected_px > 0) for m in pair)
    for m, x in zip(pair, (50.0, 55.0), strict=True):
        assert math.dist((m.x, m.y), (x, 50.0)) <= 2.0


def _far_pair() -> list[Measure]:
    """Two bright cores of half-max radius 2.5 px, 80 px apart, whose supports (50 px: their
    halos) overlap."""
    return [Measure(100.0, 100.0, "green", "bright", 1.0, radius_px=2.5, support_px=50.0),
            Measure(180.0, 100.0, "green", "bright", 1.0, radius_px=2.5, support_px=50.0)]


def _separated(monkeypatch: pytest.MonkeyPatch, planes: object, pair: list[Measure],
               options: DetectionOptions) -> list[bool]:
    """Which of ``pair`` were refined beside the other (every re-refinement moves 0.1 px)."""
    monkeypatch.setattr(candidates, "spot_patch", lambda *a, **k: object())
    monkeypatch.setattr(candidates, "neighbour_model", lambda *a, **k: object())
    monkeypatch.setattr(candidates, "refine_spot",
                        lambda planes, guess, *a, **k: (guess.x + 0.1, guess.y, 0.2))
    separate_overlapping(planes, pair, options)  # type: ignore[arg-type]
    return [m.beside for m in pair]


def test_the_reach_is_the_window_for_red_and_radii_for_green() -> None:
    pair = _far_pair()
    assert overlap_reach(RED_PLANES, pair, DetectionOptions()) == [50.0, 50.0]  # type: ignore[arg-type]
    assert overlap_reach(GREEN_PLANES, pair, DetectionOptions()) == [7.5, 7.5]  # type: ignore[arg-type]
    tiny = [Measure(0.0, 0.0, "green", "colour", 1.0, radius_px=0.4, support_px=4.0)]
    assert overlap_reach(GREEN_PLANES, tiny, DetectionOptions()) == [3.0]  # type: ignore[arg-type]
    old = DetectionOptions(luma_separation_radii=None)
    assert overlap_reach(GREEN_PLANES, pair, old) == [50.0, 50.0]  # type: ignore[arg-type]


def test_green_cores_whose_halos_overlap_are_not_separated(
        monkeypatch: pytest.MonkeyPatch) -> None:
    assert _separated(monkeypatch, GREEN_PLANES, _far_pair(), DetectionOptions()) == [False] * 2
    assert _separated(monkeypatch, RED_PLANES, _far_pair(), DetectionOptions()) == [True] * 2
    old = DetectionOptions(luma_separation_radii=None)
    assert _separated(monkeypatch, GREEN_PLANES, _far_pair(), old) == [True] * 2
    near = _pair()  # 5 px apart, radius 2: within 3 (2 + 2) px
    assert _separated(monkeypatch, GREEN_PLANES, near, DetectionOptions()) == [True] * 2


def test_a_neighbour_broader_than_the_spots_reach_is_not_removed(
        monkeypatch: pytest.MonkeyPatch) -> None:
    core = Measure(100.0, 100.0, "green", "bright", 1.0, radius_px=3.0, support_px=12.0)
    blob = Measure(100.0, 117.0, "green", "colour", 1.0, radius_px=13.0, support_px=40.0)
    # green: the core reaches 9 px, the blob 39 px; red: their windows, 12 and 40 px. The
    # blob is broader than the core's reach either way: the core keeps it, the blob has the
    # core removed.
    assert _separated(monkeypatch, GREEN_PLANES, [core, blob], DetectionOptions()) == [
        False, True]
    core.beside = blob.beside = False
    assert _separated(monkeypatch, RED_PLANES, [core, blob], DetectionOptions()) == [
        False, True]
    narrower = Measure(100.0, 117.0, "green", "colour", 1.0, radius_px=9.0, support_px=40.0)
    core.beside = False
    assert _separated(monkeypatch, GREEN_PLANES, [core, narrower], DetectionOptions()) == [
        True, True]


def test_a_bright_core_beside_a_broad_blob_keeps_its_centre() -> None:
    """``green_all`` frame 11 (seed 0): L2, a core 45× white, has its beam's glow in the water
    17 px in front of it (a maximum of half-max radius 13 px on the beam's line); refined
    beside it, the core ended 2.97 px off."""
    ci = list(CONDITIONS).index("green_all")
    frame = render_frame("green_all", 1920, 1080, np.random.default_rng([0, ci, 0, 11]))
    res = detect_spots(frame.image_rgb, parse_camera(frame.camera_spec),
                       rig_from_dict(tomllib.loads(frame.rig_toml)), DetectionOptions())
    spot, = (s for s in res.spots if s.laser == "L2")
    truth = frame.truth["L2"]
    assert truth is not None
    assert math.dist((spot.x, spot.y), truth) < 0.6


@pytest.mark.parametrize("radii", [0.0, -1.0])
def test_the_separation_radii_are_checked(radii: float) -> None:
    with pytest.raises(InputError, match="luma_separation_radii"):
        DetectionOptions(luma_separation_radii=radii)


def _errors(index: int, options: DetectionOptions, lasers: tuple[str, ...]) -> list[float]:
    """Distances (px) of ``lasers``' spots from their truths on ``clipped_cores`` frame
    ``index`` of the physical benchmark (seed 0, 1920 × 1080)."""
    ci = list(CONDITIONS).index("clipped_cores")
    frame = render_frame("clipped_cores", 1920, 1080, np.random.default_rng([0, ci, 0, index]))
    res = detect_spots(frame.image_rgb, parse_camera(frame.camera_spec),
                       rig_from_dict(tomllib.loads(frame.rig_toml)), options)
    spots = {s.laser: s for s in res.spots}
    truths = [frame.truth[n] for n in lasers]
    return [math.dist((spots[n].x, spots[n].y), t) for n, t in zip(lasers, truths, strict=True)
            if t is not None]


@pytest.mark.parametrize(("index", "laser"), [(17, "L1"), (19, "L3")])
def test_clipped_green_cores_apart_are_centred_on_their_own(index: int, laser: str) -> None:
    """Cores 16× and 38× white: refined beside the other cores (their supports 53 and 67 px)
    they were 1.14 and 1.12 px off; on their own, 0.15 and 0.23 px."""
    before, = _errors(index, DetectionOptions(luma_separation_radii=None), (laser,))
    after, = _errors(index, DetectionOptions(), (laser,))
    assert before > 1.0
    assert after < 0.3
