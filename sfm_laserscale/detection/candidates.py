"""Candidates of one laser colour: local maxima of its responses, measured, refined and scored.

For each response (:mod:`.response`: the colour response, and the brightness response in the
bands of a luma-dominant (green) laser or where the laser channel clips) the local maxima of
its multi-scale blob response above a noise-relative threshold are taken strongest first: the
DoG for the colour response, the ridge-free response (:func:`~.response.ridge_free_response`)
for the brightness, whose DoG peaks along every edge and ridge of the scene and along the
beams' glows in the water (``ridge_free_brightness``). Maxima outside
every beam band, below ``min_clutter_ratio`` × the scene's clutter level, beyond
``max_candidates`` or repeating a stronger candidate are listed with that reason and not
measured, except maxima in a band within reach of the gate (``second_look_clutter_ratio``),
which are measured for the second look of :mod:`.assign` but stay out of the first choice.
The others are measured (:mod:`.shape`), refined (:mod:`.refine`) and get their evidence
(:mod:`.score`); hard tests (no contrast, too large, not compact, weak, refinement failed)
reject a candidate with a reason, everything else is evidence in its score; a round maximum
of the brightness response whose refinement fails is centred at its sub-pixel peak instead
(:func:`_at_peak`). Overlapping spots are refined again with each other's light removed (for
a luma-dominant laser, only spots whose cores are near: :func:`overlap_reach`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.beams import SearchRegion, scene_mask
from sfm_laserscale.detection.options import DetectionOptions
from sfm_laserscale.detection.refine import (
    NeighbourModel,
    SpotGuess,
    luma_dominant,
    neighbour_model,
    refine_spot,
    spot_patch,
    subpixel_peak,
)
from sfm_laserscale.detection.response import (
    CHANNELS,
    Channels,
    Planes,
    blob_response,
    brightness,
    clutter_level,
    local_maxima,
    make_planes,
    ridge_free_response,
    robust_std,
)
from sfm_laserscale.detection.score import (
    ColourEvidence,
    clutter_term,
    colour_around,
    contrast_term,
)
from sfm_laserscale.detection.shape import (
    TOO_LARGE,
    Blob,
    expected_support_px,
    local_shape,
    shape_and_contrast,
)

F32 = NDArray[np.float32]
#: a clipped core whose colour term is below this reads whitened (:mod:`.joint`): demosaicing,
#: 4:2:0 chroma and the sensor's spectral crosstalk whiten a bright core and its rim, whatever
#: its size
WHITENED_MAX_COLOUR = 0.5
#: a brightness maximum is centred at its sub-pixel peak (a failed refinement, a centre that
#: wandered off it: :mod:`.wandered`) only when its roundness (minor over major axis) is at
#: least this: a streak of motion blur is flat along itself, its response peaks anywhere on it
PEAK_MIN_ROUNDNESS = 0.5
#: half-max radii, as shares of the largest spot radius (2 and 4 px at 1920 × 1080), at which
#: a blob too large against the far background is measured against its own surroundings
#: where the image's other spots give no radius (:func:`_shape`)
LOCAL_RADII = (1.0 / 16.0, 1.0 / 8.0)
#: … unless this share of the pixels out to its ring or more has a clipped channel: on a hot
#: spot clipped to white a spot has no surroundings to stand above (what stands there is the
#: few unclipped pixels of the scene's texture)
LOCAL_CLIPPED_MAX = 0.5
#: maxima below the clutter gate measured for the second look, per response
SECOND_LOOK_MAX = 12
#: local maxima of a response are listed from this many robust σ of its DoG over the crop
MAXIMA_SIGMAS = 4.0
WEAKER_THAN_SCENE = "no stronger than the scene's own blobs"
#: how the weak-spot test's rejection begins ("weak (SNR 3.0 < 5)")
WEAK_SNR = "weak (SNR"


@dataclass
class Measure:
    """Mutable per-candidate working record (crop, then image COLMAP px once finished)."""

    x: float
    y: float
    color: str
    source: str  # "colour" | "bright"
    response: float
    clutter_ratio: float = math.inf
    snr: float = 0.0
    radius_px: float = 0.0
    roundness: float = 0.0
    support_px: float = 0.0
    bright: bool = False  # refined on the brightness signal (its laser channel clips)
    whitened: bool = False  # a small clipped core whose colour read against it
    second_look: bool = False  # below the clutter gate, measured for the second look
    beside: bool = False  # refined with an overlapping spot's modelled light removed
    at_peak: bool = False  # its refinement failed: centred at its sub-pixel peak (_at_peak)
    taken_by: str = ""  # the rule that took it as a spot (options.TAKEN_ON_*), "" if none
    sigma_px: float = 1.0
    # the response's local maximum it was measured from (crop, then image COLMAP px)
    peak: tuple[float, float] = (math.nan, math.nan)
    colour: ColourEvidence = field(default_factory=lambda: ColourEvidence(0.5))
    terms: dict[str, float] = field(default_factory=dict)  # evidence without colour and beam
    rejected: str | None = None
    score: float = 0.0
    laser: str | None = None
    reason: str = ""
    evidence: dict[str, float] = field(default_factory=dict)  # final, for the chosen laser
    depth: dict[str, float] = field(default_factory=dict)  # laser -> depth term (assign.py)
    # laser -> ranges (m) of laser light farther along its beam (assign.py)
    farther_lit: dict[str, tuple[float, ...]] = field(default_factory=dict)
    range_fit: dict[str, float] = field(default_factory=dict)  # laser -> range term (joint.py)
    # laser -> why this whitened core was not taken at its colour (joint.why_not_rescued)
    not_rescued: dict[str, str] = field(default_factory=dict)
    # laser -> what the floor through a pair holding this candidate held (detect._pair_tried)
    pair_held: dict[str, str] = field(default_factory=dict)

    @property
    def base_score(self) -> float:
        """Product of the colour- and beam-free evidence terms."""
        return float(np.prod(list(self.terms.values()))) if self.terms else 0.0

    def guess(self) -> SpotGuess:
        """The refinement's view of this candidate."""
        return SpotGuess(self.x, self.y, self.radius_px, self.support_px, self.bright)


