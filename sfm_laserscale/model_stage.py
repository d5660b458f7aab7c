"""The ``scale`` run's stage for the reconstruction's own error (docs/DESIGN.md §4): the model
intrinsics' field around the registered laser images, each observation's mesh check and model
directions, and the model checks after fusion. Glue between registration/covariance.py,
mesh_error.py and model_checks.py for commands/scale.py; no maths of its own."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.fusion import FusedScale
from sfm_laserscale.mesh_error import (
    SharedOffset,
    SpotMeshError,
    check_rays,
    local_sigma,
    mesh_check,
    neighbours,
    shared_offset,
)
from sfm_laserscale.model import Camera, Pose, SparseModel
from sfm_laserscale.model_checks import ModelChecks, run_model_checks
from sfm_laserscale.model_error import ModelDirection, mesh_offset_direction
from sfm_laserscale.raycast import MeshRaycaster, SpotHit, cast_spots
from sfm_laserscale.registration.covariance import IntrinsicsField, analyse_intrinsics
from sfm_laserscale.run_types import ImageRun, ScaleOptions

F64 = NDArray[np.float64]


def registered_view(run: ImageRun) -> tuple[Camera, Pose] | None:
    """Camera and cam_from_world of a registered image (whatever became of its spots)."""
    reg = run.registration
    if run.camera is None or reg is None or not reg.success or reg.cam_from_world is None:
        return None
    return run.camera, reg.cam_from_world


def mesh_check_rays(run: ImageRun, options: ScaleOptions) -> tuple[F64, F64]:
    """The rays camera -> model points around the spots that the mesh check will cast (the
    mesh crop must cover them)."""
    view, reg = registered_view(run), run.registration
    if not options.mesh_error.enabled or view is None or reg is None or not run.spots:
        return np.zeros((0, 3)), np.zeros((0, 3))
    xy = np.array([[s.x, s.y] for s in run.spots], dtype=np.float64)
    return check_rays(view[1], reg.inlier_xyz,
                      neighbours(xy, reg.inlier_xy_px, view[0], options.mesh_error))


def intrinsics_field(read_model: Callable[[], SparseModel], runs: Sequence[ImageRun],
                     options: ScaleOptions) -> IntrinsicsField | None:
    """The model intrinsics' error around the registered laser images' inlier points;
    ``read_model`` gives the model again with its observations (the run dropped them after the
    index): read from its file, or the one given in memory."""
    ids = [r.registration.inlier_point3D_ids for r in runs
           if r.reason is None and r.registration is not None and registered_view(r) is not None]
    if not ids:
        return None
    return analyse_intrinsics(read_model, np.concatenate(ids),
                              options.intrinsics)


@dataclass(frozen=True)
class ModelInputs:
    """One observation's model-error inputs (uncertainty.ImageObservation's fields)."""

    mesh_sigma: F64 | None = None
    mesh_correlation: F64 | None = None
    directions: tuple[ModelDirection, ...] = ()
    mesh_errors: tuple[SpotMeshError, ...] = ()


def _check(run: ImageRun, hits: tuple[SpotHit, ...], caster: MeshRaycaster,
           field: IntrinsicsField | None, options: ScaleOptions) -> tuple[Camera, Pose, Any]:
    """The mesh check of one registered image's hits."""
    view, reg = registered_view(run), run.registration
    if view is None or reg is None:
        raise ValueError(f"image {run.name}: the mesh check needs a registered image")
    camera, pose = view
    rays = reg.inlier_xyz - pose.center
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-300)
    point_sigma = (np.zeros(len(rays)) if field is None
                   else field.point_sigma_along(reg.inlier_point3D_ids, rays))
    return camera, pose, mesh_check(caster, camera, pose, hits, reg.inlier_xy_px, reg.inlier_xyz,
                                    point_sigma, options.mesh_error)


def shared_mesh_offset(runs: Sequence[ImageRun], caster: MeshRaycaster,
                       field: IntrinsicsField | None, options: ScaleOptions) -> SharedOffset:
    """The mesh's offset from its points common to every spot of the run (a first pass of the
    mesh check over the registered images: mesh_error.shared_offset)."""
    spots: list[SpotMeshError] = []
    for r in runs:
        view = registered_view(r)
        if r.reason is not None or view is None or not r.spots or not options.mesh_error.enabled:
            continue
        cast = cast_spots(r.spots, view[0], view[1], caster, options.spot_cast)
        if cast.hits:
            spots += _check(r, cast.hits, caster, field, options)[2].spots
    return shared_offset(spots)


def model_inputs(run: ImageRun, hits: tuple[SpotHit, ...], caster: MeshRaycaster,
                 field: IntrinsicsField | None, options: ScaleOptions,
                 shared: SharedOffset | None = None) -> ModelInputs:
    """Each hit's mesh σ (with its check; the ``shared`` offset apart, as a direction common to
    every image) and the model intrinsics' directions of one image."""
    view, reg = registered_view(run), run.registration
    if view is None or reg is None:
        return ModelInputs()
    hit_xyz = np.array([h.hit_world for h in hits], dtype=np.float64).reshape(-1, 3)
    camera, pose, check = _check(run, hits, caster, field, options)
    directions = () if field is None else field.directions(
        camera, pose, reg.inlier_xy_px, reg.inlier_xyz, hit_xyz)
    if shared is not None and shared.sigma > 0:
        rays = hit_xyz - pose.center
        rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-300)
        directions = (*directions, mesh_offset_direction(shared.sigma, rays))
    sigma = np.array([local_sigma(c, shared) for c in check.spots])
    return ModelInputs(sigma, check.correlation, directions, check.spots)


def focal_sigma(runs: Sequence[ImageRun], field: IntrinsicsField | None) -> float:
    """σ(δf / f) of the laser images' camera in the model (NaN when not analysed)."""
    if field is None:
        return float("nan")
    ids = [r.camera.camera_id for r in runs if r.estimates is not None and r.camera is not None]
    cam = field.cameras.get(max(set(ids), key=ids.count)) if ids else None
    return float("nan") if cam is None else cam.focal_sigma


def check_model(headline: FusedScale, methods: dict[str, FusedScale], joint: bool,
                runs: Sequence[ImageRun], model: SparseModel, field: IntrinsicsField | None,
                options: ScaleOptions
                ) -> tuple[FusedScale, dict[str, FusedScale], ModelChecks | None]:
    """The model checks: the headline (its σ widened where the data show a larger focal error
    than the model's own σ), every method with the focal-corrected scale added, the checks."""
    if not options.model_checks.enabled or not math.isfinite(headline.value):
        return headline, methods, None
    centres = {r.name: v[1].center for r in runs if (v := registered_view(r)) is not None}
    model_centres = np.array([im.cam_from_world.center for im in model.images.values()])
    checks = run_model_checks([r.estimates for r in runs if r.estimates is not None], methods,
                              headline, joint, centres, model_centres, focal_sigma(runs, field),
                              options.model_checks, options.fusion)
    out = dict(methods)
    if checks.focal.corrected is not None:
        out[checks.focal.corrected.method] = checks.focal.corrected
    out[checks.headline.method] = checks.headline
    return checks.headline, out, checks
