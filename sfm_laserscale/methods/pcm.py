"""PCM — partially calibrated method (docs/DESIGN.md §3).

Camera frame, hits in model units, separations in metres. The camera centre is the origin of
the camera frame, so the paper's v_CM (camera centre -> midpoint X_M of the two hits) is X_M.

    v_12 = X_2 − X_1     cos α = v_12·v_CM / (‖v_12‖‖v_CM‖)     d̂ = sin α ‖v_12‖     s = d / d̂

Known bias (the paper's midpoint approximation): with v_CM at angle β to the true beam direction
u, tilted out of the plane of the beams (camera equidistant from both beams), and the hits Δ
apart along the beams, d̂ = sqrt(d² + Δ² sin² β) ≥ d: PCM overestimates d̂ (underestimates s)
whenever the hits differ in depth. For an equidistant camera it is exact when Δ = 0 (surface
perpendicular to the beams) or when v_CM ∥ u (camera centre half-way between the beams).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

#: hits closer than this fraction of their distance to the camera count as coincident.
MIN_SEPARATION_RATIO = 1e-12


@dataclass(frozen=True)
class PcmResult:
    """One PCM estimate: scale (m per model unit), d̂ (model units), α (deg), depth difference."""

    scale: float
    d_hat: float  # model units: estimated perpendicular distance between the beams
    alpha_deg: float  # angle between v_12 and the (approximated) beam direction
    depth_difference: float  # model units: v_12 along the beam direction (signed)
    valid: bool = True
    reason: str | None = None


def _perpendicular_part(v12: F64, axis: F64) -> tuple[F64, F64]:
    """(‖v12 ⟂ axis‖, v12 · axis/‖axis‖) for (..., 3) arrays."""
    with np.errstate(divide="ignore", invalid="ignore"):
        unit = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    along = np.sum(v12 * unit, axis=-1)
    perp = v12 - along[..., None] * unit
    return np.linalg.norm(perp, axis=-1), along


def pcm_scale_batch(hit1_cam: F64, hit2_cam: F64, separation_m: float | F64) -> F64:
    """Vectorised PCM (midpoint approximation): (..., 3) hits -> (...) scales; no checks."""
    h1 = np.asarray(hit1_cam, dtype=np.float64)
    h2 = np.asarray(hit2_cam, dtype=np.float64)
    d_hat, _ = _perpendicular_part(h2 - h1, 0.5 * (h1 + h2))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(separation_m / d_hat, dtype=np.float64)


def _pair_reason(h1: F64, h2: F64, separation_m: float) -> str | None:
    """Why a pair estimate is undefined, or None."""
    if not (np.all(np.isfinite(h1)) and np.all(np.isfinite(h2))):
        return "non-finite hit"
    if not (np.isfinite(separation_m) and separation_m > 0):
        return "separation must be a positive number of metres"
    if h1[2] <= 0 or h2[2] <= 0:
        return "hit behind the camera (z ≤ 0)"
    scale_ref = max(float(np.linalg.norm(h1)), float(np.linalg.norm(h2)))
    if float(np.linalg.norm(h2 - h1)) <= MIN_SEPARATION_RATIO * scale_ref:
        return "the two hits coincide"
    return None


def _pcm_result(h1: F64, h2: F64, separation_m: float, axis: F64) -> PcmResult:
    reason = _pair_reason(h1, h2, separation_m)
    if reason is not None:
        return PcmResult(np.nan, np.nan, np.nan, np.nan, False, reason)
    v12 = h2 - h1
    d_hat, along = _perpendicular_part(v12, axis)
    d_hat_f = float(d_hat)
    if not np.isfinite(d_hat_f) or d_hat_f <= MIN_SEPARATION_RATIO * float(np.linalg.norm(v12)):
        return PcmResult(np.nan, np.nan, np.nan, np.nan, False,
                         "hits aligned with the beam direction: d̂ ≈ 0")
    alpha = float(np.degrees(np.arctan2(d_hat_f, float(along))))
    return PcmResult(separation_m / d_hat_f, d_hat_f, alpha, float(along))


def pcm_scale(hit1_cam: F64, hit2_cam: F64, separation_m: float) -> PcmResult:
    """PCM scale from the hits of two parallel beams (paper's midpoint approximation of v_CM)."""
    h1 = np.asarray(hit1_cam, dtype=np.float64).reshape(3)
    h2 = np.asarray(hit2_cam, dtype=np.float64).reshape(3)
    return _pcm_result(h1, h2, float(separation_m), 0.5 * (h1 + h2))


def pcm_scale_known_direction(hit1_cam: F64, hit2_cam: F64, separation_m: float,
                              beam_direction_cam: F64) -> PcmResult:
    """PCM with a known beam direction: d̂ is the exact perpendicular distance of the hits."""
    h1 = np.asarray(hit1_cam, dtype=np.float64).reshape(3)
    h2 = np.asarray(hit2_cam, dtype=np.float64).reshape(3)
    axis = np.asarray(beam_direction_cam, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(axis)) or float(np.linalg.norm(axis)) < 1e-12:
        return PcmResult(np.nan, np.nan, np.nan, np.nan, False, "invalid beam direction")
    return _pcm_result(h1, h2, float(separation_m), axis)
