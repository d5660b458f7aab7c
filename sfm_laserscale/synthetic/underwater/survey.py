"""A multi-view underwater survey from the independent generator, for end-to-end tests of scale.

:func:`make_survey` renders, with :mod:`.views` (the physics of :mod:`.conditions`: spectral
water, lamps, Gaussian laser beams with speckle, halo and glow, Bayer sensor, camera
processing, JPEG 4:2:0), one seafloor of green coastal water with pale clutter seen by

- ``n_reference`` reference images (no lasers) along a lawnmower (lines along world x, the
  camera's long side across the track, ``along_overlap`` / ``across_overlap``, nadir-ish
  with small tilts, terrain-following altitude), the input of SfM;
- ``n_laser`` held-out laser images between them (1.8-3 m from the floor, tilted up to
  ``laser_tilt_deg``), the four 532 nm beams on: clipped white cores, green halos and glow,

and writes into ``out_dir``::

    images/ref_000.jpg …          reference images (JPEG files as the camera wrote them)
    laser_images/laser_000.jpg …  laser images
    database.db, pairs.txt        COLMAP database (SIFT, matches of overlapping views)
    sparse/0/                     pycolmap incremental reconstruction (arbitrary frame/scale)
    mesh.ply                      the floor's height field (metric, triangulated every
                                  ``mesh_spacing_m``) mapped into the model frame
    rig.toml                      the rig as a user would have it: the true beams plus the
                                  layout's calibration error (``rig_error_scale`` times it),
                                  with its sigmas (:func:`.layout.rig_toml`)
    truth.json                    true scale (metres per model unit), model_from_world, poses,
                                  true spots, the true rig, SfM statistics, and what the rig
                                  file's calibration error alone does to a one-laser FCM
                                  estimate (``rig_file_fcm_bias_pct`` per spot, and its mean)
    true_spots.csv                image,laser,x,y of the visible true spots (``--spots`` layout)

SfM and the model frame are made exactly as the demo does (``synthetic.dataset``: the same
``run_sfm`` with the known OPENCV camera held fixed, and ``model_from_world`` by Umeyama
between the true and the SfM camera centres); the true scale is
``1 / model_from_world.scale``. Nothing else comes from the rest of the package: no
detection, registration, ray casting, methods or pipeline code.

Run ``python -m sfm_laserscale.synthetic.underwater.survey --out DIR [--seed N]`` to make a
data set by hand, then ``sfm-laserscale scale --model DIR/sparse/0 --mesh DIR/mesh.ply
--laser-images DIR/laser_images --rig DIR/rig.toml --database DIR/database.db --out RUN``.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import shutil
import time
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.geometry import qvec_from_rotmat
from sfm_laserscale.model import Camera
from sfm_laserscale.synthetic.dataset import (
    Alignment,
    DemoDataOptions,
    SfmStats,
    align_model,
    model_centres,
    run_sfm,
    write_mesh_ply,
)
from sfm_laserscale.synthetic.underwater import layout, optics, spectra, surface, texture
from sfm_laserscale.synthetic.underwater.conditions import (
    Condition,
    sensor_settings,
    vehicle_lamps,
)
from sfm_laserscale.synthetic.underwater.views import (
    CameraPose,
    FloorClutter,
    SurveyScene,
    View,
    floor_clutter,
    floor_points,
    hits_of,
    pixel_floor_points,
    project_world,
    random_patches,
    render_view,
    visible_truth,
)
from sfm_laserscale.synthetic.underwater.water import WATER_TYPES

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
#: what make_survey writes (cleared first when overwriting)
OUTPUTS = ("images", "laser_images", "database.db", "pairs.txt", "sparse", "sparse_all",
           "mesh.ply", "rig.toml", "truth.json", "true_spots.csv")
#: pale patches keep this far (m, beyond their radius) from every true laser hit
SPOT_CLEARANCE_M = 0.015
#: tries to place a laser view whose four spots are all visible
MAX_LASER_TRIES = 200


@dataclass(frozen=True)
class SurveyOptions:
    """What :func:`make_survey` renders (see the module docstring)."""

    width: int = 960
    height: int = 540
    n_reference: int = 12
    lines: int = 3
    n_laser: int = 4
    altitude_m: float = 2.5
    along_overlap: float = 0.7
    across_overlap: float = 0.6
    reference_tilt_deg: float = 5.0
    laser_distance_m: tuple[float, float] = (1.8, 3.0)
    laser_tilt_deg: float = 15.0
    wavelength_nm: float = 532.0
    water: str = "green_coastal"
    peak_over_white: tuple[float, float] = (3.0, 30.0)  # clipped cores
    exposure_green: tuple[float, float] = (0.6, 0.75)  # median output green (green water)
    jpeg_quality: tuple[int, int] = (80, 95)
    pale_patches_per_m2: float = 60.0
    pale_diameter_m: tuple[float, float] = (0.006, 0.03)  # 2-10 px at 2.5 m
    relief_max_slope: float = 0.2
    rig_error_scale: float = 1.0  # 1: the layout's calibration error; 0: the true rig
    mesh_spacing_m: float = 0.02
    mesh_margin_m: float = 0.3
    max_features: int = 4000
    min_pair_overlap: float = 0.15
    seed: int = 0
    progress: bool = False


@dataclass(frozen=True)
class Survey:
    """Paths of the written data set and its headline truth."""

    out_dir: Path
    images_dir: Path
    laser_images_dir: Path
    database_path: Path
    model_dir: Path
    mesh_path: Path
    rig_path: Path
    truth_path: Path
    spots_path: Path
    true_scale: float  # metres per model unit
    sfm: SfmStats
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class _Views:
    names: list[str]
    poses: list[CameraPose]
    rendered: list[View] = field(default_factory=list)


# --------------------------------------------------------------------------- poses


def _rot(axis: int, angle: float) -> F64:
    """Rotation by ``angle`` (rad) about a coordinate axis (0 x, 1 y, 2 z)."""
    c, s = math.cos(angle), math.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def nadir_pose(centre: F64, heading_rad: float, pitch_rad: float = 0.0,
               roll_rad: float = 0.0) -> CameraPose:
    """A down-looking camera at ``centre`` travelling towards ``heading`` (image up = the
    world direction (cos h, sin h, 0)), then turned in its own frame by pitch (about its x)
    and roll (about its y)."""
    up = np.array([math.cos(heading_rad), math.sin(heading_rad), 0.0])
    z = np.array([0.0, 0.0, -1.0])
    y = -up
    x = np.cross(y, z)
    base = np.stack([x, y, z])
    turn = _rot(0, pitch_rad) @ _rot(1, roll_rad)
    R = turn.T @ base
    return CameraPose(R=R, t=-R @ np.asarray(centre, np.float64))


def _footprint_m(cam: optics.CameraModel, distance_m: float) -> tuple[float, float]:
    """Nadir footprint (across = image width, along = image height) at this distance."""
    return distance_m * cam.width / cam.fx, distance_m * cam.height / cam.fy


def reference_poses(options: SurveyOptions, cam: optics.CameraModel, relief: F64,
                    rng: np.random.Generator) -> list[CameraPose]:
    """Lawnmower: ``lines`` lines along world x (alternate headings), terrain-following."""
    across, along = _footprint_m(cam, options.altitude_m)
    step_along = (1.0 - options.along_overlap) * along
    step_across = (1.0 - options.across_overlap) * across
    per_line = math.ceil(options.n_reference / options.lines)
    tilt = math.radians(options.reference_tilt_deg)
    poses = []
    for k in range(options.n_reference):
        line, j = divmod(k, per_line)
        j = j if line % 2 == 0 else per_line - 1 - j
        x = (j - (per_line - 1) / 2) * step_along + rng.normal(0.0, 0.05)
        y = (line - (options.lines - 1) / 2) * step_across + rng.normal(0.0, 0.05)
        z = float(floor_points(relief, np.array(x), np.array(y))[2])
        z += options.altitude_m + rng.uniform(-0.15, 0.15)
        heading = (0.0 if line % 2 == 0 else math.pi) + math.radians(rng.uniform(-5.0, 5.0))
        poses.append(nadir_pose(np.array([x, y, z]), heading, rng.uniform(-tilt, tilt),
                                rng.uniform(-tilt, tilt)))
    return poses


def _laser_pose(options: SurveyOptions, relief: F64, reference: list[CameraPose],
                distance: float, tilt_deg: float, rng: np.random.Generator) -> CameraPose:
    """A view between two consecutive reference views of a line, ``distance`` from the floor
    along its axis, tilted ``tilt_deg`` towards a random azimuth."""
    per_line = math.ceil(options.n_reference / options.lines)
    line = int(rng.integers(options.lines))
    j = int(rng.integers(max(per_line - 1, 1)))
    a = reference[min(line * per_line + j, len(reference) - 1)]
    b = reference[min(line * per_line + j + 1, len(reference) - 1)]
    xy = 0.5 * (a.centre[:2] + b.centre[:2]) + rng.uniform(-0.1, 0.1, 2)
    heading = (0.0 if line % 2 == 0 else math.pi) + math.radians(rng.uniform(-10.0, 10.0))
    az = rng.uniform(0.0, 2.0 * math.pi)
    tilt = math.radians(tilt_deg)
    probe = nadir_pose(np.zeros(3), heading, tilt * math.cos(az), tilt * math.sin(az))
    target = floor_points(relief, np.array(xy[0]), np.array(xy[1]))
    return nadir_pose(target - distance * probe.axis, heading, tilt * math.cos(az),
                      tilt * math.sin(az))


def laser_poses(options: SurveyOptions, scene: SurveyScene, reference: list[CameraPose],
                rng: np.random.Generator) -> list[CameraPose]:
    """Held-out views at spread distances and tilts whose four spots are all visible."""
    n = options.n_laser
    dists = rng.permutation(np.linspace(*options.laser_distance_m, n))
    tilts = rng.permutation(np.linspace(0.0, options.laser_tilt_deg, n))
    poses = []
    for k in range(n):
        for _ in range(MAX_LASER_TRIES):
            pose = _laser_pose(options, scene.relief, reference, float(dists[k]),
                               float(tilts[k]), rng)
            hits = hits_of(scene, pose)
            if all(visible_truth(hits.get(b.name), scene.cam) for b in scene.beams):
                poses.append(pose)
                break
        else:
            raise RuntimeError(f"no laser view with every spot visible in {MAX_LASER_TRIES} "
                               "tries")
    return poses


# --------------------------------------------------------------------------- scene


def _condition(options: SurveyOptions) -> Condition:
    """The frame condition the survey's camera settings and laser spots are drawn from."""
    return Condition(
        "survey", "green 532 nm beams in green-cyan coastal water, pale clutter, clipped cores",
        wavelengths_nm=(options.wavelength_nm,), waters=(options.water,),
        peak_over_white=options.peak_over_white, exposure_green=options.exposure_green,
        pale_clutter=True, jpeg_quality=options.jpeg_quality)


