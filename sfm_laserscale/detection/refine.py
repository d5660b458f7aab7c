"""Sub-pixel spot centres (COLMAP pixel convention) and their localisation sigma.

A spot is refined on a signal free of background, in a window around its candidate position,
minus a plane fitted on a ring outside the spot's support:

- a laser whose light is mostly luma (green: :func:`luma_dominant`): the luma of the linear
  channels, when the spot's SNR there is at least LUMA_SNR_RATIO of the texture-free signal's
  (below). Camera JPEGs keep luma at full resolution and colour at half (4:2:0), so a signal
  that separates the laser from the texture by colour moves a small spot's centre with the
  2 × 2 chroma blocks; where the texture is strong in luma (green water) the texture-free
  signal is kept;
- otherwise (red and blue lasers, whose luma share is too small to see them above the
  texture): the channels projected on the part of the laser's colour orthogonal to the scene
  texture's colour (:func:`spot_light`), so the texture cancels.

Pixels where the signal is undetermined (clipped) inside the support are set to the highest
determined value there (a flat top); for a luma-dominant laser, and for any spot read on luma,
such a spot's signal is taken above CLIPPED_CUT of that plateau (a thresholded centroid: a glow
line or the luma texture beside the core does not pull its centre; red and blue spots, on the
texture-free signal, only lost accuracy with it). The centre is a Gaussian-windowed centroid
iterated to its fixed point (unbiased for any point-symmetric spot, saturated or not) or,
optionally and for spots cut by the image border, a 2D Gaussian fit to the unclipped pixels.
Overlapping spots are refined with each other's modelled light removed
(:class:`NeighbourModel`). Where a centroid runs off its spot, the peak of a blob response is
read instead (:func:`subpixel_peak`: a parabola along each axis through the maximum).

The localisation sigma is the ring noise through the centroid plus what noise does not show
(:class:`~sfm_laserscale.detection.options.SigmaModel`): light that is not point-symmetric
about the centre (:func:`structure_sigma`: the fixed point's shift under a wider window, the
spot's :func:`asymmetry`), a floor for demosaicing and chroma subsampling, and for a centre
read from the texture-free light (a colour difference) the 2 × 2 sampling of colour. A spot cut
by the border has instead :func:`cut_sigma`: how far its fit lies from the centroid whose
window keeps only pixels mirrored inside the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.optimize import least_squares

from sfm_laserscale.detection.options import SigmaModel
from sfm_laserscale.detection.response import Planes, robust_std

F64 = NDArray[np.float64]


def window(shape: tuple[int, ...], row: int, col: int, radius: int) -> tuple[slice, slice]:
    """Slices of the (2 radius + 1)² window around (row, col), clipped to the image."""
    return (slice(max(0, row - radius), min(shape[0], row + radius + 1)),
            slice(max(0, col - radius), min(shape[1], col + radius + 1)))


def grid(win: tuple[slice, slice]) -> tuple[F64, F64]:
    """Pixel-centre coordinates (x, y) of a window, COLMAP convention (centre = index + 0.5)."""
    ys = np.arange(win[0].start, win[0].stop, dtype=np.float64) + 0.5
    xs = np.arange(win[1].start, win[1].stop, dtype=np.float64) + 0.5
    gx, gy = np.meshgrid(xs, ys)
    return gx, gy


@dataclass(frozen=True)
class SpotGuess:
    """A candidate to refine: position (crop COLMAP px), half-max radius and support radius
    (px), and whether it is refined on the brightness signal (its laser channel clips)."""

    x: float
    y: float
    radius_px: float
    support_px: float
    bright: bool = False

    @property
    def window_px(self) -> float:
        """σ (px) of the centroid's Gaussian window: the half-max radius, at least 1 px."""
        return max(1.0, self.radius_px)

    @property
    def patch_support(self) -> float:
        """Support radius of the refinement window (at least 3 half-max radii)."""
        return max(self.support_px, 3.0 * self.window_px)


