"""``simulate --mode mismatch``: surveys whose data carry errors the estimator is not told about
(:mod:`.mismatch_data`), run through the code of ``scale``, and how the reported σ and the model
checks fare: coverage and std/σ of the headline per setting, and how often the checks flag it.

A survey: ``views`` laser images of random views of the demo's seafloor (2–4 m, ±20°), all in
one model (one focal error, one mesh, one rig error). Per view: model points on the true surface
(with their own noise; the model's stretch when its focal is off), pixels from the true camera
with σ_f and 10 % outliers → ``estimate_pose`` with the model's camera → true spots of the true
rig + the setting's spot errors → ``cast_spots`` on the model's mesh → the mesh check
(``mesh_check``: each spot's σ and their correlation) and, when the estimator is told a focal
σ, the intrinsics directions (``analyse_intrinsics`` on a synthetic nadir survey of the scene,
once per told σ) →
``estimate_image`` with the told rig. Then ``fuse`` per method and ``run_model_checks``: the
headline is FCM (checks may widen its σ), the truth the true scale (the survey's cameras, hence
the model's lateral scale, are unchanged by the focal stretch).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.fusion import FusionOptions, fuse
from sfm_laserscale.mesh_error import (
    MeshCheck,
    MeshErrorOptions,
    SharedOffset,
    local_sigma,
    mesh_check,
    shared_offset,
)
from sfm_laserscale.model import Camera, Image, Pose, SparseModel, Spot
from sfm_laserscale.model_checks import ModelCheckOptions, ModelChecks, run_model_checks
from sfm_laserscale.model_error import ModelDirection, mesh_offset_direction
from sfm_laserscale.raycast import MeshRaycaster, SpotCastOptions, cast_spots, pixel_rays
from sfm_laserscale.registration.covariance import (
    IntrinsicsField,
    IntrinsicsOptions,
    analyse_intrinsics,
)
from sfm_laserscale.registration.options import PoseOptions
from sfm_laserscale.registration.pose import estimate_pose
from sfm_laserscale.synthetic.simulate.areas import SimScene, load_scene
from sfm_laserscale.synthetic.simulate.configs import (
    SimulationInputs,
    SimulationOptions,
    config_rig,
    default_camera,
)
from sfm_laserscale.synthetic.simulate.mismatch_data import (
    SETTINGS,
    Mismatch,
    focal_error,
    mesh_with_error,
    rigs,
    setting,
    spot_offsets,
    stretch,
)
from sfm_laserscale.synthetic.simulate.trial import view_true_spots
from sfm_laserscale.synthetic.simulate.views import view_pose
from sfm_laserscale.uncertainty import EstimationOptions, ImageEstimates, ImageObservation
from sfm_laserscale.uncertainty import estimate_image as estimate

F64 = NDArray[np.float64]
Z95 = 1.959963984540054


@dataclass(frozen=True)
class MismatchOptions:
    """What the mismatch experiment runs."""

    settings: tuple[str, ...] = tuple(s.name for s in SETTINGS)
    surveys: int = 200  # per setting
    views: int = 8  # laser images per survey
    config: str = "C"
    distance_m: tuple[float, float] = (2.0, 4.0)
    max_angle_deg: float = 20.0
    sigma_f_px: float = 0.5
    sigma_l_px: float = 0.25
    n_points: int = 800
    outlier_ratio: float = 0.1
    point_sigma_m: float = 0.0015  # the model points' own noise (told to the mesh check)
    survey_altitude_m: float = 3.0  # the SfM survey's nadir cameras above the mean surface
    true_scale: float = 0.5  # metres per model unit
    camera: Camera = field(default_factory=default_camera)
    seed: int = 0
    progress: bool = True
    pose: PoseOptions = field(default_factory=PoseOptions)
    spot_cast: SpotCastOptions = field(default_factory=SpotCastOptions)
    estimation: EstimationOptions = field(default_factory=EstimationOptions)
    fusion: FusionOptions = field(default_factory=FusionOptions)
    mesh_error: MeshErrorOptions = field(default_factory=MeshErrorOptions)
    checks: ModelCheckOptions = field(default_factory=ModelCheckOptions)


@dataclass(frozen=True)
class SurveyResult:
    """One survey of one setting: the headline and what the checks said."""

    setting: str
    survey: int
    focal_error: float
    value: float  # FCM headline (after the checks' widening), m per model unit
    std: float
    ci95: tuple[float, float]
    flags: dict[str, bool]  # check -> failed
    corrected: float  # focal-corrected scale (NaN when not determined)
    corrected_std: float
    views: int  # views that gave an estimate


@dataclass(frozen=True)
class _World:
    """The scene and what every survey shares."""

    scene: SimScene
    true_caster: MeshRaycaster  # true surface, model units (metres / k)
    camera_height: float  # the survey's camera plane, metres along up
    survey_centres: F64  # (n, 3) the survey's camera centres, model units
    fields: dict[float, IntrinsicsField | None]  # told focal σ -> intrinsics field


# --------------------------------------------------------------------------- the SfM survey


def _survey_model(scene: SimScene, camera: Camera, height: float, altitude: float, k: float,
                  sigma_px: float, rng: np.random.Generator) -> tuple[SparseModel, F64]:
    """A nadir survey (4 × 4 images at ``height`` along up, 70 % overlap) of the central area
    as an SfM model (model units) with noisy observations; and its camera centres."""
    lo, hi = scene.central
    mid = 0.5 * (lo + hi)
    step = 0.3 * altitude * camera.width / camera.params[0]
    offsets = (np.arange(4) - 1.5) * step
    pts_w = scene.samples[rng.choice(len(scene.samples), 6000, replace=False)]
    ids = np.arange(1, len(pts_w) + 1, dtype=np.uint64)
    base = np.array([scene.basis[0], -scene.basis[1], -scene.up])  # camera axes in the world
    images, centres = {}, []
    for i, (u, v) in enumerate((a, b) for a in offsets for b in offsets):
        uv = mid + np.array([u, v])
        c_w = uv @ scene.basis + height * scene.up
        pose = Pose(base.copy(), -base @ (c_w / k))
        x_c = pose.transform(pts_w / k)
        px = camera.project(np.where(x_c[:, 2:3] > 0, x_c, 1.0))
        seen = (x_c[:, 2] > 0) & (px[:, 0] > 0) & (px[:, 0] < camera.width) & (px[:, 1] > 0) & (
            px[:, 1] < camera.height)
        obs = px[seen] + rng.normal(scale=sigma_px, size=(int(seen.sum()), 2))
        images[i + 1] = Image(i + 1, f"survey_{i}.png", camera.camera_id, pose, obs, ids[seen])
        centres.append(c_w / k)
    return SparseModel({camera.camera_id: camera}, images, ids, pts_w / k), np.array(centres)


def _world(options: MismatchOptions, settings: Sequence[Mismatch]) -> _World:
    """The scene, the survey and the intrinsics fields of the told focal σ."""
    sim = SimulationOptions(mode="random", true_scale=options.true_scale, progress=False)
    scene, caster = load_scene(SimulationInputs(), sim)
    height = float(np.mean(scene.samples @ scene.up)) + options.survey_altitude_m
    rng = np.random.default_rng(np.random.SeedSequence([options.seed, 31]))
    model, centres = _survey_model(scene, options.camera, height, options.survey_altitude_m,
                                   options.true_scale, options.sigma_f_px, rng)
    fields: dict[float, IntrinsicsField | None] = {0.0: None}
    for s in settings:
        told = s.told_focal_sigma
        if told > 0 and told not in fields:
            fields[told] = analyse_intrinsics(lambda: model, model.point3D_ids, IntrinsicsOptions(
                refined=("focal",), focal_sigma_prior=told, focal_sigma_floor=0.0))
    return _World(scene, caster, height, centres, fields)


# --------------------------------------------------------------------------- one survey


@dataclass(frozen=True)
class _Model:
    """What the estimator has in one survey: its mesh, camera and a map of true points."""

    caster: MeshRaycaster
    camera: Camera
    eps: float


def _model(world: _World, m: Mismatch, eps: float, options: MismatchOptions,
           rng: np.random.Generator) -> _Model:
    scene, k = world.scene, options.true_scale
    verts = scene.vertices
    if m.mesh_noise_m > 0 or m.mesh_smooth > 0:
        verts = mesh_with_error(verts, scene.triangles, scene.up, scene.basis, m, rng)
    if eps != 0:
        verts = stretch(verts, scene.up, world.camera_height, eps)
    caster = (world.true_caster if verts is scene.vertices
              else MeshRaycaster(verts / k, scene.triangles))
    cam = options.camera
    params = cam.params * np.array([1 + eps, 1 + eps, 1.0, 1.0])
    return _Model(caster, Camera(cam.camera_id, cam.model, cam.width, cam.height, params), eps)


def _random_pose(world: _World, options: MismatchOptions, rng: np.random.Generator
                 ) -> Pose | None:
    """A random view (metres) of a surface point of the central half."""
    lo, hi = world.scene.central
    uv = rng.uniform(lo, hi)
    start = (uv @ world.scene.basis + 100.0 * world.scene.up) / options.true_scale
    res = world.true_caster.cast(start[None], -world.scene.up[None])
    if not res.hit[0]:
        return None
    a = options.max_angle_deg
    return view_pose(res.xyz[0] * options.true_scale, world.scene.up,
                     float(rng.uniform(*options.distance_m)), float(rng.uniform(-a, a)),
                     float(rng.uniform(-a, a)))


def _features(world: _World, model: _Model, true_pose: Pose, options: MismatchOptions,
              rng: np.random.Generator) -> tuple[F64, F64]:
    """(n, 2) noisy pixels of surface points seen from the true camera and their (n, 3) model
    points (stretched when the focal is off, with their own noise), model units."""
    k, cam = options.true_scale, options.camera
    true_model = Pose(true_pose.R, true_pose.t / k)
    xy = rng.uniform((0.0, 0.0), (cam.width, cam.height), size=(2 * options.n_points, 2))
    res = world.true_caster.cast(*pixel_rays(cam, true_model.inverse(), xy))
    pts = res.xyz[res.hit][:options.n_points]
    px = cam.project(true_model.transform(pts))
    px = px + options.sigma_f_px * rng.standard_normal(px.shape)
    out = rng.random(len(px)) < options.outlier_ratio
    px[out] = rng.uniform((0.0, 0.0), (cam.width, cam.height), size=(int(out.sum()), 2))
    metric = stretch(pts * k, world.scene.up, world.camera_height, model.eps)
    metric = metric + rng.normal(scale=options.point_sigma_m, size=metric.shape)
    return px, metric / k


@dataclass(frozen=True)
class _Seen:
    """One laser image of a survey before its estimates: observation and mesh check."""

    obs: ImageObservation
    check: MeshCheck
    inliers: tuple[F64, F64]  # pixels, model points


def _view(world: _World, model: _Model, m: Mismatch, true_rig: Any,
          options: MismatchOptions, rng: np.random.Generator, name: str) -> _Seen | None:
    """One laser image of the survey: registered, its spots cast, its mesh checked (None:
    nothing usable)."""
    true_pose = _random_pose(world, options, rng)
    if true_pose is None:
        return None
    xy, xyz = _features(world, model, true_pose, options, rng)
    reg = estimate_pose(xy, xyz, model.camera, replace(options.pose, seed=int(
        rng.integers(0, 2**31 - 1))))
    if not reg.success or reg.cam_from_world is None:
        return None
    pose = reg.cam_from_world
    truth = view_true_spots(world.true_caster, options.camera, true_pose, true_rig,
                            options.true_scale)
    seen = [t for t in truth if t.xy_px is not None]
    err = spot_offsets(m, options.sigma_l_px, len(seen), rng)
    spots = [Spot(t.laser, float(t.xy_px[0] + e[0]), float(t.xy_px[1] + e[1]), 1.0,
                  options.sigma_l_px, "synthetic")
             for t, e in zip(seen, err, strict=True) if t.xy_px is not None]
    cast = cast_spots(spots, model.camera, pose, model.caster, options.spot_cast)
    if not cast.hits:
        return None
    in_xy, in_xyz = xy[reg.inlier_mask], xyz[reg.inlier_mask]
    sig_p = np.full(len(in_xyz), options.point_sigma_m / options.true_scale)
    mesh = mesh_check(model.caster, model.camera, pose, cast.hits, in_xy, in_xyz, sig_p,
                      options.mesh_error)
    obs = ImageObservation(name, model.camera, pose, reg.covariance, cast.hits)
    return _Seen(obs, mesh, (in_xy, in_xyz))


def _estimate(seen: _Seen, shared: SharedOffset, told_rig: Any,
              field_: IntrinsicsField | None, options: MismatchOptions) -> ImageEstimates:
    """The image's estimates with its model error: local mesh σ, the shared mesh offset and the
    intrinsics directions."""
    obs = seen.obs
    hits = np.array([h.hit_world for h in obs.hits])
    dirs: tuple[ModelDirection, ...] = () if field_ is None else field_.directions(
        obs.camera, obs.cam_from_world, *seen.inliers, hits)
    if shared.sigma > 0:
        rays = hits - obs.cam_from_world.center
        dirs = (*dirs, mesh_offset_direction(
            shared.sigma, rays / np.linalg.norm(rays, axis=1, keepdims=True)))
    obs = replace(obs, mesh_sigma=np.array([local_sigma(x, shared) for x in seen.check.spots]),
                  mesh_correlation=seen.check.correlation, model_directions=dirs)
    return estimate(obs, told_rig, options.estimation)


def _flags(checks: ModelChecks, inflated: bool) -> dict[str, bool]:
    """Which checks failed (True: flagged)."""
    sc = checks.scatter
    return {
        "scatter": bool(sc is not None and not sc.ok),
        "birge": bool(inflated),
        "methods": any(not c.ok for c in checks.comparisons),
        "lasers": any(not c.ok for c in checks.lasers),
        "distance": bool(checks.distance is not None and checks.distance.significant),
        "focal": bool(checks.focal.significant),
        "drift": bool(checks.drift is not None and checks.drift.significant),
    }


def run_survey(world: _World, m: Mismatch, index: int, options: MismatchOptions
               ) -> SurveyResult | None:
    """One survey of one setting (None when no FCM scale came out)."""
    rng = np.random.default_rng(np.random.SeedSequence(
        [options.seed, SETTINGS.index(m) if m in SETTINGS else 99, index]))
    eps = focal_error(m, rng)
    model = _model(world, m, eps, options, rng)
    true_rig, told_rig = rigs(config_rig(options.config), m, rng)
    field_ = world.fields.get(m.told_focal_sigma)
    seen = [s for s in (_view(world, model, m, true_rig, options, rng, f"v{v}")
                        for v in range(options.views)) if s is not None]
    shared = shared_offset([x for s in seen for x in s.check.spots])
    ests = [_estimate(s, shared, told_rig, field_, options) for s in seen]
    centres = {s.obs.image: s.obs.cam_from_world.center for s in seen}
    methods = {meth: fuse(ests, meth, options.fusion) for meth in ("fcm", "pcm")}
    head = methods["fcm"]
    if not math.isfinite(head.value):
        return None
    checks = run_model_checks(ests, methods, head, False, centres, world.survey_centres,
                              m.told_focal_sigma, options.checks, options.fusion)
    h = checks.headline
    corr = checks.focal.corrected
    return SurveyResult(m.name, index, eps, h.value, h.std, h.ci95, _flags(checks, head.inflated),
                        float("nan") if corr is None else corr.value,
                        float("nan") if corr is None else corr.std, len(ests))


# --------------------------------------------------------------------------- statistics


def setting_stats(results: Sequence[SurveyResult], truth: float) -> dict[str, Any]:
    """Per setting: n, bias, std, mean σ (% of the truth), std/σ, RMS z, 95 % coverage, the
    checks' flag rates (each and any), and the focal-corrected scale's coverage."""
    v = np.array([r.value for r in results])
    s = np.array([r.std for r in results])
    lo, hi = np.array([r.ci95[0] for r in results]), np.array([r.ci95[1] for r in results])
    e = v / truth - 1
    z = (v - truth) / s
    flags = {k: float(np.mean([r.flags[k] for r in results])) for k in results[0].flags}
    checks = [k for k in flags if k != "birge"]
    cv, cs = np.array([r.corrected for r in results]), np.array([r.corrected_std for r in results])
    ok = np.isfinite(cv) & np.isfinite(cs)
    spread = float(np.std(e, ddof=1)) if len(e) > 1 else float("nan")  # one survey: no spread
    return {
        "n": len(results),
        "bias_pct": 100 * float(np.mean(e)), "std_pct": 100 * spread,
        "sigma_pct": 100 * float(np.mean(s / truth)),
        "ratio": spread / float(np.mean(s / truth)),
        "z_rms": float(np.sqrt(np.mean(z**2))),
        "coverage95": float(np.mean((lo <= truth) & (truth <= hi))),
        "flag_rates": flags,
        "flagged_any": float(np.mean([any(r.flags[k] for k in checks) for r in results])),
        "corrected_n": int(ok.sum()),
        "corrected_coverage95": float(np.mean(np.abs(cv[ok] - truth) <= Z95 * cs[ok]))
        if ok.any() else float("nan"),
        "views_mean": float(np.mean([r.views for r in results])),
    }


def run_mismatch(options: MismatchOptions) -> dict[str, Any]:
    """Every setting's surveys and statistics (results.json's content, no files)."""
    t0 = time.perf_counter()
    settings = [setting(n) for n in options.settings]
    world = _world(options, settings)
    out: dict[str, Any] = {"true_scale": options.true_scale, "config": options.config,
                           "surveys": options.surveys, "views": options.views, "settings": []}
    for m in settings:
        t1 = time.perf_counter()
        res = [r for r in (run_survey(world, m, i, options) for i in range(options.surveys))
               if r is not None]
        stats: dict[str, Any] = setting_stats(res, options.true_scale) if res else {"n": 0}
        stats.update(name=m.name, covered=m.covered, told_focal_sigma=m.told_focal_sigma,
                     seconds=time.perf_counter() - t1)
        out["settings"].append(stats)
    out["seconds"] = time.perf_counter() - t0
    return out


def mismatch_table(results: dict[str, Any]) -> str:
    """The mismatch table (markdown): per setting, coverage and std/σ, flag rate and targets."""
    rows = ["| setting | σ claims to cover it | n | bias (%) | std (%) | mean σ (%) | std/σ | "
            "95 % coverage | flagged | target |", "|---|---|---|---|---|---|---|---|---|---|"]
    for s in results["settings"]:
        if not s.get("n"):
            rows.append(f"| {s['name']} | | 0 | | | | | | | |")
            continue
        target = "coverage 90–97 %" if s["covered"] else "flagged ≥ 80 %"
        met = (0.90 <= s["coverage95"] <= 0.97) if s["covered"] else s["flagged_any"] >= 0.8
        rows.append(f"| {s['name']} | {'yes' if s['covered'] else 'no'} | {s['n']} | "
                    f"{s['bias_pct']:+.3f} | {s['std_pct']:.3f} | {s['sigma_pct']:.3f} | "
                    f"{s['ratio']:.2f} | {100 * s['coverage95']:.1f} % | "
                    f"{100 * s['flagged_any']:.0f} % | {target}: {'met' if met else 'NOT met'} |")
    return "\n".join(rows) + "\n"
