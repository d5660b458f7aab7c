"""The geometry of a rig's declared pairs: PCM needs two PARALLEL beams, and its midpoint
approximation a camera EQUIDISTANT from both (docs/DESIGN.md §3, docs/RIG.md).

For a pair whose two lasers are calibrated:

- the angle θ between their directions, with its σ from ``sigma_direction`` (√2 σ per axis);
  a beam pair θ apart changes its separation by ρ θ over a range ρ: 1 % at 3 m for a 0.234 m
  pair already at 0.045°. Beyond ``max_angle_deg`` PCM, Direct 3D and PCM-joint are refused for
  the pair (their estimates are rejected with the reason); a significant smaller angle (beyond
  ``angle_nsigma`` σ and ``min_angle_deg``) is a warning with the separation change per metre;
- each beam's distance from the camera centre (the optical axis through it); when they differ by
  more than ``max_equidistance_ratio`` of the separation, the midpoint approximation is biased
  on relief (PCM-joint is not): a warning;
- the declared separation against the calibrated beams' perpendicular distance on the laser
  plane: a difference beyond ``max_separation_mismatch_m`` is a warning.

Pairs with an uncalibrated laser cannot be checked (stated in the result).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.rig import Pair, Rig

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class PairCheckOptions:
    """Thresholds of :func:`check_pair`."""

    max_angle_deg: float = 0.5  # beyond: PCM refused for the pair
    min_angle_deg: float = 0.01  # below: parallel, whatever the calibration σ
    angle_nsigma: float = 3.0  # an angle beyond this many σ is significant
    max_equidistance_ratio: float = 0.05  # |r1 − r2| / separation beyond: not equidistant
    max_separation_mismatch_m: float = 0.001


@dataclass(frozen=True)
class PairGeometry:
    """One declared pair's geometry and the verdicts (None: not checkable)."""

    pair: str  # "L1+L2"
    calibrated: bool  # both lasers have origin and direction
    angle_deg: float | None
    angle_sigma_deg: float | None
    separation_change_pct_per_m: float | None  # 100 θ / separation
    distance_difference_m: float | None  # |r1 − r2| of the beams from the camera centre
    separation_m: float  # declared
    calibrated_separation_m: float | None  # perpendicular distance of the beams on z = 0
    parallel: bool | None
    equidistant: bool | None
    refused: bool  # PCM, Direct 3D and PCM-joint are not used for this pair
    reason: str | None  # why it is refused


def _axis_distance(origin: F64, direction: F64) -> float:
    """Distance of the camera centre from the beam line (origin on z = 0, unit direction)."""
    return float(np.linalg.norm(origin - (origin @ direction) * direction))


def check_pair(rig: Rig, pair: Pair, options: PairCheckOptions) -> PairGeometry:
    """The geometry of one declared pair against PCM's assumptions."""
    a, b = rig.laser(pair.lasers[0]), rig.laser(pair.lasers[1])
    name = "+".join(pair.lasers)
    if a.origin is None or a.direction is None or b.origin is None or b.direction is None:
        return PairGeometry(name, False, None, None, None, None, pair.separation, None, None,
                            None, False, None)
    va, vb = np.asarray(a.direction, np.float64), np.asarray(b.direction, np.float64)
    oa, ob = np.asarray(a.origin, np.float64), np.asarray(b.origin, np.float64)
    angle = math.degrees(math.acos(float(np.clip(va @ vb, -1.0, 1.0))))
    sigma = math.degrees(math.sqrt(a.sigma_direction**2 + b.sigma_direction**2))
    axis = (va + vb) / np.linalg.norm(va + vb)
    d = ob - oa
    sep = float(np.linalg.norm(d - (d @ axis) * axis))
    diff = abs(_axis_distance(oa, va) - _axis_distance(ob, vb))
    significant = angle > max(options.min_angle_deg, options.angle_nsigma * sigma)
    refused = angle > options.max_angle_deg
    reason = (f"beams of pair {name} are {angle:.2f}° apart (not parallel; PCM needs parallel "
              f"beams, limit {options.max_angle_deg:g}°)" if refused else None)
    return PairGeometry(name, True, angle, sigma,
                        100.0 * math.radians(angle) / pair.separation, diff, pair.separation,
                        sep, not significant, diff <= options.max_equidistance_ratio
                        * pair.separation, refused, reason)


def check_pairs(rig: Rig, options: PairCheckOptions | None = None) -> tuple[PairGeometry, ...]:
    """Every declared pair of the rig."""
    opt = options or PairCheckOptions()
    return tuple(check_pair(rig, p, opt) for p in rig.pairs)


def refused_pairs(rig: Rig, options: PairCheckOptions | None = None) -> dict[str, str]:
    """Pair name -> why PCM is refused for it (pairs that are far from parallel)."""
    return {g.pair: g.reason for g in check_pairs(rig, options) if g.refused and g.reason}


def pair_warnings(g: PairGeometry, options: PairCheckOptions | None = None) -> list[str]:
    """Plain-word problems of one pair (empty when it is fine or not checkable)."""
    opt = options or PairCheckOptions()
    out = []
    if g.refused and g.reason:
        out.append(f"The rig declares {g.pair} a parallel pair, but its calibrated {g.reason}: "
                   "PCM, Direct 3D and PCM-joint are not used for it.")
    elif g.parallel is False and g.angle_deg is not None:
        out.append(f"The calibrated beams of pair {g.pair} are {g.angle_deg:.3f}° apart "
                   f"(± {g.angle_sigma_deg:.3f}°): not parallel. Their separation changes by "
                   f"{g.separation_change_pct_per_m:.2f} % per metre of range, and PCM takes it "
                   "as constant.")
    if g.equidistant is False and g.distance_difference_m is not None:
        out.append(f"The camera is not equidistant from the beams of pair {g.pair} (they are "
                   f"{1000 * g.distance_difference_m:.0f} mm apart in distance from the optical "
                   f"axis, {100 * g.distance_difference_m / g.separation_m:.0f} % of the "
                   "separation): PCM's midpoint approximation is biased on relief; PCM-joint "
                   "does not assume it.")
    if (g.calibrated_separation_m is not None
            and abs(g.calibrated_separation_m - g.separation_m) > opt.max_separation_mismatch_m):
        out.append(f"Pair {g.pair}: the declared separation {g.separation_m:.4f} m differs from "
                   f"the calibrated beams' {g.calibrated_separation_m:.4f} m.")
    return out