def _base_scene(options: SurveyOptions, rng: np.random.Generator) -> SurveyScene:
    """Camera, relief, seabed look and noise, water, lamps, camera settings, rig (no clutter
    yet: it is placed once the views are known)."""
    if options.water not in WATER_TYPES:
        raise ValueError(f"unknown water {options.water!r} (known: {', '.join(WATER_TYPES)})")
    cond = _condition(options)
    cam = optics.random_camera(rng, options.width, options.height)
    relief = surface.random_relief(rng, max_slope=options.relief_max_slope)
    look = texture.random_look(rng)
    bank = texture.make_noise_bank(rng)
    lamps = vehicle_lamps(rng)
    settings = sensor_settings(rng, cond)
    beams = layout.random_beams(rng, options.wavelength_nm)
    return SurveyScene(cam=cam, relief=relief, look=look, bank=bank,
                       water=WATER_TYPES[options.water], lamps=lamps, settings=settings,
                       beams=beams, clutter=FloorClutter.empty(), exposure_green=float(
                           rng.uniform(*options.exposure_green)), spots=cond)


def _footprint_points(scene: SurveyScene, pose: CameraPose, grid: int = 12) -> F64:
    """(M, 3) world floor points seen on a ``grid`` × ``grid`` lattice of the image."""
    cam = scene.cam
    gx, gy = np.meshgrid(np.linspace(0.5, cam.width - 0.5, grid),
                         np.linspace(0.5, cam.height - 0.5, grid))
    pts, ok = pixel_floor_points(scene.relief, cam, pose, np.column_stack([gx.ravel(),
                                                                           gy.ravel()]))
    return pts[ok]


