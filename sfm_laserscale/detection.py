"""Laser spots in one image: sub-pixel centres (COLMAP pixel convention) assigned to lasers.

Pipeline (per laser colour needed by the rig):

1. colour response: the max of ``max(R - max(G, B), 0)`` (for red) and the excess over the
   local background, ``max(R - k·max(G, B), 0)`` with k the local background ratio (texture
   and casts cancel; a faint red spot on cyan water responds). Where the laser channel is
   clipped (the white, saturated core of a bright spot) the response is filled with the
   strongest response found in a ring around the clipped region, so a saturated spot with a
   coloured halo responds (a white highlight is rejected later by its added-light colour);
2. multi-scale, scale-normalised difference-of-Gaussians on that response; local maxima above a
   noise-relative threshold and above ``min_clutter_ratio`` × the scene's clutter level (the
   99th percentile of the DoG at all its local maxima: a textured seafloor's reddish pebbles
   and patches also excite the background response, but as a population, and a laser spot
   stands far above it) are the *candidates*;
3. each candidate is measured at full resolution (half-maximum radius, roundness, contrast and
   SNR against a background annulus, compactness = the annulus must be dark) and refined to
   sub-pixel precision on a texture-free signal: the laser channel minus its local linear
   prediction from the (smoothed) other channels and a plane, fitted on a ring outside the
   spot's support, so the scene texture (present in every channel) cancels. The centre is a
   Gaussian-windowed centroid iterated to its fixed point (unbiased for any point-symmetric
   spot, saturated or not) or, optionally and for spots cut by the border, a 2D Gaussian fit.
   Candidates whose added light is white (other/laser > ``max_white_ratio``) are rejected;
   spots whose supports overlap are re-refined with each other's modelled light removed;
4. geometry: each calibrated beam between ``min_range_m`` and ``max_range_m`` is projected with
   the camera model to an image polyline; a candidate is admissible for a laser only within
   ``band_px`` of it. One spot per laser, one laser per candidate, solved as a linear
   assignment on ``-log(score)``.

Every candidate is returned with the reason it was or was not used; every laser without a spot
is in ``missing`` with a reason.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.optimize import least_squares, linear_sum_assignment

from sfm_laserscale.errors import InputError
from sfm_laserscale.memory import trim_heap
from sfm_laserscale.model import Camera, Spot
from sfm_laserscale.rig import Laser, Rig

logger = logging.getLogger(__name__)

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
#: an image as three contiguous (H, W) float32 planes R, G, B in [0, 1]
CHANNELS: dict[str, int] = {"red": 0, "green": 1, "blue": 2}
UNCALIBRATED_REASON = "uncalibrated laser: give its spots with --spots"
_INADMISSIBLE = 1e6
_TOO_LARGE = "too large to be a spot"
#: Gaussian sigma (px) of the smoothing of the texture regressor (the non-laser channels)
OTHER_SMOOTH_PX = 1.5


@dataclass(frozen=True)
class DetectionOptions:
    """Settings of :func:`detect_spots` (lengths in pixels unless named otherwise).

    - ``min_range_m``/``max_range_m``: part of each beam (metres from its origin along the beam)
      where spots are searched; its projection is the beam's image segment.
    - ``band_px``: max distance of a spot centre from its beam segment; None = 3 px + 0.5 % of
      the image diagonal (≈ 14 px at 1920×1080), to absorb calibration error.
    - ``spot_sigmas_px``: blob scales (Gaussian sigma) searched by the DoG.
    - ``max_spot_radius_px``: larger half-maximum radius = not a spot; None = 1.5 % of the
      diagonal (≈ 33 px at 1920×1080).
    - ``min_snr``: candidate threshold, peak contrast over the local background noise.
    - ``max_annulus_ratio``: compactness; the 75th percentile of the colour response in a ring
      around the spot, relative to its peak contrast, must stay below this.
    - ``min_score``: an assigned spot with a lower score is reported in ``missing`` instead.
    - ``snr_half``: SNR at which the contrast term of the score is 0.5.
    - ``refine``: "centroid" (Gaussian-windowed centroid, the default: most accurate and
      unbiased in our measurements) or "gaussian" (2D Gaussian fit to the unclipped pixels),
      both on the texture-free spot signal (see :func:`_spot_patch`). Spots cut by the image
      border always use the fit.
    - ``sigma_floor_px``: floor of the reported localisation sigma (model error).
    - ``saturation_level``: channel value (0–1) above which a pixel counts as clipped.
    - ``max_candidates``: strongest local maxima examined per colour.
    - ``input_gamma``: pixel values are decoded as ``(v / 255) ** input_gamma`` before anything
      else (2.2 for gamma-encoded camera JPEGs, 1.0 for linear images).
    - ``response``: "background" (default: laser channel minus the local background ratio times
      the other channels, see :func:`background_excess`; finds faint spots on tinted water) or
      "difference" (``max(laser - other, 0)`` only, the former default).
    - ``max_white_ratio``: a candidate whose added light (over a plane fitted on its ring) has
      ``Δother / Δlaser`` above this is white or scene texture, not a laser (unclipped spots).
    - ``min_clutter_ratio``: a candidate's blob response must be at least this many times the
      scene's *clutter level*, the 99th percentile of the blob response at all its local maxima
      in the searched region (:func:`clutter_level`: the strongest texture blobs, e.g. reddish
      pebbles, which the background response also finds). 0 disables the test.
    """

    min_range_m: float = 0.5
    max_range_m: float = 10.0
    band_px: float | None = None
    spot_sigmas_px: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0)
    max_spot_radius_px: float | None = None
    min_snr: float = 6.0
    max_annulus_ratio: float = 0.5
    min_score: float = 0.25
    snr_half: float = 10.0
    refine: str = "centroid"
    sigma_floor_px: float = 0.05
    saturation_level: float = 250.0 / 255.0
    max_candidates: int = 100
    input_gamma: float = 2.2
    response: str = "background"
    max_white_ratio: float = 0.7
    min_clutter_ratio: float = 5.0

    def __post_init__(self) -> None:
        if not 0.0 < self.min_range_m < self.max_range_m:
            raise InputError(f"detection range must satisfy 0 < min < max, got "
                             f"{self.min_range_m:g}..{self.max_range_m:g} m")
        if not self.input_gamma > 0:
            raise InputError(f"input_gamma must be positive, got {self.input_gamma}")
        if self.response not in ("background", "difference"):
            raise InputError(f"response must be 'background' or 'difference', got "
                             f"{self.response!r}")
        if not self.min_clutter_ratio >= 0:
            raise InputError(f"min_clutter_ratio must be >= 0, got {self.min_clutter_ratio}")
        if self.refine not in ("centroid", "gaussian"):
            raise InputError(f"refine must be 'centroid' or 'gaussian', got {self.refine!r}")
        if not self.spot_sigmas_px or min(self.spot_sigmas_px) <= 0:
            raise InputError("spot_sigmas_px must be positive")
        for name in ("band_px", "max_spot_radius_px"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise InputError(f"{name} must be positive, got {value}")


@dataclass(frozen=True)
class Candidate:
    """One local maximum of a colour response, as measured, and what became of it.

    ``x``/``y``: refined centre (COLMAP convention). ``response``: DoG value (intensity units,
    ≈ half the peak colour contrast). ``score``: geometry-free score times the beam term of the
    nearest admissible laser (0 when rejected). ``laser``: the laser it was assigned to, or None.
    ``reason``: "assigned to L1" or why it was not used.
    """

    x: float
    y: float
    color: str
    response: float
    snr: float
    radius_px: float
    roundness: float
    score: float
    laser: str | None
    reason: str


@dataclass(frozen=True)
class DetectionResult:
    """Assigned spots, every candidate considered, and lasers without a spot (name -> reason)."""

    spots: tuple[Spot, ...]
    candidates: tuple[Candidate, ...]
    missing: dict[str, str] = field(default_factory=dict)


@dataclass
class _Measure:
    """Mutable per-candidate working record (internal)."""

    x: float
    y: float
    color: str
    response: float
    snr: float = 0.0
    radius_px: float = 0.0
    roundness: float = 0.0
    support_px: float = 0.0
    base_score: float = 0.0
    sigma_px: float = 1.0
    rejected: str | None = None
    score: float = 0.0
    laser: str | None = None
    reason: str = ""


# ----------------------------------------------------------------------------- geometry


def default_band_px(width: int, height: int) -> float:
    """Default beam band half-width: 3 px + 0.5 % of the image diagonal."""
    return 3.0 + 0.005 * math.hypot(width, height)


def default_max_spot_radius_px(width: int, height: int) -> float:
    """Default largest spot half-maximum radius: 1.5 % of the image diagonal (at least 6 px)."""
    return max(6.0, 0.015 * math.hypot(width, height))


def _normalised_bounds(camera: Camera, margin: float = 0.15) -> F64:
    """(2, 2) [[xmin, ymin], [xmax, ymax]] of the image in normalised (z = 1) coordinates.

    Border pixels that the camera model cannot undistort (NaN, beyond the fold of a strong
    radial distortion) are skipped; if too few remain, the pinhole bounds are used.
    """
    w, h = float(camera.width), float(camera.height)
    t = np.linspace(0.0, 1.0, 9)
    border = np.concatenate([
        np.column_stack([t * w, np.zeros_like(t)]), np.column_stack([t * w, np.full_like(t, h)]),
        np.column_stack([np.zeros_like(t), t * h]), np.column_stack([np.full_like(t, w), t * h]),
    ])
    xy = camera.unproject(border)[:, :2]
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if len(xy) < 8:
        f = camera.focal_px
        c = camera.unproject(np.array([[w / 2, h / 2]]))[0, :2]
        xy = np.array([[c[0] - w / (2 * f), c[1] - h / (2 * f)],
                       [c[0] + w / (2 * f), c[1] + h / (2 * f)]])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    pad = margin * (hi - lo)
    return np.stack([lo - pad, hi + pad])


def beam_polyline_px(
    camera: Camera, laser: Laser, min_range_m: float, max_range_m: float, samples: int = 64
) -> F64:
    """(K, 2) projection of a calibrated beam's [min, max] range part (pixels); K = 0 if unseen.

    Beam points are sampled uniformly in 1 / range (uniform in the image for a pinhole) and
    only those whose normalised coordinates lie within the (padded) field of view are projected,
    so lens-distortion polynomials are never evaluated far outside their valid domain.
    """
    if laser.origin is None or laser.direction is None:
        return np.zeros((0, 2))
    inv = np.linspace(1.0 / max_range_m, 1.0 / min_range_m, samples)
    pts = laser.origin[None, :] + (1.0 / inv)[:, None] * laser.direction[None, :]
    pts = pts[pts[:, 2] > 1e-6]
    if len(pts) == 0:
        return np.zeros((0, 2))
    xy_n = pts[:, :2] / pts[:, 2:3]
    bounds = _normalised_bounds(camera)
    inside = np.all((xy_n >= bounds[0]) & (xy_n <= bounds[1]), axis=1)
    if not np.any(inside):
        return np.zeros((0, 2))
    xy = camera.project(pts[inside])
    return np.asarray(xy[np.all(np.isfinite(xy), axis=1)], dtype=np.float64)


def distance_to_polyline(xy: F64, polyline: F64) -> F64:
    """(N,) Euclidean distance of (N, 2) points to a (K, 2) polyline (inf if K = 0)."""
    xy = np.atleast_2d(xy)
    if len(polyline) == 0:
        return np.full(len(xy), np.inf)
    if len(polyline) == 1:
        return np.asarray(np.linalg.norm(xy - polyline[0], axis=1), dtype=np.float64)
    a, b = polyline[:-1], polyline[1:]  # (S, 2)
    ab = b - a
    ap = xy[:, None, :] - a[None, :, :]  # (N, S, 2)
    denom = np.maximum(np.sum(ab * ab, axis=1), 1e-12)
    t = np.clip(np.sum(ap * ab[None], axis=2) / denom[None], 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.asarray(np.linalg.norm(xy[:, None, :] - closest, axis=2).min(axis=1))


# ----------------------------------------------------------------------------- responses


@dataclass(frozen=True)
class Channels:
    """The search region of an RGB image, kept as uint8 (3 bytes per pixel, where three
    float32 planes took 12), and the decoding of its values."""

    rgb: NDArray[np.uint8]  # (H, W, 3) C-contiguous crop
    lut: F32  # (256,) pixel value -> linear intensity in [0, 1], increasing


def _laser_and_other(channels: Channels, color: str) -> tuple[F32, F32]:
    """The laser's channel and the per-pixel max of the two others, as float32 planes.

    The max is taken on the uint8 values, then decoded: the same numbers, since the
    decoding increases."""
    c = CHANNELS[color]
    o1, o2 = [i for i in range(3) if i != c]
    rgb, lut = channels.rgb, channels.lut
    return lut[rgb[..., c]], lut[np.maximum(rgb[..., o1], rgb[..., o2])]


def _fill_clipped(diff: F32, clipped: NDArray[np.bool_], max_area: float) -> None:
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


def colour_difference(
    laser: F32, other: F32, saturation_level: float, max_area: float = np.inf
) -> F32:
    """(H, W) laser-colour response max(laser - other, 0), clipped cores filled.

    ``other`` is the per-pixel max of the two non-laser channels, so blue-green casts and white
    light give 0. Pixels whose laser channel is clipped get at least the largest colour
    difference found in a ring around their clipped region (see :func:`_fill_clipped`): a
    saturated laser core inherits its coloured halo, a white highlight gets ~0.
    """
    diff = np.subtract(laser, other, dtype=np.float32)
    np.maximum(diff, np.float32(0.0), out=diff)  # in place: one (H, W) plane, not two
    clipped = laser >= saturation_level
    if np.any(clipped):
        _fill_clipped(diff, clipped, max_area)
    return np.asarray(diff, dtype=np.float32)


#: Gaussian sigma (px) of the local background used for the laser/other channel ratio
RATIO_SMOOTH_PX = 24.0


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


def background_excess(
    laser: F32, other: F32, saturation_level: float, max_area: float = np.inf
) -> F32:
    """(H, W) laser-colour response relative to the local background, clipped cores filled.

    ``max(laser - k·other, 0)`` with k the local background ratio (:func:`local_ratio`): the
    scene's texture and colour cast scale every channel alike, so this cancels them and a faint
    laser spot on a strongly tinted background (red on cyan water, where ``laser - other`` < 0)
    still responds. Clipped regions are filled from a ring around them as in
    :func:`colour_difference`. White light responds too (by 1 - k per unit): compact white
    blobs are rejected per candidate by the colour of the light they add
    (:func:`_added_light_ratio`).
    """
    # in place in k's plane (same float32 operations, same numbers): at 1920 × 1080 this
    # held three more (H, W) float32 temporaries, 25 MB
    ex = local_ratio(laser, other)
    np.multiply(ex, other, out=ex)
    np.subtract(laser, ex, out=ex)
    np.maximum(ex, np.float32(0.0), out=ex)
    clipped = laser >= saturation_level
    if np.any(clipped):
        _fill_clipped(ex, clipped, max_area)
    return np.asarray(ex, dtype=np.float32)


def _dog_at_scale(resp: F32, sigma: float) -> F32:
    """Scale-normalised DoG -(G(1.6σ) - G(σ)) / 0.6 at full size, computed on a pyramid level.

    Scales of 4 px and more are filtered on an image reduced by a power of two (area
    averaging) so that the kernel stays a few pixels wide, then resized back (bilinear).
    """
    k = 1.6
    factor = 1
    while sigma / (2 * factor) >= 2.0:
        factor *= 2
    small = resp
    if factor > 1:
        size = (max(1, resp.shape[1] // factor), max(1, resp.shape[0] // factor))
        small = cv2.resize(resp, size, interpolation=cv2.INTER_AREA)
    s = sigma / factor
    g1 = cv2.GaussianBlur(small, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    g2 = cv2.GaussianBlur(small, (0, 0), k * s, borderType=cv2.BORDER_REFLECT)
    dog = np.subtract(g1, g2, out=g1)  # in place (same numbers): one plane less at full size
    del g2
    np.divide(dog, np.float32(k - 1.0), out=dog)
    if factor > 1:
        dog = cv2.resize(dog, (resp.shape[1], resp.shape[0]), interpolation=cv2.INTER_LINEAR)
    return np.asarray(dog, dtype=np.float32)


def blob_response(resp: F32, sigmas: tuple[float, ...]) -> F32:
    """(H, W) max over ``sigmas`` of the scale-normalised DoG of a colour response."""
    out = _dog_at_scale(resp, sigmas[0])
    for s in sigmas[1:]:
        np.maximum(out, _dog_at_scale(resp, s), out=out)
    return out


def _local_maxima(dog: F32, min_value: float) -> NDArray[np.intp]:
    """(N, 2) integer (row, col) of 5×5 local maxima above ``min_value``, strongest first."""
    dilated = cv2.dilate(dog, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_REPLICATE)
    peaks = (dog >= dilated) & (dog > min_value)
    rows, cols = np.nonzero(peaks)
    order = np.argsort(-dog[rows, cols], kind="stable")
    return np.column_stack([rows[order], cols[order]])


#: fewer positive local maxima than this in the searched region: no clutter level (too small)
MIN_MAXIMA_FOR_CLUTTER = 50


def clutter_level(dog: F32, quantile: float = 99.0) -> float:
    """The scene's blob clutter: ``quantile`` % of the DoG at its positive 5×5 local maxima.

    A laser image holds a handful of spots among thousands of local maxima (noise, texture), so
    this measures the texture's strongest blobs, not the spots. On a laser-free textured
    seafloor the best texture blobs reach ~1–3.4× this level, laser spots (even very faint,
    on flat water) 10× and more (measured, docs/DETECTION.md). 0 when there are fewer than
    MIN_MAXIMA_FOR_CLUTTER maxima.
    """
    dilated = cv2.dilate(dog, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_REPLICATE)
    values = dog[(dog >= dilated) & (dog > 0)]
    if values.size < MIN_MAXIMA_FOR_CLUTTER:
        return 0.0
    return float(np.percentile(values, quantile))


def _robust_std(values: NDArray[np.floating]) -> float:
    """1.4826 × median absolute deviation."""
    if values.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


# ----------------------------------------------------------------------------- measurement


def _window(shape: tuple[int, ...], row: int, col: int, radius: int) -> tuple[slice, slice]:
    """Slices of the (2 radius + 1)² window around (row, col), clipped to the image."""
    return (slice(max(0, row - radius), min(shape[0], row + radius + 1)),
            slice(max(0, col - radius), min(shape[1], col + radius + 1)))


def _grid(win: tuple[slice, slice]) -> tuple[F64, F64]:
    """Pixel-centre coordinates (x, y) of a window, COLMAP convention (centre = index + 0.5)."""
    ys = np.arange(win[0].start, win[0].stop, dtype=np.float64) + 0.5
    xs = np.arange(win[1].start, win[1].stop, dtype=np.float64) + 0.5
    gx, gy = np.meshgrid(xs, ys)
    return gx, gy


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
class _Blob:
    """Shape and contrast of a colour blob (internal; lengths in pixels)."""

    radius: float  # half-maximum radius, sqrt(area / pi)
    roundness: float
    contrast: float  # peak minus surrounding background, colour-response units
    snr: float
    support: float  # radius where the radial profile has fallen to SUPPORT_FRACTION
    rejection: str | None = None


#: the spot support ends where the azimuthal mean colour contrast drops below this fraction
SUPPORT_FRACTION = 0.05


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


def _shape_and_contrast(
    resp: F32, row: int, col: int, max_radius: float, max_annulus_ratio: float
) -> _Blob:
    """Half-max radius, roundness, contrast, SNR and support of the colour blob at (row, col)."""
    big = int(math.ceil(2.0 * max_radius)) + 6
    win = _window(resp.shape, row, col, big)
    patch = resp[win]
    r0, c0 = row - win[0].start, col - win[1].start
    peak = float(resp[_window(resp.shape, row, col, 1)].max())
    gx, gy = _grid(win)
    rr = np.hypot(gx - (col + 0.5), gy - (row + 0.5))
    outer = patch[rr >= big - 4]
    bg = float(np.median(outer)) if outer.size else 0.0
    contrast = peak - bg
    if contrast <= 0:
        return _Blob(0.0, 0.0, contrast, 0.0, 0.0, "no contrast against its surroundings")
    inner_edges = (win[0].start > 0, win[0].stop < resp.shape[0],
                   win[1].start > 0, win[1].stop < resp.shape[1])
    region, touches = _half_max_region(patch, r0, c0, bg + 0.5 * contrast, inner_edges)
    radius = math.sqrt(region.sum() / math.pi)
    roundness = _roundness(region)
    if touches or radius > max_radius:
        return _Blob(radius, roundness, contrast, 0.0, 0.0,
                     f"{_TOO_LARGE} (half-max radius > {max_radius:.1f} px)")
    ring = patch[(rr >= 2.0 * radius + 2.0) & (rr <= 2.0 * radius + 5.0)]
    noise = max(_robust_std(ring - bg), _robust_std(outer), 0.5 / 255.0)
    snr = contrast / noise
    support = _support_radius(patch - bg, rr, contrast, radius, big - 4)
    ratio = float(np.percentile(ring - bg, 75)) / contrast if ring.size else 0.0
    if ratio > max_annulus_ratio:
        return _Blob(radius, roundness, contrast, snr, support,
                     f"not compact (coloured surroundings: ring/peak {ratio:.2f} > "
                     f"{max_annulus_ratio:g})")
    return _Blob(radius, roundness, contrast, snr, support)


# ----------------------------------------------------------------------------- sub-pixel


@dataclass(frozen=True)
class SpotPatch:
    """Background- and texture-free spot signal in a window around one candidate.

    ``gx``/``gy``: pixel centres (COLMAP convention); ``signal``: laser channel minus its local
    prediction from the other channels and a plane (so the scene's texture, which shows in every
    channel, cancels), laser-clipped pixels set to the highest unclipped value inside the
    support (a flat top); ``usable``: no channel clipped; ``noise``: robust std of the signal on
    the background ring; ``support_px``: radius of the spot support.
    """

    gx: F64
    gy: F64
    signal: F64
    usable: NDArray[np.bool_]
    noise: float
    support_px: float
    cut: bool  # the support disc is cut by the image border


def _texture_model(
    laser: F64, other: F64, gx: F64, gy: F64, ring: NDArray[np.bool_]
) -> F64:
    """Fit laser ≈ c0 + cx x + cy y + a·other on ``ring`` (ridge on a, one trim); return the fit."""
    x_c, y_c = float(gx.mean()), float(gy.mean())
    A = np.column_stack([np.ones(ring.sum()), gx[ring] - x_c, gy[ring] - y_c, other[ring]])
    b = laser[ring]
    # ridge row: with no texture in the ring, ``a`` is undetermined and should stay 0
    ridge = math.sqrt(len(b)) * 0.002
    keep = np.ones(len(b), dtype=bool)
    coef = np.zeros(4)
    for _ in range(2):
        A_r = np.vstack([A[keep], [0.0, 0.0, 0.0, ridge]])
        b_r = np.concatenate([b[keep], [0.0]])
        coef = np.linalg.lstsq(A_r, b_r, rcond=None)[0]
        res = b - A @ coef
        keep = np.abs(res) <= 3.0 * max(_robust_std(res), 1e-6)
        if keep.sum() < 6:
            break
    coef[3] = min(max(coef[3], 0.0), 1.5)
    return np.asarray(coef[0] + coef[1] * (gx - x_c) + coef[2] * (gy - y_c) + coef[3] * other)


def _smoothed_other(planes: _Planes, win: tuple[slice, slice]) -> F64:
    """``planes.other`` in ``win`` smoothed by OTHER_SMOOTH_PX (computed on a padded window).

    The texture regressor is smoothed: its own noise would otherwise attenuate the fitted
    coefficient (errors in variables) and add to the spot signal.
    """
    pad = int(math.ceil(3.0 * OTHER_SMOOTH_PX)) + 1
    h, w = planes.other.shape
    r0, r1 = max(0, win[0].start - pad), min(h, win[0].stop + pad)
    c0, c1 = max(0, win[1].start - pad), min(w, win[1].stop + pad)
    big = cv2.GaussianBlur(planes.other[r0:r1, c0:c1], (0, 0), OTHER_SMOOTH_PX,
                           borderType=cv2.BORDER_REFLECT)
    return np.asarray(big[win[0].start - r0 : win[0].stop - r0,
                          win[1].start - c0 : win[1].stop - c0], dtype=np.float64)


def _spot_patch(planes: _Planes, x0: float, y0: float, support_px: float,
                neighbours: tuple[NeighbourModel, ...] = ()) -> SpotPatch | None:
    """The texture-free signal around (x0, y0) (COLMAP px); None when too close to nothing.

    ``neighbours``: overlapping spots whose modelled light is removed from the laser channel
    first (so neither the texture fit on the ring nor the centroid sees their halo).
    """
    radius = int(math.ceil(support_px)) + 4
    win = _window(planes.laser.shape, int(math.floor(y0)), int(math.floor(x0)), radius)
    gx, gy = _grid(win)
    rr = np.hypot(gx - x0, gy - y0)
    clipped_l = planes.clipped_laser[win]
    ring = (rr >= support_px) & ~planes.clipped_any[win]
    if ring.sum() < 8:
        return None
    laser = planes.laser[win].astype(np.float64)
    for nb in neighbours:
        laser = laser - nb.at(gx, gy)
    sig = laser - _texture_model(laser, _smoothed_other(planes, win), gx, gy, ring)
    inner_ok = (rr < support_px) & ~clipped_l
    if clipped_l.any():
        sig[clipped_l] = float(sig[inner_ok].max()) if inner_ok.any() else float(sig.max())
    h, w = planes.laser.shape
    cut = bool(x0 - support_px < 0 or y0 - support_px < 0 or x0 + support_px > w
               or y0 + support_px > h)
    return SpotPatch(gx=gx, gy=gy, signal=sig, usable=~planes.clipped_any[win],
                     noise=_robust_std(sig[ring]), support_px=support_px, cut=cut)


@dataclass(frozen=True)
class NeighbourModel:
    """Radially symmetric model of a spot's texture-free light (for overlapping spots).

    ``profile[i]``: mean signal at radius i + 0.5 px from (x, y), measured on the spot's side
    facing away from the neighbour it is modelled for (where that neighbour adds nothing).
    """

    x: float
    y: float
    profile: F64

    def at(self, gx: F64, gy: F64) -> F64:
        """The modelled light at pixel centres (gx, gy); 0 beyond the profile."""
        r = np.hypot(gx - self.x, gy - self.y)
        centres = np.arange(len(self.profile)) + 0.5
        return np.asarray(np.interp(r, centres, self.profile, right=0.0), dtype=np.float64)


def neighbour_model(patch: SpotPatch, x: float, y: float, away_from: tuple[float, float]
                    ) -> NeighbourModel:
    """:class:`NeighbourModel` of the spot at (x, y) from the half of its patch facing away
    from ``away_from`` (the spot being refined), clipped at zero, ending at the support."""
    ux, uy = x - away_from[0], y - away_from[1]
    away = ((patch.gx - x) * ux + (patch.gy - y) * uy) > 0
    r = np.hypot(patch.gx - x, patch.gy - y)
    keep = away & (r < patch.support_px)
    bins = r[keep].astype(np.int64)
    n = int(math.ceil(patch.support_px))
    sums = np.bincount(bins, weights=patch.signal[keep], minlength=n)[:n]
    counts = np.bincount(bins, minlength=n)[:n]
    prof = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)
    return NeighbourModel(x=x, y=y, profile=np.clip(prof, 0.0, None))


def _centroid_step(
    patch: SpotPatch, pos: F64, x: float, y: float, sigma_w: float
) -> tuple[float, float, float, float]:
    """One windowed-centroid update from (x, y): (new x, new y, Σw, Σ g²·r²)."""
    rr2 = (patch.gx - x) ** 2 + (patch.gy - y) ** 2
    g = np.exp(-0.5 * rr2 / (sigma_w * sigma_w)) * (rr2 < patch.support_px**2)
    w = pos * g
    total = float(w.sum())
    if total <= 0:
        return x, y, 0.0, 0.0
    nx, ny = float((w * patch.gx).sum() / total), float((w * patch.gy).sum() / total)
    spread = float((g * g * ((patch.gx - nx) ** 2 + (patch.gy - ny) ** 2)).sum())
    return nx, ny, total, spread


def refine_centroid(
    patch: SpotPatch, x0: float, y0: float, sigma_w: float, iterations: int = 50
) -> tuple[float, float, float]:
    """Gaussian-windowed centroid of a :class:`SpotPatch`: (x, y, 1-sigma noise), COLMAP px.

    The window (sigma ``sigma_w``, cut at the support radius) follows the estimate until it
    stops moving; for any point-symmetric spot the true centre is the fixed point, so the
    estimate is unbiased. The sigma is the ring noise propagated through one centroid step,
    times the gain 1 / (1 - k) of the fixed-point iteration (k: how far one step follows a
    displaced window, measured by displacing it).
    """
    pos = np.clip(patch.signal, 0.0, None)
    x, y = x0, y0
    total = spread = 0.0
    for _ in range(iterations):
        nx, ny, total, spread = _centroid_step(patch, pos, x, y, sigma_w)
        moved = math.hypot(nx - x, ny - y)
        x, y = nx, ny
        if total <= 0 or moved < 1e-5:
            break
    if total <= 0:
        return x, y, math.nan
    delta = 0.25
    kx = (_centroid_step(patch, pos, x + delta, y, sigma_w)[0] - x) / delta
    ky = (_centroid_step(patch, pos, x, y + delta, sigma_w)[1] - y) / delta
    gain = 1.0 / max(1.0 - 0.5 * (kx + ky), 0.2)
    return x, y, gain * patch.noise * math.sqrt(spread / 2.0) / total


def refine_gaussian(
    patch: SpotPatch, x0: float, y0: float, sigma0: float
) -> tuple[float, float, float]:
    """2D Gaussian fit to the unclipped support pixels of a :class:`SpotPatch`: (x, y, 1-sigma).

    Clipped pixels are left out, so a saturated core does not flatten the fitted profile; the
    flanks of the spot carry its position.
    """
    use = patch.usable & ((patch.gx - x0) ** 2 + (patch.gy - y0) ** 2 < patch.support_px**2)
    if use.sum() < 8:
        return x0, y0, 1.0
    px, py, pv = patch.gx[use], patch.gy[use], patch.signal[use]

    def residual(p: F64) -> F64:
        a, x, y, s, b0 = p
        g = a * np.exp(-0.5 * ((px - x) ** 2 + (py - y) ** 2) / (s * s))
        return np.asarray(g + b0 - pv, dtype=np.float64)

    p0 = np.array([max(float(patch.signal.max()), 1e-3), x0, y0, sigma0, 0.0])
    fit = least_squares(residual, p0, method="lm", max_nfev=300)
    x, y = float(fit.x[1]), float(fit.x[2])
    if not (fit.success and math.hypot(x - x0, y - y0) < patch.support_px):
        return x0, y0, 1.0
    s2 = float(fit.fun @ fit.fun) / max(len(pv) - 5, 1)
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * s2
    except np.linalg.LinAlgError:
        return x, y, 1.0
    return x, y, math.sqrt(max(0.5 * (cov[1, 1] + cov[2, 2]), 0.0))


# ----------------------------------------------------------------------------- candidates


def _check_image(image_rgb: NDArray[np.uint8], camera: Camera) -> None:
    """Validate the image against its camera (shape, size, dtype)."""
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
        raise InputError(f"laser image must be RGB (H, W, 3), got shape {image_rgb.shape}")
    if image_rgb.shape[:2] != (camera.height, camera.width):
        raise InputError(
            f"laser image is {image_rgb.shape[1]}x{image_rgb.shape[0]} px but its camera is "
            f"{camera.width}x{camera.height} px")
    if image_rgb.dtype != np.uint8:
        raise InputError(f"laser image must be 8-bit (uint8), got {image_rgb.dtype}")


def _channels(
    image_rgb: NDArray[np.uint8], roi: tuple[int, int, int, int], gamma: float = 1.0
) -> Channels:
    """The (x0, y0, x1, y1) crop of an RGB uint8 image, values decoded as
    ``(v / 255) ** gamma`` (1 = the image is linear) when a colour's planes are made."""
    x0, y0, x1, y1 = roi
    crop = np.ascontiguousarray(image_rgb[y0:y1, x0:x1])
    lut = ((np.arange(256, dtype=np.float64) / 255.0) ** gamma).astype(np.float32)
    return Channels(crop, lut)


