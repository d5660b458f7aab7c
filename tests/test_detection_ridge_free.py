"""The ridge-free blob response (the brightness response's, ``ridge_free_brightness``): a round
blob reads its curvature, a ridge or an edge reads nothing, and a spot on a ridge is a maximum
of its own where the DoG's maxima run along the ridge (closed-form images)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sfm_laserscale.detection.response import (
    blob_response,
    dog_at_scale,
    local_maxima,
    ridge_free_at_scale,
    ridge_free_response,
)

SIGMAS = (1.0, 2.0, 4.0, 8.0)
SHAPE = (96, 128)


def _grid() -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(np.float64)
    return xx, yy


def _blob(x0: float, y0: float, sigma: float, peak: float = 1.0) -> np.ndarray:
    xx, yy = _grid()
    return peak * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * sigma**2))


def _ridge(slope: float, offset: float, sigma: float, peak: float = 1.0) -> np.ndarray:
    """A straight bright line y = slope·x + offset with a Gaussian profile across it."""
    xx, yy = _grid()
    across = (yy - slope * xx - offset) / math.hypot(1.0, slope)
    return peak * np.exp(-across**2 / (2 * sigma**2))


@pytest.mark.parametrize(("blob_sigma", "scale"), [(1.0, 2.0), (1.5, 2.0), (3.0, 2.0)])
def test_a_round_blob_reads_its_curvature(blob_sigma: float, scale: float) -> None:
    # G(s) * (A·G(b)) is a Gaussian of variance b² + s² and peak A b² / (b² + s²); its
    # curvature at the centre is -peak / (b² + s²) in every direction
    image = _blob(64.0, 48.0, blob_sigma).astype(np.float32)
    variance = blob_sigma**2 + scale**2
    expected = 2 * scale**2 * blob_sigma**2 / variance**2
    got = float(ridge_free_at_scale(image, scale)[48, 64])
    assert got == pytest.approx(expected, rel=0.06)


def test_a_ridge_and_an_edge_read_nothing_where_the_dog_responds() -> None:
    # a glow 2 px wide, slanted across the pixel grid (whose sampling leaves a few % of
    # curvature along it), and a step edge
    ridge = _ridge(0.3, 20.0, 2.0).astype(np.float32)
    _, yy = _grid()
    edge = (yy > 60).astype(np.float32)
    for image in (ridge, edge):
        dog = blob_response(image, SIGMAS)
        free = ridge_free_response(image, SIGMAS)
        inner = (slice(24, -24), slice(24, -24))  # away from the reflected borders
        assert float(dog[inner].max()) > 0.1
        assert float(free[inner].max()) < 0.05 * float(dog[inner].max())


def test_a_spot_on_a_ridge_is_a_maximum_of_its_own() -> None:
    # a faint spot on a beam's glow twice as bright: the DoG's maxima run along the glow,
    # the ridge-free response peaks at the spot alone
    spot = (70.3, 41.6)
    image = (_ridge(0.3, 20.0, 2.0, 0.6) + _blob(*spot, 1.0, 0.3)).astype(np.float32)
    dog = blob_response(image, SIGMAS)
    free = ridge_free_response(image, SIGMAS)
    inner = np.zeros(SHAPE, bool)
    inner[12:-12, 12:-12] = True
    dog_peaks = [p for p in local_maxima(dog, 0.01) if inner[p[0], p[1]]]
    free_peaks = [p for p in local_maxima(free, 0.01) if inner[p[0], p[1]]]
    assert len(free_peaks) == 1
    row, col = free_peaks[0]
    assert math.hypot(col + 0.5 - spot[0], row + 0.5 - spot[1]) < 1.5
    assert any(math.hypot(c + 0.5 - spot[0], r + 0.5 - spot[1]) > 5 for r, c in dog_peaks)


def test_large_scales_are_taken_on_the_pyramid() -> None:
    # scales of 4 px and more are filtered on a reduced image and resized back, as the DoG is;
    # the reduction's area averaging widens the blob a little (closed form 0.404)
    image = _blob(64.0, 48.0, 5.0).astype(np.float32)
    free = ridge_free_at_scale(image, 8.0)
    assert free.shape == dog_at_scale(image, 8.0).shape == SHAPE
    assert free.dtype == np.float32
    row, col = np.unravel_index(int(np.argmax(free)), SHAPE)
    assert abs(col - 64) <= 1 and abs(row - 48) <= 1
    assert float(free[row, col]) == pytest.approx(2 * 64 * 25 / 89**2, rel=0.2)
