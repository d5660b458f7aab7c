"""One spot per calibrated laser, chosen with the agreement of the spots' ranges.

The beams of a scaler hit one seafloor a few decimetres apart, so their ranges along the beams
agree to within what the floor's slope and relief allow; a candidate of one beam's band that is
something else (clutter, a glint, a lit particle) sits at a range anywhere from the beam's near
end to its far end. Each candidate's position along its beam gives its range
(:func:`~sfm_laserscale.detection.beams.range_along_beam`). Each laser's MAX_OPTIONS best
candidates get the range term ``RANGE_FLOOR + (1 − RANGE_FLOOR)·exp(-½ (ln(r / r_ref) /
RANGE_SIGMA_LN)²)``, r_ref the median range of the other lasers' best candidates (those
reaching ``min_score`` on their own; of three or more, only the largest group that agrees,
:func:`agreeing_leads`): the floor keeps a strong spot on a step of the relief (a
scarp, a coral head) that disagrees with the others. A laser takes its best candidate by score ×
range term when that reaches ``min_score``.

A small clipped core's colour is often not readable at all: demosaicing, 4:2:0 chroma and the
white balance whiten its rim, so it reads like a glint (``Measure.whitened``: half-maximum radius
at most ``candidates.WHITENED_MAX_RADIUS``; a larger glint shows its own colour). Such a
candidate keeps its colour term against it unless its range agrees within RESCUE_RANGE_LN with
the lasers chosen on their own evidence: then its colour term is CLIPPED_COLOUR instead
(``Option.rescue``) and it is taken when that reaches ``min_score``. A glint sits anywhere along
a band; a laser's spot sits at the range of the other spots. (Whitened cores agreeing only with
each other are not taken: at 4000 × 3000 the bands hold enough glints that three or four of
them agree within 15 % in most laser-free frames.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.beams import SearchRegion, range_along_beam
from sfm_laserscale.detection.candidates import Measure

F64 = NDArray[np.float64]
#: candidates per laser considered
MAX_OPTIONS = 5
#: spread (natural log of the range ratio) of the spots' ranges on one seafloor: 0.4 ≈ ±50 %
RANGE_SIGMA_LN = 0.4
#: the range term never falls below this (the seafloor may have steps: scarps, coral heads)
RANGE_FLOOR = 0.35
#: leads whose ranges agree within this (natural log) form the range reference
LEAD_AGREEMENT_LN = 0.25
#: candidates scoring below this are not considered at all
MIN_CONSIDERED = 0.02
#: colour term of a clipped core whose colour reads whitened, when its range agrees
CLIPPED_COLOUR = 1.0
#: … agrees: |ln(range / median range of the lasers chosen on their own)| at most this
RESCUE_RANGE_LN = 0.15


@dataclass(frozen=True)
class Option:
    """A candidate for a laser: its index in ``valid``, its score, its range (m) and its score
    with CLIPPED_COLOUR for colour (``rescue``, 0 unless a clipped core's colour read against
    it); ``rescued`` when chosen that way."""

    index: int
    score: float
    range_m: float
    rescue: float = 0.0
    rescued: bool = False


def range_term(range_m: float, others_m: list[float]) -> float:
    """Agreement of a spot's range with the median range of the other chosen spots."""
    if not others_m or not math.isfinite(range_m):
        return 1.0
    z = math.log(range_m / float(np.median(others_m))) / RANGE_SIGMA_LN
    return RANGE_FLOOR + (1.0 - RANGE_FLOOR) * math.exp(-0.5 * z * z)


def laser_options(name: str, scores: F64, region: SearchRegion, valid: list[Measure],
                  per_laser: int) -> list[Option]:
    """The best ``per_laser`` candidates of one laser (scores (N,), 0 = inadmissible)."""
    order = [int(j) for j in np.argsort(-scores) if scores[j] >= MIN_CONSIDERED][:per_laser]
    if not order:
        return []
    xy = np.array([[valid[j].x, valid[j].y] for j in order])
    ranges = range_along_beam(xy, region.polylines[name], region.ranges[name])
    return [Option(j, float(scores[j]), float(r), _rescue(valid[j], float(scores[j])))
            for j, r in zip(order, ranges, strict=True)]


