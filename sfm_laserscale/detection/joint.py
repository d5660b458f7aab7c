"""One spot per calibrated laser, chosen jointly: the spots a scaler's beams make on one floor.

The beams of a scaler hit one seafloor a few decimetres apart, so their ranges along the beams
agree to within what the floor's slope and relief allow; a candidate of one beam's band that is
something else (clutter, a glint, a particle lit in the water) sits at a range anywhere from the
beam's near end to its far end. Each candidate's position along its beam gives its range
(:func:`~sfm_laserscale.detection.beams.range_along_beam`).

Each laser's MAX_OPTIONS best candidates (by their evidence without range and depth) are its
options. :func:`choose_jointly` weighs every combination of options, one or none per laser and
each candidate to one laser (:func:`combination_value`):

- the combination's floor range r_ref is the range, of its options' own, that maximises its
  total; every option is worth its score × range term
  ``RANGE_FLOOR + (1 − RANGE_FLOOR)·exp(-½ (ln(r / r_ref) / RANGE_SIGMA_LN)²)`` and must reach
  ``min_score``. The floor keeps a strong spot on a step of the relief (a scarp, a coral head)
  that disagrees with the others. One reference shared by all, not the median of the others:
  two spots on a step do not pull the two on the floor down with them. An option that no other
  option of the combination taken on its own evidence agrees with (within LEAD_AGREEMENT_LN) is
  judged instead against the other lasers' ranges: their option in the combination, or else
  their lead (best option reaching ``min_score``). Leaving a laser out of a combination does not
  silence its lead: a laser-free frame's strong blobs lie at unrelated ranges;
- *depth*: a beam lights nothing beyond the first surface it meets, so laser-coloured light
  farther along an option's beam (``Option.farther_m``) makes it a particle lit in the water or
  the beam's glow (× DEPTH), unless the option's range agrees better than that light's with the
  median range of the combination's other options: then the other spots sit at the option's
  range and the farther light is a laser-coloured speck of the scene;
- a clipped core's colour is often not readable at all: demosaicing, 4:2:0 chroma, the white
  balance and the sensor's spectral crosstalk (a laser many times white raises the other
  channels to clipping too) whiten its rim, so it reads like a glint (``Measure.whitened``). It
  may be taken with CLIPPED_COLOUR for its colour term (``Option.rescue``) where its range
  agrees within RESCUE_RANGE_LN with r_ref of options taken on their own evidence: a glint sits
  anywhere along a band, a laser's spot at the range of the other spots. Beside a single option
  taken on its own evidence, a rescued core must also lie within RESCUE_BESIDE_ONE_BEAM ×
  ``band_px`` of its beam's image, where nearly every laser's spot lies: one option's range is
  weak backing, and a band dense with glints holds one at any range; unless the combination
  holds ALL_WHITENED_WIDE_MIN options or more on their lines at one range, as four whitened
  cores alone may be taken (:func:`wide_floor`). Whitened cores that
  agree only with each other are taken only as a combination of ALL_WHITENED_MIN or more, each
  within ALL_WHITENED_BEAM × ``band_px`` (how far a spot may lie from its beam's image) of that
  image and all within ALL_WHITENED_RANGE_LN of their median range (:func:`all_whitened_value`;
  four or more, ALL_WHITENED_WIDE_MIN, within ALL_WHITENED_WIDE_BEAM × ``band_px``):
  at 4000 × 3000 the bands hold enough glints that three or four of them agree within 15 % in
  most laser-free frames, but not on their beams' lines as well (a laser's spot lies on its
  beam within the rig's calibration error, a glint anywhere across the band). Two such cores
  alone, each within PAIR_BEAM × ``band_px`` of its beam's image (:func:`whitened_pairs`), are
  a floor to search the other beams on: they are taken where the search finds
  PAIR_FLOOR_SPOTS other lasers' spots on it (:mod:`.detect`). So are
  two options that are not whitened cores (:func:`plain_pairs`), each worth
  PLAIN_PAIR_MIN_SCORE and held to the tests of place of three whitened cores (within
  ALL_WHITENED_BEAM of their lines, at one range), where the search finds
  PLAIN_PAIR_FLOOR_SPOTS: faint far spots, each too weak to be taken alone, that sit where
  one floor puts them.
- an option taken on its own evidence that no other such option agrees with is judged
  against the other lasers' ranges (their option, else their lead), unless a rescued core of
  its combination backs it (:func:`_backed`): the core on its beam's line at the option's range,
  the option within BACKED_BEAM × ``band_px`` of its own. A false lead of another laser (a
  particle near the camera) then no longer vetoes a spot that a whitened core agrees with.

The combination of the highest total wins (ties: more spots). Particles lit by the beams are
laser-coloured and strong, but their ranges agree neither with each other nor with the floor;
the spots on the floor agree with each other.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.beams import SearchRegion, distance_to_polyline, range_along_beam
from sfm_laserscale.detection.candidates import Measure

F64 = NDArray[np.float64]
#: candidates per laser considered
MAX_OPTIONS = 5
#: spread (natural log of the range ratio) of the spots' ranges on one seafloor: 0.4 ≈ ±50 %
RANGE_SIGMA_LN = 0.4
#: the range term never falls below this (the seafloor may have steps: scarps, coral heads)
RANGE_FLOOR = 0.35
#: options whose ranges agree within this (natural log) back each other
LEAD_AGREEMENT_LN = 0.25
#: candidates scoring below this are not considered at all
MIN_CONSIDERED = 0.02
#: colour term of a clipped core whose colour reads whitened, when its range agrees
CLIPPED_COLOUR = 1.0
#: … agrees: |ln(range / the floor range of the options taken on their own)| at most this
RESCUE_RANGE_LN = 0.15
#: a core rescued beside a single option taken on its own evidence lies within this many
#: ``band_px`` of its beam's image (nearly every laser's spot does: docs/DETECTION.md)
RESCUE_BESIDE_ONE_BEAM = 0.2
#: factor of an option with laser light farther along its beam
DEPTH = 0.1
#: whitened cores agreeing only with each other are taken when this many or more …
ALL_WHITENED_MIN = 3
#: … each lies within this many ``band_px`` (the band's half-width) of its beam's image …
ALL_WHITENED_BEAM = 0.1
#: … and all within this (natural log) of their median range
ALL_WHITENED_RANGE_LN = 0.08
#: a combination of this many whitened cores or more (one per beam of a four-beam scaler) …
ALL_WHITENED_WIDE_MIN = 4
#: … may lie this many ``band_px`` from their beams' images: three times the rig's stated
#: calibration error, which ALL_WHITENED_BEAM is about (it holds two true cores in three), so
#: nearly every true core of the four; four glints at one range so near their lines turn up in
#: none of the laser-free frames measured (docs/DETECTION_ROUNDS.md, "The thirty-eighth round")
ALL_WHITENED_WIDE_BEAM = 0.3
#: an option taken on its own evidence within this many ``band_px`` of its beam's image (about
#: 99 % of true spots: docs/DETECTION_ROUNDS.md), with a rescued core on its line at its range,
#: is not judged alone against the other lasers' leads (:func:`_backed`)
BACKED_BEAM = 0.3
#: two such cores alone are taken when the floor through them holds this many other lasers'
#: spots (:func:`whitened_pairs`; the floor search, :mod:`.detect`)
PAIR_FLOOR_SPOTS = 2
#: … and each lies within this many ``band_px`` of its beam's image, as four such cores may
#: (ALL_WHITENED_WIDE_BEAM): the two spots the floor search must find, not the pair's place,
#: tell two lasers' cores from two glints; ALL_WHITENED_BEAM holds about two true cores in
#: three, so about four pairs of true cores in nine (docs/DETECTION_ROUNDS.md, "The
#: forty-fourth round")
PAIR_BEAM = ALL_WHITENED_WIDE_BEAM
#: at most this many pairs of whitened cores are searched for that, best first
PAIRS_TRIED = 10
#: two options that are not whitened cores, each worth this much (every evidence term but
#: range and depth) and on their beams' lines at one range as whitened pairs must be, are a
#: floor to search the other beams on too (:func:`plain_pairs`)
PLAIN_PAIR_MIN_SCORE = 0.1
#: … taken when the floor through them holds this many other lasers' spots: glints are
#: whitened, so laser-free frames hold no such pairs for one more spot to complete (measured:
#: docs/DETECTION_ROUNDS.md, "The thirty-ninth round")
PLAIN_PAIR_FLOOR_SPOTS = 1
#: why a whitened core was not rescued when no option was taken on its own evidence
NOTHING_BESIDE = (f"taken only at the range of a spot of another laser, with "
                  f"{ALL_WHITENED_MIN - 1} more such cores on their beams' lines at one range, "
                  f"or with one more where the floor through the two holds {PAIR_FLOOR_SPOTS} "
                  "other lasers' spots; none was")
#: the joint choice weighs at most this many combinations (more: each laser's weakest
#: alternatives are dropped first)
MAX_COMBINATIONS = 20000


@dataclass(frozen=True)
class Option:
    """A candidate for a laser: its index in ``valid``, its score (every evidence term but
    range and depth), its range (m), the ranges (m) of laser light farther along the laser's
    beam (``farther_m``), its score with CLIPPED_COLOUR for colour (``rescue``, 0 unless a
    clipped core's colour read against it); ``rescued`` when taken that way; its distance
    from the beam's image in ``band_px`` (``beam_share``)."""

    index: int
    score: float
    range_m: float
    rescue: float = 0.0
    rescued: bool = False
    farther_m: tuple[float, ...] = ()
    beam_share: float = math.inf


@dataclass(frozen=True)
class Choice:
    """The joint choice: laser -> option taken, the floor range r_ref (m; nan when nothing
    was taken) and each option's depth term in it (laser -> depth)."""

    chosen: dict[str, Option]
    floor_m: float = math.nan
    depth: dict[str, float] = field(default_factory=dict)
    range_ref_m: dict[str, float] = field(default_factory=dict)  # laser -> its r_ref


def range_term(range_m: float, ref_m: float) -> float:
    """Agreement of a spot's range with the floor range ``ref_m`` (1 when either is not
    finite)."""
    if not (math.isfinite(range_m) and math.isfinite(ref_m)):
        return 1.0
    z = math.log(range_m / ref_m) / RANGE_SIGMA_LN
    return RANGE_FLOOR + (1.0 - RANGE_FLOOR) * math.exp(-0.5 * z * z)


def depth_term(o: Option, others_m: list[float]) -> float:
    """DEPTH when laser light lies farther along the option's beam and the other options'
    median range (``others_m``) does not agree better with the option than with that light."""
    if not o.farther_m:
        return 1.0
    if not others_m:
        return DEPTH
    ref = float(np.median(others_m))

    def off(r: float) -> float:
        return abs(math.log(r / ref))

    return DEPTH if any(off(r) <= off(o.range_m) for r in o.farther_m) else 1.0


def laser_options(name: str, scores: F64, region: SearchRegion, valid: list[Measure],
                  farther: dict[int, tuple[float, ...]], per_laser: int) -> list[Option]:
    """The best ``per_laser`` candidates of one laser (scores (N,), 0 = inadmissible;
    ``farther``: candidate index -> ranges of laser light farther along this beam)."""
    order = [int(j) for j in np.argsort(-scores) if scores[j] >= MIN_CONSIDERED][:per_laser]
    if not order:
        return []
    xy = np.array([[valid[j].x, valid[j].y] for j in order])
    ranges = range_along_beam(xy, region.polylines[name], region.ranges[name])
    shares = distance_to_polyline(xy, region.polylines[name]) / region.band_px
    return [Option(j, float(scores[j]), float(r), _rescue(valid[j], float(scores[j])),
                   farther_m=farther.get(j, ()), beam_share=float(d))
            for j, r, d in zip(order, ranges, shares, strict=True)]


def _rescue(m: Measure, score: float) -> float:
    """A whitened clipped core's score with CLIPPED_COLOUR for its colour term (0 otherwise)."""
    if not (m.whitened and m.colour.term > 0.0):
        return 0.0
    return score / m.colour.term * CLIPPED_COLOUR


def _depths(combo: dict[str, Option]) -> dict[str, float]:
    """Each option's depth term against the other options of its combination taken on their
    own evidence."""
    return {n: depth_term(o, [p.range_m for m, p in combo.items() if m != n and not p.rescued])
            for n, o in combo.items()}


def lead_ranges(options: dict[str, list[Option]], min_score: float) -> dict[str, float]:
    """Laser -> range (m) of its lead: its best option, when that reaches ``min_score`` on its
    own."""
    return {n: opts[0].range_m for n, opts in options.items()
            if opts and opts[0].score >= min_score and math.isfinite(opts[0].range_m)}


def _lone_reference(name: str, plain: dict[str, Option], lead_m: dict[str, float]) -> float:
    """The range (m) a lone option of laser ``name`` is judged against: the median over the
    other lasers of their option in the combination, or else their lead (nan: none).

    A laser-free frame's bands hold strong blobs at unrelated ranges; each of them, taken alone,
    disagrees with the others, and leaving another laser out of the combination does not
    silence its lead."""
    others = (set(lead_m) | set(plain)) - {name}
    ranges = [plain[n].range_m if n in plain else lead_m[n] for n in sorted(others)]
    return float(np.median(ranges)) if ranges else math.nan


def _lone(plain: dict[str, Option], rescues: list[Option]) -> set[str]:
    """The options taken on their own evidence whose range no other such option of their
    combination agrees with (within LEAD_AGREEMENT_LN), and that no rescued core backs
    (:func:`_backed`). Other whitened cores do not count: one or two glints agree with a blob
    by chance in many laser-free frames."""
    return {n for n, o in plain.items()
            if not any(abs(math.log(p.range_m / o.range_m)) <= LEAD_AGREEMENT_LN
                       for m, p in plain.items() if m != n)
            and not _backed(o, rescues)}


def core_on_line_at(beam_share: float, range_m: float, ref_m: float) -> bool:
    """Whether a whitened core ``beam_share`` ``band_px`` from its beam's image lies on it
    (within ALL_WHITENED_BEAM) at the range ``ref_m`` (:func:`agrees`): a glint lies anywhere
    across a band, a laser's spot on its beam's line within the rig's calibration error."""
    return beam_share <= ALL_WHITENED_BEAM and agrees(range_m, ref_m)


def _backed(o: Option, rescues: list[Option]) -> bool:
    """Whether an option within BACKED_BEAM × ``band_px`` of its beam's image has a rescued
    core of its combination on its own beam's line at the option's range
    (:func:`core_on_line_at`): two lasers' light on their beams' lines at one range, as a pair
    of whitened cores is, and one of them of the laser's colour."""
    return o.beam_share <= BACKED_BEAM and any(
        core_on_line_at(r.beam_share, r.range_m, o.range_m) for r in rescues)


def combination_value(combo: dict[str, Option], min_score: float,
                      lead_m: dict[str, float] | None = None
                      ) -> tuple[float, Choice] | None:
    """(total value, choice) of one combination (laser -> option), or None when an option
    fails in it (module docstring). The options taken on their own evidence that agree with
    another one are judged against r_ref, of their ranges the one that maximises the total; an
    option no other agrees with, nor a rescued core backs (:func:`_lone`), against the other
    lasers (:func:`_lone_reference`; ``lead_m``: :func:`lead_ranges`), as every laser was
    before the choice was joint."""
    plain = {n: o for n, o in combo.items() if not o.rescued}
    rescues = [o for o in combo.values() if o.rescued]
    if not plain:
        return all_whitened_value(combo, min_score)
    if (len(plain) == 1 and any(o.beam_share > RESCUE_BESIDE_ONE_BEAM for o in rescues)
            and not wide_floor(combo)):
        return None
    depth = _depths(combo)
    rescue_values = [o.rescue * depth[n] for n, o in combo.items() if o.rescued]
    if rescue_values and min(rescue_values) < min_score:
        return None
    refs = {n: _lone_reference(n, plain, lead_m or {}) for n in _lone(plain, rescues)}
    lone_values = [plain[n].score * depth[n] * range_term(plain[n].range_m, r)
                   for n, r in refs.items()]
    if lone_values and min(lone_values) < min_score:
        return None
    together = {n: o for n, o in plain.items() if n not in refs}
    candidates = {o.range_m for o in together.values()} or {
        float(np.median([o.range_m for o in plain.values()]))}
    best: tuple[float, Choice] | None = None
    for ref in candidates:
        values = [o.score * depth[n] * range_term(o.range_m, ref) for n, o in together.items()]
        if (values and min(values) < min_score) or not all(agrees(o.range_m, ref)
                                                          for o in rescues):
            continue
        total = sum(values) + sum(lone_values) + sum(rescue_values)
        if best is None or total > best[0]:
            best = (total, Choice(combo, ref, depth, refs | dict.fromkeys(together, ref)))
    return best


def _on_lines_at_one_range(opts: list[Option], beam_limit: float) -> float | None:
    """The median range (m) of options that each lie within ``beam_limit`` × ``band_px`` of
    their beam's image and all within ALL_WHITENED_RANGE_LN of that range, else None."""
    if any(o.beam_share > beam_limit or not math.isfinite(o.range_m) for o in opts):
        return None
    ref = float(np.median([o.range_m for o in opts]))
    if any(abs(math.log(o.range_m / ref)) > ALL_WHITENED_RANGE_LN for o in opts):
        return None
    return ref


def wide_floor(combo: dict[str, Option]) -> bool:
    """Whether ALL_WHITENED_WIDE_MIN options or more lie within ALL_WHITENED_WIDE_BEAM ×
    ``band_px`` of their beams' images and within ALL_WHITENED_RANGE_LN of their median range:
    the place of a four-beam scaler's spots on one floor, which four whitened cores alone may
    take (:func:`all_whitened_value`)."""
    opts = list(combo.values())
    return (len(opts) >= ALL_WHITENED_WIDE_MIN
            and _on_lines_at_one_range(opts, ALL_WHITENED_WIDE_BEAM) is not None)


def all_whitened_value(combo: dict[str, Option], min_score: float
                       ) -> tuple[float, Choice] | None:
    """(total value, choice) of a combination of whitened cores alone (every option
    ``rescued``), or None: it needs ALL_WHITENED_MIN options or more, each within
    ALL_WHITENED_BEAM × ``band_px`` of its beam's image (ALL_WHITENED_WIDE_BEAM for
    ALL_WHITENED_WIDE_MIN options or more: four glints agree by chance far more rarely than
    three), all within ALL_WHITENED_RANGE_LN of their median range (its floor range), and each
    worth ``min_score`` with its depth term."""
    if len(combo) < ALL_WHITENED_MIN:
        return None
    wide = len(combo) >= ALL_WHITENED_WIDE_MIN
    return _on_one_floor(combo, ALL_WHITENED_WIDE_BEAM if wide else ALL_WHITENED_BEAM,
                         lambda o: o.rescue, min_score)


def _on_one_floor(combo: dict[str, Option], beam_limit: float,
                  worth: Callable[[Option], float], least: float
                  ) -> tuple[float, Choice] | None:
    """(total value, choice) of options each within ``beam_limit`` × ``band_px`` of its beam's
    image and all within ALL_WHITENED_RANGE_LN of their median range (the floor range), each
    worth ``worth(option)`` with its depth term; None when they are not so placed or one is
    worth less than ``least``."""
    ref_m = _on_lines_at_one_range(list(combo.values()), beam_limit)
    if ref_m is None:
        return None
    depth = _depths(combo)
    values = [worth(o) * depth[n] for n, o in combo.items()]
    if min(values) < least:
        return None
    return sum(values), Choice(combo, ref_m, depth, dict.fromkeys(combo, ref_m))


def whitened_pair_value(combo: dict[str, Option], min_score: float
                        ) -> tuple[float, Choice] | None:
    """(total value, choice) of two whitened cores (``rescued``), or None: each within
    PAIR_BEAM × ``band_px`` of its beam's image, both within ALL_WHITENED_RANGE_LN of their
    median range, each worth ``min_score`` with its depth term."""
    return _on_one_floor(combo, PAIR_BEAM, lambda o: o.rescue, min_score)


def whitened_pairs(options: dict[str, list[Option]], min_score: float) -> list[Choice]:
    """Pairs of whitened cores of two lasers that pass :func:`whitened_pair_value` (near their
    beams' lines, at one range, each worth ``min_score``), best total first, at most
    PAIRS_TRIED: each is a floor to search the other beams on. Two cores agree by chance in
    some laser-free frames; all the other spots where their floor puts them do not
    (:mod:`.detect`)."""
    cores = [(n, replace(o, rescued=True)) for n, opts in options.items() for o in opts
             if o.rescue >= min_score]
    return _best_pairs(cores, lambda pair: whitened_pair_value(pair, min_score))


def _best_pairs(cands: list[tuple[str, Option]],
                value: Callable[[dict[str, Option]], tuple[float, Choice] | None]
                ) -> list[Choice]:
    """The pairs of two lasers' candidates (laser, option) that ``value`` admits, best total
    first, at most PAIRS_TRIED; one candidate is never both lasers'."""
    valued = [v for i, (na, a) in enumerate(cands) for nb, b in cands[i + 1:]
              if na != nb and a.index != b.index and (v := value({na: a, nb: b})) is not None]
    valued.sort(key=lambda v: -v[0])
    return [choice for _, choice in valued[:PAIRS_TRIED]]


def plain_pair_value(combo: dict[str, Option]) -> tuple[float, Choice] | None:
    """(total value, choice) of two options that are not whitened cores, or None: each within
    ALL_WHITENED_BEAM × ``band_px`` of its beam's image, both within ALL_WHITENED_RANGE_LN of
    their median range, each worth PLAIN_PAIR_MIN_SCORE with its depth term."""
    return _on_one_floor(combo, ALL_WHITENED_BEAM, lambda o: o.score, PLAIN_PAIR_MIN_SCORE)


def plain_pairs(options: dict[str, list[Option]]) -> list[Choice]:
    """Pairs of two lasers' options that are not whitened cores and pass
    :func:`plain_pair_value`, best total first, at most PAIRS_TRIED: each is a floor to search
    the other beams on where nothing was chosen (:mod:`.detect`). Faint far spots, each too
    weak to be taken alone, sit on their beams' lines at one range; a laser-free frame's blobs
    that do so are glints, which read whitened (:func:`whitened_pairs`)."""
    plain = [(n, o) for n, opts in options.items() for o in opts
             if o.rescue == 0.0 and o.score >= PLAIN_PAIR_MIN_SCORE]
    return _best_pairs(plain, plain_pair_value)


def _alternatives(opts: list[Option], min_score: float) -> list[Option | None]:
    """What one laser may take, best first after nothing: an option reaching ``min_score`` on
    its own, or a whitened core's option with its rescue score (``rescued``)."""
    alts: list[Option | None] = [None]
    for o in opts:
        if o.score >= min_score:
            alts.append(o)
        if o.rescue >= min_score:
            alts.append(replace(o, rescued=True))
    return alts


def _trimmed(alts: list[list[Option | None]]) -> list[list[Option | None]]:
    """The alternatives with each laser's weakest dropped, longest list first, until their
    combinations number at most MAX_COMBINATIONS (rigs of five lasers or more)."""
    alts = [list(a) for a in alts]
    while math.prod(len(a) for a in alts) > MAX_COMBINATIONS:
        max(alts, key=len).pop()
    return alts


def choose_jointly(options: dict[str, list[Option]], min_score: float) -> Choice:
    """The combination (one option or none per laser, each candidate to one laser) of the
    highest total value (ties: more spots); an empty :class:`Choice` when none scores."""
    names = [n for n, opts in options.items() if opts]
    alts = _trimmed([_alternatives(options[n], min_score) for n in names])
    lead_m = lead_ranges(options, min_score)
    best = Choice({})
    best_key = (0.0, 0)
    for pick in itertools.product(*alts):
        combo = {n: o for n, o in zip(names, pick, strict=True) if o is not None}
        if not combo or len({o.index for o in combo.values()}) < len(combo):
            continue
        valued = combination_value(combo, min_score, lead_m)
        if valued is not None and (valued[0], len(combo)) > best_key:
            best, best_key = valued[1], (valued[0], len(combo))
    return best


def why_not_rescued(name: str, o: Option, choice: Choice, min_score: float) -> str:
    """Why laser ``name``'s whitened core ``o`` (``o.rescue`` reaching ``min_score``) was not
    taken with CLIPPED_COLOUR by ``choice``: the rescue's test it fails against the spots
    taken, in words."""
    plain = {n: p for n, p in choice.chosen.items() if not p.rescued and n != name}
    if not plain:
        return NOTHING_BESIDE
    if (len(plain) == 1 and o.beam_share > RESCUE_BESIDE_ONE_BEAM
            and not wide_floor(choice.chosen | {name: o})):
        return (f"{o.beam_share:.2f} band_px from its beam's image beside a single spot "
                f"(at most {RESCUE_BESIDE_ONE_BEAM:g})")
    if not agrees(o.range_m, choice.floor_m):
        return (f"at {o.range_m:.2f} m along its beam, not at the range of the spots chosen "
                f"with it ({choice.floor_m:.2f} m, within "
                f"{100 * math.expm1(RESCUE_RANGE_LN):.0f} %)")
    depth = depth_term(o, [p.range_m for p in plain.values()])
    if o.rescue * depth < min_score:
        return "laser light lies farther along its beam (a particle lit in the water or glow)"
    return "the combination without it scored higher"


def agrees(range_m: float, ref_m: float) -> bool:
    """Whether a range lies within RESCUE_RANGE_LN (log ratio) of a reference range."""
    return math.isfinite(range_m) and abs(math.log(range_m / ref_m)) <= RESCUE_RANGE_LN
