"""Scale methods (docs/DESIGN.md §3): pure numpy, camera frame, hits in model units, rig in
metres."""

from sfm_laserscale.methods.baselines import (
    davis_tusting_scale,
    direct3d_scale,
    direct3d_scale_batch,
)
from sfm_laserscale.methods.fcm import FcmResult, fcm_origin_hat, fcm_scale, fcm_scale_batch
from sfm_laserscale.methods.pcm import (
    PcmResult,
    pcm_scale,
    pcm_scale_batch,
    pcm_scale_known_direction,
)

__all__ = [
    "FcmResult",
    "PcmResult",
    "davis_tusting_scale",
    "direct3d_scale",
    "direct3d_scale_batch",
    "fcm_origin_hat",
    "fcm_scale",
    "fcm_scale_batch",
    "pcm_scale",
    "pcm_scale_batch",
    "pcm_scale_known_direction",
]