@dataclass(frozen=True)
class SpotPatch:
    """Background- and texture-free spot signal in a window around one candidate.

    ``gx``/``gy``: pixel centres (COLMAP convention); ``signal``: see the module docstring, with
    clipped pixels inside the support set to the highest unclipped value there (a flat top);
    ``usable``: no channel clipped; ``noise``: robust std of the signal on the background
    ring; ``support_px``: radius of the spot support; ``from_colour``: the signal is the
    texture-free light (a colour difference), not luma; ``texture``: the texture colour
    that light was freed of (:func:`texture_direction`).
    """

    gx: F64
    gy: F64
    signal: F64
    usable: NDArray[np.bool_]
    noise: float
    support_px: float
    cut: bool  # the support disc is cut by the image border
    from_colour: bool = False
    bounds: tuple[float, float] = (math.inf, math.inf)  # the crop's width and height (px)
    texture: F64 | None = None  # (3,) the texture colour the light was freed of


def _plane_residual(value: F64, gx: F64, gy: F64, ring: NDArray[np.bool_]) -> F64:
    """``value`` minus a plane fitted on ``ring`` (least squares, one 3-sigma trim)."""
    x_c, y_c = float(gx.mean()), float(gy.mean())
    A = np.column_stack([np.ones(ring.sum()), gx[ring] - x_c, gy[ring] - y_c])
    b = value[ring]
    keep = np.ones(len(b), dtype=bool)
    coef = np.zeros(3)
    for _ in range(2):
        coef = np.linalg.lstsq(A[keep], b[keep], rcond=None)[0]
        res = b - A @ coef
        keep = np.abs(res) <= 3.0 * max(robust_std(res), 1e-6)
        if keep.sum() < 6:
            break
    return np.asarray(value - (coef[0] + coef[1] * (gx - x_c) + coef[2] * (gy - y_c)))


def texture_direction(ring_rgb: F64, laser_rgb: F64) -> F64:
    """(3,) unit colour along which the scene's texture varies in a ring of (n, 3) pixels.

    Reflectance changes scale the light the scene reflects, so its texture moves along the
    scene's own colour: the first principal axis of the ring's colours when it dominates
    (variance TEXTURE_DOMINANCE × the next) and lies well away from the laser's colour (a
    spot's halo reaching into the ring varies along the laser's colour), else the ring's mean
    colour.
    """
    mean = ring_rgb.mean(axis=0)
    centred = ring_rgb - mean
    cov = centred.T @ centred / max(len(ring_rgb) - 1, 1)
    values, vectors = np.linalg.eigh(cov)
    axis = vectors[:, -1] * (1.0 if vectors[:, -1].sum() >= 0 else -1.0)
    laser_u = laser_rgb / max(float(np.linalg.norm(laser_rgb)), 1e-12)
    textured = values[-1] > TEXTURE_DOMINANCE * max(values[-2], 0.0) and values[-1] > 1e-10
    if not textured or abs(float(axis @ laser_u)) > math.cos(math.radians(MIN_AXIS_TO_LASER_DEG)):
        axis = mean
    return np.asarray(axis / max(float(np.linalg.norm(axis)), 1e-12))


#: a ring's colours vary along one texture axis when its variance is this many times the next
TEXTURE_DOMINANCE = 4.0
#: a texture axis closer than this to the laser's colour is the spot's own halo (degrees)
MIN_AXIS_TO_LASER_DEG = 30.0
#: a subset of channels (some clipped) measures laser light only when its noise gain (norm of
#: the projection over its response) is at most this many times that of all three channels
MAX_SUBSET_GAIN = 16.0


#: luma weights (ITU-R BT.601, as JPEG's YCbCr)
LUMA = np.array([0.299, 0.587, 0.114])
#: a laser whose luma is at least this share of its brightest channel is refined on luma …
MIN_LUMA_SHARE = 0.5
#: … when its SNR is at least this share of the texture-free signal's
LUMA_SNR_RATIO = 0.5
#: a luma-dominant laser's clipped core is centred on its light above this fraction of its
#: plateau (a glow line or the texture beside the core no longer pulls it off the plateau)
CLIPPED_CUT = 0.15


#: the signals a spot can be refined on: chosen by SNR, the texture-free light, luma, the
#: channels other than the laser's (:func:`crosstalk_value`)
SIGNALS = ("auto", "light", "luma", "crosstalk")


