"""Paint realistic laser spots into synthetic images (linear RGB, COLMAP pixel convention).

A spot is the sum of
- a core Gaussian (sigma ``sigma_px``) in the laser colour whose peak exceeds 1, plus a
  fraction of it leaking into every channel, so that after clipping the core is white;
- a wider, fainter halo Gaussian (sigma ``HALO_SIGMA_FACTOR * sigma_px``) in the laser colour.
Both are optionally smeared along a motion-blur vector.

Each pixel receives the exact integral of the light over its footprint (separable erf of the
Gaussian, averaged over evenly spaced positions along the blur segment), so the intensity
centroid of the added light is exactly ``xy_px``. Pixel (i, j) covers [j, j+1) x [i, i+1);
its centre is (j + 0.5, i + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

#: Linear RGB of each laser colour (dominant channel 1; small leaks as seen on real sensors).
LASER_RGB: dict[str, tuple[float, float, float]] = {
    "red": (1.0, 0.03, 0.02),
    "green": (0.05, 1.0, 0.12),
    "blue": (0.04, 0.10, 1.0),
}
#: Halo sigma as a multiple of the core sigma.
HALO_SIGMA_FACTOR = 3.0
#: Halo peak (linear intensity) per unit of ``halo``.
HALO_PEAK = 0.35
#: Fraction of the core peak shared by every channel (the core turns white once clipped).
CORE_WHITE_LEAK = 0.4
#: Samples along a motion-blur segment per pixel of its length (at least 2 in all).
BLUR_SAMPLES_PER_PX = 4.0


@dataclass(frozen=True)
class SpotRenderOptions:
    """Appearance of a painted spot (see :func:`paint_spot` for the meaning of each field)."""

    color: str = "red"
    sigma_px: float = 2.0
    peak: float = 3.0
    elongation: tuple[float, float] | None = None
    halo: float = 1.0


def _blur_offsets(elongation: tuple[float, float] | None) -> NDArray[np.float64]:
    """(K, 2) offsets along the blur segment, symmetric about 0 (centroid preserved)."""
    if elongation is None:
        return np.zeros((1, 2))
    vec = np.asarray(elongation, dtype=np.float64)
    length = float(np.linalg.norm(vec))
    if length < 1e-9:
        return np.zeros((1, 2))
    k = max(2, int(np.ceil(length * BLUR_SAMPLES_PER_PX)) + 1)
    u = np.linspace(-0.5, 0.5, k)
    return u[:, None] * vec[None, :]


def _pixel_integrals(
    edges: NDArray[np.float64], centres: NDArray[np.float64], sigma: float
) -> NDArray[np.float64]:
    """(K, n) integral of a unit 1D Gaussian (centre per row) over the n pixel intervals."""
    cdf = ndtr((edges[None, :] - centres[:, None]) / sigma)
    return np.asarray(np.diff(cdf, axis=1), dtype=np.float64)


def _blob(
    x_edges: NDArray[np.float64], y_edges: NDArray[np.float64],
    centres: NDArray[np.float64], sigma: float,
) -> NDArray[np.float64]:
    """(h, w) pixel-integrated, blur-averaged unit-peak Gaussian (peak = 1 at zero blur)."""
    ix = _pixel_integrals(x_edges, centres[:, 0], sigma)  # (K, w)
    iy = _pixel_integrals(y_edges, centres[:, 1], sigma)  # (K, h)
    mass = np.einsum("kh,kw->hw", iy, ix) / len(centres)  # fraction of the unit mass per pixel
    return np.asarray(mass * (2.0 * np.pi * sigma * sigma), dtype=np.float64)


def paint_spot(
    image: NDArray[np.float32],
    xy_px: tuple[float, float],
    color: str = "red",
    sigma_px: float = 2.0,
    peak: float = 3.0,
    elongation: tuple[float, float] | None = None,
    halo: float = 1.0,
) -> None:
    """Add a laser spot centred at ``xy_px`` (COLMAP convention) to a linear RGB image in place.

    ``image``: (H, W, 3) float, linear RGB (1 = white). ``peak``: core intensity in the laser
    channel (>1 saturates). ``elongation``: motion-blur vector in pixels (the spot is smeared
    over a segment of that length and direction, centred on ``xy_px``). ``halo``: scale of the
    wide coloured halo (0 for none).
    """
    if color not in LASER_RGB:
        raise ValueError(f"color must be one of {', '.join(LASER_RGB)}, got {color!r}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3), got {image.shape}")
    if sigma_px <= 0:
        raise ValueError(f"sigma_px must be positive, got {sigma_px}")
    h_img, w_img = image.shape[:2]
    offsets = _blur_offsets(elongation)
    centres = np.asarray(xy_px, dtype=np.float64)[None, :] + offsets
    sigma_h = HALO_SIGMA_FACTOR * sigma_px
    reach = 5.0 * (sigma_h if halo > 0 else sigma_px) + 1.0
    x0 = max(0, int(np.floor(centres[:, 0].min() - reach)))
    x1 = min(w_img, int(np.ceil(centres[:, 0].max() + reach)))
    y0 = max(0, int(np.floor(centres[:, 1].min() - reach)))
    y1 = min(h_img, int(np.ceil(centres[:, 1].max() + reach)))
    if x0 >= x1 or y0 >= y1:
        return  # entirely outside the image
    x_edges = np.arange(x0, x1 + 1, dtype=np.float64)
    y_edges = np.arange(y0, y1 + 1, dtype=np.float64)
    rgb = np.asarray(LASER_RGB[color], dtype=np.float64)
    core = _blob(x_edges, y_edges, centres, sigma_px)
    core_rgb = peak * ((1.0 - CORE_WHITE_LEAK) * rgb + CORE_WHITE_LEAK)  # laser channel = peak
    light = core[:, :, None] * core_rgb[None, None, :]
    if halo > 0:
        light += _blob(x_edges, y_edges, centres, sigma_h)[:, :, None] * (HALO_PEAK * halo * rgb)
    image[y0:y1, x0:x1, :] += light.astype(image.dtype)


def paint_spot_with(image: NDArray[np.float32], xy_px: tuple[float, float],
                    options: SpotRenderOptions) -> None:
    """:func:`paint_spot` with the appearance taken from a :class:`SpotRenderOptions`."""
    paint_spot(image, xy_px, color=options.color, sigma_px=options.sigma_px, peak=options.peak,
               elongation=options.elongation, halo=options.halo)


def to_uint8(image: NDArray[np.floating], gamma: float | None = None) -> NDArray[np.uint8]:
    """(H, W, 3) linear float -> uint8: clip to [0, 1], optional gamma encoding (v ** (1/gamma))."""
    img = np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0)
    if gamma is not None and gamma != 1.0:
        img = img ** (1.0 / gamma)
    return np.asarray(np.round(img * 255.0), dtype=np.uint8)
