"""The SfM model's own intrinsics error: its bundle-adjustment covariance and the model's response
to a change of the intrinsics (pycolmap), as the laser images see it.

1. A sub-model: the model images sharing most 3D points with the registered laser images
   (``max_images``), their observations and points (tracks of 2+ of those images; the laser
   images' inliers first, then a seeded sample, ``max_points`` in all).
2. Covariance: pycolmap's bundle-adjustment problem of the sub-model with the refined
   intrinsics free (which ones: ``refined``), evaluated as the model is (not re-solved: an
   intrinsic the images do not determine would drift), ``estimate_ba_covariance``'s covariance
   of the camera's parameters (unit pixel noise) scaled by σ̂² = Σ r² / (n_res − n_param),
   expressed in δf / f (all focal parameters together) and the extra (distortion) parameters.
   Where the images do not determine the intrinsics (the covariance is rank deficient, e.g.
   nadir images at one altitude: focal length and altitude trade exactly), or it cannot be
   estimated, ``focal_sigma_prior`` is used (a note says so); ``focal_sigma_floor`` bounds
   σ(δf / f) from below (self-calibration is less accurate than its formal precision).
3. Response: for each parameter, bundle adjustment of the sub-model with the intrinsics held at
   ±σ of it (poses and points free); each solution is aligned to the model by a similarity fitted
   to the points (so a change of the model's overall scale is part of the truth, not of the
   error), and the points' displacement per unit of the parameter is kept.
4. Per laser image (:meth:`IntrinsicsField.directions`): its inlier points displaced, its pose
   re-estimated to first order (Gauss–Newton step of its own reprojection residuals, Cauchy
   weights as in the registration), its hits displaced like the model points around them
   (inverse-distance weights of the ``neighbours`` nearest), its camera changed: one
   :class:`~sfm_laserscale.model_error.ModelDirection` per unit-σ direction of the covariance
   (Cholesky factor) and one per unit δf / f (the focal sensitivity).

Measurements and the reasoning behind the defaults: docs/DESIGN.md §4.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import pycolmap
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from sfm_laserscale.geometry import umeyama_sim3
from sfm_laserscale.model import INVALID_POINT3D_ID, Camera, Pose, SparseModel
from sfm_laserscale.model_error import FOCAL, ModelDirection, combine_directions
from sfm_laserscale.registration.pose import _jacobian as pose_jacobian

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class IntrinsicsOptions:
    """Options of :func:`analyse_intrinsics`."""

    enabled: bool = True
    refined: tuple[str, ...] = ("focal", "extra")  # what the SfM refined: focal, extra, principal
    max_images: int = 40  # sub-model size (model images sharing most points with laser images)
    max_points: int = 20000  # sub-model points: the laser images' inliers first, then a sample
    min_images: int = 3  # fewer model images: no covariance (the prior is used)
    # lower bound of σ(δf / f): self-calibration's accuracy beyond its formal precision
    # (unmodelled effects; held-out real scenes: focal errors up to 0.14 %, RMS 0.07 %)
    focal_sigma_floor: float = 1e-3
    focal_sigma_prior: float = 1e-3  # σ(δf / f) where the covariance cannot be estimated
    neighbours: int = 12  # model points interpolating a hit's displacement
    loss_scale_px: float = 1.0  # Cauchy scale of the laser image's pose update (as registration)
    ba_max_iterations: int = 100


@dataclass(frozen=True)
class CameraIntrinsics:
    """One camera's intrinsics error: its parameters (δf / f first), covariance and the sub-model
    points' displacement per unit of each parameter."""

    camera_id: int
    names: tuple[str, ...]  # "focal" (δf / f), then "param<i>" for raw camera.params[i]
    dparams: F64  # (n, P) d camera.params per unit of each parameter
    covariance: F64  # (n, n)
    displacement: F64  # (n, M, 3) model units per unit parameter, aligned to the model
    from_covariance: bool  # False: the prior σ(δf / f) (no covariance could be estimated)

    @property
    def focal_sigma(self) -> float:
        """σ(δf / f)."""
        return float(np.sqrt(self.covariance[0, 0]))

    def sigma(self, k: int) -> float:
        """σ of parameter k."""
        return float(np.sqrt(max(float(self.covariance[k, k]), 0.0)))