@dataclass(frozen=True)
class _Planes:
    """Per-colour full-resolution arrays shared by all candidates of that colour."""

    resp: F32  # (H, W) colour-difference response (clipped cores filled)
    laser: F32  # (H, W) the laser's channel
    other: F32  # (H, W) max of the two other channels
    clipped_laser: NDArray[np.bool_]  # (H, W) laser channel clipped
    clipped_any: NDArray[np.bool_]  # (H, W) any channel clipped


def _planes(
    channels: Channels, color: str, options: DetectionOptions, max_radius: float
) -> _Planes:
    """Colour response, channels and clipped masks for one laser colour."""
    laser, other = _laser_and_other(channels, color)
    resp = colour_difference(laser, other, options.saturation_level,
                             4.0 * math.pi * max_radius**2)
    # the same masks and maximum as np.maximum(laser, other) >= level and np.maximum(resp,
    # excess), without their (H, W) float32 temporaries
    clipped_laser = laser >= options.saturation_level
    clipped_any = clipped_laser | (other >= options.saturation_level)
    if options.response == "background":
        np.maximum(resp, background_excess(laser, other, options.saturation_level,
                                           4.0 * math.pi * max_radius**2), out=resp)
    return _Planes(resp=resp, laser=laser, other=other, clipped_laser=clipped_laser,
                   clipped_any=clipped_any)


