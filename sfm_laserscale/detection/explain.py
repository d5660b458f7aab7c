"""Why a calibrated laser has no spot: what was in its band, and the test each candidate failed.

The reason names up to :data:`NEAR_MISSES` candidates within the laser's band, best first:
measured ones by their score for this laser, then the others by how many clutter levels of
their own response they stand (the colour and brightness responses differ in scale). Each
comes with its position, score and why it was not taken: the hard test it failed ("weak (SNR
3.1 < 6)", "too large to be a spot ..."), its weakest evidence ("colour of the scene, not of
the laser ..."), the test of the joint choice that a clipped core whose colour cannot be read
failed (:func:`~sfm_laserscale.detection.joint.why_not_rescued`), or the laser that took it.
With nothing in the band it says so, and where the nearest candidate lay.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.assign import UNREADABLE_CORE, beam_term, evidence, why_weak
from sfm_laserscale.detection.beams import SearchRegion, distance_to_polyline
from sfm_laserscale.detection.candidates import Measure
from sfm_laserscale.detection.options import DetectionOptions
from sfm_laserscale.detection.score import below
from sfm_laserscale.rig import Laser, Rig

F64 = NDArray[np.float64]
#: candidates named when a laser has no spot
NEAR_MISSES = 3


def _line(m: Measure, las: Laser, d: float, band: float, options: DetectionOptions) -> str:
    """One candidate of a laser's band, in words."""
    where = f"({m.x:.1f}, {m.y:.1f})"
    if m.rejected is not None:
        return f"{where}: {m.rejected}"
    if m.laser is not None:
        return f"{where} was taken by {m.laser}"
    beam = float(beam_term(np.array([d]), band)[0])
    score = float(np.prod(list(evidence(m, beam, las.name).values())))
    if score < options.min_score:
        why = (f"{UNREADABLE_CORE}, not taken at the laser's colour: "
               f"{m.not_rescued[las.name]}" if las.name in m.not_rescued
               else why_weak(m, beam, las.name) + m.pair_held.get(las.name, ""))
        return (f"{where} score {below(score, options.min_score)} < min_score "
                f"{options.min_score:g}: {why}")
    return f"{where} score {score:.2f}: {m.reason}"


def near_misses(las: Laser, measures: list[Measure], region: SearchRegion,
                options: DetectionOptions) -> tuple[list[Measure], F64]:
    """The best candidates of the laser's colour within its band, and their distances."""
    line = region.polylines.get(las.name, np.zeros((0, 2)))
    same = [m for m in measures if las.color in ("any", m.color)]
    if not same or len(line) == 0:
        return [], np.zeros(0)
    dist = distance_to_polyline(np.array([[m.x, m.y] for m in same]), line)
    inside = [i for i in np.argsort(dist) if dist[i] <= region.band_px]

    def rank(i: int) -> tuple[int, float]:
        m = same[i]
        if m.rejected is not None:
            return (1, -m.clutter_ratio)
        beam = float(beam_term(dist[i : i + 1], region.band_px)[0])
        return (0, -float(np.prod(list(evidence(m, beam, las.name).values()))))

    best = sorted(inside, key=rank)[:NEAR_MISSES]
    return [same[i] for i in best], dist[best]


def missing_reason(las: Laser, measures: list[Measure], region: SearchRegion,
                   options: DetectionOptions) -> str:
    """Why a calibrated laser got no spot, naming what was in its band."""
    band = region.band_px
    best, dist = near_misses(las, measures, region, options)
    if best:
        lines = "; ".join(_line(m, las, float(d), band, options)
                          for m, d in zip(best, dist, strict=True))
        return f"no {las.color_label} spot accepted within {band:.1f} px of its beam: {lines}"
    same = [m for m in measures if las.color in ("any", m.color)]
    if not same:
        return f"no {las.color_label} spot candidate in the searched region"
    line = region.polylines.get(las.name, np.zeros((0, 2)))
    d_all = distance_to_polyline(np.array([[m.x, m.y] for m in same]), line)
    k = int(np.argmin(d_all))
    return (f"nothing within {band:.1f} px of its beam ({len(same)} {las.color_label} "
            f"candidates elsewhere; nearest at ({same[k].x:.1f}, {same[k].y:.1f}), "
            f"{d_all[k]:.1f} px away)")


def explain_missing(rig: Rig, measures: list[Measure], region: SearchRegion,
                    chosen: set[str], missing: dict[str, str], options: DetectionOptions
                    ) -> dict[str, list[Measure]]:
    """In place: a reason for every calibrated laser without a spot; its near misses."""
    shown: dict[str, list[Measure]] = {}
    for las in rig.lasers:
        if not las.calibrated or las.name in chosen or las.name in missing:
            continue
        missing[las.name] = missing_reason(las, measures, region, options)
        shown[las.name] = near_misses(las, measures, region, options)[0]
    return shown