@dataclass(frozen=True)
class IntrinsicsField:
    """The model's intrinsics error as the laser images see it (per camera)."""

    cameras: dict[int, CameraIntrinsics]
    points_xyz: F64  # (M, 3) the sub-model's points (model units)
    point_ids: NDArray[np.uint64]  # (M,)
    point_cov: dict[int, F64]  # point id -> (3, 3) covariance (σ̂²-scaled), model units²
    sigma_px: float  # σ̂ of the sub-model's reprojection residuals
    n_images: int
    notes: tuple[str, ...] = ()
    options: IntrinsicsOptions = field(default_factory=IntrinsicsOptions)

    def directions(self, camera: Camera, pose: Pose, inlier_xy: F64, inlier_xyz: F64,
                   hits_world: F64) -> tuple[ModelDirection, ...]:
        """The model directions of one laser image (empty for a camera not analysed)."""
        cam = self.cameras.get(camera.camera_id)
        if cam is None or len(inlier_xyz) < 6:
            return ()
        tree = cKDTree(self.points_xyz)
        raw = [self._raw(cam, k, tree, camera, pose, inlier_xy, inlier_xyz, hits_world)
               for k in range(len(cam.names))]
        chol = _factor(cam.covariance)
        out = [combine_directions(f"camera{cam.camera_id}.intrinsics{j + 1}",
                                  [(float(chol[k, j]), raw[k]) for k in range(len(raw))], True)
               for j in range(chol.shape[1])]
        out.append(ModelDirection(f"camera{cam.camera_id}.{FOCAL}", raw[0].camera_params,
                                  raw[0].pose, raw[0].hits_world, False))
        return tuple(out)

    def _raw(self, cam: CameraIntrinsics, k: int, tree: cKDTree, camera: Camera, pose: Pose,
             inlier_xy: F64, inlier_xyz: F64, hits_world: F64) -> ModelDirection:
        """Per unit of parameter k: camera, first-order pose and hit changes."""
        disp = cam.displacement[k]
        d_in = _interpolate(tree, disp, inlier_xyz, self.options.neighbours)
        d_hit = _interpolate(tree, disp, np.asarray(hits_world).reshape(-1, 3),
                             self.options.neighbours)
        d_pose = _pose_response(camera, pose, inlier_xy, inlier_xyz, d_in, cam.dparams[k],
                                self.options.loss_scale_px)
        return ModelDirection(cam.names[k], cam.dparams[k], d_pose, d_hit, False)

    def point_sigma_along(self, point_ids: NDArray[np.uint64], rays: F64) -> F64:
        """(N,) σ of points along unit rays (N, 3) (0 for points without a covariance)."""
        out = np.zeros(len(point_ids))
        for i, pid in enumerate(point_ids):
            cov = self.point_cov.get(int(pid))
            if cov is not None:
                out[i] = float(np.sqrt(max(float(rays[i] @ cov @ rays[i]), 0.0)))
        return out


def _factor(cov: F64) -> F64:
    """(n, m) square root L L ᵀ = cov (eigen-decomposition; zero directions dropped)."""
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    keep = vals > 1e-30
    return np.asarray(vecs[:, keep] * np.sqrt(vals[keep]), dtype=np.float64)


def _interpolate(tree: cKDTree, values: F64, xyz: F64, k: int) -> F64:
    """(N, 3) inverse-distance weighted values of the k nearest tree points at xyz (N, 3)."""
    if len(xyz) == 0:
        return np.zeros((0, 3))
    k = min(k, tree.n)
    dist, idx = tree.query(xyz, k=k)
    dist, idx = dist.reshape(len(xyz), k), idx.reshape(len(xyz), k)
    w = 1.0 / np.maximum(dist, 1e-12 * (1.0 + dist.max()))
    w /= w.sum(axis=1, keepdims=True)
    return np.asarray(np.einsum("nk,nkj->nj", w, values[idx]), dtype=np.float64)


def _pose_response(camera: Camera, pose: Pose, xy: F64, xyz: F64, dxyz: F64, dparams: F64,
                   loss_scale: float) -> F64:
    """(6,) first-order change of the pose minimising the image's (Cauchy-weighted) reprojection
    residuals when its points move by dxyz and its camera parameters by dparams."""
    res = camera.project(pose.transform(xyz)) - xy
    r2 = np.sum(res**2, axis=1)
    w = np.repeat(1.0 / (1.0 + r2 / loss_scale**2), 2)
    jac = pose_jacobian(pose, camera, xyz, False)  # (2N, 6)
    h = 1e-3
    cam_p = Camera(camera.camera_id, camera.model, camera.width, camera.height,
                   camera.params + h * dparams)
    cam_m = Camera(camera.camera_id, camera.model, camera.width, camera.height,
                   camera.params - h * dparams)
    dr = ((cam_p.project(pose.transform(xyz + h * dxyz))
           - cam_m.project(pose.transform(xyz - h * dxyz))) / (2 * h)).ravel()
    jw = jac * w[:, None]
    return np.asarray(-np.linalg.lstsq(jw.T @ jac, jw.T @ dr, rcond=None)[0], dtype=np.float64)