def _refine(planes: _Planes, m: _Measure, options: DetectionOptions,
            neighbours: tuple[NeighbourModel, ...] = ()) -> tuple[float, float, float]:
    """Sub-pixel centre and localisation sigma of one candidate (COLMAP px); NaN if impossible."""
    sigma_w = max(1.0, m.radius_px)
    patch = _spot_patch(planes, m.x, m.y, max(m.support_px, 3.0 * sigma_w), neighbours)
    if patch is None:
        return math.nan, math.nan, math.nan
    if options.refine == "gaussian" or patch.cut:
        # a spot cut by the image border: a centroid would be pulled inwards, a symmetric
        # model fitted to the visible pixels is not
        return refine_gaussian(patch, m.x, m.y, sigma_w)
    return refine_centroid(patch, m.x, m.y, sigma_w)


def _added_light_ratio(planes: _Planes, x: float, y: float, radius: float, support: float
                       ) -> float:
    """Δother / Δlaser of the light a candidate adds over planes fitted on its ring (0 = pure
    laser colour, ~1 = white); unclipped pixels only (a clipped core: its shoulders)."""
    win = _window(planes.laser.shape, int(math.floor(y)), int(math.floor(x)),
                  int(math.ceil(max(support, 4.0))) + 3)
    gx, gy = _grid(win)
    rr = np.hypot(gx - x, gy - y)
    ok = ~planes.clipped_any[win]
    # unclipped pixels of the spot: its shoulders when the core is clipped
    inner = (rr <= max(2.0, radius) + (2.0 if planes.clipped_any[win].any() else 0.0)) & ok
    ring = (rr >= max(support, 4.0)) & ok
    if inner.sum() < 4 or ring.sum() < 8:
        return 0.0
    design = np.column_stack([np.ones(ring.sum()), gx[ring] - x, gy[ring] - y])
    added = []
    for plane in (planes.laser, planes.other):
        vals = plane[win].astype(np.float64)
        coef = np.linalg.lstsq(design, vals[ring], rcond=None)[0]
        pred = coef[0] + coef[1] * (gx[inner] - x) + coef[2] * (gy[inner] - y)
        added.append(float(np.mean(vals[inner] - pred)))
    d_laser, d_other = added
    return d_other / d_laser if d_laser > 0 else math.inf


