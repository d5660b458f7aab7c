"""Per-image scale estimates (FCM, PCM, Direct 3D) with first-order uncertainty.

Each estimate of one image is a function of all its spot pixels, the 6 pose parameters and the
rig calibration. Perturbing a spot or the pose moves the hit: the perturbed ray is re-intersected
with the mesh's LOCAL TANGENT PLANE at the hit (closed form), which is exact for planar patches
and first-order correct otherwise. The Jacobian is taken by central differences along the
square-root directions of the input covariance (each step ``fd_step_sigma`` = 1 % of that
direction's standard deviation, so steps are relative to each input's own noise and unit-free),
and gives the joint covariance of the image's estimates (they share the pose error).

Inputs and their covariance (blocks are independent):
- spot pixels: σ_px² I per spot (per axis, COLMAP pixel convention);
- pose: ``pose_covariance`` (6×6), ordered [rotation (3, rad), translation (3, model units)],
  LEFT perturbation R' = exp([δ]ₓ) R, t' = t + δt (see :func:`perturb_poses`, the one place
  where this parametrisation lives). With this convention the rotation turns about the WORLD
  origin, so the covariance belongs to the world frame of the model it was estimated in: if
  the model is moved by X' = R_w X + t_w, translate it with δt' = δt + [R R_wᵀ t_w]ₓ δrot;
- mesh (``mesh_sigma``, per hit, model units): the mesh's depth error along the spot's ray
  (:mod:`sfm_laserscale.mesh_error`); the hit moves along its ray;
- rig (per calibrated laser, when the rig gives them): origin offset on the laser plane (x, y,
  ``sigma_origin`` metres each) and beam tilt about its origin (two angles perpendicular to the
  beam, ``sigma_direction`` radians each). FCM depends on them directly; PCM and Direct 3D
  through the change of the two beams' perpendicular separation at the hits (when both lasers
  of the pair are calibrated);
- the model's intrinsics (``model_directions``, :mod:`sfm_laserscale.model_error`): camera,
  pose and hits move together; each direction's response is a central difference of the
  estimators on the perturbed observation.

Rig and intrinsics errors are common to all images; they are kept apart (``rig_jacobian``, named
by ``rig_params``) so that fusion does not average them down. The random covariance is also
given term by term (``covariance_terms``: spots, pose, mesh) for the error budget.

The hits must lie on the spots' rays from ``cam_from_world`` (a warning is logged otherwise);
the normal's orientation does not matter.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from sfm_laserscale.errors import InputError
from sfm_laserscale.methods.baselines import direct3d_scale, direct3d_scale_batch
from sfm_laserscale.methods.fcm import fcm_scale, fcm_scale_batch
from sfm_laserscale.methods.pcm import pcm_scale, pcm_scale_batch
from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.model_error import (
    FOCAL,
    ModelDirection,
    on_ray,
    perturbed_camera,
    perturbed_pose,
)
from sfm_laserscale.raycast import SpotHit
from sfm_laserscale.rig import Rig
from sfm_laserscale.rig_checks import refused_pairs

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
METHODS = ("fcm", "pcm", "direct3d")
RIG_PARAM_SUFFIXES = ("origin_x", "origin_y", "direction_a", "direction_b")


@dataclass(frozen=True)
class ImageObservation:
    """A registered laser image: camera, pose (+ covariance) and its spot hits."""

    image: str
    camera: Camera
    cam_from_world: Pose
    pose_covariance: F64 | None  # (6, 6) [rot (rad), trans (model units)], left perturbation
    hits: tuple[SpotHit, ...]
    mesh_sigma: F64 | None = None  # (K,) mesh depth σ along each hit's ray, model units
    mesh_correlation: F64 | None = None  # (K, K) correlation of the hits' mesh errors (None: I)
    model_directions: tuple[ModelDirection, ...] = ()  # the model intrinsics' directions


@dataclass(frozen=True)
class EstimationOptions:
    """Options of :func:`estimate_image`."""

    include_rig_uncertainty: bool = True
    fd_step_sigma: float = 1e-2  # central-difference step in σ of each input direction
    max_direction_residual_deg: float = 3.0  # FCM residual always accepted below this
    direction_residual_nsigma: float = 5.0  # ... and below this many propagated σ
    min_incidence_cos: float = 0.02  # |cos(ray, normal)| below this: grazing ray, rejected


@dataclass(frozen=True)
class Estimate:
    """One scale estimate (metres per model unit) of one image, laser or pair, and method."""

    image: str
    method: str  # "fcm" | "pcm" | "direct3d"
    laser: str  # laser name, or "L1+L2" for a pair
    scale: float
    sigma: float  # total 1-σ (spots + pose + rig), m per model unit
    direction_residual_deg: float | None  # FCM only: angle between Ô_L and O_L
    depth_m: float  # camera–hit distance in metres (pair: camera–midpoint)
    rejected: bool
    reason: str | None


@dataclass(frozen=True)
class ImageEstimates:
    """All estimates of one image and, per method, their joint covariance (estimate order)."""

    image: str
    estimates: tuple[Estimate, ...]
    covariance: Mapping[str, F64]  # method -> (n_m, n_m) total = random + J_rig J_rigᵀ
    covariance_random: Mapping[str, F64]  # method -> (n_m, n_m) spots + pose (per image)
    rig_jacobian: Mapping[str, F64]  # method -> (n_m, R) d estimate / d unit-σ shared parameter
    rig_params: tuple[str, ...]  # the R shared parameters: "L1.origin_x", "camera1.intrinsics1"
    # method -> term (spots, pose, mesh) -> (n_m, n_m): covariance_random term by term
    covariance_terms: Mapping[str, Mapping[str, F64]] = field(default_factory=dict)
    # method -> (n_m,) d estimate / d (δf / f) of the model's focal length (empty: not computed)
    focal_sensitivity: Mapping[str, F64] = field(default_factory=dict)

    def of(self, method: str) -> tuple[Estimate, ...]:
        """This image's estimates of one method, in covariance order."""
        return tuple(e for e in self.estimates if e.method == method)


