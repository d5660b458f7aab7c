"""Shape and contrast of a blob of a response map at full resolution (lengths in pixels).

Around a local maximum: the background is the median of an outer ring, the contrast the peak
above it; the half-maximum region (connected, holding the maximum) gives the radius
``sqrt(area / pi)`` and the roundness; the noise is the robust std of a ring just outside the
blob about a plane fitted to it, so SNR = contrast / noise; the support is where the blob's
azimuthal mean falls to 5 % of its contrast; a blob whose surroundings respond almost as
strongly is not compact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from sfm_laserscale.detection.refine import grid, window
from sfm_laserscale.detection.response import robust_std

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
TOO_LARGE = "too large to be a spot"
#: the spot support ends where the azimuthal mean contrast drops below this fraction
SUPPORT_FRACTION = 0.05


def _half_max_region(
    patch: F32, r0: int, c0: int, level: float, inner_edges: tuple[bool, bool, bool, bool]
) -> tuple[NDArray[np.bool_], bool]:
    """Connected region of ``patch >= level`` holding (r0, c0), and whether it reaches a window
    edge that is not the image border (``inner_edges``: top, bottom, left, right)."""
    labels, _ = ndimage.label(patch >= level)
    lab = labels[r0, c0]
    if lab == 0:
        region = np.zeros(patch.shape, dtype=bool)
        region[r0, c0] = True
        return region, False
    region = labels == lab
    edges = (region[0].any(), region[-1].any(), region[:, 0].any(), region[:, -1].any())
    touches = any(e and inner for e, inner in zip(edges, inner_edges, strict=True))
    return region, bool(touches)


def _roundness(region: NDArray[np.bool_]) -> float:
    """sqrt(λmin / λmax) of the region's second moments (1 = round, 0 = a line)."""
    rr, cc = np.nonzero(region)
    if len(rr) < 3:
        return 1.0
    cov = np.cov(np.stack([rr, cc]).astype(np.float64)) + np.eye(2) / 12.0  # pixel extent
    ev = np.linalg.eigvalsh(cov)
    return float(np.sqrt(max(ev[0], 0.0) / max(ev[1], 1e-12)))


@dataclass(frozen=True)
class Blob:
    """Shape and contrast of a blob (lengths in pixels)."""

    radius: float  # half-maximum radius, sqrt(area / pi)
    roundness: float
    contrast: float  # peak minus surrounding background, response units
    snr: float
    support: float  # radius where the radial profile has fallen to SUPPORT_FRACTION
    rejection: str | None = None




def _support_radius(excess: F32, rr: F64, contrast: float, radius: float, limit: float) -> float:
    """Smallest radius >= max(4, 2 r_half) where the azimuthal mean of ``excess`` is small."""
    bins = rr.astype(np.int64).ravel()
    sums = np.bincount(bins, weights=excess.ravel().astype(np.float64))
    counts = np.maximum(np.bincount(bins), 1)
    profile = sums / counts
    start = int(math.ceil(max(4.0, 2.0 * radius)))
    for r in range(start, min(len(profile), int(limit))):
        if profile[r] < SUPPORT_FRACTION * contrast:
            return float(r)
    return float(max(start, min(len(profile), int(limit)) - 1))


def _ring_plane(patch: F32, gx: F64, gy: F64, in_ring: NDArray[np.bool_]) -> F64:
    """(3,) coefficients (1, x, y) of the least-squares plane through a ring's values."""
    design = np.column_stack([np.ones(in_ring.sum()), gx[in_ring], gy[in_ring]])
    coef, *_ = np.linalg.lstsq(design, patch[in_ring].astype(np.float64), rcond=None)
    return np.asarray(coef)


def _ring_noise(patch: F32, gx: F64, gy: F64, in_ring: NDArray[np.bool_]) -> float:
    """Robust std of a ring's values about a plane fitted to them: the scene's shading across
    the ring (a strobe's hot spot, a lit slope) is no noise a spot has to stand above. A plain
    least-squares plane, not ``refine._plane_residual``'s 3-sigma-trimmed one: trimming drops
    the ring's clutter from the fit and lifts clutter blobs' SNR too (measured on the physical
    benchmark's frames: 5 spots fewer and 2 false more in 1000)."""
    if in_ring.sum() < 4:
        return 0.0
    a, bx, by = _ring_plane(patch, gx, gy, in_ring)
    return robust_std(patch[in_ring] - (a + bx * gx[in_ring] + by * gy[in_ring]))