def _measure_peak(
    planes: _Planes, rc: tuple[int, int], dog_value: float, color: str,
    options: DetectionOptions, max_radius: float,
) -> _Measure:
    """Measure, validate and refine one local maximum."""
    row, col = rc
    # integer array index (row, col) -> COLMAP pixel centre (+0.5)
    m = _Measure(x=col + 0.5, y=row + 0.5, color=color, response=dog_value)
    blob = _shape_and_contrast(planes.resp, row, col, max_radius, options.max_annulus_ratio)
    m.radius_px, m.roundness, m.snr, m.support_px = (blob.radius, blob.roundness, blob.snr,
                                                     blob.support)
    why, radius, snr, roundness = blob.rejection, blob.radius, blob.snr, blob.roundness
    if why is None and snr < options.min_snr:
        why = f"weak (SNR {snr:.1f} < {options.min_snr:g})"
    if why is not None:
        m.rejected = why
        return m
    x, y, sig = _refine(planes, m, options)
    if not (math.hypot(x - m.x, y - m.y) <= max(2.0, 1.5 * radius) and math.isfinite(sig)):
        m.rejected = "sub-pixel refinement failed"
        return m
    ratio = _added_light_ratio(planes, x, y, radius, m.support_px)
    if ratio > options.max_white_ratio:
        m.rejected = (f"not laser-coloured (added light other/laser {ratio:.2f} > "
                      f"{options.max_white_ratio:g})")
        return m
    m.x, m.y = x, y
    m.sigma_px = math.hypot(sig, options.sigma_floor_px)
    m.base_score = snr / (snr + options.snr_half) * math.sqrt(roundness)
    return m