# --------------------------------------------------------------------------- the sub-model


def select_images(model: SparseModel, point_ids: NDArray[np.uint64], max_images: int
                  ) -> list[int]:
    """Model images sharing most of these 3D points (the laser images' inliers), best first."""
    wanted = np.unique(np.asarray(point_ids, dtype=np.uint64))
    counts = []
    for im in model.images.values():
        n = int(np.isin(im.point3D_ids, wanted).sum()) if len(im.point3D_ids) else 0
        if n:
            counts.append((n, im.image_id))
    counts.sort(key=lambda c: (-c[0], c[1]))
    return [iid for _, iid in counts[:max_images]]


def _tracks(model: SparseModel, image_ids: Sequence[int]
            ) -> tuple[NDArray[np.uint64], NDArray[np.int64], NDArray[np.int64], NDArray[np.intp]]:
    """Every observation of the images with a 3D point, sorted by point: (point id, image id,
    observation index) and the start of each point's run."""
    pid, iid, obs = [], [], []
    for i in image_ids:
        im = model.images[i]
        j = np.flatnonzero(im.point3D_ids != INVALID_POINT3D_ID)
        pid.append(im.point3D_ids[j])
        iid.append(np.full(len(j), i, dtype=np.int64))
        obs.append(j.astype(np.int64))
    p = np.concatenate(pid).astype(np.uint64) if pid else np.zeros(0, np.uint64)
    a = np.concatenate(iid).astype(np.int64) if iid else np.zeros(0, np.int64)
    o = np.concatenate(obs).astype(np.int64) if obs else np.zeros(0, np.int64)
    order = np.argsort(p, kind="stable")
    p, a, o = p[order], a[order], o[order]
    starts = (np.flatnonzero(np.r_[True, p[1:] != p[:-1]]).astype(np.intp) if len(p)
              else np.zeros(0, np.intp))
    return p, a, o, starts


def _chosen(p: NDArray[np.uint64], starts: NDArray[np.intp], wanted: NDArray[np.uint64],
            max_points: int, rng: np.random.Generator) -> NDArray[np.intp]:
    """Runs (indices into ``starts``) of points seen twice or more: the wanted ones first, then
    a seeded sample of the others, ``max_points`` in all."""
    counts = np.diff(np.r_[starts, len(p)])
    ok = np.flatnonzero(counts >= 2)
    first = ok[np.isin(p[starts[ok]], wanted)]
    rest = ok[~np.isin(p[starts[ok]], wanted)]
    room = max(max_points - len(first), 0)
    if len(rest) > room:
        rest = np.sort(rng.choice(rest, room, replace=False))
    return np.sort(np.concatenate([first[:max_points], rest]))


def build_reconstruction(model: SparseModel, image_ids: Sequence[int],
                         wanted: NDArray[np.uint64] | None = None, max_points: int = 20000,
                         seed: int = 0) -> tuple[pycolmap.Reconstruction, dict[int, int]]:
    """The sub-model as a pycolmap reconstruction and reconstruction point id -> model point id:
    points observed by 2+ of the images, the ``wanted`` ones first, at most ``max_points``."""
    rec = pycolmap.Reconstruction()
    for cid in sorted({model.images[i].camera_id for i in image_ids}):
        rec.add_camera_with_trivial_rig(model.cameras[cid].to_pycolmap())
    for iid in image_ids:
        im = model.images[iid]
        pts = pycolmap.Point2DList([pycolmap.Point2D(xy) for xy in im.xy_px])
        img = pycolmap.Image(name=im.name, points2D=pts, camera_id=im.camera_id, image_id=iid)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(im.cam_from_world.R), im.cam_from_world.t)
        rec.add_image_with_trivial_frame(img, pose)
    p, a, o, starts = _tracks(model, image_ids)
    want = np.zeros(0, np.uint64) if wanted is None else np.asarray(wanted, np.uint64)
    runs = _chosen(p, starts, want, max_points, np.random.default_rng(seed))
    ends = np.r_[starts[1:], len(p)]
    rows = model.point_index
    ids: dict[int, int] = {}
    for r in runs:
        pid = int(p[starts[r]])
        if pid not in rows:
            continue
        track = pycolmap.Track()
        for k in range(starts[r], ends[r]):
            track.add_element(int(a[k]), int(o[k]))
        ids[rec.add_point3D(model.points_xyz[rows[pid]], track)] = pid
    return rec, ids