def _snr(sig: F64, ring: NDArray[np.bool_], inner: NDArray[np.bool_]) -> float:
    """Peak of a signal inside a spot over its robust noise on the ring."""
    if not inner.any():
        return 0.0
    return float(sig[inner].max()) / max(robust_std(sig[ring]), 1e-12)


def luma_dominant(laser_rgb: F64) -> bool:
    """Whether a laser's light (expected linear RGB) shows mostly in luma (a green laser)."""
    return float(LUMA @ laser_rgb) >= MIN_LUMA_SHARE * float(np.max(laser_rgb))


def spot_light(rgb: F64, clipped: NDArray[np.bool_], laser_rgb: F64, texture: F64
               ) -> tuple[F64, NDArray[np.bool_]]:
    """(h, w) laser light per pixel, free of texture, and where it is undetermined.

    At each pixel the unclipped channels are projected on the part of the laser's colour that
    is orthogonal to the texture colour (``texture``: :func:`texture_direction` of a ring
    around the spot), scaled to unit response to the laser's light: texture cancels, laser
    light of any strength is measured in the same units whichever channels clipped. A pixel
    with fewer than two unclipped channels (or whose unclipped channels cannot separate the
    two colours) is undetermined.
    """
    keys = (~clipped) @ np.array([1, 2, 4])  # (h, w): which channels are unclipped
    out = np.zeros(rgb.shape[:2])
    undetermined = np.ones(rgb.shape[:2], dtype=bool)
    full = _projection(laser_rgb, texture)
    if full is None:
        return out, undetermined
    for key in np.unique(keys):
        idx = [k for k in range(3) if key & (1 << k)]
        w = _projection(laser_rgb[idx], texture[idx]) if len(idx) >= 2 else None
        if w is None or _noise_gain(w) > MAX_SUBSET_GAIN * _noise_gain(full):
            continue
        sel = keys == key
        out[sel] = rgb[sel][:, idx] @ w
        undetermined[sel] = False
    return out, undetermined


def crosstalk_value(rgb: F64, clipped: NDArray[np.bool_], laser_rgb: F64
                    ) -> tuple[F64, NDArray[np.bool_]]:
    """(h, w) sum of the linear channels other than the laser's (its brightest in
    ``laser_rgb``), and where one of them clips.

    A laser many times white clips its own channel over its core and often over its halo and
    glow as well, where the texture-free light and luma (which holds the clipped channel's
    halo) have no shape left; the sensor's spectral crosstalk puts a few per cent of its light
    in the other channels, so there the core alone still stands out, far above the noise,
    while the halo adds little."""
    others = [k for k in range(3) if k != int(np.argmax(laser_rgb))]
    return rgb[..., others].sum(axis=2), np.asarray(clipped[..., others].any(axis=2))


def _projection(laser: F64, texture: F64) -> F64 | None:
    """Weights measuring laser light in unit response, blind to the texture colour (None when
    the two colours coincide)."""
    t2 = float(texture @ texture)
    w = laser - (laser @ texture) / t2 * texture if t2 > 1e-12 else laser
    gain = float(w @ laser)
    if gain <= 1e-6 * float(laser @ laser):
        return None
    return np.asarray(w / gain)


def _noise_gain(w: F64) -> float:
    return float(np.linalg.norm(w))