def perturb_poses(pose: Pose, deltas: F64) -> tuple[F64, F64]:
    """(B, 6) perturbations [δrot (rad), δt] -> R' = exp([δrot]ₓ) R (B, 3, 3), t' = t + δt (B, 3).

    The ONE place where the pose-covariance parametrisation lives (left rotation perturbation,
    additive translation: COLMAP/ceres EigenQuaternionManifold convention).
    """
    d = np.asarray(deltas, dtype=np.float64).reshape(-1, 6)
    R = Rotation.from_rotvec(d[:, :3]).as_matrix() @ pose.R
    return np.asarray(R, dtype=np.float64), pose.t[None, :] + d[:, 3:]


def perturb_pose(pose: Pose, delta6: F64) -> Pose:
    """Pose perturbed by [δrot (3, rad), δt (3)]: R' = exp([δrot]ₓ) R, t' = t + δt (left)."""
    R, t = perturb_poses(pose, np.asarray(delta6, dtype=np.float64).reshape(1, 6))
    return Pose(R[0], t[0])


def perturbed_observation(obs: ImageObservation, direction: ModelDirection, h: float
                          ) -> ImageObservation:
    """The observation with its model inputs moved by h · ``direction``: camera and pose changed,
    each hit re-intersected along its spot's new ray with its tangent plane moved by h · δhit."""
    camera = perturbed_camera(obs.camera, direction.camera_params, h)
    pose = perturbed_pose(obs.cam_from_world, direction.pose, h)
    if not obs.hits:
        return replace(obs, camera=camera, cam_from_world=pose)
    xy = np.array([np.asarray(x.xy_px, np.float64).reshape(2) for x in obs.hits])
    point = np.array([np.asarray(x.hit_world, np.float64).reshape(3) for x in obs.hits])
    normal = np.array([np.asarray(x.normal_world, np.float64).reshape(3) for x in obs.hits])
    shift = np.asarray(direction.hits_world, dtype=np.float64).reshape(len(obs.hits), 3)
    moved = on_ray(camera, pose, xy, point + h * shift, normal)
    hits = tuple(replace(x, hit_world=moved[k]) for k, x in enumerate(obs.hits))
    return replace(obs, camera=camera, cam_from_world=pose, hits=hits)


