"""``scripts/bench_texture_cost.py``: a spot's centre on each signal with and without the scene
under it (a painted patch with a blob of texture beside the spot, and one physical frame), and
the fixed texture colour of ``refine.spot_patch`` it relies on."""

from __future__ import annotations

import math

import numpy as np

from sfm_laserscale.detection.refine import SpotGuess, spot_patch
from tests.painted_spots import GREEN, SIZE, TRUE_XY, gaussian, green_planes
from tests.script_loader import load_script

load_script("bench_centre_floor")  # imported by bench_texture_cost
cost = load_script("bench_texture_cost")


def _images(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A green spot (σ 1.2 px, 0.4 × white) on a grey-green floor with a pale blob of the
    floor's colour 2 px to its right, and the same floor without the spot; gamma 2.2."""
    rng = np.random.default_rng(seed)
    floor = np.array([0.10, 0.14, 0.10])
    dark = np.broadcast_to(floor, (SIZE, SIZE, 3)).copy()
    dark += 0.8 * gaussian((TRUE_XY[0] + 2.0, TRUE_XY[1]), 1.5)[..., None] * floor
    dark += rng.normal(0.0, 0.001, dark.shape)
    lit = dark + 0.4 * gaussian(TRUE_XY, 1.2)[..., None] * np.asarray(GREEN)

    def encode(lin: np.ndarray) -> np.ndarray:
        return np.round(255.0 * np.clip(lin, 0.0, 1.0) ** (1 / 2.2)).astype(np.uint8)
    return encode(lit), encode(dark)


GUESS = SpotGuess(20.5, 19.5, 1.4, 4.0)


def test_removing_the_scene_removes_the_blob_s_pull_on_luma() -> None:
    lit, dark = _images()
    errs = cost.signal_errors(green_planes(lit), green_planes(dark), GUESS, (0, 0), TRUE_XY, "luma")
    assert errs is not None
    with_scene, without = errs
    assert with_scene > 0.3  # the blob, bright in luma, pulls the centroid towards it
    assert without < 0.05  # the spot's own light: only noise and pixelation are left
    light = cost.signal_errors(green_planes(lit), green_planes(dark), GUESS, (0, 0), TRUE_XY,
                               "light")
    assert light is not None and light[0] < 0.1  # the blob has the floor's colour: cancelled


def test_a_given_texture_colour_is_the_one_used() -> None:
    planes = green_planes(_images()[0])
    own = spot_patch(planes, GUESS, 4.0, signal="light")
    assert own is not None and own.texture is not None
    again = spot_patch(planes, GUESS, 4.0, signal="light", texture=own.texture)
    assert again is not None
    np.testing.assert_array_equal(again.signal, own.signal)  # the default is the ring's
    other = np.array([0.0, 0.0, 1.0])
    forced = spot_patch(planes, GUESS, 4.0, signal="light", texture=other)
    assert forced is not None and forced.texture is other
    assert not np.allclose(forced.signal, own.signal)


def test_one_frame_gives_each_signal_with_and_without_the_scene() -> None:
    job = cost.Job("green_water", (1920, 1080), 0, 0)
    costs = cost.run_job(job)
    assert 2 <= len(costs) <= 4
    for c in costs:
        assert c.detector_px <= cost.MATCH_PX
        assert set(c.signals) <= {"light", "luma"} and c.signals
        assert all(math.isfinite(e) for pair in c.signals.values() for e in pair)
    luma = [c.signals["luma"] for c in costs if "luma" in c.signals]
    assert luma and np.median([w for w, _ in luma]) > np.median([wo for _, wo in luma])
    rows = cost.summary_rows([job], [costs])
    assert rows[0][:2] == ["green_water", str(len(costs))]
    assert len(rows[0]) == len(cost.HEADER)
