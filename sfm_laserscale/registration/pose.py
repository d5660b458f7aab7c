"""Absolute pose of a query image from its 2D–3D matches: pycolmap's LO-RANSAC P3P and
refinement, our acceptance rule and our pose covariance (docs/REGISTRATION.md);
``register_image`` chains matching and pose.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import pycolmap
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import (
    INVALID_POINT3D_ID,
    Camera,
    Image,
    ImageFeatures,
    Pose,
    SparseModel,
)
from sfm_laserscale.registration.index import DescriptorIndex
from sfm_laserscale.registration.match import Matches, match_to_model
from sfm_laserscale.registration.options import PoseOptions, RegistrationOptions

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class PoseResult:
    """Absolute pose, its covariance (docs/REGISTRATION.md) and the acceptance verdict."""

    success: bool
    reason: str | None
    cam_from_world: Pose | None  # None unless success (never a guessed pose)
    covariance: F64 | None  # (6, 6) over (ω, δt), scaled by sigma_px²; None unless success
    num_matches: int
    num_inliers: int
    inlier_mask: NDArray[np.bool_]  # (num_matches,)
    reproj_error_px: float  # RMS of the 2D residual norm over the inliers (nan if no pose)
    sigma_px: float  # σ̂ = sqrt(Σ‖r‖² / (2n − 6)), per-axis (nan if no pose)
    camera: Camera  # the input camera, or with the refined focal length


@dataclass(frozen=True)
class RegistrationResult:
    """Everything the report needs about one registered (or rejected) image."""

    matches: Matches
    pose: PoseResult
    inlier_xy_px: F64  # (K, 2) query keypoints of the inliers, COLMAP pixels
    inlier_xyz: F64  # (K, 3) their 3D points, model units
    inlier_point3D_ids: NDArray[np.uint64]  # noqa: N815 (COLMAP's name) (K,)
    num_features: int
    match_time_s: float
    pose_time_s: float

    @property
    def success(self) -> bool:
        """True when the pose passed the acceptance rule."""
        return self.pose.success

    @property
    def reason(self) -> str | None:
        """Why registration failed, in plain words (None on success)."""
        return self.pose.reason

    @property
    def num_matches(self) -> int:
        """Number of 2D–3D matches fed to RANSAC."""
        return self.pose.num_matches

    @property
    def num_inliers(self) -> int:
        """Number of RANSAC inliers."""
        return self.pose.num_inliers

    @property
    def reproj_error_px(self) -> float:
        """RMS reprojection error over the inliers, pixels."""
        return self.pose.reproj_error_px

    @property
    def cam_from_world(self) -> Pose | None:
        """The accepted pose, or None."""
        return self.pose.cam_from_world

    @property
    def covariance(self) -> F64 | None:
        """(6, 6) pose covariance over (ω, δt), or None."""
        return self.pose.covariance


def _pycolmap_options(options: PoseOptions) -> tuple[Any, Any]:
    """pycolmap AbsolutePoseEstimation/RefinementOptions from ours."""
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.estimate_focal_length = False
    est.ransac.max_error = float(options.ransac_max_error_px)
    est.ransac.min_inlier_ratio = float(options.ransac_min_inlier_ratio)
    est.ransac.confidence = float(options.ransac_confidence)
    est.ransac.max_num_trials = int(options.ransac_max_num_trials)
    est.ransac.random_seed = -1 if options.seed is None else int(options.seed)
    est.ransac.num_threads = 1
    ref = pycolmap.AbsolutePoseRefinementOptions()
    ref.loss_function_scale = float(options.loss_scale_px)
    ref.refine_focal_length = bool(options.refine_focal_length)
    ref.refine_extra_params = False
    return est, ref


def _run_pycolmap_pose(
    xy: F64, xyz: F64, camera: Camera, options: PoseOptions
) -> tuple[Pose, NDArray[np.bool_], Camera] | None:
    """LO-RANSAC P3P + Cauchy-loss refinement; None when pycolmap finds no pose."""
    est, ref = _pycolmap_options(options)
    cam = camera.to_pycolmap()  # refined in place when the focal length is refined
    try:
        out = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, cam, est, ref)
    except (ValueError, RuntimeError) as exc:  # pycolmap raises on degenerate input
        logger.debug("pycolmap absolute pose raised: %s", exc)
        return None
    if out is None:
        return None
    M = np.asarray(out["cam_from_world"].matrix(), dtype=np.float64)
    refined = Camera(camera.camera_id, camera.model, camera.width, camera.height,
                     np.asarray(cam.params, dtype=np.float64).copy())
    return Pose(M[:, :3].copy(), M[:, 3].copy()), np.asarray(out["inlier_mask"], bool), refined


def _focal_idxs(camera: Camera) -> list[int]:
    """Indices of the focal length parameter(s) in camera.params."""
    return [int(i) for i in camera.to_pycolmap().focal_length_idxs()]


def _projections(pose: Pose, camera: Camera, xyz: F64) -> F64:
    """(N, 2) pixels of world points."""
    return camera.project(pose.transform(xyz))


def _jacobian(pose: Pose, camera: Camera, xyz: F64, with_focal: bool) -> F64:
    """(2N, 6[+f]) d(pixels)/d(ω, δt[, f]) by central differences (any camera model)."""
    depth = float(np.median(np.abs(pose.transform(xyz)[:, 2])))
    cols = []
    for k in range(6):
        h = 1e-6 if k < 3 else 1e-6 * max(depth, 1e-12)
        d = np.zeros(6)
        d[k] = h
        plus = Pose(Rotation.from_rotvec(d[:3]).as_matrix() @ pose.R, pose.t + d[3:])
        minus = Pose(Rotation.from_rotvec(-d[:3]).as_matrix() @ pose.R, pose.t - d[3:])
        diff = _projections(plus, camera, xyz) - _projections(minus, camera, xyz)
        cols.append(diff.ravel() / (2 * h))
    for i in _focal_idxs(camera) if with_focal else []:
        h = 1e-6 * float(camera.params[i])
        p_plus, p_minus = camera.params.copy(), camera.params.copy()
        p_plus[i] += h
        p_minus[i] -= h
        c_plus = Camera(camera.camera_id, camera.model, camera.width, camera.height, p_plus)
        c_minus = Camera(camera.camera_id, camera.model, camera.width, camera.height, p_minus)
        diff = _projections(pose, c_plus, xyz) - _projections(pose, c_minus, xyz)
        cols.append(diff.ravel() / (2 * h))
    return np.column_stack(cols)


def _pose_covariance(
    pose: Pose, camera: Camera, xy: F64, xyz: F64, with_focal: bool
) -> tuple[F64 | None, float, float]:
    """(σ̂²-scaled 6×6 covariance or None if singular, σ̂ px, RMS residual norm px)."""
    res = _projections(pose, camera, xyz) - xy
    n = len(xy)
    J = _jacobian(pose, camera, xyz, with_focal)
    dof = 2 * n - J.shape[1]
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    if dof <= 0:
        return None, float("nan"), rms
    sigma2 = float(np.sum(res**2) / dof)
    JtJ = J.T @ J
    if not np.all(np.isfinite(JtJ)) or np.linalg.cond(JtJ) > 1e14:
        return None, float(np.sqrt(sigma2)), rms
    cov = sigma2 * np.linalg.inv(JtJ)[:6, :6]
    return 0.5 * (cov + cov.T), float(np.sqrt(sigma2)), rms


def _check_pose_inputs(xy: F64, xyz: F64) -> None:
    """Shapes and finiteness of the correspondences."""
    if xy.ndim != 2 or xy.shape[1] != 2 or xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"estimate_pose needs (N, 2) and (N, 3) arrays, got {xy.shape}, "
                         f"{xyz.shape}")
    if len(xy) != len(xyz):
        raise InputError(f"{len(xy)} image points but {len(xyz)} 3D points")
    if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(xyz))):
        raise InputError("non-finite 2D or 3D coordinates")


def _failed(reason: str, n: int, camera: Camera, mask: NDArray[np.bool_] | None = None,
            rms: float = float("nan"), sigma: float = float("nan")) -> PoseResult:
    """A rejected pose: diagnostics kept, no pose, no covariance."""
    mask = np.zeros(n, dtype=bool) if mask is None else mask
    return PoseResult(False, reason, None, None, n, int(mask.sum()), mask, rms, sigma, camera)


def _acceptance_reason(n: int, k: int, rms: float, options: PoseOptions) -> str | None:
    """Our acceptance rule (COLMAP's registrator thresholds); None when accepted."""
    if k < options.min_inliers:
        return f"only {k} inliers of {n} matches (need {options.min_inliers})"
    if k < options.min_inlier_ratio * n:
        return (f"inlier ratio {k / n:.2f} ({k} of {n} matches) below "
                f"{options.min_inlier_ratio:.2f}")
    if not rms <= options.max_reproj_error_px:
        return (f"RMS reprojection error {rms:.2f} px over {k} inliers exceeds "
                f"{options.max_reproj_error_px:.2f} px")
    return None


def estimate_pose(
    xy_px: F64, xyz_model: F64, camera: Camera, options: PoseOptions | RegistrationOptions
) -> PoseResult:
    """cam_from_world from 2D–3D matches: LO-RANSAC P3P + refinement, our acceptance rule."""
    if isinstance(options, RegistrationOptions):
        options = options.pose
    xy = np.ascontiguousarray(xy_px, dtype=np.float64)
    xyz = np.ascontiguousarray(xyz_model, dtype=np.float64)
    _check_pose_inputs(xy, xyz)
    n = len(xy)
    if n < 4:
        return _failed(f"only {n} matches (a pose needs at least 4; acceptance needs "
                       f"{options.min_inliers} inliers)", n, camera)
    found = _run_pycolmap_pose(xy, xyz, camera, options)
    if found is None:
        return _failed(f"RANSAC found no pose consistent with the {n} matches", n, camera)
    pose, mask, cam = found
    with_focal = options.refine_focal_length
    cov, sigma, rms = _pose_covariance(pose, cam, xy[mask], xyz[mask], with_focal)
    reason = _acceptance_reason(n, int(mask.sum()), rms, options)
    if reason is None and cov is None:
        reason = "pose covariance is singular (degenerate inlier geometry)"
    if reason is not None:
        logger.info("pose rejected: %s", reason)
        return _failed(reason, n, cam, mask, rms, sigma)
    return PoseResult(True, None, pose, cov, n, int(mask.sum()), mask, rms, sigma, cam)


def register_image(
    query: ImageFeatures, camera: Camera, index: DescriptorIndex, options: RegistrationOptions
) -> RegistrationResult:
    """Match a query image's features to the model and estimate its pose."""
    xy_all = np.asarray(query.xy_px, dtype=np.float64).reshape(-1, 2)
    if len(xy_all) and (xy_all.min() < -1 or xy_all[:, 0].max() > camera.width + 1
                        or xy_all[:, 1].max() > camera.height + 1):
        raise InputError(f"query keypoints fall outside the camera's {camera.width}×"
                         f"{camera.height} image: wrong camera or resized image?")
    t0 = time.perf_counter()
    matches = match_to_model(query, index, options.match)
    t1 = time.perf_counter()
    xy = xy_all[matches.query_idx]
    xyz = index.points_xyz[matches.point_rows]
    pose = estimate_pose(xy, xyz, camera, options.pose)
    t2 = time.perf_counter()
    m = pose.inlier_mask
    logger.info("registration: %d features, %d matches, %d inliers, %s", len(xy_all),
                len(matches), pose.num_inliers, "accepted" if pose.success else pose.reason)
    return RegistrationResult(
        matches=matches, pose=pose, inlier_xy_px=xy[m], inlier_xyz=xyz[m],
        inlier_point3D_ids=index.point3D_ids[matches.point_rows[m]],
        num_features=len(xy_all), match_time_s=t1 - t0, pose_time_s=t2 - t1,
    )


def model_pose_registration(image: Image, camera: Camera, model: SparseModel,
                            options: RegistrationOptions) -> RegistrationResult:
    """The model's own pose of one of its images (``scale --reuse-model-poses``), as a
    registration: its observations with a 3D point are the inliers, its covariance is ours
    (the same formula as a registered pose's) and the acceptance rule applies as usual."""
    has_point = image.point3D_ids != INVALID_POINT3D_ID
    index = model.point_index
    known = np.array([int(p) in index for p in image.point3D_ids[has_point]], dtype=bool)
    sel = np.flatnonzero(has_point)[known]
    xy = np.asarray(image.xy_px, dtype=np.float64)[sel].reshape(-1, 2)
    ids = image.point3D_ids[sel]
    xyz = model.points_xyz[[index[int(p)] for p in ids]].reshape(-1, 3)
    n, pose = len(sel), image.cam_from_world
    cov, sigma, rms = (_pose_covariance(pose, camera, xy, xyz, False) if n >= 4
                       else (None, float("nan"), float("nan")))
    reason = _acceptance_reason(n, n, rms, options.pose)
    if reason is None and cov is None:
        reason = "pose covariance is singular (degenerate observations)"
    mask = np.ones(n, dtype=bool)
    result = (PoseResult(True, None, pose, cov, n, n, mask, rms, sigma, camera)
              if reason is None else _failed(f"model pose: {reason}", n, camera, mask, rms, sigma))
    matches = Matches(sel.astype(np.int64), np.arange(n, dtype=np.int64),
                      np.zeros(n, dtype=np.float32))
    return RegistrationResult(matches=matches, pose=result, inlier_xy_px=xy, inlier_xyz=xyz,
                              inlier_point3D_ids=ids, num_features=len(image.xy_px),
                              match_time_s=0.0, pose_time_s=0.0)


# --------------------------------------------------------------------------- logging


def configure_colmap_logging(verbose: bool) -> None:
    """Route COLMAP's own (glog) messages: warnings and up normally, everything when verbose."""
    pycolmap.logging.minloglevel = 0 if verbose else 2
    pycolmap.logging.stderrthreshold = 0 if verbose else 2