def _covering(out: list[_Measure], x: float, y: float) -> str | None:
    """Why a maximum at (x, y) repeats an earlier one: inside a too-large blob or a spot."""
    for o in out:
        d = math.hypot(o.x - x, o.y - y)
        if o.rejected is None and d < max(2.0, o.radius_px):
            return f"duplicate of the stronger maximum at ({o.x:.1f}, {o.y:.1f})"
        if o.rejected is not None and o.rejected.startswith(_TOO_LARGE) and d < o.radius_px:
            return f"part of the too-large blob at ({o.x:.1f}, {o.y:.1f})"
    return None


def _candidates_for_colour(
    channels: Channels, color: str, options: DetectionOptions, region: _SearchRegion
) -> list[_Measure]:
    """Local maxima of one colour's blob response, measured and refined (image COLMAP px).

    Maxima outside the beam bands (when every laser is calibrated) or inside an earlier,
    too-large blob are listed, not measured.
    """
    planes = _planes(channels, color, options, region.max_radius)
    dog = blob_response(planes.resp, options.spot_sigmas_px)
    threshold = max(4.0 * _robust_std(dog[::4, ::4]), 4.0 / 255.0)
    clutter = options.min_clutter_ratio * clutter_level(dog)
    out: list[_Measure] = []
    for row, col in _local_maxima(dog, threshold)[: 4 * options.max_candidates]:
        m = _Measure(x=col + 0.5, y=row + 0.5, color=color, response=float(dog[row, col]))
        if region.near is not None and not region.near[row, col]:
            m.rejected = "off every beam band (not measured)"
        elif m.response < clutter:
            m.rejected = (f"not above the scene's texture (blob response {m.response:.4f} < "
                          f"{options.min_clutter_ratio:g} × clutter level "
                          f"{clutter / options.min_clutter_ratio:.4f}; not measured)")
        elif sum(o.rejected is None for o in out) >= options.max_candidates:
            m.rejected = f"beyond the {options.max_candidates} strongest maxima (not measured)"
        else:
            m.rejected = _covering(out, m.x, m.y)
        if m.rejected is None:
            m = _measure_peak(planes, (int(row), int(col)), m.response, color, options,
                              region.max_radius)
            if m.rejected is None:
                m.rejected = _covering(out, m.x, m.y)
        out.append(m)
    _separate_overlapping(planes, [m for m in out if m.rejected is None], options)
    x0, y0 = region.roi[:2]
    for m in out:  # crop -> image coordinates
        m.x += x0
        m.y += y0
    return out


