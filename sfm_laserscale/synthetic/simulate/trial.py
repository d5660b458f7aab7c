"""One trial: noisy features -> ``estimate_pose`` -> noisy laser spots -> ``cast_spots`` ->
``estimate_image`` -> per-view fusion, for every laser setting (``run_trial``)."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import cast

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.fusion import FusedScale, fuse
from sfm_laserscale.methods.baselines import davis_tusting_scale
from sfm_laserscale.model import Camera, Pose, Spot
from sfm_laserscale.raycast import MeshRaycaster, cast_spots, pixel_rays
from sfm_laserscale.registration.pose import estimate_pose
from sfm_laserscale.rig import Rig
from sfm_laserscale.synthetic.dataset import TrueSpot, true_spots
from sfm_laserscale.synthetic.render import SceneRaycaster
from sfm_laserscale.synthetic.simulate.configs import (
    LaserSetting,
    SimulationOptions,
    is_parallel_axis_rig,
)
from sfm_laserscale.synthetic.simulate.views import ViewJob
from sfm_laserscale.uncertainty import METHODS, ImageEstimates, ImageObservation, estimate_image

F64 = NDArray[np.float64]


#: Spots closer than this to the image border are not visible (pixels).
SPOT_MARGIN_PX = 8.0

#: Davis & Tusting query points: a 5 × 5 grid over the central half of the image.
DT_GRID = 5


@dataclass(frozen=True)
class LaserOutcome:
    """One laser setting evaluated in one registered view."""

    setting: int  # index in the settings tuple
    spot_reasons: dict[str, str]  # laser -> why it gave no hit
    estimates: ImageEstimates | None
    fused: dict[str, tuple[float, float, float, float, float]]  # method -> _fused_tuple
    davis_tusting: float  # NaN unless the rig allows it
    depth_difference_m: dict[str, float]  # pair -> (X_2 − X_1)·v of the true hits, metres
    observation: ImageObservation | None  # what scale's estimators see (for PCM-joint groups)
    edge_spots: tuple[str, ...] = ()  # lasers whose spot failed the depth-edge check
    fused_unchecked: dict[str, tuple[float, float, float, float, float]] = field(
        default_factory=dict)  # per-view fusion WITH the edge spots (when there are any)


@dataclass(frozen=True)
class TrialRecord:
    """One view: the registration and every laser setting's outcome."""

    job: ViewJob
    registered: bool
    reason: str | None
    num_inliers: int
    rotation_error_deg: float
    centre_error_m: float
    outcomes: tuple[LaserOutcome, ...]
    cpu_s: float = 0.0  # CPU time of the trial (its process)


@dataclass(frozen=True)
class TrialContext:
    """What a worker needs: the mesh (model units), camera, laser settings and options."""

    caster: MeshRaycaster
    camera: Camera
    settings: tuple[LaserSetting, ...]
    options: SimulationOptions


def _features(ctx: TrialContext, true_model: Pose, job: ViewJob, rng: np.random.Generator
              ) -> tuple[F64, F64]:
    """(n, 2) noisy feature pixels with outliers and their (n, 3) model points."""
    cam, n = ctx.camera, ctx.options.n_points
    size = (float(cam.width), float(cam.height))
    found: list[F64] = []
    have = 0
    for _ in range(6):
        xy = rng.uniform((0.0, 0.0), size, size=(2 * (n - have) + 64, 2))
        res = ctx.caster.cast(*pixel_rays(cam, true_model.inverse(), xy))
        found.append(res.xyz[res.hit])
        have += int(res.hit.sum())
        if have >= n:
            break
    xyz = np.concatenate(found)[:n]
    xy_true = cam.project(true_model.transform(xyz))
    noisy = xy_true + (job.sign * job.sigma_f_px) * rng.standard_normal(xy_true.shape)
    outlier = rng.random(len(xyz)) < ctx.options.outlier_ratio
    anywhere = rng.uniform((0.0, 0.0), size, size=xy_true.shape)
    return np.where(outlier[:, None], anywhere, noisy), xyz


