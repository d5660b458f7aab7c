"""How well a rendered scene reference fits its laser image, and the reference kept where it helps.

Both are reduced to the fine texture the detector would subtract
(:func:`sfm_laserscale.detection.scene.scene_texture`, the mean of the three channels) and cut
into cells of ``patch_px``. Per cell two things are measured:

- the residual ratio, std(image − reference) / std(image) over the pixels the reference
  covers: below 1 the reference explains the image's texture, at or above 1 subtracting it
  adds texture (a misfit, parallax, a blend of views, or noise where the image has no texture);
- the shift (px) that carries the reference's texture onto the image's, by least squares
  (Gauss–Newton on the sum of squared differences, Lucas–Kanade), where the cell is wholly
  covered and textured enough to tell.

A laser spot is in the image and not in the reference, so its own cell reads badly; each cell
is judged by the median of its 3 × 3 neighbourhood instead. A cell whose neighbourhood ratio
exceeds ``max_residual_ratio`` loses its reference (NaN): the detector searches it on the
photograph alone. docs/DETECTION.md ("A scene reference in scale") has the measurements
behind the limit.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.scene import scene_texture
from sfm_laserscale.errors import InputError

#: Gauss–Newton steps of the shift
SHIFT_STEPS = 3
#: the shift's normal matrix's condition number above which a cell cannot tell a shift
SHIFT_MAX_CONDITION = 1e3
#: px of covered pixels next to uncovered ones left out of the shift (false gradients there)
EDGE_PX = 2


@dataclass(frozen=True)
class SceneFitOptions:
    """``patch_px``: the cells' side (about); a cell's reference is dropped when its 3 × 3
    neighbourhood's median residual ratio exceeds ``max_residual_ratio`` or its median
    |shift| exceeds ``max_shift_px``; ``min_known``: the share of a cell the reference must
    cover to be measured; ``texture_sigma_px``: the fine texture's scale (the detector's
    ``scene_texture_sigma_px``); ``working_width_px``: the fit works on the images shrunk by
    an integer factor to about this width, where the limits were measured (a 1 px shift at
    1920 × 1080 is 2 px at 4000 × 3000: the same angle)."""

    patch_px: int = 64
    max_residual_ratio: float = 1.0
    max_shift_px: float = 1.0
    min_known: float = 0.5
    texture_sigma_px: float = 8.0
    working_width_px: int = 1920

    def __post_init__(self) -> None:
        if self.patch_px < 16:
            raise InputError(f"patch_px must be at least 16, got {self.patch_px}")
        if not (self.max_residual_ratio > 0 and self.max_shift_px > 0):
            raise InputError("max_residual_ratio and max_shift_px must be > 0, got "
                             f"{self.max_residual_ratio} and {self.max_shift_px}")
        if not 0 < self.min_known <= 1:
            raise InputError(f"min_known must be in (0, 1], got {self.min_known}")
        if self.working_width_px < 1:
            raise InputError(f"working_width_px must be >= 1, got {self.working_width_px}")


@dataclass(frozen=True)
class ReferenceFit:
    """The reference (H, W, 3) float32 with the cells that do not fit set to NaN; per cell
    (rows, cols) the residual ratio, the shift (dx, dy) px (NaN: not measured) and whether
    it was kept; pooled: the median ratio and the median and 90th percentile |shift| (NaN:
    none), and the share of the covered pixels still covered."""

    rgb: NDArray[np.float32]
    ratio: NDArray[np.float64]
    shift_px: NDArray[np.float64]  # (rows, cols, 2)
    kept: NDArray[np.bool_]
    ratio_median: float
    shift_median_px: float
    shift_p90_px: float
    kept_share: float


def cell_edges(size: int, patch_px: int) -> NDArray[np.int64]:
    """The edges (n + 1) of n cells of about ``patch_px`` along an axis of ``size`` px."""
    n = max(1, round(size / patch_px))
    return np.linspace(0, size, n + 1).round().astype(np.int64)


def cell_sums(values: NDArray[np.floating], rows: NDArray[np.int64],
              cols: NDArray[np.int64]) -> NDArray[np.float64]:
    """Per cell, the sum of ``values`` (H, W) over it: (rows − 1, cols − 1), float64 (summed
    in the values' own type: float32 halves the time at 12 MP, and a cell's sum of a few
    thousand terms keeps 6 digits)."""
    sums = np.add.reduceat(np.add.reduceat(values, rows[:-1], axis=0), cols[:-1], axis=1)
    return np.asarray(sums, dtype=np.float64)


def pixel_cells(edges: NDArray[np.int64]) -> NDArray[np.int64]:
    """Per pixel along an axis, the index of its cell (cell ``i`` spans edges[i]:edges[i+1])."""
    return np.repeat(np.arange(len(edges) - 1), np.diff(edges))


def residual_ratios(a: NDArray[np.float32], b: NDArray[np.float32], known: NDArray[np.bool_],
                    rows: NDArray[np.int64], cols: NDArray[np.int64],
                    min_known: float) -> NDArray[np.float64]:
    """Per cell, std(a − b) / std(a) over the known pixels (NaN: too few, or a flat)."""
    w = known.astype(np.float32)
    count = cell_sums(w, rows, cols)
    area = np.outer(np.diff(rows), np.diff(cols))

    def var(x: NDArray[np.float32]) -> NDArray[np.float64]:
        mean = cell_sums(w * x, rows, cols) / np.maximum(count, 1)
        return np.asarray(cell_sums(w * x * x, rows, cols) / np.maximum(count, 1) - mean ** 2)

    own, left = var(a), var(a - b)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.sqrt(np.maximum(left, 0.0) / own)
    ratio[(count < min_known * area) | ~(own > 0)] = np.nan
    return np.asarray(ratio)


def cell_shifts(a: NDArray[np.float32], b: NDArray[np.float32], known: NDArray[np.bool_],
                rows: NDArray[np.int64], cols: NDArray[np.int64],
                min_known: float) -> NDArray[np.float64]:
    """Per cell the translation (dx, dy) px carrying texture ``b`` onto ``a`` (a(x) =
    b(x − d)): SHIFT_STEPS Gauss–Newton steps from zero on the sum of squared differences over
    the cell's known pixels (Lucas–Kanade); NaN where too little is known or the texture
    cannot tell (too faint, or in one direction only). (rows − 1, cols − 1, 2)."""
    gy, gx = np.gradient(b)
    w = cv2.erode(known.astype(np.uint8), np.ones((2 * EDGE_PX + 1,) * 2, np.uint8),
                  borderType=cv2.BORDER_REPLICATE).astype(np.float32)
    sxx, sxy, syy = (cell_sums(w * p * q, rows, cols) for p, q in ((gx, gx), (gx, gy), (gy, gy)))
    det = sxx * syy - sxy ** 2
    trace = sxx + syy
    # cond = λmax / λmin of the 2 × 2 normal matrix, from its trace and determinant
    root = np.sqrt(np.maximum(trace ** 2 / 4 - det, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        cond = (trace / 2 + root) / (trace / 2 - root)
    area = np.outer(np.diff(rows), np.diff(cols))
    usable = (cell_sums(w, rows, cols) >= min_known * area) & (det > 0) & (
        cond <= SHIFT_MAX_CONDITION)
    d = np.zeros((*usable.shape, 2))
    pix_c, pix_r = np.meshgrid(np.arange(a.shape[1], dtype=np.float32),
                               np.arange(a.shape[0], dtype=np.float32))
    cell_r, cell_c = pixel_cells(rows), pixel_cells(cols)
    for _ in range(SHIFT_STEPS):
        dx = d[..., 0][np.ix_(cell_r, cell_c)].astype(np.float32)
        dy = d[..., 1][np.ix_(cell_r, cell_c)].astype(np.float32)
        # cubic: a linear interpolation's smoothing biases a sub-pixel shift
        moved = cv2.remap(b, pix_c - dx, pix_r - dy, cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)
        r = a - moved
        gxr, gyr = cell_sums(w * gx * r, rows, cols), cell_sums(w * gy * r, rows, cols)
        with np.errstate(invalid="ignore", divide="ignore"):
            d[..., 0] -= np.where(usable, (syy * gxr - sxy * gyr) / det, 0.0)
            d[..., 1] -= np.where(usable, (sxx * gyr - sxy * gxr) / det, 0.0)
    d[~usable] = np.nan
    return d


def neighbourhood_median(grid: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per cell, the median of the finite values in its 3 × 3 neighbourhood (NaN: none)."""
    padded = np.pad(grid, 1, constant_values=np.nan)
    rows, cols = grid.shape
    stack = np.stack([padded[dy:dy + rows, dx:dx + cols] for dy in range(3) for dx in range(3)])
    with warnings.catch_warnings():  # a neighbourhood without a measure stays NaN
        warnings.filterwarnings("ignore", message="All-NaN slice encountered")
        return np.asarray(np.nanmedian(stack, axis=0), dtype=np.float64)