def _patch_support(m: _Measure) -> float:
    return max(m.support_px, 3.0 * max(1.0, m.radius_px))


def _separate_overlapping(planes: _Planes, valid: list[_Measure], options: DetectionOptions,
                          rounds: int = 3) -> None:
    """In place: re-refine spots whose supports overlap, each with its neighbours' light
    (modelled from their far sides, :func:`neighbour_model`) removed. Alternating rounds."""
    groups = {i: [j for j, o in enumerate(valid) if j != i and
                  math.hypot(o.x - m.x, o.y - m.y) < _patch_support(m) + _patch_support(o)]
              for i, m in enumerate(valid)}
    if not any(groups.values()):
        return
    models: dict[tuple[int, int], NeighbourModel] = {}  # (spot, for whom) -> model
    for _ in range(rounds):
        fresh: dict[tuple[int, int], NeighbourModel] = {}
        for j, nbs in groups.items():  # model of spot j as seen by each neighbour i
            o = valid[j]
            for i in nbs:
                others = tuple(models[(k, j)] for k in groups[j] if (k, j) in models)
                p = _spot_patch(planes, o.x, o.y, _patch_support(o), others)
                if p is not None:
                    fresh[(j, i)] = neighbour_model(p, o.x, o.y, (valid[i].x, valid[i].y))
        models = fresh
        for i, nbs in groups.items():
            m = valid[i]
            mine = tuple(models[(j, i)] for j in nbs if (j, i) in models)
            if not mine:
                continue
            x, y, sig = _refine(planes, m, options, mine)
            if math.isfinite(sig) and math.hypot(x - m.x, y - m.y) <= max(2.0, m.radius_px):
                m.x, m.y = x, y
                m.sigma_px = math.hypot(sig, options.sigma_floor_px)