class _MetricCaster:
    """The trials' ray caster (model units) seen in metres, as ``dataset.true_spots`` casts:
    ``first_hit`` of metric rays -> ((N, 3) metric hits, NaN where none; (N,) hit mask)."""

    def __init__(self, caster: MeshRaycaster, k: float) -> None:
        self.caster, self.k = caster, k

    def first_hit(self, origins: F64, directions: F64) -> tuple[F64, NDArray[np.bool_]]:
        res = self.caster.cast(np.atleast_2d(np.asarray(origins, dtype=np.float64)) / self.k,
                               directions)
        return res.xyz * self.k, res.hit


def view_true_spots(caster: MeshRaycaster, camera: Camera, cam_from_world: Pose, rig: Rig,
                    k: float) -> list[TrueSpot]:
    """Each beam's first mesh hit and its projection when in the image and unoccluded: the demo's
    ``dataset.true_spots`` on the trials' caster (model units, ``k`` metres per unit) from the
    true view ``cam_from_world`` (metres); hits in metres."""
    metric = cast(SceneRaycaster, _MetricCaster(caster, k))  # true_spots calls first_hit only
    return true_spots(metric, camera, cam_from_world, rig, SPOT_MARGIN_PX)


def _depth_differences(rig: Rig, spots: Sequence[TrueSpot], true_model: Pose
                       ) -> dict[str, float]:
    """Per pair with both beams hitting: (X_2 − X_1)·v of the true hits, metres."""
    by = {s.laser: s for s in spots}
    out = {}
    for pair in rig.pairs:
        a, b = by[pair.lasers[0]], by[pair.lasers[1]]
        v = rig.laser(pair.lasers[0]).direction
        if a.hit_world is not None and b.hit_world is not None and v is not None:
            out["+".join(pair.lasers)] = float((b.hit_world - a.hit_world) @ (true_model.R.T @ v))
    return out


def _davis_tusting(ctx: TrialContext, rig: Rig, spots: Sequence[Spot], pose: Pose) -> float:
    """Davis & Tusting with a 5 × 5 grid of query pixels over the central half of the image."""
    if not is_parallel_axis_rig(rig) or len(spots) != 4:
        return float("nan")
    by = {s.laser: s for s in spots}
    xy = np.array([[by[las.name].x, by[las.name].y] for las in rig.lasers])
    origins = np.array([las.origin for las in rig.lasers])
    cam = ctx.camera
    g = np.linspace(0.25, 0.75, DT_GRID)
    query = np.array([(u * cam.width, v * cam.height) for u in g for v in g])
    res = ctx.caster.cast(*pixel_rays(cam, pose.inverse(), query))
    if int(res.hit.sum()) < 2:
        return float("nan")
    hits_cam = pose.transform(res.xyz[res.hit])
    return davis_tusting_scale(xy, cam, origins, query[res.hit], hits_cam)


def _fused_tuple(f: FusedScale) -> tuple[float, float, float, float, float]:
    """(value, std, ci lo, ci hi, σ without the Birge inflation)."""
    gls = math.hypot(f.std_random / (f.birge_ratio if f.inflated else 1.0), f.std_systematic)
    return (float(f.value), float(f.std), float(f.ci95[0]), float(f.ci95[1]), gls)


def _fused_per_view(ctx: TrialContext, est: ImageEstimates
                    ) -> dict[str, tuple[float, float, float, float, float]]:
    """``fusion.fuse`` of one view's estimates, per method (as ``_fused_tuple``)."""
    return {m: _fused_tuple(fuse([est], m, ctx.options.fusion)) for m in METHODS if est.of(m)}


