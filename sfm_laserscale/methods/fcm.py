"""FCM — fully calibrated method (docs/DESIGN.md §3): scale from one laser of known origin and
direction.

Camera frame (x right, y down, z forward, optical axis c_z = (0, 0, 1)); the hit is in model
units, the laser origin (on the laser plane z = 0) in metres. With X the hit:

    Ô_L = X − (X·c_z / v_L·c_z) · v_L          s_L = ‖O_L‖ / ‖Ô_L‖   (metres per model unit)

Ô_L lies on z = 0 like O_L; at the right scale s·Ô_L = O_L, so the angle between them is a free
consistency check of the spot-to-laser assignment and of the calibration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.rig import MIN_DIRECTION_Z, MIN_ORIGIN_NORM

F64 = NDArray[np.float64]

#: ‖Ô_L‖ below this fraction of the hit's distance: the hit lies on the line through the camera
#: centre parallel to the beam, where the scale is undefined.
MIN_ORIGIN_HAT_RATIO = 1e-9


@dataclass(frozen=True)
class FcmResult:
    """One FCM estimate: scale (m per model unit), Ô_L (model units), direction residual (deg)."""

    scale: float
    origin_hat: F64  # (3,) model units, on z = 0
    direction_residual_deg: float  # angle between Ô_L and O_L
    valid: bool
    reason: str | None = None


def fcm_origin_hat(hits_cam: F64, directions: F64) -> F64:
    """Ô_L for (..., 3) hits (model units) and (..., 3) unit beam directions; (..., 3) on z = 0."""
    hits = np.asarray(hits_cam, dtype=np.float64)
    dirs = np.asarray(directions, dtype=np.float64)
    ratio = hits[..., 2] / dirs[..., 2]
    o_hat = hits - ratio[..., None] * dirs
    o_hat[..., 2] = 0.0  # exactly zero up to rounding; the formula puts Ô_L on the laser plane
    return o_hat


def fcm_scale_batch(hits_cam: F64, origins_m: F64, directions: F64) -> tuple[F64, F64]:
    """Vectorised FCM: (..., 3) inputs -> (scale (...), signed direction residual in radians (...)).

    The signed residual is the rotation about c_z from O_L to Ô_L (both on z = 0); no validity
    checks here (see :func:`fcm_scale`).
    """
    o_hat = fcm_origin_hat(hits_cam, directions)
    origins = np.asarray(origins_m, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.linalg.norm(origins, axis=-1) / np.linalg.norm(o_hat, axis=-1)
    cross_z = origins[..., 0] * o_hat[..., 1] - origins[..., 1] * o_hat[..., 0]
    dot = origins[..., 0] * o_hat[..., 0] + origins[..., 1] * o_hat[..., 1]
    return np.asarray(scale, dtype=np.float64), np.arctan2(cross_z, dot)


def _invalid(reason: str) -> FcmResult:
    return FcmResult(np.nan, np.full(3, np.nan), np.nan, False, reason)


def _check_inputs(hit: F64, origin: F64, direction: F64) -> str | None:
    """Reason why FCM is undefined for these inputs, or None."""
    if not (np.all(np.isfinite(hit)) and np.all(np.isfinite(origin))
            and np.all(np.isfinite(direction))):
        return "non-finite hit, origin or direction"
    norm_v = float(np.linalg.norm(direction))
    if norm_v < 1e-12 or abs(direction[2]) / norm_v < MIN_DIRECTION_Z:
        return "beam (nearly) parallel to the laser plane: v·c_z ≈ 0"
    if float(np.linalg.norm(origin)) < MIN_ORIGIN_NORM:
        return "laser origin at the camera centre: ‖O_L‖ ≈ 0"
    if hit[2] <= 0.0:
        return "hit behind the camera (z ≤ 0)"
    return None


def fcm_scale(hit_cam: F64, origin_m: F64, direction: F64) -> FcmResult:
    """FCM scale from one hit (camera frame, model units) and its calibrated beam (metres)."""
    hit = np.asarray(hit_cam, dtype=np.float64).reshape(3)
    origin = np.asarray(origin_m, dtype=np.float64).reshape(3)
    direction = np.asarray(direction, dtype=np.float64).reshape(3)
    reason = _check_inputs(hit, origin, direction)
    if reason is not None:
        return _invalid(reason)
    direction = direction / np.linalg.norm(direction)
    if abs(origin[2]) > 1e-9 * max(1.0, float(np.linalg.norm(origin))):
        origin = origin - (origin[2] / direction[2]) * direction  # onto z = 0 along the beam
    o_hat = fcm_origin_hat(hit, direction)
    if float(np.linalg.norm(o_hat)) <= MIN_ORIGIN_HAT_RATIO * float(np.linalg.norm(hit)):
        return _invalid("hit on the camera's own parallel to the beam: ‖Ô_L‖ ≈ 0")
    scale, resid = fcm_scale_batch(hit, origin, direction)
    return FcmResult(float(scale), o_hat, float(np.degrees(abs(resid))), True, None)
