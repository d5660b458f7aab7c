"""Response maps: where the image holds something that may be a laser spot.

Two responses are built per laser channel on the searched crop (linear intensities):

- the *colour* response: the laser channel's excess over what the local background colour
  predicts (``max(laser - k·other, 0)``, k the local laser/other ratio: texture and colour casts
  scale every channel alike and cancel), combined as the max with the plain colour difference
  ``max(laser - other, 0)``. Where any channel clips (a spot's white core, which JPEG may leave
  with a dip in the laser channel) a small clipped region is filled with the strongest response
  of a ring around it, so a saturated spot responds by its coloured halo and a white highlight
  by ~0;
- the *brightness* response: the mean of the three channels. It finds compact bright blobs
  whatever their hue; only its maxima where the laser channel clips become candidates (a
  saturated laser core in water of nearly the laser's colour, where the colour response sees
  little).

Each is turned into a multi-scale, scale-normalised blob response; its local maxima are the
candidates, and :func:`clutter_level` measures the scene's own blobs (texture, clutter) on the
same response, so a candidate can be judged against them. The colour response's is a
difference of Gaussians (DoG, :func:`blob_response`). The brightness holds every edge of the
scene's texture and the beams' glows in the water: a DoG peaks along such ridges, and a spot
beside or on one is no maximum of its own. Its blob response is *ridge-free*
(:func:`ridge_free_response`, the Hessian's flattest curvature), which reads a round blob as
the DoG does and a ridge or an edge as nothing.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.options import DetectionOptions

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
#: channel name -> index in an RGB array
CHANNELS: dict[str, int] = {"red": 0, "green": 1, "blue": 2}
#: Gaussian sigma (px) of the local background used for the laser/other channel ratio
RATIO_SMOOTH_PX = 24.0
#: second differences for the Hessian: along a row (its transpose along a column), and mixed
_SECOND_DIFF = np.array([[1.0, -2.0, 1.0]], dtype=np.float32)
_CROSS_DIFF = np.array([[1.0, 0.0, -1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 1.0]], dtype=np.float32) / 4
#: fewer positive local maxima than this in the searched region: no clutter level (too small)
MIN_MAXIMA_FOR_CLUTTER = 50


@dataclass(frozen=True)
class Channels:
    """The search region of an RGB image, kept as uint8 (3 bytes per pixel, where three
    float32 planes took 12), and the decoding of its values."""

    rgb: NDArray[np.uint8]  # (H, W, 3) C-contiguous crop
    lut: F32  # (256,) pixel value -> linear intensity in [0, 1], increasing

    def linear(self, win: tuple[slice, slice]) -> F64:
        """(h, w, 3) linear RGB of a window of the crop."""
        return np.asarray(self.lut[self.rgb[win]], dtype=np.float64)


def crop_channels(
    image_rgb: NDArray[np.uint8], roi: tuple[int, int, int, int], gamma: float = 1.0
) -> Channels:
    """The (x0, y0, x1, y1) crop of an RGB uint8 image, values decoded as
    ``(v / 255) ** gamma`` (1 = the image is linear) when a colour's planes are made."""
    x0, y0, x1, y1 = roi
    crop = np.ascontiguousarray(image_rgb[y0:y1, x0:x1])
    lut = ((np.arange(256, dtype=np.float64) / 255.0) ** gamma).astype(np.float32)
    return Channels(crop, lut)


def laser_and_other(channels: Channels, color: str) -> tuple[F32, F32]:
    """The laser's channel and the per-pixel max of the two others, as float32 planes.

    The max is taken on the uint8 values, then decoded: the same numbers, since the
    decoding increases."""
    c = CHANNELS[color]
    o1, o2 = [i for i in range(3) if i != c]
    rgb, lut = channels.rgb, channels.lut
    return lut[rgb[..., c]], lut[np.maximum(rgb[..., o1], rgb[..., o2])]


def brightness(channels: Channels) -> F32:
    """(H, W) mean of the three linear channels (float32)."""
    lut = channels.lut
    out = lut[channels.rgb[..., 0]]
    out += lut[channels.rgb[..., 1]]
    out += lut[channels.rgb[..., 2]]
    out *= np.float32(1.0 / 3.0)
    return out