def spot_patch(planes: Planes, guess: SpotGuess, support_px: float,
               neighbours: tuple[NeighbourModel, ...] = (), allow_luma: bool = True,
               signal: str = "auto", texture: F64 | None = None) -> SpotPatch | None:
    """The spot signal around a guess (crop COLMAP px); None with too little background.

    ``neighbours``: overlapping spots whose modelled light is removed first (so neither the
    background fit on the ring nor the centroid sees their halo); their models and a spot
    refined beside them use the texture-free signal only (one unit for all). Otherwise a
    luma-dominant laser's spot uses luma when its SNR there is at least LUMA_SNR_RATIO of the
    texture-free signal's (texture strong in luma, e.g. green water, keeps the latter).
    ``signal`` (one of SIGNALS): "auto" chooses so (a red or blue laser's spot: the
    texture-free light); "light" and "luma" force that signal on a spot without neighbours,
    of any laser (:mod:`.centre` weighs a red or blue clipped core's luma against its light);
    "crosstalk" reads the channels other than the laser's (:func:`crosstalk_value`; a
    clipped core's, :func:`.centre.crosstalk_centre`).
    ``texture``: the texture colour the light is freed of (None: the ring's,
    :func:`texture_direction`); a second capture of the same place is read with the same
    weights by giving it the first patch's ``texture``.
    """
    if signal not in SIGNALS:
        raise ValueError(f"signal must be one of {SIGNALS}, got {signal!r}")
    x0, y0 = guess.x, guess.y
    radius = int(math.ceil(support_px)) + 4
    win = window(planes.laser.shape, int(math.floor(y0)), int(math.floor(x0)), radius)
    gx, gy = grid(win)
    rr = np.hypot(gx - x0, gy - y0)
    rgb = planes.channels.linear(win)
    clipped3 = rgb >= planes.saturation_level
    clipped = np.asarray(clipped3.any(axis=2), dtype=bool)
    ring = (rr >= support_px) & ~clipped
    if ring.sum() < 8:
        return None
    inner = rr < support_px
    if signal == "crosstalk":  # the other channels: no texture colour to free them of
        value, undetermined = crosstalk_value(rgb, clipped3, planes.laser_rgb)
    else:
        if texture is None:
            texture = texture_direction(rgb[ring], planes.laser_rgb)
        value, undetermined = spot_light(rgb, clipped3, planes.laser_rgb, texture)
    for nb in neighbours:
        value = value - nb.at(gx, gy)
    sig = _plane_residual(value, gx, gy, ring)
    from_colour = signal != "crosstalk"
    green = luma_dominant(planes.laser_rgb)
    if allow_luma and not neighbours and (signal == "luma" or (green and signal == "auto")):
        sig_l = _plane_residual(rgb @ LUMA, gx, gy, ring)
        if signal == "luma" or (_snr(sig_l, ring, inner & ~clipped)
                                >= LUMA_SNR_RATIO * _snr(sig, ring, inner & ~undetermined)):
            sig, undetermined, from_colour = sig_l, clipped, False
    top = inner & undetermined
    if top.any():
        ok = inner & ~undetermined
        level = float(sig[ok].max()) if ok.any() else float(sig.max())
        sig[top] = level
        if allow_luma and (green or not from_colour):  # a neighbour's model keeps it all
            sig = sig - CLIPPED_CUT * level
    h, w = planes.laser.shape
    cut = bool(x0 - support_px < 0 or y0 - support_px < 0 or x0 + support_px > w
               or y0 + support_px > h)
    return SpotPatch(gx=gx, gy=gy, signal=sig, usable=~clipped, noise=robust_std(sig[ring]),
                     support_px=support_px, cut=cut, from_colour=from_colour,
                     bounds=(float(w), float(h)), texture=texture)


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
) -> tuple[float, float, float]:
    """One windowed-centroid update from (x, y): (new x, new y, Σw)."""
    g = _window_weights(patch, x, y, sigma_w)
    w = pos * g
    total = float(w.sum())
    if total <= 0:
        return x, y, 0.0
    return float((w * patch.gx).sum() / total), float((w * patch.gy).sum() / total), total


def _window_weights(patch: SpotPatch, x: float, y: float, sigma_w: float) -> F64:
    """The Gaussian window (sigma ``sigma_w``, cut at the support radius) centred on (x, y);
    for a spot cut by the border, only where its reflection through (x, y) is in the image
    too (:func:`mirrored_inside`), so the window stays point-symmetric about (x, y)."""
    rr2 = (patch.gx - x) ** 2 + (patch.gy - y) ** 2
    g = np.exp(-0.5 * rr2 / (sigma_w * sigma_w)) * (rr2 < patch.support_px**2)
    if patch.cut:
        g = (g * mirrored_inside(patch.gx, x, patch.bounds[0])
             * mirrored_inside(patch.gy, y, patch.bounds[1]))
    return np.asarray(g)


def mirrored_inside(centres: F64, c: float, size: float) -> F64:
    """Share of each pixel (its centre's coordinate along one axis, px) that lies inside the
    image [0, size] with its reflection through ``c``: the interval symmetric about ``c``."""
    lo, hi = max(0.0, 2.0 * c - size), min(size, 2.0 * c)
    return np.asarray(np.clip(np.minimum(centres + 0.5, hi) - np.maximum(centres - 0.5, lo),
                              0.0, 1.0))


