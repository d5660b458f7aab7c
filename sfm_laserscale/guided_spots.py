"""Where the model puts a laser's spot: the calibrated beam met with the mesh at a known scale.

A spot the detector missed on its own (pale clutter, green water, a strobe's hot spot: the
band holds scene blobs as strong as the spot) lies at one point of its band once the scale is
known: the beam (metres, camera frame) is where the laser's light travels; divided by the scale
s (metres per model unit) and put in the model frame with the registered pose, it meets the
mesh at the spot. :func:`predict_spots` finds that point for every calibrated laser of an image
with camera rays only — the rays through the beam's image polyline (:func:`beam_rays`), which
do not depend on the scale, so the mesh crop made before the scale is known covers them: along
the polyline, the beam point at vertex k is |X_k| metres from the camera and the mesh
λ_k model units along the same ray; the spot is where |X_k| / s − λ_k changes sign (the beam
passes from in front of the floor to behind it), interpolated between the two vertices.

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

from sfm_laserscale.detection.beams import beam_samples
from sfm_laserscale.detection.guided import GuidedOptions
from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.raycast import MeshRaycaster, pixel_rays
from sfm_laserscale.rig import Laser, Rig

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GuidedSpotOptions:
    """Options of the model-guided search for spots the detector missed (``scale``).

    - ``enabled``: search at all.
    - ``samples``: vertices of each beam's polyline between the detection range's ends.
    - ``min_offset_spots``: spots of one laser found on their own needed to correct its
      predictions by their median offset (fewer: no correction).
    - ``search``: the search around each prediction (:class:`GuidedOptions`).
    """

    enabled: bool = True
    samples: int = 400
    min_offset_spots: int = 2
    search: GuidedOptions = field(default_factory=GuidedOptions)

    def __post_init__(self) -> None:
        if self.samples < 2:
            raise InputError(f"guided samples must be >= 2, got {self.samples}")
        if self.min_offset_spots < 1:
            raise InputError(f"min_offset_spots must be >= 1, got {self.min_offset_spots}")


@dataclass(frozen=True)
class BeamRays:
    """A beam's image polyline as camera rays: (K, 2) pixels, (K, 3) world origins and unit
    directions, and (K,) the beam point's distance from the camera centre (metres)."""

    pixels: F64
    origins: F64
    directions: F64
    distance_m: F64


def beam_rays(camera: Camera, cam_from_world: Pose, laser: Laser, min_range_m: float,
              max_range_m: float, samples: int) -> BeamRays:
    """The camera rays through a calibrated beam's polyline (K = 0 when the beam is unseen)."""
    xy, ranges = beam_samples(camera, laser, min_range_m, max_range_m, samples)
    if len(xy) == 0 or laser.origin is None or laser.direction is None:
        empty = np.zeros((0, 3))
        return BeamRays(np.zeros((0, 2)), empty, empty, np.zeros(0))
    points_m = laser.origin[None, :] + ranges[:, None] * laser.direction[None, :]
    origins, dirs = pixel_rays(camera, cam_from_world.inverse(), xy)
    return BeamRays(xy, origins, dirs, np.linalg.norm(points_m, axis=1))


def spot_on_polyline(rays: BeamRays, mesh_distance: F64, scale: float
                     ) -> tuple[float, float] | None:
    """The pixel where the beam meets the mesh: the first sign change, nearest range first, of
    |X_k| / scale − λ_k (NaN λ: no mesh there), interpolated linearly; None if it never does."""
    gap = rays.distance_m / scale - mesh_distance  # (K,) model units; < 0: in front of the mesh
    order = np.argsort(rays.distance_m)
    for a, b in zip(order[:-1], order[1:], strict=True):
        ga, gb = gap[a], gap[b]
        if np.isfinite(ga) and np.isfinite(gb) and ga < 0 <= gb:
            t = ga / (ga - gb)
            xy = (1 - t) * rays.pixels[a] + t * rays.pixels[b]
            return float(xy[0]), float(xy[1])
    return None


def predict_spots(camera: Camera, cam_from_world: Pose, rig: Rig, names: Iterable[str],
                  caster: MeshRaycaster, scale: float, ranges_m: tuple[float, float],
                  options: GuidedSpotOptions,
                  offsets: dict[str, tuple[float, float]] | None = None
                  ) -> tuple[dict[str, tuple[float, float]], dict[str, str]]:
    """Predicted spot (COLMAP px) of each named calibrated laser at ``scale`` (metres per model
    unit), plus its rig offset (``offsets``); and why a laser has none."""
    predicted: dict[str, tuple[float, float]] = {}
    why: dict[str, str] = {}
    for name in names:
        laser = rig.laser(name)
        if not laser.calibrated:
            why[name] = "not calibrated (no beam to meet the mesh with)"
            continue
        rays = beam_rays(camera, cam_from_world, laser, *ranges_m, options.samples)
        if len(rays.pixels) < 2:
            why[name] = "its beam is not seen in the image"
            continue
        try:
            hit = caster.cast(rays.origins, rays.directions)
        except RuntimeError:
            why[name] = "its beam's rays lie outside the mesh crop"
            continue
        xy = spot_on_polyline(rays, hit.distance, scale)
        if xy is None:
            why[name] = "its beam does not meet the mesh in the image"
            continue
        dx, dy = (offsets or {}).get(name, (0.0, 0.0))
        predicted[name] = (xy[0] + dx, xy[1] + dy)
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
