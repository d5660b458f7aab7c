"""Laser spots in one image: sub-pixel centres (COLMAP pixel convention) assigned to lasers.

:func:`detect_spots` chains the stages of this package: where to look (:mod:`.beams`), the
responses (:mod:`.response`), candidates measured, refined and scored (:mod:`.candidates`,
:mod:`.shape`, :mod:`.refine`, :mod:`.score`), the assignment to lasers (:mod:`.assign`), the
search where the plane through the spots found meets a missing laser's beam (:mod:`.floor`),
the other beams searched where a floor through a lone spot puts them (:mod:`.lone`), a lone
spot's stricter test (:func:`_drop_alone`), in an image where nothing was chosen the
floor through two whitened cores or two faint candidates (:func:`_pair_on_floor`), the chosen
spots' centres from both of a green laser's signals (:mod:`.centre`), a chosen spot whose
centre wandered off the maximum it was measured from put back (:mod:`.wandered`: also right
after the joint choice, for a spot far wider than the others) and the reasons for lasers
without a spot (:mod:`.explain`). Every candidate is returned with what became of it.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.assign import (
    PLAIN_PAIR,
    RESCUED_PAIR,
    WHITENED_FLOOR_REACH,
    WHITENED_FLOOR_SPOTS,
    assign_calibrated,
    assign_uncalibrated,
    chosen_radius,
    explain_unused,
    second_look,
    take_choice,
    whitened_at_floor,
)
from sfm_laserscale.detection.beams import SearchRegion, search_region
from sfm_laserscale.detection.candidates import Measure, candidates_for_colour
from sfm_laserscale.detection.centre import centre_chosen
from sfm_laserscale.detection.explain import explain_missing
from sfm_laserscale.detection.floor import (
    PLACE,
    floor_predictions,
    floor_radius_px,
    floor_search,
)
from sfm_laserscale.detection.inputs import check_image, colours_needed, group_rgb
from sfm_laserscale.detection.joint import (
    NOTHING_BESIDE,
    PAIR_FLOOR_SPOTS,
    PLAIN_PAIR_FLOOR_SPOTS,
    Choice,
)
from sfm_laserscale.detection.lone import LONE_PLACE, LONE_TILT_DEG, lone_floor_search
from sfm_laserscale.detection.options import (
    TAKEN_ON_FLOOR,
    TAKEN_ON_OWN,
    Candidate,
    DetectionOptions,
    DetectionResult,
)
from sfm_laserscale.detection.response import crop_channels
from sfm_laserscale.detection.scene import remove_scene
from sfm_laserscale.detection.score import below
from sfm_laserscale.detection.wandered import back_to_peak, narrow_wide_spots
from sfm_laserscale.memory import trim_heap
from sfm_laserscale.model import Camera, Spot
from sfm_laserscale.rig import Rig

logger = logging.getLogger(__name__)


def _measure_candidates(image_rgb: NDArray[np.uint8], rig: Rig, region: SearchRegion,
                        options: DetectionOptions) -> list[Measure]:
    """Every candidate spot of every colour the rig needs, within the search region."""
    measures: list[Measure] = []
    x0, y0, x1, y1 = region.roi
    if x1 > x0 and y1 > y0:
        channels = crop_channels(image_rgb, region.roi, options.input_gamma)
        for color in colours_needed(rig):
            measures += candidates_for_colour(channels, color, options, region,
                                              group_rgb(rig, color))
    return measures


def _candidate(m: Measure, taken: bool) -> Candidate:
    """What became of a candidate (``taken``: it is a spot)."""
    return Candidate(x=m.x, y=m.y, color=m.color, response=m.response, snr=m.snr,
                     radius_px=m.radius_px, roundness=m.roundness,
                     score=0.0 if m.rejected else float(m.score), laser=m.laser,
                     reason=m.rejected or m.reason, source=m.source,
                     evidence=tuple(m.evidence.items()), clutter_ratio=m.clutter_ratio,
                     taken_by=(m.taken_by or TAKEN_ON_OWN) if taken else "")


def _stated_sigma(m: Measure, options: DetectionOptions, floor_radius: float) -> float:
    """A taken spot's σ (px, per axis): its blob's, and the term of the rule that took it
    (:meth:`.options.SigmaModel.choice`; ``floor_radius``: the floor search's radius, px)."""
    return math.hypot(m.sigma_px, options.sigma_model.choice(m.taken_by, floor_radius))


def _floor_round(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig, region: SearchRegion,
                 valid: list[Measure], chosen: dict[str, int], options: DetectionOptions
                 ) -> tuple[dict[str, Measure], dict[str, str]]:
    """In place (``chosen``, ``valid``): one floor search (:mod:`.floor`) through the chosen
    spots. Its spots, marked assigned, are appended to ``valid`` (``dist`` keeps the first
    columns); returned with, for the other lasers searched, what the search saw."""
    spots_px = {name: (valid[j].x, valid[j].y) for name, j in chosen.items()}
    radius = chosen_radius(valid, chosen)
    found, why = {}, {}
    for name, find in floor_search(image_rgb, camera, rig, region, spots_px, options,
                                   radius).items():
        if find.measure is None:
            why[name] = find.why
            continue
        m = find.measure
        m.score, m.laser, m.taken_by = find.score, name, TAKEN_ON_FLOOR
        m.reason = f"assigned to {name}: {PLACE}"
        found[name] = m
        valid.append(m)
        chosen[name] = len(valid) - 1
    return found, why


def _floor_then_second_look(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig,
                            region: SearchRegion, measures: list[Measure], valid: list[Measure],
                            chosen: dict[str, int], options: DetectionOptions
                            ) -> tuple[dict[str, Measure], dict[str, str]]:
    """In place (``chosen``, ``valid``): lasers without a spot searched where the floor through
    the chosen spots puts them (:mod:`.floor`, a few pixels), then along their bands at the
    chosen spots' range (:func:`.assign.second_look`), then for a whitened clipped core near
    the floor's point (:func:`_whitened_on_floor`), then on the floor again when those took a
    spot. Returns the floor's spots and, for the lasers it searched in vain, what it saw."""
    on_floor, why = _floor_round(image_rgb, camera, rig, region, valid, chosen, options)
    looked = second_look(rig, region, measures, valid, chosen, options)
    chosen.update(looked)
    cores = _whitened_on_floor(camera, rig, region, measures, valid, chosen, options)
    chosen.update(cores)
    if looked or cores:
        more, why_more = _floor_round(image_rgb, camera, rig, region, valid, chosen, options)
        on_floor |= more
        why |= why_more
    return on_floor, why


def _whitened_on_floor(camera: Camera, rig: Rig, region: SearchRegion, measures: list[Measure],
                       valid: list[Measure], chosen: dict[str, int], options: DetectionOptions
                       ) -> dict[str, int]:
    """Lasers still without a spot, where the floor through WHITENED_FLOOR_SPOTS chosen spots
    or more puts theirs, take a whitened clipped core within WHITENED_FLOOR_REACH floor search
    radii of that point (:func:`.assign.whitened_at_floor`); laser -> index into ``valid``."""
    if not options.floor_search:
        return {}
    spots_px = {name: (valid[j].x, valid[j].y) for name, j in chosen.items()}
    predicted = floor_predictions(camera, rig, region, spots_px, WHITENED_FLOOR_SPOTS,
                                  (options.min_range_m, options.max_range_m))
    reach = WHITENED_FLOOR_REACH * floor_radius_px(camera, options)
    return whitened_at_floor(rig, region, measures, valid, chosen, predicted, reach, options)


#: what the reason of a spot centred at its peak adds (:func:`.candidates._at_peak`)
AT_PEAK_FAILED = ("; centred at its brightness maximum's sub-pixel peak: a centroid ran off it "
                  "(σ widened)")
#: what a pair's candidate's reason adds when the floor through the two held too few spots
#: (``what``: "such core" for whitened cores, "candidate" for others)
PAIR_HELD = ("; with {other}'s {what} at one range, the floor through the two holds {found} "
             "of the {spots} it needs")


def _other_spots(n: int) -> str:
    """"1 other laser's spot", "2 other lasers' spots"."""
    return f"{n} other laser's spot" if n == 1 else f"{n} other lasers' spots"


def _spots_needed(pair: Choice) -> int:
    """How many other lasers' spots the floor through a pair must hold: PAIR_FLOOR_SPOTS for
    whitened cores, PLAIN_PAIR_FLOOR_SPOTS for others (:mod:`.joint`)."""
    rescued = any(o.rescued for o in pair.chosen.values())
    return PAIR_FLOOR_SPOTS if rescued else PLAIN_PAIR_FLOOR_SPOTS


def _partner(pair: Choice, name: str) -> str:
    """The other laser of a pair."""
    return next(n for n in pair.chosen if n != name)


def _pair_tried(valid: list[Measure], pair: Choice, found: int,
                noted: set[tuple[int, str]]) -> None:
    """In place: the reasons of a pair whose floor held too few spots, for each of its
    candidates (index into ``valid``, laser) not yet in ``noted`` (its first such pair only):
    a whitened core's ``not_rescued``, another's ``pair_held``."""
    for name, o in pair.chosen.items():
        m = valid[o.index]
        why = m.not_rescued if o.rescued else m.pair_held
        if (o.index, name) in noted or (o.rescued and name not in why):
            continue
        why[name] = why.get(name, "") + PAIR_HELD.format(
            other=_partner(pair, name), what="such core" if o.rescued else "candidate", found=found,
            spots=_other_spots(_spots_needed(pair)))
        noted.add((o.index, name))


def _take_pair(rig: Rig, region: SearchRegion, valid: list[Measure], dist: NDArray[np.float64],
               pair: Choice, found: int) -> dict[str, int]:
    """In place (``valid``): a pair whose floor held enough spots, taken with its reason."""
    taken = take_choice(rig, region, valid, dist, pair, RESCUED_PAIR)
    spots = _other_spots(found)
    for name, o in pair.chosen.items():
        if not o.rescued:
            valid[o.index].reason += ": " + PLAIN_PAIR.format(other=_partner(pair, name),
                                                              spots=spots)
    return taken


def _pair_on_floor(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig,
                   region: SearchRegion, measures: list[Measure], valid: list[Measure],
                   chosen: dict[str, int], dist: NDArray[np.float64], pairs: list[Choice],
                   options: DetectionOptions) -> dict[str, Measure]:
    """In place (``chosen``, ``valid``): where nothing was chosen, the first pair
    (:func:`.joint.whitened_pairs`, then :func:`.joint.plain_pairs`, best first) through which
    the floor search finds the other lasers' spots it needs (:func:`_spots_needed`) is taken
    with those spots; the lasers still without one are then searched as after the joint
    choice. Returns the floor's spots."""
    if chosen:
        return {}
    noted: set[tuple[int, str]] = set()
    for pair in pairs:
        trial_valid, trial = list(valid), {n: o.index for n, o in pair.chosen.items()}
        found, _ = _floor_round(image_rgb, camera, rig, region, trial_valid, trial, options)
        if len(found) < _spots_needed(pair):
            _pair_tried(valid, pair, len(found), noted)
            continue
        valid[:] = trial_valid
        chosen.update(_take_pair(rig, region, valid, dist, pair, len(found)) | trial)
        more, _ = _floor_then_second_look(image_rgb, camera, rig, region, measures, valid,
                                          chosen, options)
        return found | more
    return {}


def _lone_floor(image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig, region: SearchRegion,
                valid: list[Measure], chosen: dict[str, int], options: DetectionOptions
                ) -> tuple[dict[str, Measure], str]:
    """In place (``chosen``, ``valid``): with one spot chosen, the spots found where a floor
    through it puts the other beams' (:mod:`.lone`), taken when ``options.lone_floor_spots``
    beams or more hold one, then the floor search through all. Returns the spots taken and,
    when too few were found, what the lone spot's reason adds."""
    if len(chosen) != 1 or options.lone_floor_spots == 0 or not options.floor_search:
        return {}, ""
    (name, j), = chosen.items()
    found = lone_floor_search(image_rgb, camera, rig, region, name, valid[j], options)
    if len(found) < options.lone_floor_spots:
        return {}, (f"; a floor through it, tilted up to {LONE_TILT_DEG:g}°, holds {len(found)} "
                    f"of the {options.lone_floor_spots} other lasers' spots it needs")
    place = LONE_PLACE.format(laser=name)
    for laser, (m, score) in found.items():
        m.score, m.laser, m.reason = score, laser, f"assigned to {laser}: {place}"
        m.taken_by = TAKEN_ON_FLOOR
        valid.append(m)
        chosen[laser] = len(valid) - 1
    more, _ = _floor_round(image_rgb, camera, rig, region, valid, chosen, options)
    return {laser: m for laser, (m, _) in found.items()} | more, ""


def _drop_alone(rig: Rig, valid: list[Measure], chosen: dict[str, int], unseen: dict[str, str],
                options: DetectionOptions, why_lone: str = "") -> None:
    """In place (``chosen``): a spot alone in its image (the only laser's spot, with two or more
    other calibrated beams in view; ``unseen``: lasers whose beam is outside the image) is
    dropped when it scores below ``options.alone_min_score``: nothing corroborates it
    (``why_lone``: what the lone spot's floor search adds to its reason). The reasons of
    whitened cores judged beside it (``Measure.not_rescued``) say so."""
    in_view = [las for las in rig.lasers if las.calibrated and las.name not in unseen]
    if len(chosen) != 1 or len(in_view) < 3:
        return
    (name, j), = chosen.items()
    m = valid[j]
    if m.score >= options.alone_min_score:
        return
    m.laser = None
    m.reason = (f"alone in its image: score {below(m.score, options.alone_min_score)} < "
                f"alone_min_score {options.alone_min_score:g} (no other laser's spot, "
                f"{len(in_view) - 1} other beams in view){why_lone}")
    del chosen[name]
    for other in valid:  # cores judged beside it by the joint choice (joint.why_not_rescued)
        for laser, why in other.not_rescued.items():
            if laser != name and why != NOTHING_BESIDE:
                other.not_rescued[laser] = (f"{why}, and the {name} spot chosen with it was "
                                            "dropped afterwards, alone in its image")


def _centred(image_rgb: NDArray[np.uint8], rig: Rig, valid: list[Measure],
              chosen: dict[str, int], options: DetectionOptions, max_radius: float
              ) -> dict[str, Measure]:
    """In place: the chosen spots' reported centres (:func:`.centre.centre_chosen`; a spot
    centred at its peak because its refinement failed keeps it, and says so), then a
    wide spot whose centre wandered off its maximum measured again at the other spots' radius
    and centred again, then a brightness maximum's spot that wandered off it at its sub-pixel
    peak (:mod:`.wandered`). Returns laser -> its spot."""
    taken = {name: valid[j] for name, j in chosen.items()}
    for spot in taken.values():
        if spot.at_peak:
            spot.reason += AT_PEAK_FAILED
            continue
        centre_chosen(image_rgb, spot, group_rgb(rig, spot.color), options, max_radius)
    for name in narrow_wide_spots(image_rgb, rig, valid, chosen, options, max_radius):
        centre_chosen(image_rgb, taken[name], group_rgb(rig, taken[name].color), options,
                      max_radius)
    back_to_peak(image_rgb, valid, chosen, options)
    return taken


def detect_spots(
    image_rgb: NDArray[np.uint8], camera: Camera, rig: Rig,
    options: DetectionOptions = DetectionOptions(),  # noqa: B008 (frozen dataclass)
    scene_rgb: NDArray[np.floating] | None = None,
) -> DetectionResult:
    """Detect laser spots in one image and assign them to the rig's lasers; with
    ``scene_rgb`` (the same view without the lasers, (H, W, 3) float 8-bit levels, NaN where
    unknown) on the image with that scene's texture removed (:mod:`.scene`)."""
    check_image(image_rgb, camera)
    if scene_rgb is not None:
        image_rgb = remove_scene(image_rgb, scene_rgb, options.scene_texture_sigma_px,
                                 options.scene_gain_sigma_px)
    region = search_region(camera, rig, options)
    measures = _measure_candidates(image_rgb, rig, region, options)
    trim_heap()  # the detection planes (~16 bytes per pixel) go back to the OS
    valid = [m for m in measures if m.rejected is None]
    chosen, missing, dist, pairs = assign_calibrated(rig, region, valid, options)
    narrow_wide_spots(image_rgb, rig, valid, chosen, options, region.max_radius)
    on_floor, floor_why = _floor_then_second_look(image_rgb, camera, rig, region, measures,
                                                  valid, chosen, options)
    lone, why_lone = _lone_floor(image_rgb, camera, rig, region, valid, chosen, options)
    on_floor |= lone
    _drop_alone(rig, valid, chosen, missing, options, why_lone)
    on_floor |= _pair_on_floor(image_rgb, camera, rig, region, measures, valid, chosen, dist,
                               pairs, options)
    for name in chosen:
        missing.pop(name, None)
    chosen_u, missing_u = assign_uncalibrated(rig, valid, set(chosen.values()), options)
    chosen.update(chosen_u)
    missing.update(missing_u)
    explain_unused(rig, valid, dist, region.band_px, options)
    shown = explain_missing(rig, measures, region, set(chosen), missing, options)
    for name, why in floor_why.items():
        if name not in chosen:
            missing[name] = f"{missing.get(name, 'no spot')}; {PLACE}: {why}"
    taken = _centred(image_rgb, rig, valid, chosen, options, region.max_radius)
    floor_radius = floor_radius_px(camera, options)
    spots = tuple(
        Spot(laser=name, x=m.x, y=m.y, score=float(np.clip(m.score, 0, 1)),
             sigma_px=_stated_sigma(m, options, floor_radius), source="detected")
        for name in rig.names if (m := taken.get(name)) is not None
    )
    spot_ids = {id(m) for m in taken.values()}
    candidates = tuple(_candidate(m, id(m) in spot_ids)
                       for m in [*measures, *on_floor.values()])
    index = {id(m): i for i, m in enumerate(measures)}
    near = {name: tuple(candidates[index[id(m)]] for m in ms) for name, ms in shown.items()}
    logger.debug("%d candidates, %d spots, missing: %s", len(candidates), len(spots), missing)
    return DetectionResult(spots=spots, candidates=candidates, missing=missing, near_misses=near)