def survey_bounds(scene: SurveyScene, poses: list[CameraPose], margin_m: float
                  ) -> tuple[F64, F64]:
    """(min xy, max xy) of every view's footprint, widened by ``margin_m``."""
    pts = np.concatenate([_footprint_points(scene, p)[:, :2] for p in poses])
    return pts.min(axis=0) - margin_m, pts.max(axis=0) + margin_m


def overlapping_pairs(scene: SurveyScene, poses: list[CameraPose], min_overlap: float
                      ) -> list[tuple[int, int]]:
    """Index pairs (i < j) of views that share at least ``min_overlap`` of a footprint (the
    larger fraction of one view's sampled floor points inside the other image): the pairs a
    survey's navigation would match."""
    cam = scene.cam
    feet = [_footprint_points(scene, p) for p in poses]

    def inside(points: F64, pose: CameraPose) -> float:
        px, depth = project_world(cam, pose, points)
        ok = ((depth > 0) & (px[:, 0] >= 0) & (px[:, 0] <= cam.width)
              & (px[:, 1] >= 0) & (px[:, 1] <= cam.height))
        return float(ok.mean()) if len(ok) else 0.0

    return [(i, j) for i in range(len(poses)) for j in range(i + 1, len(poses))
            if max(inside(feet[i], poses[j]), inside(feet[j], poses[i])) >= min_overlap]


