"""The reported centre of a chosen spot: a green laser's, or any clipped core's, from both of its
signals; an unclipped spot's from a Gaussian fit where the centroid's window was too wide and the
two agree.

A luma-dominant laser's spot can be refined on two signals (:mod:`.refine`): its light freed of
the scene's texture by colour, and luma. Each fails in its own way. The texture-free light
carries the 2 × 2 blocks of 4:2:0 chroma, and on a clipped core it is read from the channels
that did not clip, whose share of a green laser's light is the sensor's crosstalk alone, so a
few pixels of the core set its centre. Luma is kept at full resolution and sees a clipped core
whole, but holds the scene's texture. The candidate search picks one of them by SNR, which
a clipped core's crosstalk pixels inflate; once a laser's spot is chosen,
:func:`centre_on_both` refines it on both:

- a clipped core (its laser channel clips) whose two centres agree (within TWO_SIGNALS_AGREE
  of their σ combined and TWO_SIGNALS_MAX_APART_PX) takes their inverse-variance weighted
  mean, with the smaller of the two σ (the texture-free light's σ holds the 2 × 2 sampling
  of colour, ``SigmaModel.chroma_px``);
- a clipped core whose two centres disagree and whose σ differ by TWO_SIGNALS_SIGMA_RATIO or
  more takes the centre of the smaller σ. The σ holds how far the light is from
  point-symmetric about the centre and how far a wider window moves it, so the centre whose
  light is a clean spot wins (the other one's signal holds texture, a lamp's hot spot or the
  scene's colour under the core);
- otherwise the spot keeps the centre the search chose: two centres that disagree by similar
  σ cannot tell which of them is off, and on an unclipped spot the SNR choice compares like
  with like.

Either way its σ gains (disagreement_gain · d)², d the distance between the two centres
(:class:`~sfm_laserscale.detection.options.SigmaModel`). A red or blue laser's clipped core is
refined on luma too, but luma holds more of the scene's texture than of its light: it takes
luma's centre only by the σ rule above, and otherwise keeps its centre and σ. Measured in
docs/DETECTION.md ("Two signals"; docs/DETECTION_ROUNDS.md, the twenty-first round).

A clipped core has a third signal: the region where its laser channel clips, whose shape the
scene's texture and colour do not pull. Its centroid is coarse (whole pixels, a noisy rim), so
:func:`clipped_core_centre` takes it only where the centre from the two signals states a σ of
twice the centroid's or more and lies CLIPPED_CENTROID_APART_PX from it, and where the region
is a compact blob no wider than the spot (docs/DETECTION_ROUNDS.md, the twenty-fourth round).

Then :func:`polish_with_fit` fits a 2D Gaussian plus a constant to an unclipped chosen spot
(:func:`fit_centre`, on the signal and window it was refined on). The centroid's Gaussian
window is the spot's measured half-maximum radius; where noise or the beam's glow widened that
measure (a faint spot), the window weights pixels that hold more noise than light, while the
fit's width is free. So the fit's centre is taken where the window is WIDE_WINDOW times the
fitted σ or more: with a window of the right size the two estimators are equally precise,
with a wider one the fit is the more precise (tests/test_detection_fit_centre.py). A fit can
also follow something beside the spot (a texture edge, a neighbour's flank) where the
centroid's fixed point does not, so it is taken only within ``fit_agree_sigmas`` of the spot's
σ from the centroid, and the σ stays the centroid's. Clipped cores keep the centroid: a fit to
their flanks alone was measured less accurate (docs/DETECTION_ROUNDS.md, the sixteenth round).

Then :func:`narrow_window_centre` refines the spot again under centroid windows narrower than
its measured radius (NARROW_WINDOWS_PX) and takes the centre whose stated σ is
``narrow_window_ratio`` times smaller: a radius read on the smoothed response is wider than a
small spot, and a window that wide weighs the scene beside it, which the σ's structure terms
show.

Last, :func:`crosstalk_centre` reads a red or blue laser's clipped core on a fourth signal: the
channels other than its laser's (:func:`.refine.crosstalk_value`). A laser many times white
clips its own channel over its core and often over its halo and glow too, where the
texture-free light is undetermined and luma holds the clipped channel's halo, so neither has
the core's shape; the sensor's spectral crosstalk puts a few per cent of the light in the other
channels, where the core stands far above the noise and the halo barely shows. The centre is
taken where its noise σ is at most ``crosstalk_max_noise_px`` (a core that bright), it lies
within max(3 px, CROSSTALK_REACH_RADII half-maximum radii) of the centre so far, and its stated
σ is the smaller (its structure terms hold the scene's texture in those channels). A green
laser's cores keep theirs: its crosstalk channels are red and blue, where green water's
texture and the 4:2:0 chroma weigh more (measured in docs/DETECTION_ROUNDS.md, the
thirty-second round). :func:`centre_chosen` runs these steps on one crop around the spot.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from sfm_laserscale.detection.candidates import Measure
from sfm_laserscale.detection.options import DetectionOptions, SigmaModel
from sfm_laserscale.detection.refine import (
    SpotGuess,
    centroid_sigma,
    gaussian_fit,
    luma_dominant,
    refine_centroid,
    refine_spot,
    spot_patch,
    window,
)
from sfm_laserscale.detection.response import Planes, crop_channels, make_planes

#: two centres of one spot agree when they lie within this many of their σ combined …
TWO_SIGNALS_AGREE = 4.0
#: … and within this many pixels (farther apart, one is off by half of it or more, whatever
#: the σ say)
TWO_SIGNALS_MAX_APART_PX = 1.0
#: two centres of a clipped core that disagree: the one whose σ is this many times smaller
#: is taken (its light is point-symmetric about it and its window did not move it)
TWO_SIGNALS_SIGMA_RATIO = 3.0
#: an unclipped spot takes its Gaussian fit's centre only where the centroid's window σ (its
#: half-maximum radius, at least 1 px) is at least this many times the fitted σ: a window
#: wider than the spot weights pixels that hold more noise than light
WIDE_WINDOW = 1.25
#: pixels of background around a spot's support in the crop it is centred in
MARGIN_PX = 12
#: the σ of a clipped core's centroid of clipped pixels (px; their median error on clipped
#: cores is 0.27 px) …
CLIPPED_CENTROID_SIGMA_PX = 0.3
#: … which is taken where the core's centre states a σ of this much or more (px; twice the
#: centroid's: the two signals disagreed, or a wider window moved the centre) …
CLIPPED_CENTROID_WHEN_SIGMA_PX = 0.6
#: … when the centroid lies this far from it or more (px) …
CLIPPED_CENTROID_APART_PX = 0.8
#: … and the clipped region is a compact blob of this many pixels or more (fewer are a few
#: pixels of the rim, whose centroid is no better than the spot's) …
CLIPPED_CENTROID_MIN_PIXELS = 3
#: … and of at most this many times the area of the spot's half-maximum disc (a larger one
#: holds clipped scene beside the spot, which pulls its centroid off the spot) …
CLIPPED_CENTROID_MAX_AREAS = 1.0
#: … and of at most this many pixels (a disc 4.4 px in radius): a larger region is a core
#: merged with its clipped halo or with clipped scene, whose outline follows them, not the core
CLIPPED_CENTROID_MAX_PIXELS = 60
#: the clipped region taken is the one with a pixel within this distance of the centre (px)
CLIPPED_CENTROID_REACH_PX = 1.5
#: the centroid windows (σ, px) a chosen spot is also refined under, where narrower than its
#: own (:func:`narrow_window_centre`)
NARROW_WINDOWS_PX = (2.0, 1.5, 1.0)
#: a clipped core's crosstalk centre lies within max(CROSSTALK_REACH_PX, this many half-maximum
#: radii) of the centre so far (:func:`crosstalk_centre`)
CROSSTALK_REACH_RADII = 1.5
CROSSTALK_REACH_PX = 3.0

Centre = tuple[float, float, float]  # (x, y, σ), px


def two_signal_centre(planes: Planes, guess: SpotGuess, refine: str, sigma_model: SigmaModel,
                      chosen: Centre) -> Centre:
    """A spot centred on its texture-free light and on luma (crop COLMAP px), combined by
    :func:`combine_centres`; ``chosen`` (the centre the candidate search refined) is returned
    unchanged when either signal cannot be refined or moves more than max(2, radius) px
    from it."""
    reach = max(2.0, guess.radius_px)
    light, luma = (refine_spot(planes, guess, refine, sigma_model=sigma_model, signal=s)
                   for s in ("light", "luma"))
    if not all(math.isfinite(c[2]) and math.hypot(c[0] - chosen[0], c[1] - chosen[1]) <= reach
               for c in (light, luma)):
        return chosen
    return combine_centres(light, luma, chosen, guess.bright,
                           luma_dominant(planes.laser_rgb), sigma_model.disagreement_gain)


def combine_centres(light: Centre, luma: Centre, chosen: Centre, clipped: bool, green: bool,
                    disagreement_gain: float) -> Centre:
    """One centre (x, y, σ; px) from a spot's two signals' centres and the search's ``chosen``.

    A green (luma-dominant) laser's spot: the weighted mean of the two when its laser channel
    clips (``clipped``) and they agree; else ``chosen``. Two centres of a clipped core that
    disagree and whose σ differ by TWO_SIGNALS_SIGMA_RATIO or more: the one of the smaller σ
    (the other one's light is not point-symmetric about it, or its window moved it); for a red
    or blue laser only when that is luma (its usual signal is the texture-free light, and luma
    holds the scene's texture). σ gains the disagreement term, except where a red or blue
    spot keeps ``chosen``.
    """
    (xa, ya, sa), (xb, yb, sb) = light, luma
    apart = math.hypot(xa - xb, ya - yb)
    spread = disagreement_gain * apart
    agree = apart <= min(TWO_SIGNALS_AGREE * math.hypot(sa, sb), TWO_SIGNALS_MAX_APART_PX)
    if green and clipped and agree:
        wa, wb = 1.0 / sa**2, 1.0 / sb**2
        return ((wa * xa + wb * xb) / (wa + wb), (wa * ya + wb * yb) / (wa + wb),
                math.hypot(min(sa, sb), spread))
    luma_sharper = sb < sa
    if (clipped and not agree and TWO_SIGNALS_SIGMA_RATIO * min(sa, sb) <= max(sa, sb)
            and (green or luma_sharper)):
        x, y, sigma = luma if luma_sharper else light
        return x, y, math.hypot(sigma, spread)
    if not green:
        return chosen
    return chosen[0], chosen[1], math.hypot(chosen[2], spread)


def clipped_centroid(clipped: NDArray[np.bool_], x: float, y: float
                     ) -> tuple[float, float, int] | None:
    """The centroid (x, y; COLMAP px of the mask) and pixel count of the 8-connected region of
    ``clipped`` (H, W) with a pixel within CLIPPED_CENTROID_REACH_PX of (x, y); None where
    there is none."""
    labels, _ = ndimage.label(clipped, structure=np.ones((3, 3), dtype=bool))
    rows, cols = np.nonzero(labels)
    if rows.size == 0:
        return None
    dist = np.hypot(cols + 0.5 - x, rows + 0.5 - y)
    nearest = int(np.argmin(dist))
    if dist[nearest] > CLIPPED_CENTROID_REACH_PX:
        return None
    mine = labels[rows, cols] == labels[rows[nearest], cols[nearest]]
    return (float(cols[mine].mean()) + 0.5, float(rows[mine].mean()) + 0.5, int(mine.sum()))


def clipped_core_centre(clipped: NDArray[np.bool_], guess: SpotGuess, centre: Centre,
                        disagreement_gain: float) -> Centre:
    """A clipped core's centre (x, y, σ; crop COLMAP px): the centroid of its clipped pixels
    (``clipped``, the laser channel at saturation) where ``centre``'s σ is
    CLIPPED_CENTROID_WHEN_SIGMA_PX or more, the centroid lies CLIPPED_CENTROID_APART_PX or more
    from it, and the region is compact (CLIPPED_CENTROID_MIN_PIXELS to
    CLIPPED_CENTROID_MAX_AREAS half-maximum discs of ``guess`` and
    CLIPPED_CENTROID_MAX_PIXELS); else ``centre``.

    The clipped region's shape does not depend on the scene's texture or colour under it,
    which pull a centre read from either signal; its centroid is coarser (whole pixels, the
    rim's noise), so it is taken only where the centre's own σ says the signals disagreed.
    Its σ: CLIPPED_CENTROID_SIGMA_PX and the disagreement term of the distance moved.
    """
    x, y, sigma = centre
    if sigma < CLIPPED_CENTROID_WHEN_SIGMA_PX:
        return centre
    found = clipped_centroid(clipped, x, y)
    if found is None:
        return centre
    cx, cy, n = found
    apart = math.hypot(cx - x, cy - y)
    max_pixels = min(CLIPPED_CENTROID_MAX_AREAS * math.pi * max(1.0, guess.radius_px) ** 2,
                     CLIPPED_CENTROID_MAX_PIXELS)
    if apart < CLIPPED_CENTROID_APART_PX or not CLIPPED_CENTROID_MIN_PIXELS <= n <= max_pixels:
        return centre
    return cx, cy, math.hypot(CLIPPED_CENTROID_SIGMA_PX, disagreement_gain * apart)


def narrow_window_centre(planes: Planes, guess: SpotGuess, refine: str,
                         sigma_model: SigmaModel, chosen: Centre, sigma_ratio: float) -> Centre:
    """A chosen spot's centre (x, y, σ; crop COLMAP px) refined again under each centroid
    window of NARROW_WINDOWS_PX narrower than its half-maximum radius (``guess.radius_px``),
    started at ``chosen``: the one whose stated σ is ``sigma_ratio`` times smaller than the
    best so far (``chosen`` first) replaces it, when it lies within max(2, radius) px of
    ``chosen``; else ``chosen``. The σ returned gains the disagreement term of the distance
    moved, as two signals' centres do (:func:`combine_centres`), and is no smaller than
    ``chosen``'s divided by ``sigma_ratio``, the bound the window was taken by: the smallest
    of several σ, each read with noise, understates the error of the centre it picks.

    The window is the spot's measured half-maximum radius, which the candidate search reads on
    a smoothed response: for a small spot it is wider than the light, so the window weights the
    scene around it, and a gradient or a patch beside the spot pulls the fixed point off it.
    The σ says so: its structure term is how far a wider window moves the centre and how far
    the light is from point-symmetric about it. A window on the spot's own scale, whose centre
    states a much smaller σ, reads the spot and not its surroundings."""
    best = chosen
    reach = max(2.0, guess.radius_px)
    for window_px in NARROW_WINDOWS_PX:
        if window_px >= guess.radius_px:
            continue
        narrow = replace(guess, x=chosen[0], y=chosen[1], radius_px=window_px)
        x, y, sigma = refine_spot(planes, narrow, refine, sigma_model=sigma_model)
        if (math.isfinite(sigma) and sigma_ratio * sigma < best[2]
                and math.hypot(x - chosen[0], y - chosen[1]) <= reach):
            best = (x, y, sigma)
    if best is chosen:
        return chosen
    moved = math.hypot(best[0] - chosen[0], best[1] - chosen[1])
    sigma = max(math.hypot(best[2], sigma_model.disagreement_gain * moved),
                chosen[2] / sigma_ratio)
    return best[0], best[1], sigma


def crosstalk_centre(planes: Planes, guess: SpotGuess, sigma_model: SigmaModel,
                     chosen: Centre, max_noise_px: float) -> Centre:
    """A red or blue laser's clipped core's centre (x, y, σ; crop COLMAP px) read on the
    channels other than its laser's (:func:`.refine.crosstalk_value`), started at ``chosen``:
    taken where the centroid's noise σ is at most ``max_noise_px``, it lies within
    max(CROSSTALK_REACH_PX, CROSSTALK_REACH_RADII · radius) of ``chosen`` and its σ is
    smaller than ``chosen``'s; else ``chosen``. Its σ: the noise, the structure terms and the
    floor, as :func:`.refine.refine_spot` states them (no chroma term: the crosstalk is read
    at full resolution in each channel); the structure terms hold the scene's texture in the
    other channels (blue water's, under a red core), which a small noise σ does not show."""
    start = replace(guess, x=chosen[0], y=chosen[1])
    patch = spot_patch(planes, start, guess.patch_support, signal="crosstalk")
    if patch is None:
        return chosen
    sigma_w = guess.window_px
    x, y, noise = refine_centroid(patch, start.x, start.y, sigma_w)
    reach = max(CROSSTALK_REACH_PX, CROSSTALK_REACH_RADII * guess.radius_px)
    if not (math.isfinite(noise) and noise <= max_noise_px
            and math.hypot(x - chosen[0], y - chosen[1]) <= reach):
        return chosen
    sigma = centroid_sigma(patch, x, y, noise, sigma_w, sigma_model, guess.radius_px)
    return (x, y, sigma) if sigma < chosen[2] else chosen


def local_planes(image_rgb: NDArray[np.uint8], m: Measure,
                 laser_rgb: tuple[float, float, float], options: DetectionOptions,
                 max_radius: float) -> tuple[Planes, SpotGuess, int, int]:
    """The planes of a crop around a chosen spot (its support and MARGIN_PX), the spot as a
    guess in that crop, and the crop's corner (x0, y0) in image px."""
    rows, cols = window(image_rgb.shape, int(math.floor(m.y)), int(math.floor(m.x)),
                        int(math.ceil(m.guess().patch_support)) + MARGIN_PX)
    x0, y0 = cols.start, rows.start
    planes = make_planes(crop_channels(image_rgb, (x0, y0, cols.stop, rows.stop),
                                       options.input_gamma), m.color, options, max_radius,
                         laser_rgb)
    guess = SpotGuess(m.x - x0, m.y - y0, m.radius_px, m.support_px, m.bright)
    return planes, guess, x0, y0


def _two_signals_apply(m: Measure, laser_rgb: tuple[float, float, float],
                       options: DetectionOptions) -> bool:
    """Whether :func:`two_signal_centre` refines this chosen spot: a green laser's, or a red
    or blue laser's clipped core (``m.bright``), unless refined beside an overlapping one."""
    return (options.two_signal_centre and not m.beside
            and (m.bright or luma_dominant(np.asarray(laser_rgb))))


def _fit_applies(m: Measure, options: DetectionOptions) -> bool:
    """Whether :func:`fit_centre` may move this chosen spot."""
    return (options.fit_agree_sigmas > 0 and options.refine != "gaussian" and not m.bright
            and not m.beside)


def _crosstalk_applies(m: Measure, laser_rgb: tuple[float, float, float],
                       options: DetectionOptions) -> bool:
    """Whether :func:`crosstalk_centre` may move this chosen spot: a red or blue laser's
    clipped core (``m.bright``), also one refined beside an overlapping spot."""
    return (options.crosstalk_max_noise_px > 0 and m.bright
            and not luma_dominant(np.asarray(laser_rgb)))


def _centre(image_rgb: NDArray[np.uint8], m: Measure, laser_rgb: tuple[float, float, float],
            options: DetectionOptions, max_radius: float, both: bool, fit: bool,
            narrow: bool = False, crosstalk: bool = False) -> None:
    """In place: a chosen spot's centre and σ from :func:`two_signal_centre` (``both``), then
    :func:`fit_centre` (``fit``), then :func:`narrow_window_centre` (``narrow``), then
    :func:`crosstalk_centre` (``crosstalk``), on one crop around it."""
    if not (both or fit or narrow or crosstalk):
        return
    planes, guess, x0, y0 = local_planes(image_rgb, m, laser_rgb, options, max_radius)
    start = (m.x - x0, m.y - y0, m.sigma_px)
    centre = start
    if both:
        centre = two_signal_centre(planes, guess, options.refine, options.sigma_model, centre)
        if guess.bright:
            centre = clipped_core_centre(planes.clipped_laser, guess, centre,
                                         options.sigma_model.disagreement_gain)
    if fit:
        centre = fit_centre(planes, replace(guess, x=centre[0], y=centre[1]), centre,
                            options.fit_agree_sigmas)
    if narrow:
        centre = narrow_window_centre(planes, guess, options.refine, options.sigma_model,
                                      centre, options.narrow_window_ratio)
    if crosstalk:
        centre = crosstalk_centre(planes, guess, options.sigma_model, centre,
                                  options.crosstalk_max_noise_px)
    if centre != start:
        m.x, m.y, m.sigma_px = centre[0] + x0, centre[1] + y0, centre[2]


def centre_on_both(image_rgb: NDArray[np.uint8], m: Measure,
                   laser_rgb: tuple[float, float, float],
                   options: DetectionOptions, max_radius: float) -> None:
    """In place: a chosen spot's centre and σ (image COLMAP px) from :func:`two_signal_centre`,
    for a luma-dominant laser (``laser_rgb``, its expected linear colour) when
    ``options.two_signal_centre``; other spots, and spots refined beside an overlapping one
    (their neighbour's light removed), keep theirs."""
    _centre(image_rgb, m, laser_rgb, options, max_radius,
            both=_two_signals_apply(m, laser_rgb, options), fit=False)


def fit_centre(planes: Planes, guess: SpotGuess, chosen: Centre, agree_sigmas: float
               ) -> Centre:
    """An unclipped spot's centre from a 2D Gaussian fit (:func:`.refine.gaussian_fit`, on the
    signal and window of :func:`.refine.spot_patch`) started at ``chosen`` (x, y, σ; crop
    COLMAP px), when the centroid's window was too wide for the spot (WIDE_WINDOW) and the
    fit lies within ``agree_sigmas`` · σ of ``chosen``; else ``chosen``. The σ is kept. A
    clipped core (``guess.bright``) or a spot cut by the border keeps ``chosen``."""
    if guess.bright:
        return chosen
    patch = spot_patch(planes, guess, guess.patch_support)
    if patch is None or patch.cut:
        return chosen
    window_px = guess.window_px  # the centroid's window σ (refine_spot)
    fit = gaussian_fit(patch, chosen[0], chosen[1], window_px)
    if (fit is None or WIDE_WINDOW * fit[3] > window_px
            or math.hypot(fit[0] - chosen[0], fit[1] - chosen[1]) > agree_sigmas * chosen[2]):
        return chosen
    return fit[0], fit[1], chosen[2]


def polish_with_fit(image_rgb: NDArray[np.uint8], m: Measure,
                    laser_rgb: tuple[float, float, float], options: DetectionOptions,
                    max_radius: float) -> None:
    """In place: a chosen unclipped spot's centre (image COLMAP px) from :func:`fit_centre`
    with ``options.fit_agree_sigmas`` (0: off). Clipped cores, spots refined beside an
    overlapping one, and every spot when ``options.refine`` is already "gaussian" keep
    theirs."""
    _centre(image_rgb, m, laser_rgb, options, max_radius, both=False,
            fit=_fit_applies(m, options))


def centre_chosen(image_rgb: NDArray[np.uint8], m: Measure,
                  laser_rgb: tuple[float, float, float], options: DetectionOptions,
                  max_radius: float) -> None:
    """In place: a chosen spot's reported centre and σ: :func:`centre_on_both`, then
    :func:`polish_with_fit`, then :func:`narrow_window_centre` (``options.narrow_window_ratio``;
    not for spots refined beside an overlapping one), then :func:`crosstalk_centre` (a red or
    blue laser's clipped core, ``options.crosstalk_max_noise_px``), on one crop (image COLMAP
    px)."""
    _centre(image_rgb, m, laser_rgb, options, max_radius,
            both=_two_signals_apply(m, laser_rgb, options), fit=_fit_applies(m, options),
            narrow=options.narrow_window_ratio > 0 and not m.beside,
            crosstalk=_crosstalk_applies(m, laser_rgb, options))