#: a step between these fractions of the previous one, in the same direction, is a steady creep:
#: the window is moved to where the steps' geometric series ends (nearer 1 the jump would
#: multiply the step's own noise)
CREEP_RATIO = (0.3, 0.95)


def _towards_fixed_point(start: tuple[float, float], step: tuple[float, float],
                         before: tuple[float, float] | None
                         ) -> tuple[float, float, tuple[float, float] | None]:
    """Where a windowed centroid goes next from ``start`` after a plain ``step``, and the step
    to compare the next one with (None after a changed step).

    The step itself; half of it when it reverses the ``before`` step (a window that jumps back
    and forth across the fixed point: halving the step makes the map contract); the end of the
    geometric series when it repeats ``before`` shrunk by a steady ratio k (within CREEP_RATIO).
    Only the way to the fixed point changes, never the fixed point.
    """
    x, y = start[0] + step[0], start[1] + step[1]
    if before is None:
        return x, y, step
    if step[0] * before[0] + step[1] * before[1] < 0.0:
        return start[0] + 0.5 * step[0], start[1] + 0.5 * step[1], None
    k = math.hypot(*step) / math.hypot(*before)
    if CREEP_RATIO[0] <= k < CREEP_RATIO[1]:
        return x + step[0] * k / (1.0 - k), y + step[1] * k / (1.0 - k), None
    return x, y, step


def refine_centroid(
    patch: SpotPatch, x0: float, y0: float, sigma_w: float, iterations: int = 50
) -> tuple[float, float, float]:
    """Gaussian-windowed centroid of a :class:`SpotPatch`: (x, y, 1-sigma noise), COLMAP px.

    The window (sigma ``sigma_w``, cut at the support radius) follows the estimate until it
    stops moving (:func:`_towards_fixed_point` shortens the way there); for any point-symmetric
    spot the true centre is the fixed point, so the estimate is unbiased. The sigma is the ring
    noise propagated through one centroid step, times the gain 1 / (1 - k) of the fixed-point
    iteration (k: how far one step follows a displaced window, measured by displacing it).
    """
    pos = np.clip(patch.signal, 0.0, None)
    x, y = x0, y0
    x_in, y_in = x, y
    total = 0.0
    before: tuple[float, float] | None = None  # the previous plain step (dx, dy)
    for _ in range(iterations):
        x_in, y_in = x, y
        x, y, total = _centroid_step(patch, pos, x_in, y_in, sigma_w)
        step = (x - x_in, y - y_in)
        if total <= 0 or math.hypot(*step) < 1e-5:
            break
        x, y, before = _towards_fixed_point((x_in, y_in), step, before)
    if total <= 0:
        return x, y, math.nan
    g = _window_weights(patch, x_in, y_in, sigma_w)  # the last step's window
    spread = float((g * g * ((patch.gx - x) ** 2 + (patch.gy - y) ** 2)).sum())
    delta = 0.25
    kx = (_centroid_step(patch, pos, x + delta, y, sigma_w)[0] - x) / delta
    ky = (_centroid_step(patch, pos, x, y + delta, sigma_w)[1] - y) / delta
    gain = 1.0 / max(1.0 - 0.5 * (kx + ky), 0.2)
    return x, y, gain * patch.noise * math.sqrt(spread / 2.0) / total