def _with_patches(scene: SurveyScene, options: SurveyOptions, bounds: tuple[F64, F64],
                  laser: list[CameraPose], rng: np.random.Generator) -> SurveyScene:
    """The scene with its pale clutter, kept ``SPOT_CLEARANCE_M`` from every laser hit."""
    away = [(np.asarray(pose.R.T @ (hit.point_m - pose.t)), SPOT_CLEARANCE_M)
            for pose in laser for hit in hits_of(scene, pose).values()]
    patches = random_patches(rng, bounds, options.pale_patches_per_m2, options.pale_diameter_m,
                             away)
    return replace(scene, clutter=floor_clutter(scene.relief, patches))


# --------------------------------------------------------------------------- mesh


def grid_triangles(nx: int, ny: int) -> NDArray[np.int32]:
    """(2 (nx-1)(ny-1), 3) triangles of a row-major ny × nx vertex grid, counter-clockwise
    seen from +z."""
    idx = np.arange(nx * ny, dtype=np.int32).reshape(ny, nx)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def floor_mesh(relief: F64, bounds: tuple[F64, F64], spacing_m: float
               ) -> tuple[F64, NDArray[np.int32]]:
    """The floor's height field over ``bounds`` triangulated every ``spacing_m`` (metres)."""
    lo, hi = bounds
    nx = int(math.ceil((hi[0] - lo[0]) / spacing_m)) + 1
    ny = int(math.ceil((hi[1] - lo[1]) / spacing_m)) + 1
    x, y = np.meshgrid(lo[0] + spacing_m * np.arange(nx), lo[1] + spacing_m * np.arange(ny))
    return floor_points(relief, x.ravel(), y.ravel()), grid_triangles(nx, ny)


# --------------------------------------------------------------------------- writing