def _rescue(m: Measure, score: float) -> float:
    """A whitened clipped core's score with CLIPPED_COLOUR for its colour term (0 otherwise)."""
    if not (m.whitened and m.colour.term > 0.0):
        return 0.0
    return score / m.colour.term * CLIPPED_COLOUR


def choose(options: dict[str, list[Option]], min_score: float) -> dict[str, Option]:
    """Laser -> chosen option: each laser's best by score × range term against the median
    range of the other lasers' best-scoring candidates (those reaching ``min_score``), if it
    reaches ``min_score``; a candidate wanted by two lasers goes to the higher value."""
    lead = leads(options, min_score)
    picked: dict[str, tuple[Option, float]] = {}
    for name, opts in options.items():
        others = [o.range_m for n, o in lead.items() if n != name]
        ranked = [(o, o.score * range_term(o.range_m, others)) for o in opts]
        best = max(ranked, key=lambda ov: ov[1], default=None)
        if best is not None and best[1] >= min_score:
            picked[name] = best
    chosen: dict[str, Option] = {}
    for name, (o, _) in sorted(picked.items(), key=lambda kv: -kv[1][1]):
        if all(c.index != o.index for c in chosen.values()):
            chosen[name] = o
    return {**chosen, **rescued(options, chosen, min_score)}


def leads(options: dict[str, list[Option]], min_score: float) -> dict[str, Option]:
    """The range reference's candidates: each laser's best reaching ``min_score`` on its own,
    of those the ones that agree (:func:`agreeing_leads`)."""
    return agreeing_leads({n: opts[0] for n, opts in options.items()
                           if opts and opts[0].score >= min_score})


def agreeing_leads(lead: dict[str, Option]) -> dict[str, Option]:
    """The leading candidates whose ranges agree: with three or more leads, the largest group
    within LEAD_AGREEMENT_LN of one of them (ties: the higher total score), when it holds at
    least two. One wrong lead moves a median of two or three; two clutter leads (the lasers'
    own spots whitened, below ``min_score`` on their own) would pull every true spot's range
    term to its floor and leave the frame without a spot."""
    finite = {n: o for n, o in lead.items() if math.isfinite(o.range_m)}
    if len(finite) < 3:
        return lead
    best: list[str] = []
    best_key = (0, 0.0)
    for o in finite.values():
        members = [m for m, p in finite.items()
                   if abs(math.log(p.range_m / o.range_m)) <= LEAD_AGREEMENT_LN]
        key = (len(members), sum(finite[m].score for m in members))
        if key > best_key:
            best, best_key = members, key
    return {n: lead[n] for n in best} if len(best) >= 2 else lead


def rescued(options: dict[str, list[Option]], chosen: dict[str, Option], min_score: float
            ) -> dict[str, Option]:
    """Lasers without a spot that take a clipped core of whitened colour at the range of the
    spots ``chosen`` on their own evidence (see the module docstring)."""
    if not chosen:
        return {}
    ref = float(np.median([o.range_m for o in chosen.values()]))
    taken = {o.index for o in chosen.values()}
    out: dict[str, Option] = {}
    for name, opts in options.items():
        if name in chosen:
            continue
        fits = [o for o in opts if o.rescue >= min_score and o.index not in taken
                and agrees(o.range_m, ref)]
        if fits:
            best = max(fits, key=lambda o: o.rescue)
            out[name] = replace(best, rescued=True)
            taken.add(best.index)
    return out


def agrees(range_m: float, ref_m: float) -> bool:
    """Whether a range lies within RESCUE_RANGE_LN (log ratio) of a reference range."""
    return math.isfinite(range_m) and abs(math.log(range_m / ref_m)) <= RESCUE_RANGE_LN