def gaussian_fit(
    patch: SpotPatch, x0: float, y0: float, sigma0: float
) -> tuple[float, float, float, float] | None:
    """2D Gaussian plus a constant fitted to the unclipped support pixels of a
    :class:`SpotPatch`, started at (x0, y0) with width ``sigma0``: (x, y, 1-sigma of the
    position, the fitted Gaussian's σ) in COLMAP px, or None when it fails (fewer than 8
    pixels, no convergence, or a centre beyond the support).

    Clipped pixels are left out, so a saturated core does not flatten the fitted profile; the
    flanks of the spot carry its position.
    """
    use = patch.usable & ((patch.gx - x0) ** 2 + (patch.gy - y0) ** 2 < patch.support_px**2)
    if use.sum() < 8:
        return None
    px, py, pv = patch.gx[use], patch.gy[use], patch.signal[use]

    def residual(p: F64) -> F64:
        a, x, y, s, b0 = p
        g = a * np.exp(-0.5 * ((px - x) ** 2 + (py - y) ** 2) / (s * s))
        return np.asarray(g + b0 - pv, dtype=np.float64)

    p0 = np.array([max(float(patch.signal.max()), 1e-3), x0, y0, sigma0, 0.0])
    fit = least_squares(residual, p0, method="lm", max_nfev=300)
    x, y, width = float(fit.x[1]), float(fit.x[2]), abs(float(fit.x[3]))
    if not (fit.success and math.hypot(x - x0, y - y0) < patch.support_px):
        return None
    s2 = float(fit.fun @ fit.fun) / max(len(pv) - 5, 1)
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * s2
    except np.linalg.LinAlgError:
        return x, y, 1.0, width
    return x, y, math.sqrt(max(0.5 * (cov[1, 1] + cov[2, 2]), 0.0)), width


def refine_gaussian(
    patch: SpotPatch, x0: float, y0: float, sigma0: float
) -> tuple[float, float, float]:
    """:func:`gaussian_fit`'s centre and its σ, or (x0, y0, 1) where it fails."""
    fit = gaussian_fit(patch, x0, y0, sigma0)
    return (x0, y0, 1.0) if fit is None else fit[:3]


#: the wider window of the structure term: a centroid's fixed point under a window this many
#: times wider (light that is point-symmetric about the centre does not move it)
WIDE_WINDOW_RATIO = 1.6


def structure_sigma(patch: SpotPatch, x: float, y: float, sigma_w: float,
                    model: SigmaModel) -> float:
    """σ (px, per axis) of a centre from light that is not point-symmetric about it (texture,
    a halo's skew, a neighbour): every spot model is point-symmetric, so its fixed point does
    not depend on the window and its mirror image matches it."""
    xw, yw, _ = refine_centroid(patch, x, y, WIDE_WINDOW_RATIO * sigma_w)
    shift = math.hypot(xw - x, yw - y)
    skew = math.sqrt(asymmetry(patch, x, y, sigma_w)) * sigma_w
    return math.hypot(model.window_gain * shift, model.asymmetry_gain * skew)


def cut_sigma(patch: SpotPatch, x: float, y: float, sigma_w: float,
              model: SigmaModel) -> float:
    """σ (px, per axis) of a cut spot's fitted centre (x, y) from light the symmetric model
    does not hold: window_gain × its distance to the centroid whose window keeps only pixels
    mirrored inside the image (both unbiased for a point-symmetric spot); 0 for uncut spots."""
    if not patch.cut or not math.isfinite(x):
        return 0.0
    xs, ys, _ = refine_centroid(patch, x, y, sigma_w)
    return model.window_gain * math.hypot(xs - x, ys - y) if math.isfinite(xs) else 0.0


def refine_spot(planes: Planes, guess: SpotGuess, refine: str,
                neighbours: tuple[NeighbourModel, ...] = (),
                sigma_model: SigmaModel = SigmaModel(),  # noqa: B008 (frozen dataclass)
                signal: str = "auto") -> tuple[float, float, float]:
    """Sub-pixel centre and localisation sigma (:class:`SigmaModel`) of one candidate (crop
    COLMAP px); NaN if impossible. ``refine``: "centroid" or "gaussian" (spots cut by the
    border: always); ``signal``: see :func:`spot_patch`."""
    sigma_w = guess.window_px
    patch = spot_patch(planes, guess, guess.patch_support, neighbours, signal=signal)
    if patch is None:
        return math.nan, math.nan, math.nan
    floor = floor_sigma(patch, sigma_model, guess.radius_px)
    if refine == "gaussian" or patch.cut:
        # a spot cut by the image border: a centroid would be pulled inwards, a symmetric
        # model fitted to the visible pixels is not (and has no wide-window term: the wider
        # window's centroid would move inwards for any spot)
        x, y, sig = refine_gaussian(patch, guess.x, guess.y, sigma_w)
        return x, y, math.hypot(sig, floor, cut_sigma(patch, x, y, sigma_w, sigma_model))
    x, y, sig = refine_centroid(patch, guess.x, guess.y, sigma_w)
    if not math.isfinite(sig):
        return x, y, sig
    return x, y, centroid_sigma(patch, x, y, sig, sigma_w, sigma_model, guess.radius_px)