def _prepare_out_dir(out_dir: Path, overwrite: bool) -> None:
    """Create ``out_dir``; refuse a non-empty one unless ``overwrite`` (then clear our files)."""
    if out_dir.exists() and any(out_dir.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out_dir}: output folder is not empty (use overwrite)")
        for name in OUTPUTS:
            p = out_dir / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    (out_dir / "laser_images").mkdir(parents=True, exist_ok=True)


def _render_all(scene: SurveyScene, ref: _Views, las: _Views, out_dir: Path, seed: int,
                progress: bool) -> None:
    """Render every view (one random stream each) and write its JPEG file."""
    jobs = [(ref, k, False, "images") for k in range(len(ref.names))]
    jobs += [(las, k, True, "laser_images") for k in range(len(las.names))]
    streams = np.random.SeedSequence([seed, 0x5E7]).spawn(len(jobs))
    for n, ((views, k, on, folder), stream) in enumerate(zip(jobs, streams, strict=True)):
        t0 = time.perf_counter()
        view = render_view(scene, views.poses[k], on, np.random.default_rng(stream))
        (out_dir / folder / views.names[k]).write_bytes(view.jpeg)
        views.rendered.append(view)
        (logger.info if progress else logger.debug)(
            "rendered %s (%d/%d) in %.1f s", views.names[k], n + 1, len(jobs),
            time.perf_counter() - t0)


def _pose_json(pose: CameraPose) -> dict[str, list[float]]:
    return {"rotation_wxyz": [float(v) for v in qvec_from_rotmat(pose.R)],
            "translation": [float(v) for v in pose.t]}


def _cam_from_model(align: Alignment, pose: CameraPose) -> CameraPose:
    """The same camera in the model frame (translation in model units)."""
    R = pose.R @ align.R.T
    return CameraPose(R=R, t=align.scale * pose.t - R @ align.t)


def rig_file_bias_pct(rig: dict[str, tuple[F64, F64]], laser: str, pose: CameraPose,
                      hit_world: F64) -> float:
    """How far (%) a one-laser FCM scale would be from the truth with the true hit and the
    rig file's beam ``rig[laser]`` = (origin, direction): its calibration error alone. FCM
    (DESIGN.md §3) moves the hit X (camera frame) back along the beam to the plane z = 0,
    O' = X - (X_z / v_z) v, and compares |O'| with the file's |O| (here in metres: the true
    scale is 1)."""
    origin, direction = rig[laser]
    v = direction / np.linalg.norm(direction)
    x = pose.R @ hit_world + pose.t
    o_hat = x - (x[2] / v[2]) * v
    return float(100.0 * (np.linalg.norm(origin) / np.linalg.norm(o_hat) - 1.0))


def read_rig_beams(text: str) -> dict[str, tuple[F64, F64]]:
    """Laser name -> (origin, direction) of a rig file's text."""
    return {las["name"]: (np.asarray(las["origin"], np.float64),
                          np.asarray(las["direction"], np.float64))
            for las in tomllib.loads(text)["laser"]}


def _spots_json(view: View, pose: CameraPose, align: Alignment,
                rig: dict[str, tuple[F64, F64]]) -> list[dict[str, Any]]:
    out = []
    for name, xy in view.truth.items():
        hit = view.hits_world.get(name)
        meta = view.meta["spots"].get(name, {})
        out.append({
            "laser": name, "visible": xy is not None,
            "x": None if xy is None else xy[0], "y": None if xy is None else xy[1],
            "hit_world": None if hit is None else [float(v) for v in hit],
            "hit_model": None if hit is None else [float(v) for v in align.apply(hit)[0]],
            "beam_range_m": meta.get("range_m"), "camera_distance_m": meta.get(
                "camera_distance_m"), "peak_over_white": meta.get("peak_over_white"),
            "sigma_major_px": meta.get("sigma_major_px"),
            "rig_file_fcm_bias_pct": None if hit is None else rig_file_bias_pct(
                rig, name, pose, hit)})
    return out


