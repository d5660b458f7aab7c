"""Evidence that a candidate is a laser spot: terms in 0–1 that multiply into its score.

- *contrast*: ``snr / (snr + snr_half)``;
- *roundness*: ``sqrt(roundness)`` of its half-maximum region;
- *clutter*: how far its blob response stands above the scene's own blobs,
  ``r² / (r² + clutter_half²)`` with r the response in clutter levels (1 when the region is too
  small to have a clutter level);
- *colour*: the light the candidate adds over its surroundings (:func:`added_light`, unclipped
  pixels only), split into the laser's expected colour, the colour along which the scene's
  texture varies there, and the rest. Scene texture and pale clutter add light of the scene's
  colour, marine snow and highlights mostly white light; a laser adds its own. The term is the
  logistic of ``(laser-coloured share − ½) / colour_tau``: ~1 for laser-coloured light, ~0 for
  scene-coloured light, 0.5 when the colours cannot be told apart (a laser of the water's
  colour, or a spot clipped everywhere, whose colour cannot be measured).

Colour is evidence, not a gate: a saturated white core with no measurable halo keeps a neutral
colour term, and the other terms decide.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.refine import grid, texture_direction, window
from sfm_laserscale.detection.response import Channels

F64 = NDArray[np.float64]
#: fewer unclipped pixels than this in the spot or its ring: the colour is not measured
MIN_COLOUR_PIXELS = 4
#: the added light must exceed this many times its noise for its colour to count
MIN_COLOUR_SNR = 3.0
#: below this sine of the angle between the laser's and the texture's colours, the two cannot
#: be told apart (a laser of the water's colour): the colour is not evidence
MIN_COLOUR_SEPARATION = 0.1


@dataclass(frozen=True)
class ColourEvidence:
    """The light a candidate adds, split into the laser's colour, the scene's texture colour and
    the rest; ``fraction`` the laser-coloured share (0–1); ``term`` the evidence;
    ``measured`` False when the split is not possible (term 0.5)."""

    term: float
    fraction: float = math.nan
    measured: bool = False


@dataclass(frozen=True)
class AddedLight:
    """A candidate's light per component (laser colour, texture colour, orthogonal rest): the
    contrast of each over planes fitted on its ring, and their noise."""

    laser: float
    texture: float
    rest: float
    noise: float


def _basis(texture: F64, laser_rgb: F64) -> F64 | None:
    """(3, 3) columns: texture colour, laser colour, their normal (units); None if parallel."""
    t = texture / max(float(np.linalg.norm(texture)), 1e-12)
    ell = laser_rgb / max(float(np.linalg.norm(laser_rgb)), 1e-12)
    n = np.cross(t, ell)
    if float(np.linalg.norm(n)) < MIN_COLOUR_SEPARATION:
        return None
    return np.column_stack([t, ell, n / float(np.linalg.norm(n))])


def added_light(channels: Channels, clipped_any: NDArray[np.bool_], x: float, y: float,
                radius: float, support: float, laser_rgb: F64) -> AddedLight | None:
    """The light added by a candidate at (x, y) (crop COLMAP px), split by colour.

    Every unclipped pixel is split into the scene's texture colour (:func:`texture_direction`
    of its ring), the laser's colour and the colour normal to both; each component's contrast
    is its mean over the spot's unclipped pixels (within ``max(2, radius) + 2`` px, or
    ``2 radius + 3`` px when the core clips: the halo around a white core) above a plane fitted
    on the ring beyond the support. None when the colours are parallel or too few pixels
    are usable.
    """
    win = window(channels.rgb.shape, int(math.floor(y)), int(math.floor(x)),
                 int(math.ceil(max(support, 4.0))) + 3)
    gx, gy = grid(win)
    rr = np.hypot(gx - x, gy - y)
    ok = ~clipped_any[win]
    core_clips = bool(clipped_any[win][rr <= max(2.0, radius)].any())
    reach = max(2.0, radius) + (radius + 1.0 if core_clips else 0.0) + 2.0
    inner = (rr <= reach) & (rr < max(support, 4.0)) & ok
    ring = (rr >= max(support, 4.0)) & ok
    if inner.sum() < MIN_COLOUR_PIXELS or ring.sum() < 2 * MIN_COLOUR_PIXELS:
        return None
    rgb = channels.linear(win)
    basis = _basis(texture_direction(rgb[ring], laser_rgb), laser_rgb)
    if basis is None:
        return None
    parts = rgb @ np.linalg.inv(basis).T  # (h, w, 3): texture, laser, rest
    design = np.column_stack([np.ones(ring.sum()), gx[ring] - x, gy[ring] - y])
    coef, *_ = np.linalg.lstsq(design, parts[ring], rcond=None)
    pred = np.column_stack([np.ones(inner.sum()), gx[inner] - x, gy[inner] - y]) @ coef
    texture, laser, rest = (parts[inner] - pred).mean(axis=0)
    noise = float(np.linalg.norm((parts[ring] - design @ coef).std(axis=0))
                  / math.sqrt(inner.sum()))
    return AddedLight(laser=float(laser), texture=float(texture), rest=float(rest), noise=noise)


def colour_evidence(light: AddedLight | None, tau: float) -> ColourEvidence:
    """The colour term: the logistic of (laser-coloured share − ½) / ``tau``."""
    if light is None:
        return ColourEvidence(0.5)
    total = max(light.laser, 0.0) + abs(light.texture) + abs(light.rest)
    if total < MIN_COLOUR_SNR * light.noise:
        return ColourEvidence(0.5)
    fraction = max(light.laser, 0.0) / total
    return ColourEvidence(1.0 / (1.0 + math.exp(-(fraction - 0.5) / tau)), fraction, True)


def contrast_term(snr: float, snr_half: float) -> float:
    """``snr / (snr + snr_half)``."""
    return snr / (snr + snr_half) if snr > 0 else 0.0


def clutter_term(ratio: float, half: float) -> float:
    """``r² / (r² + half²)`` of a response ``ratio`` clutter levels strong (inf -> 1)."""
    if not math.isfinite(ratio):
        return 1.0
    return ratio * ratio / (ratio * ratio + half * half)


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
                f"the light it adds has the laser's colour)")
    if name == "colour":
        return "colour not measurable"
    return f"far from the beam (beam term {evidence[name]:.2f})"