def _finite_stat(values: NDArray[np.float64], q: float) -> float:
    finite = values[np.isfinite(values)]
    return float(np.percentile(finite, q)) if len(finite) else math.nan


def working_factor(width_px: int, options: SceneFitOptions) -> int:
    """The integer factor the fit shrinks an image by: about ``working_width_px`` wide."""
    return max(1, round(width_px / options.working_width_px))


def shrink(image_rgb: NDArray[np.floating] | NDArray[np.uint8],
           factor: int) -> NDArray[np.float32]:
    """(H, W, 3) averaged over ``factor`` × ``factor`` blocks (H // factor, W // factor, 3); a
    block with an unknown (NaN) pixel is unknown."""
    if factor == 1:
        return np.asarray(image_rgb, dtype=np.float32)
    height, width = (n // factor * factor for n in image_rgb.shape[:2])
    blocks = np.asarray(image_rgb[:height, :width], dtype=np.float32).reshape(
        height // factor, factor, width // factor, factor, 3)
    return np.asarray(blocks.mean(axis=(1, 3)), dtype=np.float32)  # NaN propagates


def fit_reference(image_rgb: NDArray[np.uint8], reference_rgb: NDArray[np.float32],
                  options: SceneFitOptions = SceneFitOptions()) -> ReferenceFit:  # noqa: B008
    """Measure the reference against the image per cell and drop it where it does not fit
    (module docstring). Both are first shrunk to about ``working_width_px`` wide by an
    integer factor k; cells, texture scale and shift limit are in those pixels (k of the
    image's), and the shifts returned in the image's."""
    if reference_rgb.shape != image_rgb.shape:
        raise InputError(f"the reference is {reference_rgb.shape}, the image {image_rgb.shape}")
    k = working_factor(image_rgb.shape[1], options)
    small_ref = shrink(reference_rgb, k)
    sigma = options.texture_sigma_px
    a = scene_texture(shrink(image_rgb, k), sigma).mean(axis=2, dtype=np.float32)
    b = scene_texture(small_ref, sigma).mean(axis=2, dtype=np.float32)
    covered: NDArray[np.bool_] = np.asarray(np.isfinite(small_ref).all(axis=2))
    rows = cell_edges(a.shape[0], options.patch_px)
    cols = cell_edges(a.shape[1], options.patch_px)
    ratio = residual_ratios(a, b, covered, rows, cols, options.min_known)
    shift = cell_shifts(a, b, covered, rows, cols, options.min_known) * k
    length = np.hypot(shift[..., 0], shift[..., 1])
    kept = ~((neighbourhood_median(ratio) > options.max_residual_ratio)
             | (neighbourhood_median(length) > options.max_shift_px * k))
    full_rows, full_cols = rows * k, cols * k
    full_rows[-1], full_cols[-1] = image_rgb.shape[0], image_rgb.shape[1]  # the rims' rest
    keep_px = kept[np.ix_(pixel_cells(full_rows), pixel_cells(full_cols))]
    rgb = np.where(keep_px[..., None], reference_rgb, np.float32(np.nan)).astype(np.float32)
    known = np.isfinite(reference_rgb).all(axis=2)
    before = int(known.sum())
    return ReferenceFit(rgb=rgb, ratio=ratio, shift_px=shift, kept=kept,
                        ratio_median=_finite_stat(ratio, 50),
                        shift_median_px=_finite_stat(length, 50),
                        shift_p90_px=_finite_stat(length, 90),
                        kept_share=int((known & keep_px).sum()) / before if before else 0.0)