def _truth(options: SurveyOptions, scene: SurveyScene, ref: _Views, las: _Views,
           align: Alignment, stats: SfmStats, n_pairs: int, rig_text: str) -> dict[str, Any]:
    """The content of truth.json."""
    rig = read_rig_beams(rig_text)
    laser_images = [
        {"name": n, "cam_from_world": _pose_json(p),
         "cam_from_model": _pose_json(_cam_from_model(align, p)),
         "distance_m": v.meta["distance_m"], "tilt_deg": v.meta["tilt_deg"],
         "pale_patches_drawn": v.meta["pale_patches_drawn"],
         "spots": _spots_json(v, p, align, rig)}
        for n, p, v in zip(las.names, las.poses, las.rendered, strict=True)]
    biases = [s["rig_file_fcm_bias_pct"] for im in laser_images for s in im["spots"]
              if s["visible"]]
    return {
        "generator": __name__,
        "true_scale": 1.0 / align.scale, "true_scale_units": "metres per model unit",
        "model_from_world": {"scale": align.scale,
                             "rotation_wxyz": [float(v) for v in qvec_from_rotmat(align.R)],
                             "translation": [float(v) for v in align.t]},
        "alignment_rms_m": align.rms_m, "alignment_max_m": align.max_m,
        "camera": optics.colmap_camera_spec(scene.cam), "seed": options.seed,
        "water": scene.water.name, "wavelength_nm": options.wavelength_nm,
        "exposure_green": scene.exposure_green, "jpeg_quality": scene.settings.jpeg_quality,
        "pale_patches": len(scene.clutter.patches), "rig_error_scale": options.rig_error_scale,
        "rig_file_fcm_bias_pct_mean": float(np.mean(biases)) if biases else None,
        "true_rig": [{"name": b.name, "origin": [float(v) for v in b.origin_m],
                      "direction": [float(v) for v in b.direction],
                      "waist_mm": 1e3 * b.waist_m, "divergence_mrad": 1e3 * b.divergence_rad}
                     for b in scene.beams],
        "sfm": {"n_images": stats.n_images, "n_registered": stats.n_registered,
                "n_points": stats.n_points, "n_models": stats.n_models, "n_pairs": n_pairs,
                "mean_reprojection_error_px": stats.mean_reprojection_error_px,
                "mean_track_length": stats.mean_track_length},
        "reference_images": [{"name": n, "cam_from_world": _pose_json(p),
                              "pale_patches_drawn": v.meta["pale_patches_drawn"]}
                             for n, p, v in zip(ref.names, ref.poses, ref.rendered, strict=True)],
        "laser_images": laser_images,
    }


