"""Spots to lasers: one spot per laser, one laser per candidate, and why a laser has none.

A calibrated laser may take a candidate of its colour (any colour for "any": the colour evidence
then compares with each candidate's channel) within ``band_px`` of its beam segment; its score
is the candidate's evidence (:mod:`.score`; its colour is measured against the expected colour
of its channel's lasers) times the beam term ``exp(-½ (d / band)²)``. The assignment is linear
on ``-log(score)``; a laser whose best candidate scores below ``min_score`` gets none. An
uncalibrated laser takes the best free candidate of its colour when no other laser shares that
colour. A laser without a spot is explained by the best candidates in its band, each with its
score and the test it failed or its weakest evidence.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from sfm_laserscale.detection.beams import SearchRegion, distance_to_polyline
from sfm_laserscale.detection.candidates import Measure
from sfm_laserscale.detection.options import DetectionOptions
from sfm_laserscale.detection.score import describe_weakest
from sfm_laserscale.rig import Rig

F64 = NDArray[np.float64]
UNCALIBRATED_REASON = "uncalibrated laser: give its spots with --spots"
_INADMISSIBLE = 1e6


def beam_term(dist_px: F64, band_px: float) -> F64:
    """Score factor for the distance to the beam segment: exp(-½ (d / band)²)."""
    return np.asarray(np.exp(-0.5 * (dist_px / band_px) ** 2), dtype=np.float64)


def evidence(m: Measure, beam: float) -> dict[str, float]:
    """Every evidence term of a candidate at a beam term ``beam``."""
    return {**m.terms, "colour": m.colour.term, "beam": beam}


def why_weak(m: Measure, beam: float) -> str:
    """The weakest evidence of a measured candidate, in words."""
    return describe_weakest(evidence(m, beam), m.snr, m.roundness, m.clutter_ratio, m.colour)


def _score(m: Measure, beam: float) -> float:
    return float(np.prod(list(evidence(m, beam).values())))


def _laser_costs(
    rig: Rig, region: SearchRegion, valid: list[Measure], options: DetectionOptions
) -> tuple[F64, F64, dict[str, str]]:
    """(L, N) assignment cost -log(score) and distance to beam for calibrated lasers."""
    band = region.band_px
    xy = np.array([[m.x, m.y] for m in valid]).reshape(-1, 2)
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
        beam = beam_term(dist[i], band)
        for j, m in enumerate(valid):
            if dist[i, j] <= band and las.color in ("any", m.color):
                cost[i, j] = -math.log(max(_score(m, float(beam[j])), 1e-12))
    return cost, dist, unseen


def assign_calibrated(
    rig: Rig, region: SearchRegion, valid: list[Measure], options: DetectionOptions
) -> tuple[dict[str, int], dict[str, str], F64]:
    """Laser name -> index into ``valid`` by linear assignment; missing reasons; distances."""
    cost, dist, missing = _laser_costs(rig, region, valid, options)
    chosen: dict[str, int] = {}
    rows, cols = linear_sum_assignment(cost) if cost.size else (np.array([]), np.array([]))
    for li, cj in zip(rows.tolist(), cols.tolist(), strict=True):
        if cost[li, cj] >= _INADMISSIBLE:
            continue
        las, score = rig.lasers[li], math.exp(-cost[li, cj])
        m = valid[cj]
        beam = float(beam_term(dist[li, cj : cj + 1], region.band_px)[0])
        if score < options.min_score:
            m.reason = f"score {score:.2f} below min_score for {las.name}"
            continue
        m.score, m.laser, m.reason = score, las.name, f"assigned to {las.name}"
        m.evidence = evidence(m, beam)
        chosen[las.name] = cj
    return chosen, missing, dist


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
                                 f"scores {scores[j]:.2f} < min_score {options.min_score:g}: "
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
    for j, m in enumerate(valid):
        if m.laser is not None:
            continue
        col = dist[:, j] if dist.size else np.zeros(0)
        finite = np.isfinite(col)
        li = int(np.argmin(np.where(finite, col, np.inf))) if finite.any() else None
        beam = float(beam_term(col[li : li + 1], band)[0]) if li is not None else 1.0
        m.evidence = evidence(m, beam)
        m.score = float(np.prod(list(m.evidence.values())))
        if m.reason:
            continue
        if li is None:
            m.reason = "no calibrated laser of its colour to take it"
        elif col[li] > band:
            m.reason = f"off every beam band (nearest: {names[li]} at {col[li]:.1f} px)"
        else:
            m.reason = f"a better candidate was assigned to {names[li]}"