def fill_clipped(diff: F32, clipped: NDArray[np.bool_], max_area: float) -> None:
    """In place: each clipped region of ``diff`` gets at least the max of a ring around it.

    The ring is as wide as the region's equivalent radius (2–12 px). Regions larger than
    ``max_area`` pixels (sky, glare) are left alone: they are no spot.
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats(clipped.astype(np.uint8), 8)
    h, w = diff.shape
    for i in range(1, n):
        x, y, bw, bh, area = (int(v) for v in stats[i])
        if area > max_area:
            continue
        width = int(math.ceil(min(max(math.sqrt(area / math.pi), 2.0), 12.0)))
        x0, y0 = max(0, x - width), max(0, y - width)
        x1, y1 = min(w, x + bw + width), min(h, y + bh + width)
        region = labels[y0:y1, x0:x1] == i
        src = np.where(region, 0, 255).astype(np.uint8)
        dist = cv2.distanceTransform(src, cv2.DIST_L2, 5)
        ring = (dist > 0) & (dist <= width) & ~clipped[y0:y1, x0:x1]
        if not ring.any():
            continue
        sub = diff[y0:y1, x0:x1]
        sub[region] = np.maximum(sub[region], sub[ring].max())


def colour_difference(laser: F32, other: F32) -> F32:
    """(H, W) laser-colour response ``max(laser - other, 0)`` (``other``: the max of the two
    other channels, so casts towards them and white light give 0)."""
    diff = np.subtract(laser, other, dtype=np.float32)
    np.maximum(diff, np.float32(0.0), out=diff)  # in place: one (H, W) plane, not two
    return diff


def local_ratio(laser: F32, other: F32, sigma_px: float = RATIO_SMOOTH_PX) -> F32:
    """(H, W) local background ratio k = G(laser) / G(other) (Gaussian means, clipped 0–1.5).

    Computed on a 4× reduced image (area averaging) and resized back: the background varies
    slowly, and a spot of a few pixels barely moves a 24 px mean.
    """
    h, w = laser.shape
    f = 4 if min(h, w) >= 64 else 1
    size = (max(1, w // f), max(1, h // f))
    small = [cv2.resize(c, size, interpolation=cv2.INTER_AREA) if f > 1 else c
             for c in (laser, other)]
    num, den = (cv2.GaussianBlur(c, (0, 0), sigma_px / f, borderType=cv2.BORDER_REFLECT)
                for c in small)
    k = np.clip(num / np.maximum(den, np.float32(1e-4)), 0.0, 1.5).astype(np.float32)
    if f > 1:
        k = cv2.resize(k, (w, h), interpolation=cv2.INTER_LINEAR)
    return np.asarray(k, dtype=np.float32)


def background_excess(laser: F32, other: F32) -> F32:
    """(H, W) ``max(laser - k·other, 0)``, k the local background ratio (:func:`local_ratio`).

    The scene's texture and colour cast scale every channel alike, so this cancels them and a
    faint laser spot on a strongly tinted background (red on cyan water, where
    ``laser - other`` < 0) still responds. White light responds too (by 1 - k per unit): the
    colour evidence of each candidate tells it apart (:mod:`.score`).
    """
    # in place in k's plane (same float32 operations): three (H, W) temporaries fewer
    ex = local_ratio(laser, other)
    np.multiply(ex, other, out=ex)
    np.subtract(laser, ex, out=ex)
    np.maximum(ex, np.float32(0.0), out=ex)
    return ex


@dataclass(frozen=True)
class Planes:
    """Per-colour full-resolution arrays of the crop shared by all candidates of that colour."""

    channels: Channels
    resp: F32  # (H, W) colour response (clipped regions filled)
    laser: F32  # (H, W) the laser's channel
    other: F32  # (H, W) max of the two other channels
    clipped_laser: NDArray[np.bool_]  # (H, W) laser channel clipped
    clipped_any: NDArray[np.bool_]  # (H, W) any channel clipped
    laser_rgb: F64  # (3,) expected linear camera response of the laser light (max 1)
    saturation_level: float  # linear value from which a channel counts as clipped


def make_planes(
    channels: Channels, color: str, options: DetectionOptions, max_radius: float,
    laser_rgb: tuple[float, float, float],
) -> Planes:
    """Colour response, channels and clipped masks for one laser colour."""
    laser, other = laser_and_other(channels, color)
    if options.response == "background":
        resp = background_excess(laser, other)
    else:
        resp = colour_difference(laser, other)
    clipped_laser = laser >= options.saturation_level
    clipped_any = clipped_laser | (other >= options.saturation_level)
    if np.any(clipped_any):
        fill_clipped(resp, clipped_any, 4.0 * math.pi * max_radius**2)
    return Planes(channels=channels, resp=resp, laser=laser, other=other,
                  clipped_laser=clipped_laser, clipped_any=clipped_any,
                  laser_rgb=np.asarray(laser_rgb, dtype=np.float64),
                  saturation_level=options.saturation_level)


def _pyramid_level(resp: F32, sigma: float) -> tuple[F32, int]:
    """The response on the pyramid level where a Gaussian of ``sigma`` px stays a few pixels
    wide (reduced by a power of two with area averaging, from 4 px on), and that power."""
    factor = 1
    while sigma / (2 * factor) >= 2.0:
        factor *= 2
    if factor == 1:
        return resp, 1
    size = (max(1, resp.shape[1] // factor), max(1, resp.shape[0] // factor))
    return np.asarray(cv2.resize(resp, size, interpolation=cv2.INTER_AREA), np.float32), factor


def _full_size(plane: F32, shape: tuple[int, ...], factor: int) -> F32:
    """A pyramid level's plane resized back to the response's ``shape`` (bilinear)."""
    if factor > 1:
        plane = cv2.resize(plane, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return np.asarray(plane, dtype=np.float32)


def dog_at_scale(resp: F32, sigma: float) -> F32:
    """Scale-normalised DoG -(G(1.6σ) - G(σ)) / 0.6 at full size, computed on a pyramid level.

    Scales of 4 px and more are filtered on an image reduced by a power of two (area
    averaging) so that the kernel stays a few pixels wide, then resized back (bilinear).
    """
    k = 1.6
    small, factor = _pyramid_level(resp, sigma)
    s = sigma / factor
    g1 = cv2.GaussianBlur(small, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    g2 = cv2.GaussianBlur(small, (0, 0), k * s, borderType=cv2.BORDER_REFLECT)
    dog = np.subtract(g1, g2, out=g1)  # in place (same numbers): one plane less at full size
    del g2
    np.divide(dog, np.float32(k - 1.0), out=dog)
    return _full_size(dog, resp.shape, factor)


def ridge_free_at_scale(resp: F32, sigma: float) -> F32:
    """Scale-normalised curvature of a bright blob along its flattest direction at full size:
    ``-2 σ² λ`` with λ the larger eigenvalue of the Hessian of G(σ) * resp, 0 where λ >= 0.

    A round bright blob curves down alike in every direction (λ1 = λ2 = ΔL / 2), so it reads
    as the DoG does (-σ² ΔL); a ridge (a beam's glow in the water, a lit edge, a streak of the
    texture) is flat along itself (λ ≈ 0) and reads 0; a spot on a ridge reads its own
    curvature. Computed on the pyramid level :func:`dog_at_scale` uses (a curvature per pixel
    of that level times its σ² is the same number at full size).
    """
    small, factor = _pyramid_level(resp, sigma)
    s = sigma / factor
    smooth = cv2.GaussianBlur(small, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    lxx = cv2.filter2D(smooth, -1, _SECOND_DIFF, borderType=cv2.BORDER_REFLECT)
    lyy = cv2.filter2D(smooth, -1, _SECOND_DIFF.T, borderType=cv2.BORDER_REFLECT)
    lxy = cv2.filter2D(smooth, -1, _CROSS_DIFF, borderType=cv2.BORDER_REFLECT)
    half_gap = np.hypot(0.5 * (lxx - lyy), lxy)
    flattest = 0.5 * (lxx + lyy) + half_gap  # the larger eigenvalue
    out = np.maximum(np.float32(-2.0 * s * s) * flattest, np.float32(0.0))
    return _full_size(out, resp.shape, factor)


def _max_over_scales(resp: F32, sigmas: tuple[float, ...],
                     at_scale: Callable[[F32, float], F32]) -> F32:
    """(H, W) max over ``sigmas`` of a scale-normalised blob response ``at_scale``."""
    out = at_scale(resp, sigmas[0])
    for s in sigmas[1:]:
        np.maximum(out, at_scale(resp, s), out=out)
    return out


def blob_response(resp: F32, sigmas: tuple[float, ...]) -> F32:
    """(H, W) max over ``sigmas`` of the scale-normalised DoG of a colour response."""
    return _max_over_scales(resp, sigmas, dog_at_scale)


def ridge_free_response(resp: F32, sigmas: tuple[float, ...]) -> F32:
    """(H, W) max over ``sigmas`` of :func:`ridge_free_at_scale`."""
    return _max_over_scales(resp, sigmas, ridge_free_at_scale)


def local_maxima(dog: F32, min_value: float) -> NDArray[np.intp]:
    """(N, 2) integer (row, col) of 5×5 local maxima above ``min_value``, strongest first."""
    dilated = cv2.dilate(dog, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_REPLICATE)
    peaks = (dog >= dilated) & (dog > min_value)
    rows, cols = np.nonzero(peaks)
    order = np.argsort(-dog[rows, cols], kind="stable")
    return np.column_stack([rows[order], cols[order]])


def clutter_level(dog: F32, quantile: float = 99.0, where: NDArray[np.bool_] | None = None
                  ) -> float:
    """The scene's blob clutter: ``quantile`` % of the DoG at its positive 5×5 local maxima.

    A laser image holds a handful of spots among thousands of local maxima (noise, texture), so
    this measures the texture's strongest blobs, not the spots. ``where``: count only maxima
    there (away from the beam bands, whose own laser light — spots, the beams' glow in the
    water — is not the scene's); all of them when fewer than MIN_MAXIMA_FOR_CLUTTER lie there.
    0 when there are fewer than MIN_MAXIMA_FOR_CLUTTER maxima in all.
    """
    dilated = cv2.dilate(dog, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_REPLICATE)
    peaks = (dog >= dilated) & (dog > 0)
    if where is not None and int(np.count_nonzero(peaks & where)) >= MIN_MAXIMA_FOR_CLUTTER:
        peaks &= where
    values = dog[peaks]
    if values.size < MIN_MAXIMA_FOR_CLUTTER:
        return 0.0
    return float(np.percentile(values, quantile))


def robust_std(values: NDArray[np.floating]) -> float:
    """1.4826 × median absolute deviation."""
    if values.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


