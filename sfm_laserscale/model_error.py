"""The reconstruction's own error as inputs of the per-image estimates: how a change of the SfM
model's intrinsics moves one laser image's camera, pose and mesh hits (``ModelDirection``), and
the error budget's terms.

A change δθ of the model's intrinsics (focal length, distortion) changes three things a laser
image's estimate depends on: the camera it is unprojected with, its registered pose (it is
registered against the changed model) and the mesh its spots hit (the mesh follows the model's
points). ``ModelDirection`` holds the derivative of each with respect to one intrinsics
parameter direction, for one laser image; :mod:`sfm_laserscale.registration.covariance`
computes them (bundle adjustment with the intrinsics held at perturbed values), and
``uncertainty.perturbed_observation`` applies one to an observation, so that an estimator's response
is a finite difference of the estimator itself. The directions with ``in_sigma`` are the unit-σ
directions of the intrinsics covariance: common to every image, like the rig calibration, so
fusion adds them after averaging. The ``focal`` direction (per unit relative focal error, not
part of σ) is what the focal-error fit of :mod:`sfm_laserscale.model_checks` uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.model import Camera, Pose

F64 = NDArray[np.float64]

#: The error budget's terms: random per image, then common to every image (docs/DESIGN.md §4).
RANDOM_TERMS = ("spots", "pose", "mesh")
SHARED_TERMS = ("rig", "intrinsics")
#: The Birge-ratio widening of the random part, a budget line of its own when it happens.
SCATTER_TERM = "scatter"
BUDGET_TERMS = (*RANDOM_TERMS, *SHARED_TERMS, SCATTER_TERM)
#: Name suffix of the focal-sensitivity direction (per unit relative focal error; not in σ).
FOCAL = "focal"


@dataclass(frozen=True)
class ModelDirection:
    """How one laser image's inputs move per unit of one intrinsics direction.

    ``in_sigma``: a unit-σ direction of the intrinsics covariance (its response is part of σ);
    otherwise the focal sensitivity (per unit relative focal error, δf / f).
    """

    name: str  # "camera1.intrinsics1" (unit σ) or "camera1.focal" (per unit δf / f)
    camera_params: F64  # (P,) d camera.params
    pose: F64  # (6,) d pose, [rotation (rad), translation (model units)], left perturbation
    hits_world: F64  # (K, 3) d hit positions, model units, in the observation's hit order
    in_sigma: bool = True


#: Name of the shared mesh offset's direction (mesh_error.shared_offset).
MESH_OFFSET = "mesh.offset"


def term_of(param: str) -> str:
    """The budget term of a shared parameter name: ``intrinsics``, ``mesh`` or ``rig``."""
    if param.startswith("camera"):
        return "intrinsics"
    return "mesh" if param.startswith("mesh.") else "rig"


def mesh_offset_direction(sigma: float, rays_world: F64) -> ModelDirection:
    """The shared mesh offset (σ model units) as a direction: every hit moved along its ray."""
    rays = np.asarray(rays_world, dtype=np.float64).reshape(-1, 3)
    return ModelDirection(MESH_OFFSET, np.zeros(0), np.zeros(6), sigma * rays, True)


def perturbed_camera(camera: Camera, dparams: F64, h: float) -> Camera:
    """The camera with ``params + h · dparams`` (an empty dparams: unchanged)."""
    d = np.asarray(dparams, np.float64)
    if d.size == 0:
        return camera
    params = np.asarray(camera.params, dtype=np.float64) + h * d
    return Camera(camera.camera_id, camera.model, camera.width, camera.height, params)


def perturbed_pose(pose: Pose, d6: F64, h: float) -> Pose:
    """Pose moved by h · [δrot, δt] (left perturbation, as uncertainty.perturb_poses)."""
    from scipy.spatial.transform import Rotation

    d = h * np.asarray(d6, dtype=np.float64).reshape(6)
    R = Rotation.from_rotvec(d[:3]).as_matrix() @ pose.R
    return Pose(np.asarray(R, dtype=np.float64), pose.t + d[3:])


def on_ray(camera: Camera, pose: Pose, xy: F64, point: F64, normal: F64) -> F64:
    """(K, 3) world points where the rays through pixels ``xy`` meet the planes (point, normal)."""
    rays_cam = camera.unproject(xy)
    centre = pose.center
    d = rays_cam @ pose.R  # world directions (rows): Rᵀ r
    denom = np.sum(normal * d, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.sum(normal * (point - centre), axis=1) / denom
    return np.asarray(centre + lam[:, None] * d, dtype=np.float64)


def combine_directions(name: str, parts: list[tuple[float, ModelDirection]], in_sigma: bool
                       ) -> ModelDirection:
    """Σ c · direction (first order: the changes of camera, pose and hits add)."""
    c0, d0 = parts[0]
    cam, pose, hits = c0 * d0.camera_params, c0 * d0.pose, c0 * d0.hits_world
    for c, d in parts[1:]:
        cam = cam + c * d.camera_params
        pose = pose + c * d.pose
        hits = hits + c * d.hits_world
    return ModelDirection(name, cam, pose, hits, in_sigma)