def floor_sigma(patch: SpotPatch, sigma_model: SigmaModel, radius_px: float) -> float:
    """The σ floor (px) of a centre read on ``patch``: the model's floor and, for the
    texture-free light (a colour difference), the colour term of a spot of ``radius_px``."""
    return math.hypot(sigma_model.floor_px,
                      sigma_model.chroma(radius_px) if patch.from_colour else 0.0)


def centroid_sigma(patch: SpotPatch, x: float, y: float, noise: float, sigma_w: float,
                   sigma_model: SigmaModel, radius_px: float) -> float:
    """The stated σ (px) of a centroid (x, y) of ``patch`` under a window ``sigma_w``: its
    ``noise`` σ, the structure terms (:func:`structure_sigma`) and :func:`floor_sigma`."""
    return math.hypot(noise, structure_sigma(patch, x, y, sigma_w, sigma_model),
                      floor_sigma(patch, sigma_model, radius_px))


def asymmetry(patch: SpotPatch, x: float, y: float, radius_px: float) -> float:
    """How far the spot signal is from point symmetry about (x, y): 0 symmetric, ~1 not.

    ``Σ (s(p) - s(p'))² / Σ (s(p)² + s(p')²)`` over the support's determined pixels, p' the
    reflection of p through the centre (bilinear). Every spot model (a Gaussian footprint on a
    tilted surface, motion blur, a clipped core) is point-symmetric; light of something else
    overlapping it (an object's edge, a neighbour) is not.
    """
    reach = max(2.0 * radius_px, 3.0)
    inside = (patch.gx - x) ** 2 + (patch.gy - y) ** 2 < reach * reach
    if inside.sum() < 5:
        return 0.0
    x0, y0 = float(patch.gx[0, 0]), float(patch.gy[0, 0])
    rows = (2.0 * y - patch.gy[inside]) - y0
    cols = (2.0 * x - patch.gx[inside]) - x0
    mirrored = ndimage.map_coordinates(patch.signal, [rows, cols], order=1, mode="nearest")
    direct = patch.signal[inside]
    den = float(np.sum(direct**2 + mirrored**2))
    return float(np.sum((direct - mirrored) ** 2) / den) if den > 0 else 0.0


def subpixel_peak(response: NDArray[np.float32], corner: tuple[int, int],
                  peak: tuple[float, float]) -> tuple[float, float] | None:
    """The sub-pixel position (image COLMAP px) of the largest value of ``response`` (a crop
    whose corner is ``corner``, (x0, y0) image px) within 1 px of the pixel ``peak`` (image
    COLMAP px): a parabola through it and its two neighbours along each axis. None where that
    value is not a maximum along both axes or lies on the crop's edge."""
    x0, y0 = corner
    row, col = int(math.floor(peak[1])) - y0, int(math.floor(peak[0])) - x0
    rows, cols = response.shape
    if not (2 <= row < rows - 2 and 2 <= col < cols - 2):
        return None
    around = response[row - 1:row + 2, col - 1:col + 2]
    dr, dc = np.unravel_index(int(np.argmax(around)), around.shape)
    row, col = row + int(dr) - 1, col + int(dc) - 1
    x = parabola_vertex(response[row, col - 1:col + 2])
    y = parabola_vertex(response[row - 1:row + 2, col])
    if x is None or y is None:
        return None
    return x0 + col + 0.5 + x, y0 + row + 0.5 + y


def parabola_vertex(three: NDArray[np.float32]) -> float | None:
    """Offset (px, within ±0.5) of the vertex of the parabola through three equally spaced
    values whose middle one is the largest; None otherwise."""
    left, mid, right = (float(v) for v in three)
    curvature = left - 2.0 * mid + right
    if not (mid >= left and mid >= right and curvature < 0):
        return None
    return 0.5 * (left - right) / curvature