def _colours_needed(rig: Rig) -> list[str]:
    """Laser colours to search, in channel order ("any" needs all three)."""
    wanted = {las.color for las in rig.lasers}
    if "any" in wanted:
        return list(CHANNELS)
    return [c for c in CHANNELS if c in wanted]


# ----------------------------------------------------------------------------- assignment


def _beam_term(dist_px: F64, band_px: float) -> F64:
    """Score factor for the distance to the beam segment: exp(-½ (d / band)²)."""
    return np.asarray(np.exp(-0.5 * (dist_px / band_px) ** 2), dtype=np.float64)


def _any_colour(valid: list[_Measure], dist: F64, band: float) -> str:
    """For a colour-'any' laser: the colour of the strongest admissible candidate."""
    best = max(
        (m for m, d in zip(valid, dist, strict=True) if d <= band),
        key=lambda m: m.response, default=None,
    )
    return best.color if best is not None else "red"


def _laser_costs(
    rig: Rig, region: _SearchRegion, valid: list[_Measure], options: DetectionOptions
) -> tuple[F64, F64, dict[str, str]]:
    """(L, N) assignment cost -log(score) and distance to beam for calibrated lasers."""
    band = region.band_px
    xy = np.array([[m.x, m.y] for m in valid]).reshape(-1, 2)
    base = np.array([m.base_score for m in valid])
    cost = np.full((len(rig.lasers), len(valid)), _INADMISSIBLE)
    dist = np.full((len(rig.lasers), len(valid)), np.inf)
    unseen: dict[str, str] = {}
    for i, las in enumerate(rig.lasers):
        if not las.calibrated:
            continue
        line = region.polylines[las.name]
        if len(line) == 0:
            unseen[las.name] = (f"its beam ({options.min_range_m:g}–{options.max_range_m:g} m) "
                                "is outside the image")
            continue
        dist[i] = distance_to_polyline(xy, line) if len(valid) else dist[i]
        color = las.color if las.color != "any" else _any_colour(valid, dist[i], band)
        ok = (dist[i] <= band) & np.array([m.color == color for m in valid], dtype=bool)
        score = base * _beam_term(dist[i], band)
        cost[i, ok] = -np.log(np.maximum(score[ok], 1e-12))
    return cost, dist, unseen


def _missing_reason(las: Laser, li: int, valid: list[_Measure], dist: F64, band: float) -> str:
    """Why a calibrated laser got no admissible candidate."""
    same = [j for j, m in enumerate(valid) if las.color in ("any", m.color)]
    if not same:
        return f"no {las.color} spot candidate in the image"
    j = min(same, key=lambda k: dist[li, k])
    return (f"no {las.color} spot within {band:.1f} px of its beam "
            f"(nearest candidate {dist[li, j]:.1f} px away)")


def _assign_calibrated(
    rig: Rig, region: _SearchRegion, valid: list[_Measure], options: DetectionOptions
) -> tuple[dict[str, int], dict[str, str], F64]:
    """Laser name -> index into ``valid`` by linear assignment; missing reasons; distances."""
    band = region.band_px
    cost, dist, missing = _laser_costs(rig, region, valid, options)
    chosen: dict[str, int] = {}
    rows, cols = linear_sum_assignment(cost) if cost.size else (np.array([]), np.array([]))
    for li, cj in zip(rows.tolist(), cols.tolist(), strict=True):
        if cost[li, cj] >= _INADMISSIBLE:
            continue
        las, score = rig.lasers[li], math.exp(-cost[li, cj])
        m = valid[cj]
        if score < options.min_score:
            missing[las.name] = (f"best candidate ({m.x:.1f}, {m.y:.1f}) scores {score:.2f} "
                                 f"< min_score {options.min_score:g}")
            m.reason = f"score {score:.2f} below min_score for {las.name}"
            continue
        m.score, m.laser, m.reason = score, las.name, f"assigned to {las.name}"
        chosen[las.name] = cj
    for li, las in enumerate(rig.lasers):
        if las.calibrated and las.name not in chosen and las.name not in missing:
            missing[las.name] = _missing_reason(las, li, valid, dist, band)
    return chosen, missing, dist


