"""Where the model puts a laser's spot: the calibrated beam met with the mesh at a known scale.

A spot the detector missed on its own (pale clutter, green water, a strobe's hot spot: the
band holds scene blobs as strong as the spot) lies at one point of its band once the scale is
known. The beam (metres, camera frame: origin o, unit direction d) divided by the scale s
(metres per model unit) and put in the model frame with the registered pose is the ray
world_from_cam(o / s) + t · Rᵀd; its first hit on the mesh is where the laser lights the floor,
and that point projected with the camera is the spot (:func:`predict_spots`; exact on any
mesh, one ray per laser and image).

The rig's calibration error moves every spot of one laser alike; :func:`laser_offsets` takes
the median offset of the spots found on their own from their predictions, per laser, and
:func:`predict_spots` adds it. :func:`sfm_laserscale.detection.guided.detect_near` then searches
a few pixels around each prediction.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.guided import GuidedOptions
from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.raycast import MeshRaycaster
from sfm_laserscale.rig import Rig

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GuidedSpotOptions:
    """Options of the model-guided search for spots the detector missed (``scale``).

    - ``enabled``: search at all.
    - ``min_offset_spots``: spots of one laser found on their own needed to correct its
      predictions by their median offset (fewer: no correction).
    - ``search``: the search around each prediction (:class:`GuidedOptions`).
    """

    enabled: bool = True
    min_offset_spots: int = 2
    search: GuidedOptions = field(default_factory=GuidedOptions)

    def __post_init__(self) -> None:
        if self.min_offset_spots < 1:
            raise InputError(f"min_offset_spots must be >= 1, got {self.min_offset_spots}")


@dataclass(frozen=True)
class BeamRays:
    """The named calibrated lasers' beams as model-frame rays at one scale: (K,) names, (K, 3)
    origins (model units) and (K, 3) unit directions."""

    names: tuple[str, ...]
    origins: F64
    directions: F64


def beam_rays(cam_from_world: Pose, rig: Rig, names: Iterable[str], scale: float) -> BeamRays:
    """The beams of the named calibrated lasers in the model frame at ``scale`` (metres per
    model unit); uncalibrated lasers are left out."""
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    lasers = [las for las in (rig.laser(n) for n in names)
              if las.origin is not None and las.direction is not None]
    if not lasers:
        return BeamRays((), np.zeros((0, 3)), np.zeros((0, 3)))
    origins_cam = np.array([las.origin for las in lasers], dtype=np.float64) / scale
    dirs_cam = np.array([las.direction for las in lasers], dtype=np.float64)
    world_from_cam = cam_from_world.inverse()
    origins = world_from_cam.transform(origins_cam)
    dirs = dirs_cam @ cam_from_world.R  # Rᵀ d, row-wise
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return BeamRays(tuple(las.name for las in lasers), origins, dirs)


def predict_spots(camera: Camera, cam_from_world: Pose, rig: Rig, names: Iterable[str],
                  caster: MeshRaycaster, scale: float,
                  offsets: dict[str, tuple[float, float]] | None = None
                  ) -> tuple[dict[str, tuple[float, float]], dict[str, str]]:
    """Predicted spot (COLMAP px) of each named calibrated laser at ``scale`` (metres per model
    unit), plus its rig offset (``offsets``); and why a laser has none."""
    names = list(names)
    why = {n: "not calibrated (no beam to meet the mesh with)" for n in names
           if not rig.laser(n).calibrated}
    rays = beam_rays(cam_from_world, rig, names, scale)
    predicted: dict[str, tuple[float, float]] = {}
    if not rays.names:
        return predicted, why
    hit = caster.cast(rays.origins, rays.directions)
    xy = camera.project(cam_from_world.transform(np.where(hit.hit[:, None], hit.xyz, 0.0)))
    for k, name in enumerate(rays.names):
        in_front = hit.hit[k] and cam_from_world.transform(hit.xyz[k][None])[0, 2] > 0
        if not in_front or not np.all(np.isfinite(xy[k])):
            why[name] = "its beam does not meet the mesh in front of the camera"
            continue
        dx, dy = (offsets or {}).get(name, (0.0, 0.0))
        predicted[name] = (float(xy[k, 0]) + dx, float(xy[k, 1]) + dy)
    return predicted, why


def laser_offsets(pairs: Sequence[tuple[str, float, float, float, float]], min_spots: int
                  ) -> dict[str, tuple[float, float]]:
    """Per laser, the median (found − predicted) offset (px) of its spots found on their own,
    from (laser, x_found, y_found, x_predicted, y_predicted) rows; lasers with fewer than
    ``min_spots`` rows get none."""
    out: dict[str, tuple[float, float]] = {}
    for name in sorted({p[0] for p in pairs}):
        rows = np.array([p[1:] for p in pairs if p[0] == name], dtype=np.float64)
        if len(rows) >= min_spots:
            d = np.median(rows[:, :2] - rows[:, 2:], axis=0)
            out[name] = (float(d[0]), float(d[1]))
    return out