def rig_parameter_names(rig: Rig) -> tuple[str, ...]:
    """Names of the rig calibration parameters, 4 per calibrated laser, in rig order."""
    return tuple(f"{las.name}.{s}" for las in rig.lasers if las.calibrated
                 for s in RIG_PARAM_SUFFIXES)


def tilt_basis(v: F64) -> F64:
    """(2, 3) unit vectors perpendicular to the unit beam direction v (deterministic)."""
    x, y, z = (float(c) for c in v)
    n = float(np.hypot(z, x))  # v·c_z > 0.01 (rig validation), so n > 0
    a = (z / n, 0.0, -x / n)  # (0, 1, 0) × v, normalised
    b = (y * a[2], z * a[0] - x * a[2], -y * a[0])  # v × a
    return np.array([a, b], dtype=np.float64)


@dataclass(frozen=True)
class _Beams:
    """The calibrated beams in rig order; beam j owns rig parameters 4j .. 4j+3."""

    names: tuple[str, ...]
    origin: F64  # (nb, 3) metres on z = 0
    direction: F64  # (nb, 3) unit
    tilt: F64  # (nb, 2, 3) basis of the direction perturbation

    def perturbed(self, drig: F64) -> tuple[F64, F64]:
        """(B, nb, 3) origins and unit directions for (B, 4 nb) rig parameter offsets."""
        d = drig.reshape(len(drig), len(self.names), 4)
        origin = np.repeat(self.origin[None], len(drig), axis=0)
        origin[..., :2] += d[..., :2]
        v = self.direction + d[..., 2:3] * self.tilt[:, 0] + d[..., 3:4] * self.tilt[:, 1]
        return origin, v / np.sqrt(np.sum(v * v, axis=-1, keepdims=True))


@dataclass(frozen=True)
class _Layout:
    names: tuple[str, ...]  # laser of each hit
    xy: F64  # (K, 2)
    sigma_px: F64  # (K,)
    hit_world: F64  # (K, 3)
    normal_world: F64  # (K, 3)
    beams: _Beams
    fcm_beam: NDArray[np.intp]  # (nf,) beam of each FCM estimate
    fcm_hit: NDArray[np.intp]  # (nf,) its hit
    pair_names: tuple[str, ...]  # "L1+L2"
    pair_hits: NDArray[np.intp]  # (np, 2)
    pair_beams: NDArray[np.intp]  # (np, 2), −1 for an uncalibrated laser
    pair_sep: F64  # (np,) metres
    rig_sigma: F64  # (4 nb,)
    mesh_sigma: F64  # (K,) model units along each hit's ray
    ray_world: F64  # (K, 3) unit world directions of the spots' rays
    mesh_sqrt: F64  # (K, r) square root of the hits' mesh covariance (model units)

    @property
    def n_out(self) -> int:
        return 2 * len(self.fcm_beam) + 2 * len(self.pair_names)


def _hit_arrays(obs: ImageObservation, rig: Rig) -> tuple[tuple[str, ...], F64, F64, F64, F64]:
    """Validated per-hit arrays (names, xy, σ, hit, unit normal) of an observation."""
    names = tuple(h.laser for h in obs.hits)
    for name in names:
        if name not in rig.names:
            raise InputError(f"image {obs.image}: spot for unknown laser {name!r}")
        if names.count(name) > 1:
            raise InputError(f"image {obs.image}: two spots assigned to laser {name!r}")
    k = len(names)
    xy = np.array([np.asarray(h.xy_px, np.float64).reshape(2) for h in obs.hits]).reshape(k, 2)
    sig = np.array([float(h.sigma_px) for h in obs.hits], dtype=np.float64)
    hw = np.array([np.asarray(h.hit_world, np.float64).reshape(3) for h in obs.hits]).reshape(k, 3)
    nw = np.array([np.asarray(h.normal_world, np.float64).reshape(3) for h in obs.hits])
    nw = nw.reshape(k, 3)
    if np.any(~np.isfinite(sig)) or np.any(sig < 0):
        raise InputError(f"image {obs.image}: spot sigma must be finite and >= 0")
    with np.errstate(divide="ignore", invalid="ignore"):
        nw = nw / np.linalg.norm(nw, axis=1, keepdims=True)
    return names, xy, sig, hw, nw


