"""scene_fit: a rendered scene reference measured against its photograph, and dropped where it
does not fit (closed-form textures: known shifts, an unrelated texture, a spot)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.scene_fit import (
    SceneFitOptions,
    cell_edges,
    fit_reference,
    neighbourhood_median,
)

SIZE = (384, 512)  # rows, cols: 6 x 8 cells of 64 px


def _texture(seed: int, shape: tuple[int, int] = SIZE) -> NDArray[np.float32]:
    """A seafloor-like texture: blobs of 2-4 px over a mid grey, in 8-bit levels (H, W, 3)."""
    rng = np.random.default_rng(seed)
    grey = cv2.GaussianBlur(rng.normal(0.0, 1.0, shape).astype(np.float32), (0, 0), 2.0)
    grey = 120.0 + 20.0 * grey / grey.std()
    return np.repeat(grey[..., None], 3, axis=2).astype(np.float32)


def _shifted(rgb: NDArray[np.float32], dx: float, dy: float) -> NDArray[np.float32]:
    """``rgb`` moved by (dx, dy) px: out(x) = rgb(x − d)."""
    move = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], dtype=np.float32)
    return cv2.warpAffine(rgb, move, (rgb.shape[1], rgb.shape[0]), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


def _photo(rgb: NDArray[np.float32], seed: int = 9) -> NDArray[np.uint8]:
    noisy = rgb + np.random.default_rng(seed).normal(0.0, 1.0, rgb.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def test_a_reference_off_by_a_known_shift_is_measured_and_kept() -> None:
    floor = _texture(1)
    photo = _photo(_shifted(floor, 0.3, -0.2))
    fit = fit_reference(photo, floor)
    assert fit.shift_median_px == pytest.approx(np.hypot(0.3, 0.2), abs=0.05)
    assert np.nanmedian(fit.shift_px[..., 0]) == pytest.approx(0.3, abs=0.05)
    assert np.nanmedian(fit.shift_px[..., 1]) == pytest.approx(-0.2, abs=0.05)
    assert fit.kept.all() and fit.kept_share == 1.0
    assert fit.ratio_median < 0.5
    np.testing.assert_array_equal(fit.rgb, floor)


def test_a_reference_two_pixels_off_is_dropped() -> None:
    floor = _texture(2)
    fit = fit_reference(_photo(_shifted(floor, 1.6, 1.2)), floor)
    assert fit.shift_median_px == pytest.approx(2.0, abs=0.2)
    assert not fit.kept.any() and fit.kept_share == 0.0
    assert np.isnan(fit.rgb).all()


def test_where_the_reference_shows_another_floor_it_is_dropped() -> None:
    floor, other = _texture(3), _texture(4)
    reference = floor.copy()
    reference[:, 256:] = other[:, 256:]  # the right half is not this photograph's floor
    fit = fit_reference(_photo(floor), reference)
    assert fit.kept[:, :3].all() and not fit.kept[:, 5:].any()
    assert np.nanmin(fit.ratio[:, 5:]) > 1.0 and np.nanmax(fit.ratio[:, :3]) < 0.5
    assert np.isfinite(fit.rgb[:, :192]).all() and np.isnan(fit.rgb[:, 320:]).all()
    assert 0.4 < fit.kept_share < 0.6


def test_a_laser_spot_in_the_photograph_keeps_its_cell() -> None:
    floor = _texture(5)
    photo = floor.copy()
    rows, cols = np.mgrid[0:SIZE[0], 0:SIZE[1]]
    spot = 400.0 * np.exp(-((cols - 160.0) ** 2 + (rows - 96.0) ** 2) / (2 * 4.0 ** 2))
    photo = np.minimum(photo + spot[..., None], 255)  # a clipped white core
    fit = fit_reference(_photo(photo), floor)
    others = np.delete(fit.ratio.ravel(), 1 * 8 + 2)
    assert fit.ratio[1, 2] > 3 * others.max()
    # judged alone, the spot's cell would lose its reference; by its neighbourhood it keeps it
    strict = SceneFitOptions(max_residual_ratio=0.5 * (fit.ratio[1, 2] + others.max()))
    assert fit_reference(_photo(photo), floor, strict).kept.all()


def test_unknown_pixels_are_neither_measured_nor_counted() -> None:
    floor = _texture(6)
    reference = floor.copy()
    reference[:128] = np.nan
    fit = fit_reference(_photo(floor), reference)
    assert np.isnan(fit.ratio[:2]).all() and np.isnan(fit.shift_px[:2]).all()
    assert fit.kept_share == 1.0 and np.isnan(fit.rgb[:128]).all()
    empty = fit_reference(_photo(floor), np.full_like(floor, np.nan))
    assert empty.kept_share == 0.0 and np.isnan(empty.ratio_median)


def test_cells_and_neighbourhoods() -> None:
    assert list(cell_edges(1080, 64)) == [round(k * 1080 / 17) for k in range(18)]
    assert list(cell_edges(40, 64)) == [0, 40]
    grid = np.array([[1.0, np.nan, 3.0], [np.nan, 9.0, np.nan]])
    out = neighbourhood_median(grid)
    assert out[0, 0] == 5.0 and out[0, 1] == 3.0 and out[1, 2] == 6.0
    assert np.isnan(neighbourhood_median(np.full((2, 2), np.nan))).all()


def test_bad_input_is_refused() -> None:
    with pytest.raises(InputError, match="patch_px"):
        SceneFitOptions(patch_px=8)
    with pytest.raises(InputError, match="max_residual_ratio"):
        SceneFitOptions(max_shift_px=0.0)
    with pytest.raises(InputError, match="min_known"):
        SceneFitOptions(min_known=0.0)
    with pytest.raises(InputError, match="the reference is"):
        fit_reference(np.zeros((10, 10, 3), np.uint8), np.zeros((10, 12, 3), np.float32))


def test_a_large_image_is_fitted_at_the_working_width() -> None:
    """4000 px wide: the fit works at half size (k = 2), so its 1 px limit is 2 px of the
    image (the same angle as 1 px at 1920 × 1080); shifts are returned in the image's px."""
    wide = _texture(7, (512, 4000))
    kept = fit_reference(_photo(_shifted(wide, 1.2, 0.9)), wide)
    assert kept.ratio.shape == (4, 31)  # cells of 64 px at 2000 x 256
    assert kept.shift_median_px == pytest.approx(1.5, abs=0.2) and kept.kept.all()
    dropped = fit_reference(_photo(_shifted(wide, 2.4, 1.8)), wide)
    # 1.5 working px on a 1 px texture: three steps read it short, still beyond the limit
    assert 2.0 < dropped.shift_median_px < 3.2 and not dropped.kept.any()
    odd = _texture(8, (515, 4001))  # the rims beyond whole blocks go with the last cells
    fit = fit_reference(_photo(odd), odd)
    assert fit.kept.all() and np.isfinite(fit.rgb).all() and fit.kept_share == 1.0