def _assign_uncalibrated(
    rig: Rig, valid: list[_Measure], taken: set[int], options: DetectionOptions
) -> tuple[dict[str, int], dict[str, str]]:
    """Uncalibrated lasers: the best free candidate of their colour if that colour is unique."""
    chosen: dict[str, int] = {}
    missing: dict[str, str] = {}
    for las in rig.lasers:
        if las.calibrated:
            continue
        same = [o for o in rig.lasers if o.color == las.color]
        if las.color == "any" or len(same) > 1:
            missing[las.name] = UNCALIBRATED_REASON
            continue
        free = [j for j, m in enumerate(valid) if m.color == las.color and j not in taken]
        if not free:
            missing[las.name] = f"no free {las.color} spot candidate in the image"
            continue
        j = max(free, key=lambda k: valid[k].base_score)
        m = valid[j]
        if m.base_score < options.min_score:
            missing[las.name] = (f"best {las.color} candidate ({m.x:.1f}, {m.y:.1f}) scores "
                                 f"{m.base_score:.2f} < min_score {options.min_score:g}")
            m.reason = f"score below min_score for {las.name}"
            continue
        m.score, m.laser, m.reason = m.base_score, las.name, f"assigned to {las.name} by colour"
        chosen[las.name] = j
        taken.add(j)
    return chosen, missing


def _explain_unused(rig: Rig, valid: list[_Measure], dist: F64, band: float) -> None:
    """Fill the reason (and a geometry-aware score) of valid candidates left unassigned."""
    names = rig.names
    for j, m in enumerate(valid):
        if m.laser is not None:
            continue
        col = dist[:, j] if dist.size else np.zeros(0)
        finite = np.isfinite(col)
        m.score = m.base_score * (float(_beam_term(col[finite], band).max()) if finite.any()
                                  else 1.0)
        if m.reason:
            continue
        if not finite.any():
            m.reason = "no calibrated laser of its colour to take it"
            continue
        li = int(np.argmin(np.where(finite, col, np.inf)))
        if col[li] > band:
            m.reason = f"off every beam band (nearest: {names[li]} at {col[li]:.1f} px)"
        else:
            m.reason = f"a better candidate was assigned to {names[li]}"


# ----------------------------------------------------------------------------- entry point


@dataclass(frozen=True)
class _SearchRegion:
    """Where to look: crop of the image, beam polylines and the near-band mask (crop pixels)."""

    roi: tuple[int, int, int, int]  # x0, y0, x1, y1 (array indices, end exclusive)
    polylines: dict[str, F64]  # calibrated laser -> (K, 2) beam segment, image COLMAP px
    near: NDArray[np.bool_] | None  # (y1-y0, x1-x0) within reach of a band; None = everywhere
    band_px: float
    max_radius: float


def _search_region(camera: Camera, rig: Rig, options: DetectionOptions) -> _SearchRegion:
    """Whole image if a laser is uncalibrated, else the beam bands' bounding box plus margins."""
    band = options.band_px or default_band_px(camera.width, camera.height)
    max_radius = options.max_spot_radius_px or default_max_spot_radius_px(
        camera.width, camera.height)
    polylines = {las.name: beam_polyline_px(camera, las, options.min_range_m, options.max_range_m)
                 for las in rig.lasers if las.calibrated}
    full = (0, 0, camera.width, camera.height)
    if not all(las.calibrated for las in rig.lasers):
        return _SearchRegion(full, polylines, None, band, max_radius)
    pts = [p for p in polylines.values() if len(p)]
    if not pts:
        return _SearchRegion((0, 0, 0, 0), polylines, None, band, max_radius)
    allp = np.concatenate(pts)
    margin = band + 2.0 * max_radius + 4.0 * max(options.spot_sigmas_px) + 4.0
    lo = np.floor(allp.min(axis=0) - margin).astype(int)
    hi = np.ceil(allp.max(axis=0) + margin).astype(int)
    x0, y0 = max(0, int(lo[0])), max(0, int(lo[1]))
    x1, y1 = min(camera.width, int(hi[0])), min(camera.height, int(hi[1]))
    if x1 - x0 < 8 or y1 - y0 < 8:
        return _SearchRegion((0, 0, 0, 0), polylines, None, band, max_radius)
    near = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
    for line in pts:
        # COLMAP px -> array index coordinates of the crop: subtract 0.5 and the crop origin
        idx = np.round((line - 0.5 - [x0, y0]) * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(near, [idx], False, 255, thickness=2 * int(math.ceil(band)) + 5,
                      shift=4)
    return _SearchRegion((x0, y0, x1, y1), polylines, near > 0, band, max_radius)


def _measure_candidates(image_rgb: NDArray[np.uint8], rig: Rig, region: _SearchRegion,
                        options: DetectionOptions) -> list[_Measure]:
    """Every candidate spot of every colour the rig needs, within the search region."""
    measures: list[_Measure] = []
    x0, y0, x1, y1 = region.roi
    if x1 > x0 and y1 > y0:
        channels = _channels(image_rgb, region.roi, options.input_gamma)
        for color in _colours_needed(rig):
            measures += _candidates_for_colour(channels, color, options, region)
    return measures


def detect_spots(
    image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig,
    options: DetectionOptions = DetectionOptions(),  # noqa: B008 (frozen dataclass)
) -> DetectionResult:
    """Detect laser spots in one image and assign them to the rig's lasers."""
    _check_image(image_rgb, camera)
    region = _search_region(camera, rig, options)
    measures = _measure_candidates(image_rgb, rig, region, options)
    trim_heap()  # the detection planes (~16 bytes per pixel) go back to the OS
    valid = [m for m in measures if m.rejected is None]
    chosen, missing, dist = _assign_calibrated(rig, region, valid, options)
    chosen_u, missing_u = _assign_uncalibrated(rig, valid, set(chosen.values()), options)
    chosen.update(chosen_u)
    missing.update(missing_u)
    _explain_unused(rig, valid, dist, region.band_px)
    spots = tuple(
        Spot(laser=name, x=valid[j].x, y=valid[j].y, score=float(np.clip(valid[j].score, 0, 1)),
             sigma_px=valid[j].sigma_px, source="detected")
        for name in rig.names if (j := chosen.get(name)) is not None
    )
    candidates = tuple(
        Candidate(x=m.x, y=m.y, color=m.color, response=m.response, snr=m.snr,
                  radius_px=m.radius_px, roundness=m.roundness,
                  score=0.0 if m.rejected else float(m.score), laser=m.laser,
                  reason=m.rejected or m.reason)
        for m in measures
    )
    logger.debug("%d candidates, %d spots, missing: %s", len(candidates), len(spots), missing)
    return DetectionResult(spots=spots, candidates=candidates, missing=missing)