@dataclass(frozen=True)
class _Source:
    """One response's blobs and what they are judged against."""

    name: str
    plane: F32  # the response (crop)
    blobs: F32  # its blob response (DoG, or ridge-free for the brightness)
    threshold: float
    clutter: float
    where: NDArray[np.bool_] | None  # maxima allowed only here (None: everywhere)


def _threshold(blobs: F32, maxima_sigmas: float) -> float:
    """``maxima_sigmas`` robust σ of a blob response over the crop, and at least 4/255."""
    return max(maxima_sigmas * robust_std(blobs[::4, ::4]), 4.0 / 255.0)


def source_blobs(name: str, plane: F32, options: DetectionOptions) -> F32:
    """The blob response whose maxima are the candidates of the ``name`` ("colour" or
    "bright") response ``plane``: its DoG, or the brightness's ridge-free response when
    ``options.ridge_free_brightness``."""
    ridge_free = name == "bright" and options.ridge_free_brightness
    response = ridge_free_response if ridge_free else blob_response
    return response(plane, options.spot_sigmas_px)


def _source(name: str, plane: F32, options: DetectionOptions, scene: NDArray[np.bool_] | None,
            where: NDArray[np.bool_] | None, maxima_sigmas: float) -> _Source:
    blobs = source_blobs(name, plane, options)
    return _Source(name, plane, blobs, _threshold(blobs, maxima_sigmas),
                   clutter_level(blobs, where=scene), where)