def _variable_idxs(camera: pycolmap.Camera, refined: tuple[str, ...]) -> list[int]:
    """Indices of camera.params the bundle adjustment refines."""
    idx = list(camera.focal_length_idxs()) if "focal" in refined else []
    idx += list(camera.extra_params_idxs()) if "extra" in refined else []
    idx += list(camera.principal_point_idxs()) if "principal" in refined else []
    return sorted(int(i) for i in idx)


def _ba_options(refined: tuple[str, ...], fixed: bool, max_iterations: int
                ) -> pycolmap.BundleAdjustmentOptions:
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = not fixed and "focal" in refined
    opts.refine_extra_params = not fixed and "extra" in refined
    opts.refine_principal_point = not fixed and "principal" in refined
    opts.print_summary = False
    opts.ceres.solver_options.max_num_iterations = max(int(max_iterations), 0)
    opts.ceres.solver_options.function_tolerance = 1e-12
    opts.ceres.solver_options.gradient_tolerance = 1e-12
    opts.ceres.solver_options.parameter_tolerance = 1e-12
    opts.ceres.solver_options.num_threads = 1
    return opts


def _adjuster(rec: pycolmap.Reconstruction, options: pycolmap.BundleAdjustmentOptions,
              constant_cameras: Sequence[int] = ()) -> pycolmap.CeresBundleAdjuster:
    config = pycolmap.BundleAdjustmentConfig()
    for iid in rec.reg_image_ids():
        config.add_image(iid)
    for cid in constant_cameras:
        config.set_constant_cam_intrinsics(cid)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    return pycolmap.create_default_ceres_bundle_adjuster(options, config, rec)


def _points(rec: pycolmap.Reconstruction, order: Sequence[int]) -> F64:
    return np.array([rec.points3D[i].xyz for i in order], dtype=np.float64).reshape(-1, 3)


@dataclass(frozen=True)
class _Adjusted:
    """The sub-model as given, and what its covariance gave."""

    rec: pycolmap.Reconstruction
    sigma_px: float
    cov: pycolmap.BACovariance | None


def _adjust(rec: pycolmap.Reconstruction, options: IntrinsicsOptions) -> _Adjusted:
    """The bundle-adjustment problem with the refined intrinsics free, evaluated where the model
    is (no iteration: the SfM left it at its optimum, and an unobservable intrinsic would drift):
    covariance and σ̂ of the residuals."""
    ba = _adjuster(rec, _ba_options(options.refined, False, 0))
    summary = ba.solve()
    ceres = summary.ceres_summary
    dof = int(ceres.num_residuals) - int(ceres.num_effective_parameters)
    sigma = float(np.sqrt(2.0 * ceres.final_cost / dof)) if dof > 0 else float("nan")
    cov_opts = pycolmap.BACovarianceOptions()
    try:
        cov = pycolmap.estimate_ba_covariance(cov_opts, rec, ba)
    except (RuntimeError, ValueError) as exc:  # pycolmap raises on a degenerate problem
        logger.info("BA covariance failed: %s", exc)
        cov = None
    return _Adjusted(rec, sigma, cov)


def _parametrisation(camera: pycolmap.Camera, refined: tuple[str, ...]
                     ) -> tuple[tuple[str, ...], F64, F64]:
    """Our parameters (δf / f, then raw variable non-focal ones): names, (n, P) d params per unit
    and (n, V) d parameter / d variable camera param (V = refined params in index order)."""
    params = np.asarray(camera.params, dtype=np.float64)
    var = _variable_idxs(camera, refined)
    focal = [int(i) for i in camera.focal_length_idxs()]
    others = [i for i in var if i not in focal]
    names = ("focal", *(f"param{i}" for i in others))
    dparams = np.zeros((len(names), len(params)))
    dparams[0, focal] = params[focal]
    to_ours = np.zeros((len(names), len(var)))
    f0 = float(np.mean(params[focal]))
    for j, i in enumerate(var):
        if i in focal:
            to_ours[0, j] = 1.0 / (len(focal) * f0)
    for k, i in enumerate(others, start=1):
        dparams[k, i] = 1.0
        to_ours[k, var.index(i)] = 1.0
    return names, dparams, to_ours