def shape_and_contrast(
    resp: F32, row: int, col: int, max_radius: float, max_annulus_ratio: float
) -> Blob:
    """Half-max radius, roundness, contrast, SNR and support of the blob at (row, col)."""
    big = int(math.ceil(2.0 * max_radius)) + 6
    win = window(resp.shape, row, col, big)
    patch = resp[win]
    r0, c0 = row - win[0].start, col - win[1].start
    peak = float(resp[window(resp.shape, row, col, 1)].max())
    gx, gy = grid(win)
    rr = np.hypot(gx - (col + 0.5), gy - (row + 0.5))
    outer = patch[rr >= big - 4]
    bg = float(np.median(outer)) if outer.size else 0.0
    contrast = peak - bg
    if contrast <= 0:
        return Blob(0.0, 0.0, contrast, 0.0, 0.0, "no contrast against its surroundings")
    inner_edges = (win[0].start > 0, win[0].stop < resp.shape[0],
                   win[1].start > 0, win[1].stop < resp.shape[1])
    region, touches = _half_max_region(patch, r0, c0, bg + 0.5 * contrast, inner_edges)
    radius = math.sqrt(region.sum() / math.pi)
    roundness = _roundness(region)
    if touches or radius > max_radius:
        return Blob(radius, roundness, contrast, 0.0, 0.0,
                     f"{TOO_LARGE} (half-max radius > {max_radius:.1f} px)")
    in_ring = (rr >= 2.0 * radius + 2.0) & (rr <= 2.0 * radius + 5.0)
    ring = patch[in_ring]
    noise = max(_ring_noise(patch, gx, gy, in_ring), 0.5 / 255.0)
    snr = contrast / noise
    support = _support_radius(patch - bg, rr, contrast, radius, big - 4)
    ratio = float(np.percentile(ring - bg, 75)) / contrast if ring.size else 0.0
    if ratio > max_annulus_ratio:
        return Blob(radius, roundness, contrast, snr, support,
                     f"not compact (coloured surroundings: ring/peak {ratio:.2f} > "
                     f"{max_annulus_ratio:g})")
    return Blob(radius, roundness, contrast, snr, support)



def expected_support_px(radius_px: float) -> float:
    """Support radius (px) of a spot of half-max radius ``radius_px`` taken from the image's
    other spots: 2 r + 2, at least 4 px (:func:`shape_and_contrast` measures a spot's as at
    least 4 px and 2 r)."""
    return max(4.0, 2.0 * radius_px + 2.0)


def local_shape(resp: F32, row: int, col: int, radius_px: float) -> Blob | None:
    """Shape and contrast of the blob at (row, col) against its own surroundings, for a spot of
    about ``radius_px`` (the half-max radius of the image's other spots); None when its
    half-maximum region reaches that ring, or it stands above none of it.

    :func:`shape_and_contrast` measures a blob against the median of a ring twice the largest
    spot out; a spot on a bright patch (a lit slope, green water near full scale) then has a
    half-maximum region that runs into the patch and an SNR taken against texture far away.
    Here the background is the plane fitted on the ring 2r + 2 to 2r + 5 px out, and the noise
    its residual's robust std: the patch is the spot's background, as it is the eye's.
    """
    big = int(math.ceil(2.0 * radius_px + 6.0))
    win = window(resp.shape, row, col, big)
    patch = resp[win]
    gx, gy = grid(win)
    rr = np.hypot(gx - (col + 0.5), gy - (row + 0.5))
    in_ring = (rr >= 2.0 * radius_px + 2.0) & (rr <= 2.0 * radius_px + 5.0)
    if in_ring.sum() < 8:
        return None
    a, bx, by = _ring_plane(patch, gx, gy, in_ring)
    excess = (patch - (a + bx * gx + by * gy)).astype(np.float32)
    r0, c0 = row - win[0].start, col - win[1].start
    contrast = float(excess[max(0, r0 - 1):r0 + 2, max(0, c0 - 1):c0 + 2].max())
    if contrast <= 0:
        return None
    inside = rr < 2.0 * radius_px + 2.0
    region, _ = _half_max_region(np.where(inside, excess, -np.inf).astype(np.float32), r0, c0,
                                 0.5 * contrast, (False,) * 4)
    if (ndimage.binary_dilation(region) & ~inside).any():
        return None  # the half-maximum region reaches the ring: larger than a spot here
    noise = max(robust_std(excess[in_ring]), 0.5 / 255.0)
    return Blob(math.sqrt(region.sum() / math.pi), _roundness(region), contrast, contrast / noise,
                expected_support_px(radius_px))