def _sources(channels: Channels, planes: Planes, options: DetectionOptions,
             region: SearchRegion, maxima_sigmas: float) -> list[_Source]:
    """The colour response, and the brightness response: in every band for a laser whose light
    is mostly luma (green: in green water its colour response is weak, its brightness is not),
    else where the laser channel clips."""
    scene = scene_mask(region)
    out = [_source("colour", planes.resp, options, scene, None, maxima_sigmas)]
    if luma_dominant(planes.laser_rgb):
        out.append(_source("bright", brightness(channels), options, scene, None, maxima_sigmas))
        return out
    clipped = planes.clipped_laser if region.near is None else planes.clipped_laser & region.near
    if clipped.any():
        near_clip = cv2.dilate(clipped.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        out.append(_source("bright", brightness(channels), options, scene, near_clip,
                           maxima_sigmas))
    return out


def _covering(out: list[Measure], m: Measure, origin: tuple[int, int]) -> str | None:
    """Why maximum ``m`` repeats an earlier candidate, or None (``origin``: the crop's corner,
    so the reason names image pixels).

    A maximum inside a too-large blob's half-maximum region is not a repeat: a far spot at the
    end of its beam's in-water glow, or on the flank of a bright patch, is a maximum of its own
    there, and its own shape test decides.
    """
    for o in out:
        if o.rejected is None and math.hypot(o.x - m.x, o.y - m.y) < max(2.0, o.radius_px):
            return (f"duplicate of the stronger maximum at ({o.x + origin[0]:.1f}, "
                    f"{o.y + origin[1]:.1f})")
    return None


def _bright_candidate(src: _Source, rc: tuple[int, int], region: SearchRegion) -> bool:
    """A maximum of the brightness response near a band where the laser channel clips."""
    row, col = rc
    near = region.near is None or bool(region.near[row, col])
    return near and (src.where is None or bool(src.where[row, col]))


def _unmeasured_reason(m: Measure, rc: tuple[int, int], src: _Source, region: SearchRegion,
                       n_valid: int, options: DetectionOptions) -> str | None:
    """Why a maximum is listed but not measured, or None."""
    row, col = rc
    if region.near is not None and not region.near[row, col]:
        return "off every beam band (not measured)"
    if m.response < options.min_clutter_ratio * src.clutter:
        return (f"{WEAKER_THAN_SCENE} (response {m.clutter_ratio:.2f} × clutter level; "
                "not measured)")
    if n_valid >= options.max_candidates:
        return f"beyond the {options.max_candidates} strongest maxima (not measured)"
    return None


def _shape(m: Measure, plane: F32, bright_plane: F32 | None, planes: Planes,
           rc: tuple[int, int], options: DetectionOptions, region: SearchRegion) -> Blob:
    """Shape of a maximum on its own response; a blob whose laser channel clips and that fails
    there (a colour response flat over a wide clipped halo) is measured on the brightness.
    A blob that fails against the far background is measured against its own surroundings
    (:func:`.shape.local_shape`) and taken when it stands ``min_snr`` above them: at the radius
    the image's other spots give (``region.spot_radius_px``), or else, for a blob too large
    there (a small core on a strobe's hot spot or a lit slope, whose half-maximum region runs
    into its bright surroundings), at LOCAL_RADII × the largest spot radius, smallest first,
    where under LOCAL_CLIPPED_MAX of those surroundings clip."""
    row, col = rc
    blob = shape_and_contrast(plane, row, col, region.max_radius, options.max_annulus_ratio)
    core = planes.clipped_laser[max(0, row - 2):row + 3, max(0, col - 2):col + 3]
    m.bright = bool(core.any())
    if (blob.rejection is not None and m.bright and bright_plane is not None
            and plane is not bright_plane):
        plane = bright_plane
        blob = shape_and_contrast(plane, row, col, region.max_radius, options.max_annulus_ratio)
    if blob.rejection is None and blob.snr >= options.min_snr:
        return blob
    if region.spot_radius_px is not None:
        radii: tuple[float, ...] = (region.spot_radius_px,)
    elif (blob.rejection is not None and blob.rejection.startswith(TOO_LARGE) and LOCAL_RADII
          and not _clipped_around(planes, rc, max(LOCAL_RADII) * region.max_radius)):
        radii = tuple(share * region.max_radius for share in LOCAL_RADII)
    else:
        return blob
    for radius in radii:
        local = local_shape(plane, row, col, radius)
        if local is not None and local.snr >= options.min_snr:
            return local
    return blob


def _clipped_around(planes: Planes, rc: tuple[int, int], radius_px: float) -> bool:
    """Whether LOCAL_CLIPPED_MAX or more of the pixels within 2 ``radius_px`` + 5 px of
    (row, col) have a clipped channel."""
    reach = int(math.ceil(2.0 * radius_px + 5.0))
    row, col = rc
    around = planes.clipped_any[max(0, row - reach):row + reach + 1,
                                max(0, col - reach):col + reach + 1]
    return bool(around.size) and float(around.mean()) >= LOCAL_CLIPPED_MAX


def _measure(planes: Planes, m: Measure, src: _Source, bright_plane: F32 | None,
             rc: tuple[int, int], options: DetectionOptions, region: SearchRegion) -> None:
    """In place: shape, refinement, added light and evidence terms of one maximum."""
    blob = _shape(m, src.plane, bright_plane, planes, rc, options, region)
    m.radius_px, m.roundness, m.snr, m.support_px = (blob.radius, blob.roundness, blob.snr,
                                                     blob.support)
    m.rejected = blob.rejection
    if m.rejected is None and m.snr < options.min_snr:
        m.rejected = f"{WEAK_SNR} {m.snr:.1f} < {options.min_snr:g})"
    if m.rejected is not None:
        return
    refined = (_refined(planes, m, options, region.spot_radius_px)
               or _at_peak(m, src, options, region.max_radius))
    if refined is None:
        m.rejected = "sub-pixel refinement failed"
        return
    x, y, sig = refined
    m.x, m.y = x, y
    m.sigma_px = sig
    if options.colour_evidence:
        m.colour = colour_around(planes.channels, planes.clipped_laser, planes.clipped_any,
                                 (x, y), (m.radius_px, m.support_px), CHANNELS[m.color],
                                 options.colour_tau, clipped=m.bright)
        m.whitened = m.bright and m.colour.measured and m.colour.term < WHITENED_MAX_COLOUR
    else:
        m.colour = ColourEvidence(1.0)
    m.terms = {"contrast": contrast_term(m.snr, options.snr_half),
               "roundness": math.sqrt(max(m.roundness, 0.0)),
               "clutter": clutter_term(m.clutter_ratio, options.clutter_half)}


def _at_peak(m: Measure, src: _Source, options: DetectionOptions, max_radius: float
             ) -> tuple[float, float, float] | None:
    """(x, y, σ) (crop COLMAP px) of a round maximum of the brightness response at its
    sub-pixel peak (:func:`.refine.subpixel_peak`), for one whose refinement failed; None for
    other maxima, or where the peak has no vertex. Marks it ``at_peak``.

    A compact core beside a particle, a hot spot's rim or a turbid glow: its centroid window
    centres them and runs beyond max(2 px, its radius), but the band-pass response at the
    spot's own scales still peaks on the spot. Its σ per axis is disagreement_gain × its
    half-maximum radius with the floor: no centroid agrees with the peak, and a neighbour's
    flank within that radius moves it (:class:`~.options.SigmaModel`). The radius counts at
    least 1 px and at most the largest of LOCAL_RADII × ``max_radius`` (the largest spot
    radius, px): a half-maximum region that ran into a hot spot is the hot spot's size. A
    streak's response peaks anywhere along it (roundness below PEAK_MIN_ROUNDNESS), a colour
    response on a clipped core's halo: those stay rejected."""
    if (not options.peak_when_refinement_fails or src.name != "bright"
            or m.roundness < PEAK_MIN_ROUNDNESS):
        return None
    peak = subpixel_peak(src.blobs, (0, 0), m.peak)
    if peak is None:
        return None
    m.at_peak = True
    sigma = options.sigma_model
    radius = min(max(1.0, m.radius_px), max(1.0, max(LOCAL_RADII) * max_radius))
    return peak[0], peak[1], math.hypot(sigma.floor_px, sigma.disagreement_gain * radius)


def _refined(planes: Planes, m: Measure, options: DetectionOptions,
             spot_radius_px: float | None) -> tuple[float, float, float] | None:
    """Sub-pixel centre and σ of a measured maximum (crop px), or None when the refinement
    fails: no finite result, or a centre beyond max(2, radius) px of the maximum.

    A maximum on bright surroundings (a lit patch, green water near full scale) can measure a
    half-maximum region that runs into them (8.5 px for a 3 × 2 px clipped core), and a centroid
    window that wide wanders off the spot. Where the radius of the image's other spots is known
    (``spot_radius_px``, a search near a predicted point) and smaller, such a maximum is refined
    again at that radius, and takes it: the spots of one scaler on one floor are footprints of
    like beams at like ranges. So is one ``options.wide_maximum_ratio`` times wider than that
    radius or more whose own window's centre lies beyond max(2, that radius) px of it
    (:func:`_wandered`), where the narrower refinement holds.
    """
    def attempt(radius: float, support: float) -> tuple[float, float, float] | None:
        return refine_within(planes, SpotGuess(m.x, m.y, radius, support, m.bright), options)

    refined = attempt(m.radius_px, m.support_px)
    if spot_radius_px is None or spot_radius_px >= m.radius_px:
        return refined
    if refined is not None and not _wandered(m, refined, spot_radius_px, options):
        return refined
    support = expected_support_px(spot_radius_px)
    again = attempt(spot_radius_px, support)
    if again is None:
        return refined
    m.radius_px, m.support_px = spot_radius_px, support
    return again


def refine_within(planes: Planes, guess: SpotGuess, options: DetectionOptions
                  ) -> tuple[float, float, float] | None:
    """(x, y, σ) (crop COLMAP px) of ``guess`` refined (:func:`.refine.refine_spot`), or None
    when that gives no finite result or a centre beyond max(2, its radius) px of it."""
    x, y, sig = refine_spot(planes, guess, options.refine, sigma_model=options.sigma_model)
    ok = math.isfinite(sig) and math.hypot(x - guess.x, y - guess.y) <= max(2.0, guess.radius_px)
    return (x, y, sig) if ok else None


def _wandered(m: Measure, centre: tuple[float, float, float], spot_radius_px: float,
              options: DetectionOptions) -> bool:
    """Whether a maximum ``options.wide_maximum_ratio`` × the other spots' radius wide or more
    was centred beyond max(2, that radius) px of itself: its window centroids its surroundings
    (a red patch 10 px off, green water's bright texture), not a spot of the others' size."""
    ratio = options.wide_maximum_ratio
    moved = math.hypot(centre[0] - m.x, centre[1] - m.y)
    return ratio > 0 and m.radius_px >= ratio * spot_radius_px and moved > max(2.0, spot_radius_px)


def candidates_for_colour(
    channels: Channels, color: str, options: DetectionOptions, region: SearchRegion,
    laser_rgb: tuple[float, float, float], maxima_sigmas: float = MAXIMA_SIGMAS,
) -> list[Measure]:
    """Local maxima of one colour's responses, measured and refined (image COLMAP px).

    ``laser_rgb``: the expected colour of this channel's lasers (the refinement separates
    their light from the scene's texture with it). ``maxima_sigmas``: a maximum is listed
    from this many robust σ of its response's DoG over the crop (and 4/255).
    """
    planes = make_planes(channels, color, options, region.max_radius, laser_rgb)
    sources = _sources(channels, planes, options, region, maxima_sigmas)
    bright_plane = sources[-1].plane if sources[-1].name == "bright" else None
    out: list[Measure] = []
    for src in sources:
        n_valid = n_second = 0
        for row, col in local_maxima(src.blobs, src.threshold)[: 4 * options.max_candidates]:
            rc = (int(row), int(col))
            if src.name == "bright" and not _bright_candidate(src, rc, region):
                continue  # the brightness response proposes clipped blobs in the bands only
            value = float(src.blobs[row, col])
            m = Measure(x=col + 0.5, y=row + 0.5, color=color, source=src.name, response=value,
                        clutter_ratio=value / src.clutter if src.clutter > 0 else math.inf,
                        peak=(col + 0.5, row + 0.5))
            m.rejected = (_unmeasured_reason(m, rc, src, region, n_valid, options)
                          or _covering(out, m, region.roi[:2]))
            if n_second < SECOND_LOOK_MAX and _second_look(m, rc, region, options):
                n_second += 1
                _measure_second_look(out, m, rc, planes, src, bright_plane, options, region)
            elif m.rejected is None:
                _measure(planes, m, src, bright_plane, rc, options, region)
                m.rejected = m.rejected or _covering(out, m, region.roi[:2])
                n_valid += m.rejected is None
            if src.name == "bright" and m.rejected is not None and m.rejected.startswith("dup"):
                _better_of_the_two(out, m, rc, planes, src, bright_plane, options, region)
                continue  # a colour candidate stands there (replaced if this one is better)
            out.append(m)
    separate_overlapping(planes, [m for m in out if m.rejected is None and not m.at_peak],
                         options)
    x0, y0 = region.roi[:2]
    for m in out:  # crop -> image coordinates
        m.x += x0
        m.y += y0
        m.peak = (m.peak[0] + x0, m.peak[1] + y0)
    return out


def _second_look(m: Measure, rc: tuple[int, int], region: SearchRegion,
                 options: DetectionOptions) -> bool:
    """Whether a maximum held back by the clutter gate is measured for the second look: inside
    a band, at least ``second_look_clutter_ratio`` clutter levels strong."""
    row, col = rc
    in_band = region.near is None or bool(region.near[row, col])
    return (in_band and m.rejected is not None and m.rejected.startswith(WEAKER_THAN_SCENE)
            and m.clutter_ratio >= options.second_look_clutter_ratio)


def _measure_second_look(out: list[Measure], m: Measure, rc: tuple[int, int], planes: Planes,
                         src: _Source, bright_plane: F32 | None, options: DetectionOptions,
                         region: SearchRegion) -> None:
    """In place: measure a maximum below the clutter gate; it stays out of the first choice
    (``rejected`` keeps the gate's reason, and the test it then failed) and is marked
    ``second_look`` when it measured."""
    m.rejected = None
    _measure(planes, m, src, bright_plane, rc, options, region)
    failed = m.rejected or _covering(out, m, region.roi[:2])
    m.second_look = failed is None
    then = f"and {failed}" if failed else "taken only at the range of the other lasers' spots"
    m.rejected = f"{WEAKER_THAN_SCENE} (response {m.clutter_ratio:.2f} × clutter level; {then})"


def _better_of_the_two(out: list[Measure], m: Measure, rc: tuple[int, int], planes: Planes,
                       src: _Source, bright_plane: F32 | None, options: DetectionOptions,
                       region: SearchRegion) -> None:
    """In place: a brightness maximum ``m`` repeating a colour candidate is measured too, and
    replaces it when its evidence is stronger.

    A clipped core reads white over green-cyan water: its colour response peaks on the green
    halo beside the core, its brightness at the core, so the colour candidate is measured off
    the spot (2-3 px) and the spot itself was dropped as its duplicate. Where both peak on the
    core, the two are still measured on different responses (the colour response of a core in
    a glow line is wide and weak, its brightness compact), so the better one is kept there too.
    """
    near = [o for o in out if o.rejected is None and o.source == "colour"
            and math.hypot(o.x - m.x, o.y - m.y) < max(2.0, o.radius_px)]
    if not near:
        return
    o = near[0]
    m.rejected = None
    _measure(planes, m, src, bright_plane, rc, options, region)
    if m.rejected is None and m.base_score * m.colour.term > o.base_score * o.colour.term:
        out[out.index(o)] = m


def overlap_reach(planes: Planes, valid: list[Measure], options: DetectionOptions
                  ) -> list[float]:
    """Per candidate, its reach (px): two candidates overlap when their centres lie closer
    than their reaches summed (a spot has a neighbour removed only when the neighbour's
    half-maximum radius is within its own reach, :func:`separate_overlapping`).

    A spot refined beside its neighbours is read on the texture-free light alone, without
    luma (:mod:`.refine`, :mod:`.centre`). For red and blue lasers that is their signal anyway,
    and their reach is the refinement window (``patch_support``): a neighbour's halo inside
    it also enters the background fitted on its ring (turbid water). A luma-dominant (green)
    laser's spot loses luma by it, on a clipped core the better of its two signals, and a
    bright core's support holds its forward-scatter halo, so cores far apart would be refined
    beside each other. Its reach is ``options.luma_separation_radii`` half-maximum radii (at
    least 1 px each): a neighbour's light within the centroid's window. None: the window for
    every colour. Measured in docs/DETECTION.md ("Overlapping spots").
    """
    radii = options.luma_separation_radii
    if radii is None or not luma_dominant(planes.laser_rgb):
        return [m.guess().patch_support for m in valid]
    return [radii * max(1.0, m.radius_px) for m in valid]


def separate_overlapping(planes: Planes, valid: list[Measure], options: DetectionOptions,
                         rounds: int = 3) -> None:
    """In place: re-refine spots that overlap (:func:`overlap_reach`), each with its
    neighbours' light (modelled from their far sides, :func:`neighbour_model`) removed.
    Alternating rounds; the rounds together move a spot at most max(2, radius) px from its
    measured centre.

    A spot does not have a neighbour removed whose half-maximum radius exceeds the spot's whole
    reach: that light is smooth across the spot's window, where the plane fitted on its ring
    takes it, and its model, read on its far side, holds the spot's own halo (the beam's glow
    in the water, a maximum of half-maximum radius 13 px 17 px in front of a core 45× white,
    moved the core 2.6 px off). The broad one still has the compact one removed.
    """
    support = [m.guess().patch_support for m in valid]
    reach = overlap_reach(planes, valid, options)
    removed = {i: [j for j, o in enumerate(valid) if j != i and o.radius_px <= reach[i]
                   and math.hypot(o.x - m.x, o.y - m.y) < reach[i] + reach[j]]
               for i, m in enumerate(valid)}
    if not any(removed.values()):
        return
    start = [(m.x, m.y) for m in valid]
    models: dict[tuple[int, int], NeighbourModel] = {}  # (spot, for whom) -> model
    for _ in range(rounds):
        fresh: dict[tuple[int, int], NeighbourModel] = {}
        for i, nbs in removed.items():  # the model of each neighbour j as spot i sees it
            for j in nbs:
                o = valid[j]
                others = tuple(models[(k, j)] for k in removed[j] if (k, j) in models)
                p = spot_patch(planes, o.guess(), support[j], others, allow_luma=False)
                if p is not None:
                    fresh[(j, i)] = neighbour_model(p, o.x, o.y, (valid[i].x, valid[i].y))
        models = fresh
        for i, nbs in removed.items():
            m = valid[i]
            mine = tuple(models[(j, i)] for j in nbs if (j, i) in models)
            if not mine:
                continue
            x, y, sig = refine_spot(planes, m.guess(), options.refine, mine, options.sigma_model)
            if math.isfinite(sig) and math.dist((x, y), start[i]) <= max(2.0, m.radius_px):
                m.x, m.y = x, y
                m.sigma_px = sig
                m.beside = True
