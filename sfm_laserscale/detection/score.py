"""Evidence that a candidate is a laser spot: terms in 0–1 that multiply into its score.

- *contrast*: ``snr / (snr + snr_half)``;
- *roundness*: ``sqrt(roundness)`` of its half-maximum region;
- *clutter*: how far its blob response stands above the scene's own blobs,
  ``r² / (r² + clutter_half²)`` with r the response in clutter levels (1 when the region is too
  small to have a clutter level);
- *colour*: evidence against light of the scene's own colour. The light the candidate adds
  over its surroundings (:func:`added_light`) in the laser's channel is compared with what the
  scene's colour there explains (:func:`colour_evidence`): scene texture and pale clutter add
  light of the scene's colour, highlights and marine snow white light, a laser its own. 1 for
  laser-coloured light or when a clipped core's colour cannot be measured (its edge the
  camera's processing of highlights whitens), ½ when an unclipped blob's cannot, falling to ~0
  for the scene's colour;
- *beam*: ``exp(-½ (d / (band / 2))²)`` of the distance to the beam's image;
- *depth*: DEPTH when laser light lies farther along the same beam (:mod:`.assign`).

Colour is evidence, not a gate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from sfm_laserscale.detection.refine import grid, window
from sfm_laserscale.detection.response import Channels

F64 = NDArray[np.float64]
#: fewer unclipped pixels than this in the spot or its ring: the colour is not measured
MIN_COLOUR_PIXELS = 4
#: the added light must exceed this many times its noise for its colour to count
MIN_COLOUR_SNR = 3.0
#: the colour of a clipped core is read on its rim, from this far beyond the clipped pixels (px)
RIM_START = 0.5
#: … over this width (px)
RIM_WIDTH = 2.5
#: a clipped core is elongated (a glint, a streak) when its farthest pixel lies beyond this
#: many times the radius of a disc of its area
ELONGATED_CORE = 1.25
#: angular sectors of a spot whose median added light is its colour
SECTORS = 8
#: laser-coloured share of the added light at which the colour term is ½
MID_FRACTION = 0.25
#: the colour term of an unclipped candidate whose colour cannot be measured
UNMEASURED_UNCLIPPED = 0.5
#: the colour is read at the centre and this far (px) from it on either axis, the median kept
COLOUR_JITTER_PX = 0.3
#: the scene's laser/other channel ratio used is at most this (a scene of nearly the laser's
#: colour leaves the colour undecided rather than negative)
MAX_SCENE_RATIO = 1.5


@dataclass(frozen=True)
class ColourEvidence:
    """How much of the light a candidate adds in the laser's channel the scene's own colour
    cannot explain (``fraction``, 0–1), and the term; ``measured`` False when it could not be
    measured (term 0.5)."""

    term: float
    fraction: float = math.nan
    measured: bool = False


@dataclass(frozen=True)
class AddedLight:
    """Mean linear RGB a candidate adds over planes fitted on its ring (``delta_rgb``), the
    ring's mean colour (``scene_rgb``) and the noise of ``delta_rgb`` (per channel)."""

    delta_rgb: F64
    scene_rgb: F64
    noise: F64