def _write_spots_csv(path: Path, las: _Views) -> None:
    """The visible true spots as ``image,laser,x,y`` (COLMAP pixel convention)."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(["image", "laser", "x", "y"])
        for name, view in zip(las.names, las.rendered, strict=True):
            for laser, xy in view.truth.items():
                if xy is not None:
                    writer.writerow([name, laser, f"{xy[0]:.6f}", f"{xy[1]:.6f}"])


def _camera(cam: optics.CameraModel) -> Camera:
    """The generator's camera as the package's OPENCV camera (for COLMAP)."""
    return Camera(camera_id=1, model="OPENCV", width=cam.width, height=cam.height,
                  params=np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.k1, cam.k2, cam.p1,
                                   cam.p2]))


# --------------------------------------------------------------------------- the job


def _plan(options: SurveyOptions) -> tuple[SurveyScene, _Views, _Views, tuple[F64, F64]]:
    """Scene, reference and laser views, surveyed area (everything before rendering)."""
    scene_ss, pose_ss, patch_ss = np.random.SeedSequence([options.seed, 0x5C]).spawn(3)
    scene = _base_scene(options, np.random.default_rng(scene_ss))
    pose_rng = np.random.default_rng(pose_ss)
    ref_poses = reference_poses(options, scene.cam, scene.relief, pose_rng)
    las_poses = laser_poses(options, scene, ref_poses, pose_rng)
    bounds = survey_bounds(scene, ref_poses + las_poses, options.mesh_margin_m)
    scene = _with_patches(scene, options, bounds, las_poses, np.random.default_rng(patch_ss))
    ref = _Views([f"ref_{k:03d}.jpg" for k in range(len(ref_poses))], ref_poses)
    las = _Views([f"laser_{k:03d}.jpg" for k in range(len(las_poses))], las_poses)
    return scene, ref, las, bounds


def make_survey(out_dir: Path, options: SurveyOptions = SurveyOptions(),
                overwrite: bool = False) -> Survey:
    """Render, reconstruct and write the survey data set (see the module docstring)."""
    out_dir = Path(out_dir)
    timings: dict[str, float] = {}
    t_all = t0 = time.perf_counter()
    _prepare_out_dir(out_dir, overwrite)
    scene, ref, las, bounds = _plan(options)
    timings["plan"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    _render_all(scene, ref, las, out_dir, options.seed, options.progress)
    timings["render"] = time.perf_counter() - t0
    pairs = overlapping_pairs(scene, ref.poses, options.min_pair_overlap)
    (out_dir / "pairs.txt").write_text(
        "".join(f"{ref.names[i]} {ref.names[j]}\n" for i, j in pairs), encoding="utf-8")
    sfm_options = DemoDataOptions(max_features=options.max_features, sift_first_octave=0,
                                  seed=options.seed, progress=options.progress)
    rec, stats, sfm_t = run_sfm(out_dir / "images", ref.names, out_dir / "database.db",
                                out_dir / "sparse" / "0", _camera(scene.cam),
                                out_dir / "pairs.txt", sfm_options)
    timings.update(sfm_t)
    t0 = time.perf_counter()
    align = align_model({n: p.centre for n, p in zip(ref.names, ref.poses, strict=True)},
                        model_centres(rec))
    vertices, triangles = floor_mesh(scene.relief, bounds, options.mesh_spacing_m)
    write_mesh_ply(out_dir / "mesh.ply", align.apply(vertices), triangles)
    rig_rng = np.random.default_rng(np.random.SeedSequence([options.seed, 0x216]))
    rig_text = layout.rig_toml(scene.beams, spectra.color_name(options.wavelength_nm), rig_rng,
                               name=f"underwater survey rig ({options.wavelength_nm:.0f} nm)",
                               error_scale=options.rig_error_scale)
    (out_dir / "rig.toml").write_text(rig_text, encoding="utf-8")
    truth = _truth(options, scene, ref, las, align, stats, len(pairs), rig_text)
    (out_dir / "truth.json").write_text(json.dumps(truth, indent=2), encoding="utf-8")
    _write_spots_csv(out_dir / "true_spots.csv", las)
    timings["write"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    logger.info("survey in %s: %d/%d reference images registered, scale %.6g m/unit, "
                "alignment RMS %.2g mm, %.0f s", out_dir, stats.n_registered, stats.n_images,
                truth["true_scale"], 1e3 * align.rms_m, timings["total"])
    return Survey(out_dir=out_dir, images_dir=out_dir / "images",
                  laser_images_dir=out_dir / "laser_images",
                  database_path=out_dir / "database.db", model_dir=out_dir / "sparse" / "0",
                  mesh_path=out_dir / "mesh.ply", rig_path=out_dir / "rig.toml",
                  truth_path=out_dir / "truth.json", spots_path=out_dir / "true_spots.csv",
                  true_scale=float(truth["true_scale"]), sfm=stats, timings=timings)


def main(argv: list[str] | None = None) -> int:
    """``python -m sfm_laserscale.synthetic.underwater.survey --out DIR [--seed N]``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder (created)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rig-error-scale", type=float, default=1.0,
                        help="calibration error of rig.toml: 1 the layout's, 0 none")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    survey = make_survey(args.out, SurveyOptions(seed=args.seed, progress=True,
                                                 rig_error_scale=args.rig_error_scale),
                         overwrite=args.overwrite)
    logger.info("true scale %.9g m per model unit (%s)", survey.true_scale, survey.truth_path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