def _beams(rig: Rig, options: EstimationOptions) -> tuple[_Beams, F64]:
    """The rig's calibrated beams and the σ of their 4 calibration parameters each."""
    cal = [las for las in rig.lasers if las.origin is not None and las.direction is not None]
    on = float(options.include_rig_uncertainty)
    sigma = np.array([[on * x.sigma_origin] * 2 + [on * x.sigma_direction] * 2 for x in cal],
                     dtype=np.float64).reshape(-1)
    beams = _Beams(tuple(x.name for x in cal),
                   np.array([x.origin for x in cal], dtype=np.float64).reshape(-1, 3),
                   np.array([x.direction for x in cal], dtype=np.float64).reshape(-1, 3),
                   np.array([tilt_basis(np.asarray(x.direction)) for x in cal]).reshape(-1, 2, 3))
    return beams, sigma


def mesh_sqrt(obs: ImageObservation, order: list[int] | None = None) -> tuple[F64, F64]:
    """(K,) mesh depth σ of the hits (0 when not given; ``order``: these hits) and (K, r) the
    square root of their covariance diag(σ) R diag(σ), R = ``mesh_correlation`` (I if None)."""
    n = len(obs.hits)
    sig = np.zeros(n) if obs.mesh_sigma is None else np.asarray(obs.mesh_sigma, np.float64)
    corr = np.eye(n) if obs.mesh_correlation is None else np.asarray(obs.mesh_correlation,
                                                                      np.float64)
    if (sig.shape != (n,) or np.any(~np.isfinite(sig)) or np.any(sig < 0)
            or corr.shape != (n, n) or not np.all(np.isfinite(corr))):
        raise InputError(f"image {obs.image}: mesh sigma must be {n} finite values >= 0 (and "
                         f"its correlation a finite {n}×{n} matrix)")
    idx = list(range(n)) if order is None else order
    sig, corr = sig[idx], corr[np.ix_(idx, idx)]
    cov = np.outer(sig, sig) * (0.5 * (corr + corr.T))
    vals, vecs = np.linalg.eigh(cov)
    keep = vals > 1e-12 * max(float(vals.max(initial=0.0)), 1e-300)
    return sig, np.asarray(vecs[:, keep] * np.sqrt(vals[keep]), dtype=np.float64)


def _mesh_inputs(obs: ImageObservation, hw: F64) -> tuple[F64, F64, F64]:
    """(K,) mesh depth σ, (K, r) square root of its covariance, (K, 3) unit world rays."""
    sig, root = mesh_sqrt(obs)
    rays = hw - obs.cam_from_world.center
    with np.errstate(divide="ignore", invalid="ignore"):
        rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return sig, root, np.nan_to_num(rays)


def _layout(obs: ImageObservation, rig: Rig, options: EstimationOptions) -> _Layout:
    """Index the observation's hits against the rig: FCM lasers, PCM pairs, rig σ."""
    names, xy, sig, hw, nw = _hit_arrays(obs, rig)
    mesh_sigma, root, rays = _mesh_inputs(obs, hw)
    beams, rig_sigma = _beams(rig, options)
    fcm = [(j, names.index(n)) for j, n in enumerate(beams.names) if n in names]
    pairs = [p for p in rig.pairs if p.lasers[0] in names and p.lasers[1] in names]

    def beam(n: str) -> int:
        return beams.names.index(n) if n in beams.names else -1

    return _Layout(
        names, xy, sig, hw, nw, beams,
        np.array([f[0] for f in fcm], dtype=np.intp), np.array([f[1] for f in fcm], np.intp),
        tuple(f"{p.lasers[0]}+{p.lasers[1]}" for p in pairs),
        np.array([[names.index(n) for n in p.lasers] for p in pairs], np.intp).reshape(-1, 2),
        np.array([[beam(n) for n in p.lasers] for p in pairs], np.intp).reshape(-1, 2),
        np.array([p.separation for p in pairs], dtype=np.float64), rig_sigma, mesh_sigma, rays,
        root)


