"""``scripts/bench_centre_floor.py``: the two estimators on closed-form spots, and one frame."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import erf

from tests.script_loader import load_script

floor = load_script("bench_centre_floor")


def _spot(centre: tuple[float, float], sigma: float, size: int = 31) -> np.ndarray:
    """A pixel-integrated 2D Gaussian of unit volume (COLMAP pixel centres at +0.5)."""
    edges = np.arange(size + 1, dtype=np.float64)
    k = 1.0 / (math.sqrt(2.0) * sigma)
    px = np.diff(0.5 * erf((edges - centre[0]) * k))
    py = np.diff(0.5 * erf((edges - centre[1]) * k))
    return np.outer(py, px)


@pytest.mark.parametrize(("centre", "sigma"), [((15.3, 14.8), 0.6), ((15.5, 15.2), 1.5)])
def test_both_estimators_find_a_clean_spot(centre: tuple[float, float], sigma: float) -> None:
    light = _spot(centre, sigma)
    start = (centre[0] + 0.4, centre[1] - 0.3)
    fx, fy = floor.gaussian_fit(light, start, sigma * 1.3)
    assert math.dist((fx, fy), centre) < 1e-3  # the model is exact
    cx, cy = floor.windowed_centroid(light, start, 1.5 * sigma + 0.5)
    assert math.dist((cx, cy), centre) < 0.05  # a pixelated spot: pixel-locking only
    errs = floor.spot_errors(light + 0.01, centre, sigma)  # a constant under it
    assert errs is not None
    assert errs[1] < 1e-3


def test_a_spot_at_the_border_is_left_out() -> None:
    assert floor.spot_errors(_spot((3.0, 15.0), 0.6), (3.0, 15.0), 0.6) is None


def test_one_frame_gives_errors_near_its_spots() -> None:
    job = floor.Job("red_clean", (1920, 1080), 0, 0)
    errs = floor.run_job(job)
    assert 2 <= len(errs) <= 4
    assert all(0.0 <= e < 1.0 for pair in errs for e in pair)
    rows = floor.summary_rows([job], [errs])
    assert rows[0][:2] == ("red_clean", len(errs))


def test_an_unknown_condition_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert floor.main(["--conditions", "red_clean,nope", "--per-condition", "1"]) == 2
    assert "nope" in capsys.readouterr().err


def test_the_image_sigma_adds_the_blurs_in_quadrature() -> None:
    meta = {"psf_sigma_px": 0.3, "motion_px": 12.0 ** 0.5 * 0.4, "defocus_radius_px": 2.0}
    assert floor.image_sigma_px(meta, 0.0) == pytest.approx(math.sqrt(0.09 + 0.16 + 1.0))
    assert floor.image_sigma_px({}, 0.2) == 0.5
