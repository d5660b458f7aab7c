"""Spots to lasers: one spot per laser, one laser per candidate, and why a laser has none.

A calibrated laser may take a candidate of its colour (any colour for "any": the colour evidence
then compares with each candidate's channel) within ``band_px`` of its beam segment; its score
is the candidate's evidence (:mod:`.score`), ``depth`` (below) and the agreement of its range
with the other lasers' spots; the spots are chosen jointly (:mod:`.joint`) and a laser whose
best candidate scores below ``min_score`` gets none; a laser still without a spot then takes a
laser-coloured maximum held back by the clutter gate at the range of the other spots, or a
candidate whose colour reads as not the laser's (a whitened clipped core, a far spot whose
colour JPEG averages away: :func:`colour_unread`) on its beam's line there
(:func:`second_look`), or one a few pixels from where the floor through three of them puts
its spot (:func:`whitened_at_floor`). An
uncalibrated laser takes the best free candidate of its colour when no other laser shares
that colour. A laser without a spot is explained by the best candidates in its band, each
with its score and the test it failed or its weakest evidence.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.beams import SearchRegion, distance_to_polyline, range_along_beam
from sfm_laserscale.detection.candidates import WHITENED_MAX_COLOUR, Measure
from sfm_laserscale.detection.joint import (
    CLIPPED_COLOUR,
    DEPTH,
    MAX_OPTIONS,
    Choice,
    Option,
    agrees,
    choose_jointly,
    core_on_line_at,
    depth_term,
    laser_options,
    plain_pairs,
    range_term,
    whitened_pairs,
    why_not_rescued,
)
from sfm_laserscale.detection.options import TAKEN_ON_SECOND_LOOK, DetectionOptions
from sfm_laserscale.detection.score import below, describe_weakest
from sfm_laserscale.rig import Rig

F64 = NDArray[np.float64]
UNCALIBRATED_REASON = "uncalibrated laser: give its spots with --spots"
#: colour term from which a candidate counts as laser light (for the depth order)
LIT_COLOUR = 0.7
#: "farther" means beyond this fraction of the candidate's own range
DEPTH_MARGIN = 0.05
#: clutter term of a maximum below the clutter gate taken at the other spots' range
CLUTTER_AT_RANGE = 1.0
#: chosen spots needed before the second look takes a whitened clipped core: one spot's range
#: is weak backing (a glint on a band's line agrees with a lone false spot in laser-free frames)
WHITENED_LOOK_SPOTS = 2
#: chosen spots the floor must stand on before a whitened clipped core near its point is taken
#: (:func:`whitened_at_floor`): three spots give a plane, two only its least tilted guess
WHITENED_FLOOR_SPOTS = 3
#: how far from the floor's point such a core may lie, in floor search radii: the rig's
#: calibration error puts the point a median 2.7 px from the spot at 1920 × 1080, 41 % of
#: them beyond the search's 3.1 px (docs/DETECTION_ROUNDS.md, "The twenty-fifth round")
WHITENED_FLOOR_REACH = 1.5
#: … and from its beam's image, as a share of ``band_px`` (a true core's is up to 0.26 there)
WHITENED_FLOOR_BEAM = 0.3
#: where such a core lies, in its reason
AT_FLOOR = "{d:.1f} px from where the floor through the other lasers' spots puts it"
#: an unclipped blob whose colour reads as not the laser's is taken by those rules only when
#: its half-maximum radius is below this many times the chosen spots' median: with its colour
#: unread, its size is what tells it from a wide glint (a whitened clipped core is exempt: its
#: brightness makes it wider than a fainter spot beside it)
UNLIT_MAX_WIDTH = 2.0


def beam_term(dist_px: F64, band_px: float) -> F64:
    """Score factor for the distance to the beam segment: exp(-½ (2 d / band)²)."""
    return np.asarray(np.exp(-0.5 * (2.0 * dist_px / band_px) ** 2), dtype=np.float64)


def evidence(m: Measure, beam: float, laser: str | None = None) -> dict[str, float]:
    """Every evidence term of a candidate at a beam term ``beam`` (and, for a laser, whether
    laser light lies farther along that laser's beam, ``depth``, and whether its range agrees
    with the other lasers' spots, ``range``: :mod:`.joint`)."""
    return {**m.terms, "colour": m.colour.term, "beam": beam,
            "depth": m.depth.get(laser, 1.0) if laser else 1.0,
            "range": m.range_fit.get(laser, 1.0) if laser else 1.0}


def why_weak(m: Measure, beam: float, laser: str | None = None) -> str:
    """The weakest evidence of a measured candidate, in words."""
    return describe_weakest(evidence(m, beam, laser), m.snr, m.roundness, m.clutter_ratio,
                            m.colour)


def _score(m: Measure, beam: float, laser: str | None = None) -> float:
    return float(np.prod(list(evidence(m, beam, laser).values())))


def option_score(m: Measure, beam: float, laser: str) -> float:
    """A candidate's score for a laser on its own evidence: without the range agreement and
    the depth term, which the joint choice judges against the spots taken with it."""
    ev = evidence(m, beam, laser)
    ev.pop("range")
    ev.pop("depth")
    return float(np.prod(list(ev.values())))


def _lit(m: Measure, beam: float, options: DetectionOptions) -> bool:
    """Laser light for sure: it scores and its added light has the laser's colour."""
    return (m.colour.measured and m.colour.term >= LIT_COLOUR
            and _score(m, beam) >= options.min_score)


def _mark_depth(las_name: str, i: int, region: SearchRegion, valid: list[Measure], dist: F64,
                lit: list[int], others_m: list[float]) -> None:
    """In place: each candidate of a beam records the ranges of the laser light farther along
    it (``farther_lit``, which the joint choice judges against the spots it takes with it,
    :mod:`.joint`), and gets a provisional ``depth`` DEPTH when there is such light.

    A beam lights nothing beyond the first surface it meets: laser-coloured light nearer than
    other laser light on the same beam is a particle lit in the water, or the beam's glow.
    ``lit``: indices into ``valid`` of this beam's laser light (:func:`_beam_light`; light
    nearer to another beam's line does not count). Provisionally, nor does farther light whose
    range agrees less than the candidate's with ``others_m`` (m: the ranges of the other beams'
    strongest laser light): then the other beams' spots sit at the candidate's range, and the
    farther light is a laser-coloured speck of the scene, not this beam's end.
    """
    admissible = [j for j in range(len(valid)) if dist[i, j] <= region.band_px]
    if len(admissible) < 2 or not lit:
        return
    xy = np.array([[valid[j].x, valid[j].y] for j in admissible + lit])
    rng = range_along_beam(xy, region.polylines[las_name], region.ranges[las_name])
    lit_m = rng[len(admissible):]
    ref = float(np.median(others_m)) if others_m else None

    def off(r: float) -> float:
        return abs(math.log(r / ref)) if ref is not None else 0.0

    for k, j in enumerate(admissible):
        far = [float(r) for r in lit_m if r > rng[k] * (1.0 + DEPTH_MARGIN)]
        valid[j].farther_lit[las_name] = tuple(far)
        if any(ref is None or off(r) <= off(rng[k]) for r in far):
            valid[j].depth[las_name] = DEPTH


def _range_m(m: Measure, las_name: str, region: SearchRegion) -> float:
    """Range (m) along a laser's beam of a candidate's position."""
    xy = np.array([[m.x, m.y]])
    return float(range_along_beam(xy, region.polylines[las_name], region.ranges[las_name])[0])


def _beam_light(i: int, region: SearchRegion, valid: list[Measure], dist: F64,
                options: DetectionOptions) -> list[int]:
    """Indices into ``valid`` of beam ``i``'s laser light (:func:`_lit`, in its band and
    nearer its line than any other beam's), strongest first."""
    beam = beam_term(dist[i], region.band_px)
    lit = [j for j in range(len(valid)) if dist[i, j] <= region.band_px
           and dist[i, j] <= dist[:, j].min() and _lit(valid[j], float(beam[j]), options)]
    return sorted(lit, key=lambda j: -_score(valid[j], float(beam[j])))


def _laser_scores(
    rig: Rig, region: SearchRegion, valid: list[Measure], options: DetectionOptions
) -> tuple[F64, F64, dict[str, str]]:
    """(L, N) option scores (:func:`option_score`; 0 where a laser may not take a candidate)
    and distances to the beams (px) for calibrated lasers."""
    band = region.band_px
    xy = np.array([[m.x, m.y] for m in valid]).reshape(-1, 2)
    scores = np.zeros((len(rig.lasers), len(valid)))
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
    seen = [i for i in range(len(rig.lasers)) if np.isfinite(dist[i]).any()]
    lit = {i: _beam_light(i, region, valid, dist, options) for i in seen}
    strongest_m = {i: _range_m(valid[js[0]], rig.lasers[i].name, region)
                   for i, js in lit.items() if js}
    for i in seen:
        las = rig.lasers[i]
        beam = beam_term(dist[i], band)
        others_m = [r for k, r in strongest_m.items() if k != i]
        _mark_depth(las.name, i, region, valid, dist, lit[i], others_m)
        for j, m in enumerate(valid):
            if dist[i, j] <= band and las.color in ("any", m.color):
                scores[i, j] = option_score(m, float(beam[j]), las.name)
    return scores, dist, unseen


def _farther(valid: list[Measure], name: str) -> dict[int, tuple[float, ...]]:
    """Candidate index -> ranges (m) of laser light farther along a laser's beam."""
    return {j: m.farther_lit[name] for j, m in enumerate(valid) if m.farther_lit.get(name)}


def _mark_choice(opts: dict[str, list[Option]], choice: Choice, valid: list[Measure]) -> None:
    """In place: every option's range and depth terms as the joint choice judges them (against
    its floor range and the spots it took; no range term when it took none)."""
    plain = {n: o for n, o in choice.chosen.items() if not o.rescued}
    for name, ranked in opts.items():
        others = [o.range_m for n, o in plain.items() if n != name]
        for o in ranked:
            m = valid[o.index]
            taken = choice.chosen.get(name)
            mine = taken is not None and taken.index == o.index
            m.range_fit[name] = range_term(
                o.range_m, choice.range_ref_m.get(name, choice.floor_m) if mine
                else choice.floor_m)
            m.depth[name] = choice.depth[name] if mine else depth_term(o, others)


#: how a reason names a whitened clipped core (:data:`.candidates.WHITENED_MAX_COLOUR`)
UNREADABLE_CORE = "a clipped core whose colour cannot be read"
#: the reasons of whitened cores taken at the other lasers' range, alone on their beams' lines
#: at one range, and as a pair whose floor holds the other lasers' spots (:mod:`.joint`)
RESCUED_BESIDE = f"{UNREADABLE_CORE}, at the range of the other lasers' spots"
RESCUED_ALONE = f"{UNREADABLE_CORE}, one of {{n}} such cores on their beams' lines at one range"
RESCUED_PAIR = (f"{UNREADABLE_CORE}, one of 2 such cores on their beams' lines at one range, "
                "where the floor through them holds the other lasers' spots")
#: why a spot of a pair that is not whitened cores was taken (:func:`.joint.plain_pairs`)
PLAIN_PAIR = ("too weak alone, on its beam's line at one range with {other}'s candidate, where "
              "the floor through the two holds {spots}")
#: … and taken on the second look, on its beam's line (at the other lasers' spots' range)
WHITENED_AT_RANGE = f"{UNREADABLE_CORE}, on its beam's line"
#: … and an unclipped blob whose colour reads as not the laser's, taken there too
COLOURLESS_AT_RANGE = "its colour not the laser's (colour {term:.2f}), on its beam's line"
#: why a candidate reaching min_score on its own was not chosen for a laser left without a
#: spot: every combination holding it put an option below min_score, or the spot chosen
#: instead was dropped afterwards (alone in its image)
LEFT_OUT = ("the joint choice left it out (its range disagrees with the other lasers' "
            "candidates, or the spot chosen instead was dropped afterwards)")


def take_choice(rig: Rig, region: SearchRegion, valid: list[Measure], dist: F64,
                choice: Choice, rescued_why: str) -> dict[str, int]:
    """In place (``valid``): the choice's candidates assigned to their lasers, with their
    evidence (a rescued core's colour term CLIPPED_COLOUR, ``rescued_why`` in its reason).
    Returns laser -> index into ``valid``."""
    chosen: dict[str, int] = {}
    for name, o in choice.chosen.items():
        li = rig.names.index(name)
        m = valid[o.index]
        beam = float(beam_term(dist[li, o.index : o.index + 1], region.band_px)[0])
        m.evidence = evidence(m, beam, name)
        m.laser, m.reason = name, f"assigned to {name}"
        if o.rescued:
            m.evidence["colour"] = CLIPPED_COLOUR
            m.reason += f": {rescued_why}"
        m.score = float(np.prod(list(m.evidence.values())))
        chosen[name] = o.index
    return chosen


def assign_calibrated(
    rig: Rig, region: SearchRegion, valid: list[Measure], options: DetectionOptions
) -> tuple[dict[str, int], dict[str, str], F64, list[Choice]]:
    """Laser name -> index into ``valid`` (chosen jointly, :mod:`.joint`); missing reasons;
    distances; the pairs a floor search may take when nothing was chosen: of whitened cores
    (:func:`.joint.whitened_pairs`), then of other options (:func:`.joint.plain_pairs`)."""
    scores, dist, missing = _laser_scores(rig, region, valid, options)
    opts = {las.name: laser_options(las.name, scores[i], region,
                                    valid, _farther(valid, las.name), MAX_OPTIONS)
            for i, las in enumerate(rig.lasers) if las.calibrated and las.name not in missing}
    choice = choose_jointly(opts, options.min_score)
    _mark_choice(opts, choice, valid)
    picked = choice.chosen
    whitened_only = all(o.rescued for o in picked.values())
    chosen = take_choice(rig, region, valid, dist, choice,
                         RESCUED_ALONE.format(n=len(picked)) if whitened_only
                         else RESCUED_BESIDE)
    for name, ranked in opts.items():
        for o in ranked:
            m = valid[o.index]
            if m.laser is None and o.rescue >= options.min_score:
                m.not_rescued[name] = why_not_rescued(name, o, choice, options.min_score)
            if m.laser is None and not m.reason and _score(m, 1.0, name) < options.min_score:
                m.reason = f"score below min_score for {name}"
    return chosen, missing, dist, whitened_pairs(opts, options.min_score) + plain_pairs(opts)


def second_look(rig: Rig, region: SearchRegion, measures: list[Measure], valid: list[Measure],
                chosen: dict[str, int], options: DetectionOptions) -> dict[str, int]:
    """Calibrated lasers still without a spot take a maximum held back by the clutter gate
    (``Measure.second_look``), or a candidate left unassigned, whose light has the laser's
    colour (colour term at least LIT_COLOUR) and whose range agrees with the median range of
    the ``chosen`` spots (:func:`~sfm_laserscale.detection.joint.agrees`); its clutter term is
    then CLUTTER_AT_RANGE and it is taken when that scores ``min_score``. A blob of the scene's
    texture sits anywhere along a band; a laser's spot sits at the range of the other spots.
    A candidate whose colour reads as not the laser's (:func:`colour_unread`: a whitened
    clipped core, or any blob with a colour term below :data:`.candidates.WHITENED_MAX_COLOUR`)
    qualifies too, beside two chosen spots or more, on its beam's line at their range
    (:func:`_whitened_at_range`). Taken maxima are appended to ``valid``; returns laser name ->
    index into ``valid``."""
    free = set(range(len(valid))) - set(chosen.values())
    pool = [m for m in measures if m.second_look] + [valid[j] for j in sorted(free)]
    ref = _chosen_range(region, valid, chosen)
    radius = chosen_radius(valid, chosen)
    index = {id(m): j for j, m in enumerate(valid)}
    taken: dict[str, int] = {}
    for las in rig.lasers:
        if not pool or ref is None or las.name in chosen or not las.calibrated:
            continue
        fits = [(vb, m) for m in pool if las.color in ("any", m.color)
                and (vb := _second_look_value(m, las.name, region, ref, options,
                                              len(chosen) >= WHITENED_LOOK_SPOTS, radius)
                     )[0] > 0.0]
        if fits:
            (value, beam), m = max(fits, key=lambda f: f[0][0])
            _take_second_look(m, las.name, value, beam)
            taken[las.name] = _in_valid(m, valid, index)
            pool.remove(m)
    return taken


def _in_valid(m: Measure, valid: list[Measure], index: dict[int, int]) -> int:
    """In place (``valid``, ``index``: id of each measure -> its index in ``valid``): ``m``'s
    index in ``valid``, appended there first when it is not in it (a maximum held back by the
    clutter gate)."""
    if id(m) not in index:
        valid.append(m)
        index[id(m)] = len(valid) - 1
    return index[id(m)]


def _chosen_range(region: SearchRegion, valid: list[Measure], chosen: dict[str, int]
                  ) -> float | None:
    """Median range (m) of the chosen spots of calibrated lasers, or None without any."""
    ranges = [_range_m(valid[j], name, region)
              for name, j in chosen.items() if len(region.polylines.get(name, ())) > 0]
    finite = [r for r in ranges if math.isfinite(r)]
    return float(np.median(finite)) if finite else None


def _reads_unlit(m: Measure) -> bool:
    """Whether a candidate's measured colour term is below WHITENED_MAX_COLOUR."""
    return m.colour.measured and m.colour.term < WHITENED_MAX_COLOUR


def colour_unread(m: Measure, spot_radius_px: float | None) -> bool:
    """Whether a candidate's colour reads as not the laser's and its place must speak for it:
    a whitened clipped core, or any blob whose colour term is below WHITENED_MAX_COLOUR (a core
    whose laser channel nearly clips, a far spot of a pixel or two whose colour the camera's
    chroma averages with its surroundings) whose half-maximum radius is below UNLIT_MAX_WIDTH ×
    ``spot_radius_px`` (the chosen spots' median; None without any)."""
    return m.whitened or (_reads_unlit(m) and spot_radius_px is not None
                          and m.radius_px < UNLIT_MAX_WIDTH * spot_radius_px)


def chosen_radius(valid: list[Measure], chosen: Mapping[str, int]) -> float | None:
    """Median half-maximum radius (px) of the chosen spots (None without any)."""
    return float(np.median([valid[j].radius_px for j in chosen.values()])) if chosen else None


def _second_look_value(m: Measure, name: str, region: SearchRegion, ref_m: float,
                       options: DetectionOptions, whitened_ok: bool,
                       spot_radius_px: float | None) -> tuple[float, float]:
    """(score, beam term) of a second-look maximum for a laser; score 0 when it does not
    qualify. A candidate whose colour reads as not the laser's (:func:`colour_unread`;
    ``whitened_ok``: beside WHITENED_LOOK_SPOTS chosen spots or more, of median radius
    ``spot_radius_px``) scores with CLIPPED_COLOUR for its colour where
    :func:`_whitened_at_range`."""
    line = region.polylines[name]
    lit = m.colour.term >= LIT_COLOUR
    unread = colour_unread(m, spot_radius_px)
    if len(line) == 0 or not (lit or (unread and whitened_ok)):
        return 0.0, 0.0
    dist = float(distance_to_polyline(np.array([[m.x, m.y]]), line)[0])
    range_m = _range_m(m, name, region)
    if not (_whitened_at_range(dist, range_m, ref_m, region.band_px) if unread
            else dist <= region.band_px and agrees(range_m, ref_m)):
        return 0.0, 0.0
    colour = CLIPPED_COLOUR if unread else m.colour.term
    return _waived_value(m, name, colour, dist, region.band_px, options.min_score)


def _waived_value(m: Measure, name: str, colour: float, dist_px: float, band_px: float,
                  min_score: float) -> tuple[float, float]:
    """(score, beam term) for a laser of a candidate ``dist_px`` from its beam's image, taken
    with its clutter term waived (CLUTTER_AT_RANGE) and colour term ``colour``; score 0 below
    ``min_score``."""
    terms = {**m.terms, "clutter": CLUTTER_AT_RANGE, "colour": colour}
    beam = float(beam_term(np.array([dist_px]), band_px)[0])
    value = float(np.prod(list(terms.values()))) * beam * m.depth.get(name, 1.0)
    return (value, beam) if value >= min_score else (0.0, 0.0)


def _whitened_at_range(dist_px: float, range_m: float, ref_m: float, band_px: float) -> bool:
    """Whether a whitened clipped core ``dist_px`` from its beam's image lies on it at the
    chosen spots' range ``ref_m`` (:func:`.joint.core_on_line_at`, the joint choice's test)."""
    return core_on_line_at(dist_px / band_px, range_m, ref_m)


def _take_second_look(m: Measure, name: str, value: float, beam: float,
                      where: str = "at the range of the other lasers' spots") -> None:
    """In place: a second-look maximum becomes laser ``name``'s spot (``beam``: its term;
    ``where``: what placed it, in words)."""
    gated = m.rejected is not None
    unread = m.whitened or _reads_unlit(m)  # a laser-coloured one's term is >= LIT_COLOUR
    colour = _colour_words(m) if unread else "laser-coloured"
    m.terms["clutter"] = CLUTTER_AT_RANGE
    m.range_fit[name] = 1.0
    m.evidence = evidence(m, beam, name)
    if unread:
        m.evidence["colour"] = CLIPPED_COLOUR
    m.rejected, m.laser, m.score, m.taken_by = None, name, value, TAKEN_ON_SECOND_LOOK
    strength = ("below the clutter gate" if gated else "its clutter term waived")
    m.reason = (f"assigned to {name}: {strength} ({m.clutter_ratio:.2f} × clutter level), "
                f"{colour}, {where}")


def _colour_words(m: Measure) -> str:
    """How a candidate whose colour reads as not the laser's is named in its reason."""
    if m.whitened:
        return WHITENED_AT_RANGE
    return COLOURLESS_AT_RANGE.format(term=m.colour.term)


def whitened_at_floor(rig: Rig, region: SearchRegion, measures: list[Measure],
                      valid: list[Measure], chosen: dict[str, int],
                      predicted_px: Mapping[str, tuple[float, float]], reach_px: float,
                      options: DetectionOptions) -> dict[str, int]:
    """Calibrated lasers still without a spot take the candidate whose colour reads as not the
    laser's (:func:`colour_unread`, a whitened clipped core among them) nearest the point
    where the floor through the chosen spots puts theirs (``predicted_px``: laser -> COLMAP
    (x, y)), within ``reach_px`` of it and WHITENED_FLOOR_BEAM × ``band_px`` of its beam's image,
    scored as the second look scores one (clutter term waived, colour CLIPPED_COLOUR) when that
    reaches ``min_score``. Taken candidates are appended to ``valid``; returns laser name ->
    index."""
    free = set(range(len(valid))) - set(chosen.values())
    radius = chosen_radius(valid, chosen)
    pool = [m for m in measures if m.second_look and colour_unread(m, radius)]
    pool += [valid[j] for j in sorted(free) if colour_unread(valid[j], radius)]
    index = {id(m): j for j, m in enumerate(valid)}
    taken: dict[str, int] = {}
    for name, (px, py) in predicted_px.items():
        las = rig.laser(name)
        if name in chosen or not las.calibrated:
            continue
        near = sorted((math.hypot(m.x - px, m.y - py), k) for k, m in enumerate(pool)
                      if las.color in ("any", m.color))
        for d_px, k in near:
            if d_px > reach_px:
                break
            if (vb := _core_at_floor(pool[k], name, region, options))[0] > 0.0:
                m = pool.pop(k)
                _take_second_look(m, name, *vb, where=AT_FLOOR.format(d=d_px))
                taken[name] = _in_valid(m, valid, index)
                break
    return taken


def _core_at_floor(m: Measure, name: str, region: SearchRegion, options: DetectionOptions
                   ) -> tuple[float, float]:
    """(score, beam term) of a candidate whose colour reads as not the laser's near the floor's
    point for a laser; score 0 when it lies beyond WHITENED_FLOOR_BEAM × ``band_px`` of its
    beam's image or scores below ``min_score``."""
    line = region.polylines[name]
    if len(line) == 0:
        return 0.0, 0.0
    dist = float(distance_to_polyline(np.array([[m.x, m.y]]), line)[0])
    if dist > WHITENED_FLOOR_BEAM * region.band_px:
        return 0.0, 0.0
    return _waived_value(m, name, CLIPPED_COLOUR, dist, region.band_px, options.min_score)


def assign_uncalibrated(
    rig: Rig, valid: list[Measure], taken: set[int], options: DetectionOptions
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
            missing[las.name] = f"no free {las.color_label} spot candidate in the image"
            continue
        scores = {j: _score(valid[j], 1.0) for j in free}
        j = max(free, key=lambda k: scores[k])
        m = valid[j]
        if scores[j] < options.min_score:
            missing[las.name] = (f"best {las.color_label} candidate ({m.x:.1f}, {m.y:.1f}) "
                                 f"scores {below(scores[j], options.min_score)} < min_score "
                                 f"{options.min_score:g}: "
                                 f"{why_weak(m, 1.0)}")
            m.reason = f"score below min_score for {las.name}"
            continue
        m.score, m.laser, m.reason = scores[j], las.name, f"assigned to {las.name} by colour"
        m.evidence = evidence(m, 1.0)
        chosen[las.name] = j
        taken.add(j)
    return chosen, missing


def explain_unused(rig: Rig, valid: list[Measure], dist: F64, band: float,
                   options: DetectionOptions) -> None:
    """Fill the reason, evidence and a geometry-aware score of valid candidates left over."""
    names = rig.names
    taken = {m.laser for m in valid if m.laser is not None}
    for j, m in enumerate(valid):
        if m.laser is not None:
            continue
        col = dist[:, j] if dist.size else np.zeros(0)
        finite = np.isfinite(col)
        li = int(np.argmin(np.where(finite, col, np.inf))) if finite.any() else None
        beam = float(beam_term(col[li : li + 1], band)[0]) if li is not None else 1.0
        m.evidence = evidence(m, beam, names[li] if li is not None else None)
        m.score = float(np.prod(list(m.evidence.values())))
        if m.reason:
            continue
        if li is None:
            m.reason = "no calibrated laser of its colour to take it"
        elif col[li] > band:
            m.reason = f"off every beam band (nearest: {names[li]} at {col[li]:.1f} px)"
        elif names[li] in taken:
            m.reason = f"a better candidate was assigned to {names[li]}"
        else:
            m.reason = f"not chosen for {names[li]}: {LEFT_OUT}"