def _camera_covariance(adj: _Adjusted, cid: int, options: IntrinsicsOptions
                       ) -> tuple[tuple[str, ...], F64, F64, bool]:
    """Names, d params, covariance in our parametrisation, and whether it is the BA's."""
    cam = adj.rec.cameras[cid]
    names, dparams, to_ours = _parametrisation(cam, options.refined)
    raw = None if adj.cov is None else adj.cov.get_other_params_cov(cam.params)
    ok = (raw is not None and np.isfinite(adj.sigma_px)
          and np.shape(raw) == (to_ours.shape[1], to_ours.shape[1])
          and bool(np.all(np.isfinite(raw))))
    if ok:
        cov = adj.sigma_px**2 * to_ours @ np.asarray(raw) @ to_ours.T
    else:
        names, dparams = names[:1], dparams[:1]
        cov = np.array([[options.focal_sigma_prior**2]])
    cov = 0.5 * (cov + cov.T)
    if cov[0, 0] < options.focal_sigma_floor**2:
        cov[0, 0] = options.focal_sigma_floor**2
    return names, dparams, cov, bool(ok)


def _response(rec: pycolmap.Reconstruction, cid: int, dparams: F64, h: float, order: list[int],
              nominal: F64, options: IntrinsicsOptions) -> F64:
    """(M, 3) displacement of the points per unit parameter: BA with the intrinsics held at
    ±h along dparams, each aligned to ``nominal`` by a similarity, central difference."""
    out = []
    for sign in (1.0, -1.0):
        r = pycolmap.Reconstruction(rec)
        cam = r.cameras[cid]
        cam.params = np.asarray(cam.params, dtype=np.float64) + sign * h * dparams
        _adjuster(r, _ba_options(options.refined, True, options.ba_max_iterations),
                  [cid]).solve()
        pts = _points(r, order)
        s, R, t = umeyama_sim3(pts, nominal)
        out.append(s * pts @ R.T + t)
    return np.asarray((out[0] - out[1]) / (2 * h), dtype=np.float64)


def _point_covariances(adj: _Adjusted, ids: dict[int, int], wanted: set[int]) -> dict[int, F64]:
    """Model point id -> σ̂²-scaled (3, 3) covariance, for the wanted points of the sub-model."""
    out: dict[int, F64] = {}
    if adj.cov is None or not np.isfinite(adj.sigma_px):
        return out
    for rid, pid in ids.items():
        if pid in wanted:
            c = adj.cov.get_point_cov(rid)
            if c is not None and np.shape(c) == (3, 3):
                out[pid] = adj.sigma_px**2 * np.asarray(c, dtype=np.float64)
    return out


def analyse_intrinsics(load_model: Callable[[], SparseModel], laser_point_ids: NDArray[np.uint64],
                       options: IntrinsicsOptions) -> IntrinsicsField | None:
    """The model's intrinsics error around the laser images' inlier points (None: disabled, or
    no model image shares their points)."""
    if not options.enabled or len(laser_point_ids) == 0:
        return None
    model = load_model()
    image_ids = select_images(model, laser_point_ids, options.max_images)
    if len(image_ids) < 2:
        return None
    rec, ids = build_reconstruction(model, image_ids, laser_point_ids, options.max_points)
    del model
    if len(ids) < 10:
        return None
    adj = _adjust(rec, options)
    order = sorted(ids)
    nominal = _points(adj.rec, order)
    notes: list[str] = []
    cameras = {}
    for cid in sorted(adj.rec.cameras):
        names, dparams, cov, ok = _camera_covariance(adj, cid, options)
        if not ok or len(image_ids) < options.min_images:
            notes.append(f"camera {cid}: no bundle-adjustment covariance of its intrinsics; "
                         f"prior sigma(df/f) {options.focal_sigma_prior:.3g} used")
        steps = [max(float(np.sqrt(cov[k, k])), 1e-6) for k in range(len(names))]
        disp = np.array([_response(adj.rec, cid, dparams[k], steps[k], order, nominal, options)
                         for k in range(len(names))])
        cameras[cid] = CameraIntrinsics(cid, names, dparams, cov, disp, ok)
        logger.info("camera %d intrinsics: sigma(df/f) %.3g %% from %d model images%s", cid,
                    100 * cameras[cid].focal_sigma, len(image_ids), "" if ok else " (prior)")
    wanted = {int(p) for p in np.asarray(laser_point_ids).tolist()}
    return IntrinsicsField(cameras, nominal, np.array([ids[i] for i in order], dtype=np.uint64),
                           _point_covariances(adj, ids, wanted), adj.sigma_px, len(image_ids),
                           tuple(notes), options)
