"""The scene-render benchmark's measures: patch shifts of a texture moved by a known amount,
and the pooled lines."""

from __future__ import annotations

from types import ModuleType

import cv2
import numpy as np
import pytest
from script_loader import load_script


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_script("bench_scene_render")


def test_patch_shifts_measure_a_known_shift(bench: ModuleType) -> None:
    """A smooth random texture and the same moved by (0.3, -0.4) px: every patch reads 0.5 px;
    patches not wholly usable are left out."""
    rng = np.random.default_rng(1)
    base = cv2.GaussianBlur(rng.normal(0, 20, (256, 320)).astype(np.float32), (0, 0), 1.5)
    moved = cv2.warpAffine(base, np.array([[1, 0, 0.3], [0, 1, -0.4]], dtype=np.float32),
                           (320, 256), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    usable = np.ones(base.shape, dtype=bool)
    usable[:64, :64] = False
    shifts = bench.patch_shifts(moved, base, usable)
    assert len(shifts) == 4 * 5 - 1
    assert np.median(shifts) == pytest.approx(0.5, abs=0.02)
    dx, dy = bench.patch_shift(moved[64:128, 64:128], base[64:128, 64:128])
    assert (dx, dy) == (pytest.approx(0.3, abs=0.02), pytest.approx(-0.4, abs=0.02))
    assert bench.patch_shift(np.zeros((64, 64), np.float32), np.zeros((64, 64), np.float32)) \
        is None


def test_pooled_lines(bench: ModuleType) -> None:
    fits = [bench.ImageFit("a.jpg", 0.9, 8.0, 3.0, (0.2, 0.4), (3, 4), 4,
                           ((0.3, 0.5, 0.7), (0.2, 0.3, 0.4, 0.5))),
            bench.ImageFit("b.jpg", 1.0, 10.0, 5.0, (0.6,), (4, 4), 4,
                           ((0.1, 0.1, 0.1, 0.1), (0.1, 0.1, 0.1, 0.1)))]
    first, alone, scene = bench.pooled_lines(fits)
    assert first.startswith("2 images: coverage median 0.950; fine texture 9.00 -> 4.00")
    assert "patch shifts (n = 3) median 0.40 px" in first
    assert alone.startswith("alone: 7 of 8 spots within 1.5 px, mean error 0.271 px")
    assert scene.startswith("with the reference: 8 of 8 spots within 1.5 px")
