"""``scale``: the model's metric scale from its laser images, and every output written.

Chains readers -> detection -> registration -> detection again against each image's scene
reference -> ray casting -> methods -> fusion -> writers. It owns no maths; each stage is a
function of its own module. ``run`` is the whole command; its
inputs and options (:class:`~sfm_laserscale.run_types.ScaleInputs`,
:class:`~sfm_laserscale.run_types.ScaleOptions`) are shared with the report writer, so they live
in :mod:`sfm_laserscale.run_types`.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from sfm_laserscale.detection import DetectionResult, detect_spots
from sfm_laserscale.detection.guided import detect_near
from sfm_laserscale.errors import InputError
from sfm_laserscale.footprints import (
    Footprint,
    FootprintView,
    footprint_summary,
    footprints,
    model_views,
)
from sfm_laserscale.fusion import FusedScale, fuse
from sfm_laserscale.guided_spots import (
    beam_rays,
    laser_offsets,
    predict_spots,
)
from sfm_laserscale.held_out import check_held_out, reused_registrations
from sfm_laserscale.io.colmap_write import write_scaled_colmap_model
from sfm_laserscale.io.footprints_csv import write_footprints_csv
from sfm_laserscale.io.images import LaserImage, find_laser_images, read_rgb
from sfm_laserscale.io.in_memory import (
    InMemoryInputs,
    write_scaled_open3d_mesh,
    write_scaled_reconstruction,
)
from sfm_laserscale.io.meshes.mesh import TriangleMesh, load_mesh, write_scaled_mesh
from sfm_laserscale.io.models import load_model
from sfm_laserscale.io.openmvg import write_scaled_openmvg_sfm_data
from sfm_laserscale.io.outputs import check_output_dir, staged_output_dir
from sfm_laserscale.io.spots_csv import read_spots_csv
from sfm_laserscale.memory import trim_heap
from sfm_laserscale.mesh_error import SharedOffset
from sfm_laserscale.methods.pcm_joint import (
    PcmJointOptions,
    PcmJointResult,
    estimate_pcm_joint,
)
from sfm_laserscale.model import Camera, Pose, SparseModel, Spot
from sfm_laserscale.model_checks import ModelChecks
from sfm_laserscale.model_stage import (
    check_model,
    intrinsics_field,
    mesh_check_rays,
    model_inputs,
    registered_view,
    shared_mesh_offset,
)
from sfm_laserscale.provenance import (
    captured_colmap_log,
    captured_log,
    digests_in_background,
    glog_without_files,
    merged_glog,
    progress_bar,
    provenance,
    run_log_text,
)
from sfm_laserscale.raycast import (
    MeshCrop,
    MeshRaycaster,
    cast_spots,
    crop_for_rays,
    pixel_rays,
    spot_cast_rays,
)
from sfm_laserscale.registration.covariance import IntrinsicsField
from sfm_laserscale.registration.features import open_model_features
from sfm_laserscale.registration.index import DescriptorIndex, build_index, select_index_candidates
from sfm_laserscale.registration.pose import register_image
from sfm_laserscale.registration.sift import extract_sift
from sfm_laserscale.registration.sift_workers import start_sift_pool
from sfm_laserscale.report.inputs_used import add_input_keys
from sfm_laserscale.report.writer import build_report, summary_line, write_outputs
from sfm_laserscale.rig import Rig, load_rig
from sfm_laserscale.run_types import ImageRun, LoadedInputs, ScaleInputs, ScaleOptions, Timer
from sfm_laserscale.scene_stage import detect_all_with_references
from sfm_laserscale.uncertainty import ImageObservation, estimate_image
from sfm_laserscale.version import __version__

__all__ = ["ScaleInputs", "ScaleOptions", "ScaleResult", "run"]

logger = logging.getLogger(__name__)
METHODS = ("fcm", "pcm", "direct3d")


@dataclass(frozen=True)
class ScaleResult:
    """The finished job: headline scale (NaN when none), per-method fusions, per-image runs."""

    success: bool
    scale: FusedScale
    methods: dict[str, FusedScale]
    images: tuple[ImageRun, ...]
    report: dict[str, Any]
    out_dir: Path | None  # None: nothing was written
    summary: str
    footprints: tuple[Footprint, ...] = ()  # every laser and model image's, in model units


def load_inputs(inputs: ScaleInputs, options: ScaleOptions,
                given: InMemoryInputs | None = None) -> LoadedInputs:
    """Read and validate every input; raises InputError on bad input (exit 2). The laser
    images' SIFT starts in worker processes as soon as they are listed (``sift_pool``), or
    once the model images' are done when those are re-extracted (``--images``). ``given``:
    a model and/or mesh already in memory, used instead of reading ``inputs.model``/``mesh``."""
    given = given or InMemoryInputs()
    rig = load_rig(inputs.rig)
    model = given.model if given.model is not None else load_model(inputs.model)
    laser_images = find_laser_images(inputs.laser_images, model)
    held = check_held_out(laser_images, model, inputs.model_images or inputs.images)
    laser_images, reused = (reused_registrations(held, laser_images, model, options.registration)
                            if options.reuse_model_poses else (laser_images, {}))
    manual: dict[str, list[Spot]] = {}
    if inputs.spots is not None:
        manual = read_spots_csv(inputs.spots, [li.name for li in laser_images], rig.names)
    # the model images' SIFT, when it is re-extracted, has the workers first (the index
    # needs it before any laser image can be registered)
    reextract = inputs.images is not None and inputs.database is None
    pool = None if reextract else start_sift_pool(laser_images, options.sift,
                                                  options.sift_workers)
    try:
        model, index = _load_index(inputs, model, options)
        if reextract:
            pool = start_sift_pool(laser_images, options.sift, options.sift_workers)
        mesh = given.mesh if given.mesh is not None else load_mesh(inputs.mesh)
    except BaseException:
        if pool is not None:
            pool.close()
        raise
    return LoadedInputs(model, mesh, rig, tuple(laser_images), manual, index,
                        index.num_descriptors, pool, held, reused)


def _load_index(inputs: ScaleInputs, model: SparseModel,
                options: ScaleOptions) -> tuple[SparseModel, DescriptorIndex]:
    """The descriptor index, and the model without the 2D observations it no longer needs."""
    # peak memory: a database's features are read one image at a time by the index build,
    # never all held beside the index, and the mesh is read once the index is built
    with open_model_features(model, inputs.model, inputs.database, inputs.images,
                             inputs.features, replace(options.tie, progress=options.progress),
                             options.sift_workers) as features:
        try:
            candidates = select_index_candidates(model, features, options.index)
            # the candidates hold what the index needs of the 2D observations; the rest of
            # the run uses cameras, poses and points only (46 MB less at 1M points)
            model = model.without_observations()
            trim_heap()
            index = build_index(model, candidates, features, options.index)
        except InputError as exc:  # name the descriptor source as well as the image
            source = inputs.database or inputs.features or inputs.images
            if source is None or exc.path is None:
                raise
            raise InputError(f"image {exc.path}: {exc.problem}", source) from exc
    del candidates
    trim_heap()
    return model, index


def _spots_for(
    name: str, rgb: np.ndarray, camera: Camera, loaded: LoadedInputs, options: ScaleOptions
) -> tuple[tuple[Spot, ...], DetectionResult | None, dict[str, str]]:
    manual = loaded.manual_spots.get(name)
    if manual is not None:
        given = {s.laser for s in manual}
        missing = {n: "not given in --spots" for n in loaded.rig.names if n not in given}
        return tuple(manual), None, missing
    det = detect_spots(rgb, camera, loaded.rig, options.detection)
    return det.spots, det, dict(det.missing)


def _image_run(image: LaserImage, reason: str | None, **kw: Any) -> ImageRun:
    base: dict[str, Any] = dict(name=image.name, path=image.path, camera=image.camera,
                                registration=None, detection=None, spots=(), hits=(),
                                spot_reasons={}, estimates=None, reason=reason)
    base.update(kw)
    return ImageRun(**base)


def detect_and_register(image: LaserImage, loaded: LoadedInputs, options: ScaleOptions,
                        timer: Timer) -> ImageRun:
    """Detect the spots of one laser image and register it; failures become reasons. A
    registered image comes back with ``reason`` None and no hits yet (see cast_and_estimate)."""
    camera = image.camera
    if camera is None:
        return _image_run(image, "not a readable image")
    try:
        rgb = read_rgb(image.path)
    except InputError as exc:
        logger.warning("laser image %s: %s; reported and skipped", image.path, exc.problem)
        damaged = exc.problem.startswith("damaged")
        return _image_run(image, exc.problem if damaged else f"cannot read image: {exc.problem}")
    with timer("detect"):
        spots, det, spot_reasons = _spots_for(image.name, rgb, camera, loaded, options)
    if loaded.index is None:
        raise ValueError("the descriptor index was released: register before scale.run drops it")
    with timer("register"):
        pool = loaded.sift_pool
        reg = loaded.reused_poses.get(image.name)  # --reuse-model-poses
        if reg is None:
            feats = (extract_sift(rgb, options.sift) if pool is None
                     else pool.features(image.path, rgb))
            reg = register_image(feats, camera, loaded.index, options.registration)
        del rgb
    done = dict(registration=reg, detection=det, spots=spots, spot_reasons=spot_reasons)
    if not reg.success or reg.cam_from_world is None:
        return _image_run(image, reg.reason or "registration failed", **done)
    return _image_run(image, None, **done)  # registered: hits and estimates to come


def _view(run: ImageRun) -> tuple[Camera, Pose] | None:
    """Camera and cam_from_world of a registered image still without a reason, else None."""
    if run.reason is not None or run.camera is None or run.registration is None:
        return None
    pose = run.registration.cam_from_world
    return None if pose is None else (run.camera, pose)


def _views(runs: Sequence[ImageRun]) -> list[tuple[ImageRun, Camera, Pose]]:
    return [(r, *v) for r in runs if (v := _view(r)) is not None]


def crop_mesh(runs: Sequence[ImageRun], loaded: LoadedInputs, options: ScaleOptions,
              extra_rays: Sequence[tuple[np.ndarray, np.ndarray]] = ()) -> MeshCrop:
    """The mesh cropped to every ray the registered images' spots will cast (and
    ``extra_rays``: (origins, directions) pairs) and to the mesh-check points (exact:
    raycast.crop_for_rays). The check itself runs after casting, on the points of the images
    still estimated: a subset of these."""
    rays = [spot_cast_rays(r.spots, camera, pose, options.spot_cast)
            for r, camera, pose in _views(runs)]
    rays += list(extra_rays)
    rays += [mesh_check_rays(r, options) for r, _, _ in _views(runs)]
    origins = np.concatenate([o for o, _ in rays]) if rays else np.zeros((0, 3))
    dirs = np.concatenate([d for _, d in rays]) if rays else np.zeros((0, 3))
    if loaded.mesh is None:
        raise ValueError("crop_mesh needs the loaded mesh (it was released)")
    radius = options.mesh_check_radius * loaded.model.extent
    return crop_for_rays(loaded.mesh.vertices, loaded.mesh.triangles, origins, dirs,
                         mesh_check_points(runs, options, loaded.model.extent),
                         replace(options.crop, point_radius=radius))


def mesh_check_points(runs: Sequence[ImageRun], options: ScaleOptions,
                      extent: float) -> np.ndarray:
    """(N, 3) the registered laser images' inlier model points near their spots' rays: where
    the scale is read off the mesh, so where mesh and model must agree (docs/DESIGN.md §4)."""
    pts, dist = [], []
    for r, camera, pose in _views(runs):
        if not r.spots or r.registration is None:
            continue
        inliers = r.registration.inlier_xyz
        xy = np.array([[s.x, s.y] for s in r.spots], dtype=np.float64)
        origins, dirs = pixel_rays(camera, pose.inverse(), xy)
        rel = inliers[:, None, :] - origins[None]  # (K, S, 3)
        along = np.maximum(np.einsum("ksj,sj->ks", rel, dirs), 0.0)
        off = np.linalg.norm(rel - along[..., None] * dirs[None], axis=2).min(axis=1)
        pts.append(inliers)
        dist.append(off)
    if not pts:
        return np.zeros((0, 3))
    xyz, inverse = np.unique(np.concatenate(pts), axis=0, return_inverse=True)
    off = np.full(len(xyz), np.inf)
    np.minimum.at(off, inverse.reshape(-1), np.concatenate(dist))  # a point seen in 2 images
    near = off <= options.mesh_check_near * extent
    if near.sum() < options.mesh_check_min_points:  # sparse models: the nearest ones
        near = np.zeros(len(off), dtype=bool)
        near[np.argsort(off, kind="stable")[:options.mesh_check_min_points]] = True
    sel = xyz[near]
    if len(sel) > options.mesh_check_points:
        rng = np.random.default_rng(options.seed)
        sel = sel[np.sort(rng.choice(len(sel), options.mesh_check_points, replace=False))]
    return sel


def mesh_model_agreement(points: np.ndarray, caster: MeshRaycaster, extent: float,
                         whole_mesh: Callable[[], TriangleMesh]) -> float:
    """Median distance of the check points to the mesh / model extent (NaN without points).

    On a cropped caster distances up to its point radius are exact; a median beyond it (a mesh
    that does not belong to the model) is computed on ``whole_mesh()``, at the whole mesh's cost.
    """
    if len(points) == 0:
        return float("nan")
    median = float(np.median(caster.distances(points)))
    limit = np.inf if caster.coverage is None else caster.coverage.point_radius
    if median > limit:
        logger.warning("mesh–model check: median distance beyond %.3g model units; computing it "
                       "on the whole mesh", limit)
        mesh = whole_mesh()
        median = float(np.median(MeshRaycaster(mesh.vertices, mesh.triangles).distances(points)))
    return median / max(extent, 1e-12)


def cast_and_estimate(run: ImageRun, loaded: LoadedInputs, caster: MeshRaycaster,
                      options: ScaleOptions, timer: Timer,
                      field: IntrinsicsField | None = None,
                      mesh_offset: SharedOffset | None = None) -> ImageRun:
    """Cast the spots of a registered image into the mesh and estimate the scale (with the
    model's own error: the mesh's at each spot, the intrinsics' in ``field``)."""
    view = _view(run)
    if view is None or run.registration is None:
        return run
    camera, pose = view
    with timer("raycast"):
        cast = cast_spots(run.spots, camera, pose, caster, options.spot_cast)
    spot_reasons = {**run.spot_reasons, **cast.reasons}
    if not cast.hits:
        why = ("no laser spot found" if not run.spots else
               "no usable spot hit on the mesh: " + "; ".join(sorted(set(cast.reasons.values()))))
        return replace(run, spot_reasons=spot_reasons, reason=why)
    with timer("estimate"):
        extra = model_inputs(run, cast.hits, caster, field, options, mesh_offset)
        obs = ImageObservation(image=run.name, camera=camera, cam_from_world=pose,
                               pose_covariance=run.registration.covariance, hits=cast.hits,
                               mesh_sigma=extra.mesh_sigma, model_directions=extra.directions,
                               mesh_correlation=extra.mesh_correlation)
        est = estimate_image(obs, loaded.rig, options.estimation)
    usable = [e for e in est.estimates if not e.rejected]
    reason = None if usable else "every estimate of this image was rejected"
    return replace(run, hits=cast.hits, spot_reasons=spot_reasons, estimates=est, reason=reason,
                   observation=obs, mesh_errors=extra.mesh_errors)


def _beam_rays(runs: Sequence[ImageRun], rig: Rig,
               scale: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every calibrated beam of every registered image as a model-frame ray at ``scale``."""
    names = [las.name for las in rig.lasers if las.calibrated]
    out = []
    for r in runs:
        if (view := registered_view(r)) is not None:
            b = beam_rays(view[1], rig, names, scale)
            out.append((b.origins, b.directions))
    return out


def _offsets(runs: Sequence[ImageRun], rig: Rig, caster: MeshRaycaster, scale: float,
             options: ScaleOptions) -> dict[str, tuple[float, float]]:
    """Per laser, the median offset of the spots found on their own from their predictions."""
    pairs = []
    for r in runs:
        own = [s for s in r.spots if s.source == "detected"]
        if (view := registered_view(r)) is None or not own:
            continue
        pred, _ = predict_spots(*view, rig, [s.laser for s in own], caster, scale)
        pairs += [(s.laser, s.x, s.y, *pred[s.laser]) for s in own if s.laser in pred]
    return laser_offsets(pairs, options.guided.min_offset_spots)


def _guided_run(run: ImageRun, loaded: LoadedInputs, caster: MeshRaycaster, scale: float,
                offsets: dict[str, tuple[float, float]], options: ScaleOptions) -> ImageRun:
    """One registered image's missing calibrated lasers searched where the model puts them;
    with new spots it comes back without hits or estimates (and without a reason)."""
    view = registered_view(run)
    have = {s.laser for s in run.spots}
    missing = [las.name for las in loaded.rig.lasers if las.calibrated and las.name not in have]
    if view is None or not missing:
        return run
    pred, why = predict_spots(*view, loaded.rig, missing, caster, scale, offsets)
    found = (detect_near(read_rgb(run.path), view[0], loaded.rig, pred, options.detection,
                         options.guided.search) if pred else None)
    reasons = dict(run.spot_reasons)
    for name in missing:
        extra = why.get(name) or (found.missing.get(name) if found else None)
        if extra:
            reasons[name] = f"{reasons.get(name, 'not found')}; where the model puts it: {extra}"
    if found is None or not found.spots:
        return replace(run, spot_reasons=reasons)
    for s in found.spots:
        reasons.pop(s.laser, None)
        logger.info("laser image %s: %s found where the model puts it (%.1f, %.1f)", run.name,
                    s.laser, s.x, s.y)
    return replace(run, spots=run.spots + found.spots, spot_reasons=reasons, reason=None,
                   hits=(), estimates=None, observation=None, mesh_errors=())


def covering_caster(runs: Sequence[ImageRun], caster: MeshRaycaster, whole: LoadedInputs,
                    options: ScaleOptions,
                    extra_rays: Sequence[tuple[np.ndarray, np.ndarray]] = ()) -> MeshRaycaster:
    """``caster`` when it covers every spot ray, mesh-check ray and check point of ``runs`` and
    ``extra_rays``, else a caster on the whole mesh (``whole.mesh``) cropped again for them
    (the beams at the first scale, then the guided search's spots, lie off the first crop)."""
    rays = [spot_cast_rays(r.spots, camera, pose, options.spot_cast)
            for r, camera, pose in _views(runs)]
    rays += [*extra_rays, *(mesh_check_rays(r, options) for r, _, _ in _views(runs))]
    if caster.coverage is None or not rays:
        return caster
    o = np.concatenate([a for a, _ in rays])
    d = np.concatenate([b for _, b in rays])
    points = mesh_check_points(runs, options, whole.model.extent)
    if caster.coverage.covers_rays(o, d).all() and caster.coverage.covers_points(points).all():
        return caster
    crop = crop_mesh(runs, whole, options, extra_rays)
    logger.info("mesh cropped again for the guided search: %d of %d triangles",
                len(crop.triangles), crop.source_triangles)
    return crop.raycaster()


def _estimate_guided(run: ImageRun, before: ImageRun, loaded: LoadedInputs,
                     caster: MeshRaycaster, options: ScaleOptions, timer: Timer,
                     field: IntrinsicsField | None, mesh_offset: SharedOffset | None) -> ImageRun:
    """Cast and estimate an image that gained spots in the guided search (``before``: the same
    image before it, kept with a reason when the new spots' rays lie outside the mesh crop)."""
    if run is before or run.estimates is not None or run.reason is not None:
        return run
    try:
        return cast_and_estimate(run, loaded, caster, options, timer, field, mesh_offset)
    except RuntimeError:  # a ray covering_caster did not see (it should not happen)
        new = {s.laser for s in run.spots} - {s.laser for s in before.spots}
        why = "found where the model puts it, but its ray lies outside the mesh crop"
        return replace(before, spot_reasons={**before.spot_reasons,
                                             **{n: why for n in sorted(new)}})


def guided_search(runs: Sequence[ImageRun], loaded: LoadedInputs, caster: MeshRaycaster,
                  whole: LoadedInputs, scale: float, options: ScaleOptions
                  ) -> tuple[list[ImageRun], MeshRaycaster] | None:
    """The runs with spots the detector missed found where the model puts them at ``scale``,
    or with the reason they were not, and a caster covering every ray they will cast (cropped
    again from ``whole.mesh`` when needed). None when there is no scale yet. The caller runs it
    only with the search on and no spots given by hand (``whole`` is kept for it then)."""
    if not np.isfinite(scale):
        return None
    caster = covering_caster(runs, caster, whole, options, _beam_rays(runs, loaded.rig, scale))
    offsets = _offsets(runs, loaded.rig, caster, scale, options)
    out = [_guided_run(r, loaded, caster, scale, offsets, options) for r in runs]
    return out, covering_caster(out, caster, whole, options)


def _observations(runs: Sequence[ImageRun]) -> list[ImageObservation]:
    """The estimated images as the estimators' observations (pose, covariance, hits)."""
    out = []
    for r in runs:
        reg = r.registration
        if r.estimates is None or r.camera is None or reg is None or reg.cam_from_world is None:
            continue
        out.append(r.observation if r.observation is not None else ImageObservation(
            image=r.name, camera=r.camera, cam_from_world=reg.cam_from_world,
            pose_covariance=reg.covariance, hits=r.hits))
    return out


@dataclass(frozen=True)
class MethodFusion:
    """Every method fused over the images, the headline among them and the PCM-joint fits."""

    headline: FusedScale
    methods: dict[str, FusedScale]
    pcm_joint: PcmJointResult
    model_checks: ModelChecks | None = None
    intrinsics: IntrinsicsField | None = None


def fuse_all(runs: Sequence[ImageRun], rig: Rig, options: ScaleOptions) -> MethodFusion:
    """Fuse every method over the images; pick the headline (FCM when the rig allows, else
    PCM-joint when its joint beam direction was estimated, else PCM)."""
    per_image = [r.estimates for r in runs if r.estimates is not None]
    fused = {m: fuse(per_image, m, options.fusion) for m in METHODS}
    joint = estimate_pcm_joint(_observations(runs), rig, PcmJointOptions(
        estimation=options.estimation, fusion=options.fusion))
    fused["pcm_joint"] = joint.fused
    pcm = ["pcm_joint", "pcm"] if joint.joint else ["pcm"]
    order = {"fcm": ["fcm"], "pcm": pcm, "all": ["fcm", *pcm]}[options.method]
    if not rig.has_fcm:
        order = [m for m in order if m != "fcm"] or pcm
    headline = next((fused[m] for m in order if np.isfinite(fused[m].value)), fused[order[0]])
    return MethodFusion(headline, fused, joint)


def register_all(loaded: LoadedInputs, options: ScaleOptions, timer: Timer) -> list[ImageRun]:
    """Detect and register every laser image, in order (SIFT may come from the pool)."""
    runs = []
    for li in progress_bar(options.progress, "laser images", iterable=loaded.laser_images,
                           unit="img"):
        t0 = time.perf_counter()
        runs.append(detect_and_register(li, loaded, options, timer))
        trim_heap()  # the image's pixels and detection planes (~16 bytes per pixel)
        what = runs[-1].reason and f"not registered ({runs[-1].reason})"
        logger.info("laser image %s (%s): %s in %.2f s", li.name, li.path,
                    what or "registered", time.perf_counter() - t0)
    pool = loaded.sift_pool
    if pool is not None:
        timer.seconds["sift_here"] = pool.seconds_here
        timer.seconds["sift_in_workers"] = pool.seconds_in_workers
        logger.info("SIFT: %d of %d laser images in %d worker process(es), %.2f s there, "
                    "%.2f s here", pool.images_in_workers, len(runs), pool.workers,
                    pool.seconds_in_workers, pool.seconds_here)
    return runs


def scene_references(runs: Sequence[ImageRun], loaded: LoadedInputs, inputs: ScaleInputs,
                     options: ScaleOptions, timer: Timer) -> list[ImageRun]:
    """Every registered laser image detected again against its scene reference, rendered
    from the model images through the whole mesh (scene_stage.py)."""
    if not options.scene.enabled:
        return list(runs)
    if loaded.mesh is None:
        raise ValueError("scene references need the whole mesh: run them before the crop")
    folder = inputs.model_images or inputs.images
    with timer("scene") if folder is not None else contextlib.nullcontext():  # when it runs
        return detect_all_with_references(
            runs, loaded.model, loaded.mesh, loaded.rig, folder, list(loaded.manual_spots),
            options.detection, options.scene, options.progress)


def image_footprints(runs: Sequence[ImageRun], loaded: LoadedInputs,
                     options: ScaleOptions) -> tuple[Footprint, ...]:
    """The footprint on the whole mesh of every laser image (registered ones; the others with
    their reason) and of every model image, in model units (footprints.py)."""
    if not options.footprints.enabled or loaded.mesh is None:
        return ()
    views = [FootprintView(r.name, "laser", r.camera, None if v is None else v[1],
                           None if v is not None else r.reason or "not registered")
             for r in runs for v in [_view(r)]]
    views += model_views(loaded.model)
    return footprints(views, loaded.mesh.vertices, loaded.mesh.triangles, options.footprints,
                      progress=lambda batches: progress_bar(
                          options.progress, "footprints", iterable=batches, unit="group"))


def _estimate_all(
    inputs: ScaleInputs, loaded: LoadedInputs, runs: list[ImageRun], options: ScaleOptions,
    timer: Timer, given: InMemoryInputs,
) -> tuple[LoadedInputs, list[ImageRun], MethodFusion, dict[str, Any], tuple[Footprint, ...]]:
    """Measure every image's footprint, crop the mesh to the rays, cast and estimate every
    image, fuse, check the mesh against the model: (inputs without the full mesh, runs,
    fusion, checks, footprints)."""
    with timer("footprints"):
        found = image_footprints(runs, loaded, options)
    with timer("raycast"):
        crop = crop_mesh(runs, loaded, options)
        # the crop is all the rest needs but the guided search, which crops again for its rays
        whole = loaded if options.guided.enabled and not loaded.manual_spots else None
        loaded = replace(loaded, mesh=None)
        trim_heap()
        caster = crop.raycaster()
    logger.info("mesh cropped to the spots' rays and the check points: %d of %d triangles "
                "(%.2f %%)", len(crop.triangles), crop.source_triangles, 100 * crop.kept_fraction)
    with timer("estimate"):
        field = intrinsics_field(
            lambda: given.model if given.model is not None else load_model(inputs.model),
            runs, options)
        offset = shared_mesh_offset(runs, caster, field, options)
    runs = [cast_and_estimate(r, loaded, caster, options, timer, field, offset) for r in runs]
    fusion = fuse_all(runs, loaded.rig, options)
    if whole is not None:
        with timer("guided"):
            guided = guided_search(runs, loaded, caster, whole, fusion.headline.value, options)
        if guided is not None:
            searched, caster = guided
            estimated = [_estimate_guided(g, r, loaded, caster, options, timer, field, offset)
                         for g, r in zip(searched, runs, strict=True)]
            if any(e.estimates is not r.estimates for e, r in zip(estimated, runs, strict=True)):
                fusion = fuse_all(estimated, loaded.rig, options)  # new estimates: fuse again
            runs = estimated
        whole = None
        trim_heap()
    for r in runs:
        logger.info("laser image %s: %s", r.name,
                    "estimated" if r.reason is None else f"no estimate ({r.reason})")
    head, methods, model_checks = check_model(fusion.headline, fusion.methods,
                                              fusion.pcm_joint.joint, runs, loaded.model,
                                              field, options)
    fusion = MethodFusion(head, methods, fusion.pcm_joint, model_checks, field)
    checks = {"mesh_model_agreement": mesh_model_agreement(
        mesh_check_points(runs, options, loaded.model.extent), caster, loaded.model.extent,
        lambda: given.mesh if given.mesh is not None else load_mesh(inputs.mesh))}
    logger.info("timings so far: %s", timer.as_dict())
    return loaded, runs, fusion, checks, found


def write_footprints(out: Path, found: Sequence[Footprint], scale: float) -> None:
    """footprints.csv in ``out`` when there is a scale and footprints were measured."""
    if found and np.isfinite(scale):
        write_footprints_csv(out / "footprints.csv", [f.metric(scale) for f in found])


def _provenance_inputs(inputs: ScaleInputs, loaded: LoadedInputs,
                       given: InMemoryInputs) -> list[Path | None]:
    """The files the provenance block hashes: every input of the run given as a file."""
    return [None if given.model is not None else inputs.model,
            None if given.mesh is not None else inputs.mesh,
            inputs.rig, inputs.database, inputs.spots, *(li.path for li in loaded.laser_images)]


def _scaled_writer(inputs: ScaleInputs,
                   given: InMemoryInputs) -> Callable[[Path, float], None] | None:
    """How ``scaled/`` is written when a model or mesh was given in memory (None: from the
    files, report/writer.py): the object rescaled (COLMAP binary model, mesh.ply), the other
    input from its file."""
    if given.reconstruction is None and given.open3d_mesh is None:
        return None

    def write(scaled: Path, scale: float) -> None:
        if given.reconstruction is not None:
            write_scaled_reconstruction(given.reconstruction, scaled / "model", scale)
        elif load_model(inputs.model).source_format == "openmvg":
            write_scaled_openmvg_sfm_data(inputs.model, scaled / "model" / "sfm_data.json",
                                          scale)
        else:
            write_scaled_colmap_model(inputs.model, scaled / "model", scale)
        if given.open3d_mesh is not None:
            write_scaled_open3d_mesh(given.open3d_mesh, scaled, scale)
        else:
            write_scaled_mesh(inputs.mesh, scaled, scale)

    return write


def run(
    inputs: ScaleInputs,
    out_dir: Path | None,
    options: ScaleOptions = ScaleOptions(),  # noqa: B008
    overwrite: bool = False,
    given: InMemoryInputs | None = None,
) -> ScaleResult:
    """The whole ``scale`` command: estimate, fuse and write every output (docs/OUTPUTS.md).
    ``out_dir`` None: nothing is written (not even pycolmap's log capture); the result holds
    the report. ``given``: a model and/or mesh already in memory (the Python API)."""
    given = given or InMemoryInputs()
    if out_dir is not None:
        check_output_dir(out_dir, overwrite)
    timer = Timer()
    glog_capture = captured_colmap_log() if out_dir is not None else glog_without_files()
    with captured_log() as log_lines, glog_capture as colmap_log:
        logger.info("sfm-laserscale %s: scale %s", __version__, inputs)
        for line in inputs.found:  # what a pipeline folder held and what was chosen
            logger.info("found in the pipeline folder: %s", line)
        with timer("load"):
            loaded = load_inputs(inputs, options, given)
        worker_glog: list[str] = []
        try:
            runs = register_all(loaded, options, timer)
        finally:
            if loaded.sift_pool is not None:
                loaded.sift_pool.close()
                worker_glog = loaded.sift_pool.glog_lines
        # registration is over: the index's memory goes
        loaded = replace(loaded, index=None, sift_pool=None)
        trim_heap()
        runs = scene_references(runs, loaded, inputs, options, timer)
        # the SIFT workers are done: the inputs' SHA-256 for the provenance is computed on
        # the core they leave, beside the rest of the run
        hashed = _provenance_inputs(inputs, loaded, given)
        with digests_in_background(hashed) as digests:
            loaded, runs, fusion, checks, found = _estimate_all(inputs, loaded, runs, options,
                                                                timer, given)
            headline, fused, joint = fusion.headline, fusion.methods, fusion.pcm_joint
            with timer("write"):
                report = build_report(inputs, options, loaded, runs, headline, fused, checks,
                                      timer, pcm_joint=joint, model=fusion)
                report["provenance"] = provenance(hashed, options, digests)
                add_input_keys(report, inputs, loaded.held_out, options.reuse_model_poses)
                report["footprints"] = (footprint_summary(found, headline.value)
                                        if found and np.isfinite(headline.value) else None)
            if out_dir is not None:
                with staged_output_dir(out_dir, overwrite) as tmp, timer("write"):
                    write_footprints(tmp, found, headline.value)
                    write_outputs(tmp, inputs, loaded, runs, headline, report, options, timer,
                                  write_scaled=_scaled_writer(inputs, given))
                    logger.info("run finished: %s", report["timings_s"])
                    glog = merged_glog(colmap_log.lines(), worker_glog)
                    (tmp / "run.log").write_text(run_log_text(log_lines, glog),
                                                 encoding="utf-8")
            else:
                report["timings_s"] = timer.as_dict()
    return ScaleResult(
        success=bool(np.isfinite(headline.value)),
        scale=headline,
        methods=fused,
        images=tuple(runs),
        report=report,
        out_dir=out_dir,
        summary=summary_line(headline, runs),
        footprints=found,
    )