def evaluate_setting(ctx: TrialContext, index: int, truth: Sequence[TrueSpot], job: ViewJob,
                     pose: Pose, covariance: F64 | None, z: F64) -> LaserOutcome:
    """Noisy spots (z: (L, 2) unit normals) → ray casts with the estimated pose → estimates.

    The estimates (``estimates``) include the depth-edge spots, flagged in ``edge_spots``, so
    that the rows can report each method with and without them; ``fused`` and ``observation``
    are what ``scale`` computes (without them).
    """
    setting = ctx.settings[index]
    sigma = setting.sigma_l_px
    spots = [Spot(t.laser, float(t.xy_px[0] + sigma * z[j, 0]), float(t.xy_px[1] + sigma * z[j, 1]),
                  1.0, sigma, "synthetic")
             for j, t in enumerate(truth) if t.xy_px is not None]
    reasons = {t.laser: t.reason for t in truth if not t.visible}
    cast = cast_spots(spots, ctx.camera, pose, ctx.caster, ctx.options.spot_cast)
    edges = tuple(h.laser for h in cast.edge_hits)
    reasons.update({las: why for las, why in cast.reasons.items() if las not in edges})
    k = ctx.options.true_scale
    depth = _depth_differences(setting.rig, truth,
                               Pose(job.cam_from_world.R, job.cam_from_world.t / k))
    order = {s.laser: i for i, s in enumerate(spots)}
    every = tuple(sorted((*cast.hits, *cast.edge_hits), key=lambda h: order[h.laser]))
    if not every:
        return LaserOutcome(index, reasons, None, {}, float("nan"), depth, None)
    name = f"v{job.index}" + ("m" if job.sign < 0 else "")
    obs = ImageObservation(name, ctx.camera, pose, covariance, cast.hits)
    est = estimate_image(replace(obs, hits=every), setting.rig, ctx.options.estimation)
    kept = estimate_image(obs, setting.rig, ctx.options.estimation) if edges and cast.hits else est
    fused = _fused_per_view(ctx, kept) if cast.hits else {}
    dt = _davis_tusting(ctx, setting.rig, spots, pose)
    unchecked = _fused_per_view(ctx, est) if edges else {}  # the edge spots put back
    return LaserOutcome(index, reasons, est, fused, dt, depth, obs if cast.hits else None, edges,
                        unchecked)


def _pose_errors(true_model: Pose, est: Pose, k: float) -> tuple[float, float]:
    """Rotation error (degrees) and camera-centre error (metres) of an estimated pose."""
    dR = est.R @ true_model.R.T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
    return angle, float(np.linalg.norm(est.center - true_model.center) * k)


def run_trial(ctx: TrialContext, job: ViewJob) -> TrialRecord:
    """Features → estimate_pose → spots → ray casts → estimates, for every laser setting."""
    cpu0 = time.process_time()
    rng = np.random.default_rng(job.seed)
    k = ctx.options.true_scale
    true_model = Pose(job.cam_from_world.R, job.cam_from_world.t / k)
    xy, xyz = _features(ctx, true_model, job, rng)
    seed = int(rng.integers(0, 2**31 - 1))
    n_lasers = max(len(s.rig.lasers) for s in ctx.settings)
    z = job.sign * rng.standard_normal((len(ctx.settings), n_lasers, 2))
    res = estimate_pose(xy, xyz, ctx.camera, replace(ctx.options.pose, seed=seed))
    if not res.success or res.cam_from_world is None:
        nan = float("nan")
        return TrialRecord(job, False, res.reason, res.num_inliers, nan, nan, (),
                           time.process_time() - cpu0)
    pose = res.cam_from_world
    truths: dict[str, list[TrueSpot]] = {}
    outcomes = []
    for i, s in enumerate(ctx.settings):
        if s.config not in truths:
            truths[s.config] = view_true_spots(ctx.caster, ctx.camera, job.cam_from_world, s.rig,
                                               k)
        outcomes.append(evaluate_setting(ctx, i, truths[s.config], job, pose, res.covariance,
                                         z[i]))
    rot, centre = _pose_errors(true_model, pose, k)
    return TrialRecord(job, True, None, res.num_inliers, rot, centre, tuple(outcomes),
                       time.process_time() - cpu0)