def _spot_zones(clipped_laser: NDArray[np.bool_], rr: F64, radius: float, support: float,
                outline: bool = False) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(inner, ring) masks of the window where a spot's colour and its background are measured.

    An unclipped spot: inner within ``max(2, radius) + 2`` px, ring beyond the support. A spot
    whose laser channel clips: its colour is read on the rim of the clipped core (RIM_START to
    RIM_START + RIM_WIDTH px beyond the circle through its farthest clipped pixel), where its
    light falls through the channels' range (a small spot's own light is gone a few pixels
    further out), and the ring lies beyond that. With ``outline``, an elongated core's rim
    (ELONGATED_CORE) lies that far from its nearest clipped pixel instead: the circle through
    the tip of a streak passes its sides in the background.
    """
    core = clipped_laser & (rr <= max(2.0, radius) + 1.0)
    if not core.any():
        inner = rr <= max(2.0, radius) + 2.0
        return inner & (rr < max(support, 4.0)), rr >= max(support, 4.0)
    r_clip = float(rr[core].max())
    start = r_clip + RIM_START
    stop = start + RIM_WIDTH
    ring = rr >= max(stop + 1.0, support)
    if outline and r_clip > ELONGATED_CORE * math.sqrt(float(core.sum()) / math.pi):
        beyond = ndimage.distance_transform_edt(~core)  # px to the nearest clipped pixel
        return (beyond >= RIM_START) & (beyond <= RIM_START + RIM_WIDTH), ring
    return (rr >= start) & (rr <= stop), ring


def added_light(channels: Channels, clipped_laser: NDArray[np.bool_],
                clipped_any: NDArray[np.bool_], x: float, y: float, radius: float,
                support: float, outline: bool = False) -> AddedLight | None:
    """The light added by a candidate at (x, y) (crop COLMAP px); None when too few pixels are
    usable (``outline``: see :func:`_spot_zones`).

    Per channel, the light of the spot's unclipped pixels (:func:`_spot_zones`) above a plane
    fitted on its ring, averaged in SECTORS angular sectors and the median of those taken: a
    spot's light is the same all around it, a texture edge through the spot is not.
    """
    reach = int(math.ceil(max(support, 2.0 * radius + 8.0))) + 6
    win = window(channels.rgb.shape, int(math.floor(y)), int(math.floor(x)), reach)
    gx, gy = grid(win)
    rr = np.hypot(gx - x, gy - y)
    ok = ~clipped_any[win]
    inner, ring = _spot_zones(clipped_laser[win], rr, radius, support, outline)
    inner &= ok
    ring &= ok & (rr <= reach)
    if inner.sum() < MIN_COLOUR_PIXELS or ring.sum() < 2 * MIN_COLOUR_PIXELS:
        return None
    rgb = channels.linear(win)
    design = np.column_stack([np.ones(ring.sum()), gx[ring] - x, gy[ring] - y])
    coef, *_ = np.linalg.lstsq(design, rgb[ring], rcond=None)  # (3, 3): a plane per channel
    pred = np.column_stack([np.ones(inner.sum()), gx[inner] - x, gy[inner] - y]) @ coef
    noise = (rgb[ring] - design @ coef).std(axis=0) / math.sqrt(inner.sum())
    sector = np.floor((np.arctan2(gy[inner] - y, gx[inner] - x) + math.pi)
                      * (SECTORS / (2 * math.pi))).astype(np.int64) % SECTORS
    delta = rgb[inner] - pred
    means = [delta[sector == k].mean(axis=0) for k in range(SECTORS) if np.any(sector == k)]
    return AddedLight(delta_rgb=np.median(np.asarray(means), axis=0),
                      scene_rgb=rgb[ring].mean(axis=0), noise=noise)


def colour_evidence(light: AddedLight | None, channel: int, tau: float,
                    clipped: bool = True) -> ColourEvidence:
    """The colour term of a candidate for a laser brightest in ``channel`` (0, 1, 2).

    ``fraction = max(0, Δlaser − max(k, 1)·Δother) / Δlaser``: Δ the added light, other the
    brighter of the two other channels, k the scene's laser/other ratio. Light of the scene's own
    colour (texture, pale clutter) and white light (the lamps' colour: glints, marine snow) give
    ≤ 0, a laser ~0.3–1 (however the camera renders its crosstalk). Not measurable: 1 (no
    evidence either way) where the laser channel ``clipped`` (a clipped core's rim is often too
    thin or whitened by the camera), UNMEASURED_UNCLIPPED where it did not: an unclipped laser
    spot adds measurable light in its channel, a blob that does not is as likely the scene's.
    """
    unmeasured = ColourEvidence(1.0 if clipped else UNMEASURED_UNCLIPPED)
    if light is None:
        return unmeasured
    others = [k for k in range(3) if k != channel]
    d_laser = float(light.delta_rgb[channel])
    k_other = max(others, key=lambda k: float(light.delta_rgb[k]))
    d_other = float(light.delta_rgb[k_other])
    if d_laser < MIN_COLOUR_SNR * float(light.noise[channel]):
        if d_other < MIN_COLOUR_SNR * float(light.noise[k_other]):
            return unmeasured
        return ColourEvidence(_against(0.0, tau), 0.0, True)
    ratio = float(light.scene_rgb[channel]) / max(float(light.scene_rgb[k_other]), 1e-6)
    # beyond the scene's colour and beyond white (the lamps' own colour: glints, snow)
    fraction = max(0.0, d_laser - max(min(ratio, MAX_SCENE_RATIO), 1.0) * d_other) / d_laser
    return ColourEvidence(_against(fraction, tau), fraction, True)


def colour_around(channels: Channels, clipped_laser: NDArray[np.bool_],
                  clipped_any: NDArray[np.bool_], xy: tuple[float, float],
                  size: tuple[float, float], channel: int, tau: float, clipped: bool = True
                  ) -> ColourEvidence:
    """The median :func:`colour_evidence` at a centre ``xy`` (crop COLMAP px) and at the four
    points COLOUR_JITTER_PX from it (``size``: the spot's radius and support, px).

    A small spot's zones hold a few dozen pixels; which of them fall inside changes with a
    centre moved by a tenth of a pixel (a refinement's detail), and one reading with them,
    from ~0 to 1: the median of five readings does not hinge on one.

    A clipped core whose rim reads no light at all (no evidence: term 1) is read again on its
    outline when it is elongated (:func:`_spot_zones`): the circle through the tip of a white
    glint's streak lies in the background on its sides, where the outline reads its white light.
    """
    x, y = xy
    offsets = ((0.0, 0.0), (COLOUR_JITTER_PX, 0.0), (-COLOUR_JITTER_PX, 0.0),
               (0.0, COLOUR_JITTER_PX), (0.0, -COLOUR_JITTER_PX))

    def median_reading(outline: bool) -> ColourEvidence:
        readings = sorted((colour_evidence(added_light(channels, clipped_laser, clipped_any,
                                                       x + dx, y + dy, size[0], size[1], outline),
                                           channel, tau, clipped) for dx, dy in offsets),
                          key=lambda e: e.term)
        return readings[len(readings) // 2]

    reading = median_reading(outline=False)
    return reading if reading.measured or not clipped else median_reading(outline=True)


def _against(fraction: float, tau: float) -> float:
    """1 for laser-coloured light, falling to ~0 for the scene's colour: ``min(1, 2 logistic((
    fraction − MID_FRACTION) / tau))``."""
    return min(1.0, 2.0 / (1.0 + math.exp(-(fraction - MID_FRACTION) / tau)))


def contrast_term(snr: float, snr_half: float) -> float:
    """``snr / (snr + snr_half)``."""
    return snr / (snr + snr_half) if snr > 0 else 0.0


def clutter_term(ratio: float, half: float) -> float:
    """``r² / (r² + half²)`` of a response ``ratio`` clutter levels strong (inf -> 1)."""
    if not math.isfinite(ratio):
        return 1.0
    return ratio * ratio / (ratio * ratio + half * half)


def below(value: float, limit: float) -> str:
    """``value`` in two decimals, or in as many more (up to six) as it takes to read below
    ``limit``: a score of 0.598 against 0.6 reads "0.598", not "0.60"."""
    for digits in range(2, 6):
        text = f"{value:.{digits}f}"
        if float(text) < limit:
            return text
    return f"{value:.6f}"


def describe_weakest(evidence: dict[str, float], snr: float, roundness: float,
                     clutter_ratio: float, colour: ColourEvidence) -> str:
    """The weakest evidence term of a candidate, in words."""
    name = min(evidence, key=lambda k: evidence[k])
    if name == "contrast":
        return f"weak (SNR {snr:.1f})"
    if name == "roundness":
        return f"not round (roundness {roundness:.2f})"
    if name == "clutter":
        return f"no stronger than the scene's own blobs ({clutter_ratio:.1f} × clutter level)"
    if name == "colour" and colour.measured:
        return (f"colour of the scene, not of the laser (only {100 * colour.fraction:.0f} % of "
                f"the light it adds in the laser's channel is beyond the scene's colour)")
    if name == "colour":
        return "colour not measurable"
    if name == "range":
        return "its range along the beam disagrees with the other lasers' spots"
    if name == "depth":
        return ("in front of laser light farther along its beam (a particle lit in the water, "
                "or the beam's glow)")
    return f"far from the beam (beam term {evidence[name]:.2f})"