def _hits_cam(lay: _Layout, camera: Camera, dpx: F64, R: F64, t: F64,
              dmesh: F64 | None = None) -> tuple[F64, F64]:
    """(B, K, 3) camera-frame hits (model units) of perturbed rays on the tangent planes.

    Also returns (B, K) |cos| of the ray–normal angle. The camera centre is the origin of the
    camera frame, so the hit is λ·ray with λ = n_c·H_c / n_c·ray (plane through H_c, normal n_c).
    ``dmesh`` (B, K): the tangent planes moved along the spots' rays (mesh depth error).
    """
    b, k = dpx.shape[0], len(lay.names)
    rays = camera.unproject((lay.xy[None] + dpx).reshape(b * k, 2)).reshape(b, k, 3)
    n_c = np.einsum("bij,kj->bki", R, lay.normal_world)
    hw = lay.hit_world[None] if dmesh is None else (
        lay.hit_world[None] + dmesh[..., None] * lay.ray_world[None])
    h_c = np.einsum("bij,bkj->bki", R, np.broadcast_to(hw, (b, k, 3))) + t[:, None, :]
    denom = np.sum(n_c * rays, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.sum(n_c * h_c, axis=2) / denom
        cos_inc = np.abs(denom) / np.linalg.norm(rays, axis=2)
    return rays * lam[..., None], cos_inc


def _pair_rig_factor(lay: _Layout, x: F64, origins: F64, dirs: F64, pcm0: F64) -> F64:
    """(B, np) relative change of each pair's perpendicular beam separation at its hits.

    PCM and Direct 3D take the pair separation as exact; with calibrated lasers, an origin or
    direction error changes the true separation of the two hit points (non-parallel beams).
    Ranges along the beams come from the nominal hits (row 0) at the pair's nominal scale pcm0.
    """
    factor = np.ones((x.shape[0], len(lay.pair_names)))
    cal = np.flatnonzero(np.all(lay.pair_beams >= 0, axis=1))
    if len(cal) == 0:
        return factor
    b1, b2 = lay.pair_beams[cal, 0], lay.pair_beams[cal, 1]
    v1, v2 = lay.beams.direction[b1], lay.beams.direction[b2]
    axis = (v1 + v2) / np.linalg.norm(v1 + v2, axis=1, keepdims=True)  # (m, 3)
    r1 = pcm0[cal] * x[0, lay.pair_hits[cal, 0], 2] / v1[:, 2]
    r2 = pcm0[cal] * x[0, lay.pair_hits[cal, 1], 2] / v2[:, 2]
    d = (origins[:, b2] + r2[:, None] * dirs[:, b2]) - (origins[:, b1] + r1[:, None] * dirs[:, b1])
    perp = d - np.sum(d * axis, axis=-1, keepdims=True) * axis
    sep = np.sqrt(np.sum(perp * perp, axis=-1))  # (B, m)
    factor[:, cal] = sep / sep[0]
    return factor


def _outputs(lay: _Layout, x: F64, drig: F64) -> F64:
    """(B, n_out) [FCM scales, FCM signed residuals (rad), PCM, Direct 3D]; row 0 nominal."""
    origins, dirs = lay.beams.perturbed(drig)
    s, resid = fcm_scale_batch(x[:, lay.fcm_hit], origins[:, lay.fcm_beam], dirs[:, lay.fcm_beam])
    h1, h2 = x[:, lay.pair_hits[:, 0]], x[:, lay.pair_hits[:, 1]]
    pcm = pcm_scale_batch(h1, h2, lay.pair_sep)
    factor = _pair_rig_factor(lay, x, origins, dirs, pcm[0])
    d3 = direct3d_scale_batch(h1, h2, lay.pair_sep)
    return np.concatenate([s, resid, pcm * factor, d3 * factor], axis=1).reshape(len(x), -1)


def pose_sqrt(obs: ImageObservation) -> F64:
    """(6, m) square root of the pose covariance (zero directions dropped)."""
    cov = obs.pose_covariance
    if cov is None:
        return np.zeros((6, 0))
    cov = np.asarray(cov, dtype=np.float64)
    if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
        raise InputError(f"image {obs.image}: pose covariance must be a finite 6×6 matrix")
    cov = 0.5 * (cov + cov.T)
    vals, vecs = np.linalg.eigh(cov)
    if vals.min() < -1e-9 * max(float(vals.max()), 1e-300):
        raise InputError(f"image {obs.image}: pose covariance is not positive semi-definite")
    keep = vals > 1e-14 * max(float(vals.max()), 1e-300)
    return np.asarray(vecs[:, keep] * np.sqrt(vals[keep]), dtype=np.float64)


#: Random-term codes of the input directions (rig directions carry their parameter index >= 0).
_SPOTS, _POSE, _MESH = -1, -2, -3
_TERM_CODES = {"spots": _SPOTS, "pose": _POSE, "mesh": _MESH}


def _directions(lay: _Layout, pose_sqrt: F64) -> tuple[F64, NDArray[np.intp]]:
    """(P, n) input-space σ directions and, per direction, its rig parameter index (>= 0) or its
    random term's code (``_SPOTS``, ``_POSE``, ``_MESH``).

    Inputs are ordered [spot pixels (2 per hit), pose (6), mesh (1 per hit, correlated within
    the image), rig (4 per calibrated laser)]; directions of zero σ are dropped.
    """
    k, r, m = len(lay.names), len(lay.rig_sigma), pose_sqrt.shape[1]
    px_sigma = np.repeat(lay.sigma_px, 2)
    px = np.flatnonzero(px_sigma > 0)
    q = lay.mesh_sqrt.shape[1]
    rig = np.flatnonzero(lay.rig_sigma > 0)
    n_rand = len(px) + m + q
    d = np.zeros((3 * k + 6 + r, n_rand + len(rig)))
    d[px, np.arange(len(px))] = px_sigma[px]
    d[2 * k:2 * k + 6, len(px):len(px) + m] = pose_sqrt
    d[2 * k + 6:3 * k + 6, len(px) + m:n_rand] = lay.mesh_sqrt
    d[3 * k + 6 + rig, n_rand + np.arange(len(rig))] = lay.rig_sigma[rig]
    codes = [np.full(len(px), _SPOTS), np.full(m, _POSE), np.full(q, _MESH), rig]
    return d, np.concatenate(codes).astype(np.intp)


def _jacobian(lay: _Layout, obs: ImageObservation, options: EstimationOptions
              ) -> tuple[F64, NDArray[np.intp], F64, F64]:
    """J·D (n_out, n) by central differences along D's columns, rig index per column, and the
    nominal camera-frame hits (K, 3) with their |cos| incidence (K,)."""
    d, rig_idx = _directions(lay, pose_sqrt(obs))
    h = options.fd_step_sigma
    deltas = np.vstack([np.zeros(d.shape[0]), h * d.T, -h * d.T])  # (1 + 2n, P), row 0 nominal
    k = len(lay.names)
    R, t = perturb_poses(obs.cam_from_world, deltas[:, 2 * k:2 * k + 6])
    x, cos_inc = _hits_cam(lay, obs.camera, deltas[:, :2 * k].reshape(-1, k, 2), R, t,
                           deltas[:, 2 * k + 6:3 * k + 6])
    f = _outputs(lay, x, deltas[:, 3 * k + 6:])
    n = d.shape[1]
    diff = f[1:1 + n] - f[1 + n:]
    nf = len(lay.fcm_beam)
    diff[:, nf:2 * nf] = (diff[:, nf:2 * nf] + np.pi) % (2 * np.pi) - np.pi  # residual angles
    return (diff / (2 * h)).T, rig_idx, x[0], cos_inc[0]


def _split(jd: F64, rig_idx: NDArray[np.intp], n_rig: int) -> tuple[dict[str, F64], F64]:
    """Random covariance (n_out, n_out) per term and rig Jacobian (n_out, R) from J·D."""
    terms = {}
    for term, code in _TERM_CODES.items():
        a = jd[:, rig_idx == code]
        terms[term] = a @ a.T
    g = np.zeros((jd.shape[0], n_rig))
    for col in np.flatnonzero(rig_idx >= 0):
        g[:, rig_idx[col]] = jd[:, col]
    return terms, g


def _model_columns(obs: ImageObservation, rig: Rig, lay: _Layout, options: EstimationOptions
                   ) -> tuple[list[str], F64, F64 | None]:
    """Responses of the outputs to the model's intrinsics directions: names and (n_out, D) of
    the unit-σ ones, and (n_out,) per unit δf / f of the focal one (None without it).

    Central differences of the estimators on perturbed observations, step ``fd_step_sigma``
    (the focal direction: 1e-4 · δf / f).
    """
    names, cols, focal = [], [], None
    zero_rig = np.zeros((1, len(lay.rig_sigma)))
    for d in obs.model_directions:
        h = options.fd_step_sigma if d.in_sigma else 1e-4
        f = []
        for sign in (1.0, -1.0):
            o = perturbed_observation(obs, d, sign * h)
            lay_s = _layout(o, rig, options)
            R, t = perturb_poses(o.cam_from_world, np.zeros((1, 6)))
            x, _ = _hits_cam(lay_s, o.camera, np.zeros((1, len(lay_s.names), 2)), R, t)
            f.append(_outputs(lay_s, x, zero_rig)[0])
        col = (f[0] - f[1]) / (2 * h)
        nf = len(lay.fcm_beam)
        col[nf:2 * nf] = 0.0  # residual angles: not part of the systematic budget
        if d.in_sigma:
            names.append(d.name)
            cols.append(col)
        elif d.name.endswith(FOCAL):
            focal = col
    return names, np.array(cols).T.reshape(lay.n_out, len(cols)), focal


def _sigma(cov: F64, i: int) -> float:
    v = float(cov[i, i])
    return float(np.sqrt(v)) if np.isfinite(v) and v >= 0 else float("nan")


def _grazing(lay: _Layout, cos_inc: F64, hits: tuple[int, ...], options: EstimationOptions
             ) -> str | None:
    """Reason when one of these hits' rays grazes the mesh, else None."""
    for k in hits:
        if not cos_inc[k] >= options.min_incidence_cos:
            angle = float(np.degrees(np.arccos(min(float(cos_inc[k]), 1.0))))
            return f"ray of laser {lay.names[k]} grazes the mesh (incidence {angle:.1f}°)"
    return None


def _residual_reason(laser: str, resid_deg: float, sigma_deg: float,
                     options: EstimationOptions) -> str | None:
    """FCM direction-residual check: far beyond what the propagated noise explains."""
    limit = max(options.max_direction_residual_deg, options.direction_residual_nsigma * sigma_deg)
    if resid_deg > limit or not np.isfinite(sigma_deg):
        return (f"spot inconsistent with beam {laser} geometry "
                "(wrong laser assignment or calibration)")
    return None


def _fcm_estimates(lay: _Layout, image: str, x0: F64, cos0: F64, cov: F64,
                   options: EstimationOptions) -> list[Estimate]:
    """FCM estimates (rows 0..nf−1 of the outputs; residual angles in rows nf..2nf−1)."""
    nf = len(lay.fcm_beam)
    out: list[Estimate] = []
    for i, (b, k) in enumerate(zip(lay.fcm_beam, lay.fcm_hit, strict=True)):
        laser = lay.beams.names[b]
        res = fcm_scale(x0[k], lay.beams.origin[b], lay.beams.direction[b])
        sigma = _sigma(cov, i)
        reason = res.reason or _grazing(lay, cos0, (k,), options)
        if reason is None and not np.isfinite(sigma):
            reason = "uncertainty could not be propagated (non-finite sigma)"
        if reason is None:
            sigma_res = float(np.degrees(_sigma(cov, nf + i)))
            reason = _residual_reason(laser, res.direction_residual_deg, sigma_res, options)
        depth = res.scale * float(np.linalg.norm(x0[k]))
        out.append(Estimate(image, "fcm", laser, res.scale, sigma,
                            res.direction_residual_deg if res.valid else None, depth,
                            reason is not None, reason))
    return out


def _pair_estimates(lay: _Layout, image: str, x0: F64, cos0: F64, cov: F64,
                    options: EstimationOptions, refused: Mapping[str, str]) -> list[Estimate]:
    """PCM and Direct 3D estimates of each pair with both hits (``refused``: pairs whose beams
    are far from parallel, rejected with that reason)."""
    nf, npair = len(lay.fcm_beam), len(lay.pair_names)
    pcm: list[Estimate] = []
    d3: list[Estimate] = []
    for j, name in enumerate(lay.pair_names):
        k1, k2 = (int(k) for k in lay.pair_hits[j])
        h1, h2, sep = x0[k1], x0[k2], float(lay.pair_sep[j])
        res = pcm_scale(h1, h2, sep)
        graze = refused.get(name) or _grazing(lay, cos0, (k1, k2), options)
        mid = float(np.linalg.norm(0.5 * (h1 + h2)))
        for method, value, row, dest, reason in (
            ("pcm", res.scale, 2 * nf + j, pcm, res.reason or graze),
            ("direct3d", direct3d_scale(h1, h2, sep), 2 * nf + npair + j, d3,
             res.reason or graze),
        ):
            sigma = _sigma(cov, row)
            if reason is None and not (np.isfinite(value) and np.isfinite(sigma)):
                reason = "non-finite estimate or sigma"
            dest.append(Estimate(image, method, name, float(value), sigma, None,
                                 float(value) * mid, reason is not None, reason))
    return pcm + d3


def _per_method(lay: _Layout, matrix: F64, estimates: list[Estimate], square: bool
                ) -> dict[str, F64]:
    """Split an (n_out, ·) output matrix into per-method blocks; invalid rows become NaN."""
    nf, npair = len(lay.fcm_beam), len(lay.pair_names)
    rows = {"fcm": slice(0, nf), "pcm": slice(2 * nf, 2 * nf + npair),
            "direct3d": slice(2 * nf + npair, 2 * nf + 2 * npair)}
    blocks: dict[str, F64] = {}
    for method, idx in rows.items():
        block = np.array(matrix[idx, idx] if square else matrix[idx], dtype=np.float64)
        bad = [i for i, e in enumerate(e for e in estimates if e.method == method)
               if not np.isfinite(e.scale)]
        block[bad] = np.nan
        if square:
            block[:, bad] = np.nan
        blocks[method] = block
    return blocks


def _check_hits_on_rays(lay: _Layout, obs: ImageObservation, x0: F64) -> None:
    """Warn when a mesh hit does not lie on its spot's ray (inconsistent inputs)."""
    given = obs.cam_from_world.transform(lay.hit_world)
    off = np.linalg.norm(given - x0, axis=1) / np.linalg.norm(given, axis=1)
    for k in np.flatnonzero(~(off < 1e-3)):
        logger.warning("image %s laser %s: mesh hit is %.2g (relative) off the spot's ray",
                       obs.image, lay.names[k], off[k])


def estimate_image(obs: ImageObservation, rig: Rig, options: EstimationOptions
                   ) -> ImageEstimates:
    """FCM per calibrated laser, PCM and Direct 3D per pair, with joint first-order covariance."""
    lay = _layout(obs, rig, options)
    names = rig_parameter_names(rig)
    if lay.n_out == 0:
        empty = {m: np.zeros((0, 0)) for m in METHODS}
        return ImageEstimates(obs.image, (), empty, dict(empty),
                              {m: np.zeros((0, len(names))) for m in METHODS}, names)
    jd, rig_idx, x0, cos0 = _jacobian(lay, obs, options)
    terms, g = _split(jd, rig_idx, len(lay.rig_sigma))
    model_names, g_model, focal = _model_columns(obs, rig, lay, options)
    g = np.hstack([g, g_model])
    c_rand = sum(terms.values(), np.zeros((lay.n_out, lay.n_out)))
    c_tot = c_rand + g @ g.T
    _check_hits_on_rays(lay, obs, x0)
    ests = _fcm_estimates(lay, obs.image, x0, cos0, c_tot, options)
    ests += _pair_estimates(lay, obs.image, x0, cos0, c_tot, options, refused_pairs(rig))
    per_term: dict[str, dict[str, F64]] = {m: {} for m in METHODS}
    for term, cov in terms.items():
        for m, block in _per_method(lay, cov, ests, True).items():
            per_term[m][term] = block
    sens = {} if focal is None else _per_method(lay, focal[:, None], ests, False)
    return ImageEstimates(obs.image, tuple(ests), _per_method(lay, c_tot, ests, True),
                          _per_method(lay, c_rand, ests, True),
                          _per_method(lay, g, ests, False), (*names, *model_names), per_term,
                          {m: v[:, 0] for m, v in sens.items()})
