"""The demo data set: rendered survey images, a real SfM model of them, laser images and truth.

:func:`make_demo_dataset` writes into ``out_dir``::

    images/ref_000.png …        reference images (rendered, no laser spots) — the SfM input
    laser_images/laser_000.png  held-out images with laser spots (rendered + painted + noise)
    database.db                 COLMAP database of the reference images (SIFT, matches)
    pairs.txt                   the image pairs matched: views that overlap (navigation-based
                                pairing, as a survey would use its vehicle's navigation)
    sparse/0/                   pycolmap incremental reconstruction (binary), arbitrary frame/scale
    mesh.ply                    the metric scene mesh mapped INTO THE MODEL FRAME (float64 x y z,
                                uchar colours, faces) — stands in for an MVS mesh
    rig.toml                    the laser rig (metres, camera frame)
    truth.json                  true scale (metres per model unit), model_from_world, true poses,
                                true spot positions, SfM statistics
    true_spots.csv              image,laser,x,y of the true spots (the ``--spots`` CSV layout)

The world is metric (scene.py: z up, metres). ``model_from_world`` is the similarity estimated
by Umeyama between the true camera centres and the SfM camera centres, so the true scale the
tool must find is ``s_true = 1 / model_from_world.scale`` metres per model unit.

Laser rigs (``DemoDataOptions.rig``), origins at the four corners of a 0.234 m square around the
lens (‖O‖ = 0.165 m), all of one colour (``DemoDataOptions.laser_color``: red, green or blue):

- ``"rov"`` (default, like the paper's configuration C, a misaligned ROV scaler): L3 and L4 are
  2.2° and 2.8° off the optical axis in unrelated directions; L1 and L2 are *exactly parallel*
  to each other, 1.5° off the axis (tilted in the camera's y–z plane, so the camera is
  equidistant from both beams) and form the one ``[[pair]]`` (separation 0.234 m) for PCM.
- ``"parallel"``: four beams parallel to the optical axis; pairs (L1, L2) and (L4, L3).
- ``"diverging"``: each beam tilted 3° outwards (away from the optical axis, along its origin's
  direction): FCM responds to a focal-length error of the model almost one to one.

``sfm_focal_error`` (δf / f): the SfM is run with the camera's focal length off by this much
(held fixed), a reconstruction with its own error; the mesh is then the scene carried into that
model by a smooth map fitted to its points (``synthetic/model_warp.py``), as an MVS mesh of that
model would be. Such a model is no similarity of the world: its camera centres and its points
have slightly different scales (by ~0.2 × δf/f on the demo's survey). The true scale is then
the one of the mesh a user measures on, the Umeyama fit of the mesh's vertices (world ->
model); the camera centres' fit is kept in truth.json as ``true_scale_cameras``.

Spots are painted (``spots.paint_spot``, sigma = focal · ``beam_sigma_m`` / depth, in the rig's
colour, white clipped core) only where the beam's first hit projects inside the image and is not
occluded from the camera.

Water (``DemoDataOptions.water``): ``"clear"`` keeps ``options.render`` and ``options.scene`` as
given; ``"green"`` (green coastal water, as for green-beam surveys) replaces the render's water
colour and attenuation by :data:`GREEN_WATER_RGB` and :data:`GREEN_WATER_ATTENUATION` (red dies
fast, green carries: a green-cyan cast and veiling light) and scatters pale clutter (shell hash,
mineral speckle, 8-40 mm: 2-10 px in the images) over the seafloor texture
(``SceneOptions.pale_patches_per_m2`` = :data:`GREEN_WATER_PALE_PATCHES_PER_M2`). Rendering is
seeded and exact; COLMAP's multi-threaded mapping is not bit-reproducible (the true scale of two
runs agrees to ~1e-7), but every file of one run is consistent with its own truth.json.
"""

from __future__ import annotations

import csv
import json
import logging
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import plyfile
import pycolmap
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.geometry import qvec_from_rotmat, umeyama_sim3
from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.provenance import progress_bar
from sfm_laserscale.registration.mapping import mapping_options
from sfm_laserscale.rig import Laser, Pair, Rig, rig_to_toml
from sfm_laserscale.synthetic.model_warp import fit_model_warp
from sfm_laserscale.synthetic.render import (
    RenderOptions,
    SceneRaycaster,
    add_sensor_noise,
    nadir_pose,
    render_image,
)
from sfm_laserscale.synthetic.scene import Scene, SceneOptions, make_scene
from sfm_laserscale.synthetic.spots import paint_spot, to_uint8

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Laser origins: corners of a square of side 2 × 0.117 m (‖O‖ = 0.1655 m), camera frame.
_CORNER = 0.117
#: Laser colours the demo paints (spots.LASER_RGB) and water presets it knows.
LASER_COLORS = ("red", "green", "blue")
WATERS = ("clear", "green")
#: Green coastal water: veiling light (linear RGB, green-cyan) and attenuation per channel (1/m).
GREEN_WATER_RGB: tuple[float, float, float] = (0.02, 0.20, 0.15)
GREEN_WATER_ATTENUATION: tuple[float, float, float] = (0.45, 0.07, 0.12)
#: Pale clutter density in green water (≈ 300 patches in a 2.8 × 2.1 m view).
GREEN_WATER_PALE_PATCHES_PER_M2 = 50.0
#: Files and folders that make_demo_dataset writes (removed first when overwriting).
OUTPUTS = ("images", "laser_images", "database.db", "pairs.txt", "sparse", "mesh.ply",
           "rig.toml", "truth.json", "true_spots.csv")


class SfmFailedError(RuntimeError):
    """The reconstruction of the rendered reference images failed or is incomplete."""


@dataclass(frozen=True)
class DemoDataOptions:
    """What :func:`make_demo_dataset` renders and reconstructs.

    ``small=True`` replaces image size, focal, image counts and the scene by a faster preset
    (640 × 480, 8 reference and 3 laser images, a 7 × 7 m scene with a 2048² texture).
    ``seed`` seeds everything (it replaces ``scene.seed``). ``laser_color`` (red | green | blue)
    is the colour of every beam (rig file and painted spots); ``water`` (clear | green) selects
    the water preset (module docstring).
    """

    image_size: tuple[int, int] = (1024, 768)  # width, height (pixels)
    focal_px: float = 900.0  # PINHOLE fx = fy; principal point at the image centre
    n_reference: int = 16  # lawnmower grid (rows × cols chosen near square)
    n_laser: int = 6
    altitude_m: float = 2.5  # mean reference altitude above the mean floor (z = 0)
    along_overlap: float = 0.65  # image overlap between neighbours along a line
    across_overlap: float = 0.55  # overlap between neighbouring lines
    reference_tilt_deg: float = 12.0  # max |pitch|, |roll| of reference views (uniform)
    laser_distance_m: tuple[float, float] = (1.8, 3.5)  # range along the optical axis
    laser_max_tilt_deg: float = 20.0
    rig: str = "rov"  # rov | parallel (see the module docstring)
    laser_color: str = "red"  # red | green | blue
    water: str = "clear"  # clear | green (green coastal water, pale clutter on the floor)
    beam_sigma_m: float = 0.005  # spot radius (Gaussian sigma) on the surface, metres
    spot_peak: float = 3.0  # linear peak of the spot core (> 1 saturates)
    noise_std: float = 0.004  # Gaussian sensor noise, linear units
    gamma: float = 2.2  # encoding of the 8-bit PNGs
    max_features: int = 4000  # SIFT features per image for SfM
    sift_first_octave: int = 0  # 0: no upsampling (≈5× faster than COLMAP's −1 here)
    min_pair_overlap: float = 0.15  # match only image pairs whose views overlap this much
    scene: SceneOptions = field(default_factory=SceneOptions)
    render: RenderOptions = field(default_factory=RenderOptions)
    seed: int = 0
    small: bool = False
    progress: bool = True
    colmap_log: bool = False  # let COLMAP print its INFO log
    sfm_focal_error: float = 0.0  # δf / f of the focal length the SfM is given (held fixed)


@dataclass(frozen=True)
class TrueSpot:
    """Where a beam meets the scene and where that point appears in an image."""

    laser: str
    visible: bool
    xy_px: tuple[float, float] | None  # COLMAP convention; None when not visible
    hit_world: F64 | None  # (3,) metres
    beam_range_m: float  # from the laser origin to the hit (inf if none)
    reason: str = ""  # why not visible


@dataclass(frozen=True)
class SfmStats:
    """Summary of the reconstruction of the reference images."""

    n_images: int
    n_registered: int
    n_points: int
    mean_reprojection_error_px: float
    mean_track_length: float
    n_models: int


@dataclass(frozen=True)
class Alignment:
    """``model_from_world`` similarity (X_model = s R X_world + t) and its fit residual."""

    scale: float
    R: F64
    t: F64
    rms_m: float  # RMS of the camera-centre residuals, metres
    max_m: float

    def apply(self, xyz_world: F64) -> F64:
        """(N, 3) world metres -> model units."""
        return np.asarray(self.scale * np.atleast_2d(xyz_world) @ self.R.T + self.t)

    def cam_from_model(self, cam_from_world: Pose) -> Pose:
        """The same camera's pose in the model frame (translation in model units)."""
        R = cam_from_world.R @ self.R.T
        t = self.scale * cam_from_world.t - R @ self.t
        return Pose(R=R, t=t)


@dataclass(frozen=True)
class DemoDataset:
    """Paths of the written data set and its ground truth."""

    out_dir: Path
    images_dir: Path
    laser_images_dir: Path
    database_path: Path
    model_dir: Path
    mesh_path: Path
    rig_path: Path
    truth_path: Path
    spots_path: Path
    rig: Rig
    camera: Camera
    true_scale: float  # metres per model unit
    alignment_rms_m: float
    sfm: SfmStats
    timings: dict[str, float]


# --------------------------------------------------------------------------- options, rigs


def resolve_options(options: DemoDataOptions) -> DemoDataOptions:
    """Check the colour and water names, apply the ``small`` preset and the water preset
    (a no-op for the defaults)."""
    if options.laser_color not in LASER_COLORS:
        raise InputError(f"unknown laser colour {options.laser_color!r} "
                         f"(known: {', '.join(LASER_COLORS)})")
    if options.water not in WATERS:
        raise InputError(f"unknown water {options.water!r} (known: {', '.join(WATERS)})")
    if options.small:
        scene = replace(options.scene, size_m=(7.0, 7.0), texture_px=2048)
        options = replace(options, image_size=(640, 480), focal_px=900.0 * 640 / 1024,
                          n_reference=8, n_laser=3, max_features=2000, scene=scene)
    if options.water == "green":
        render = replace(options.render, water_rgb=GREEN_WATER_RGB,
                         attenuation_per_m=GREEN_WATER_ATTENUATION)
        scene = replace(options.scene, pale_patches_per_m2=GREEN_WATER_PALE_PATCHES_PER_M2)
        options = replace(options, render=render, scene=scene)
    return options


def demo_camera(options: DemoDataOptions) -> Camera:
    """The PINHOLE camera of every demo image (principal point at the image centre)."""
    w, h = options.image_size
    f = float(options.focal_px)
    return Camera(camera_id=1, model="PINHOLE", width=int(w), height=int(h),
                  params=np.array([f, f, w / 2.0, h / 2.0]))


def _dir(tilt_deg: float, azimuth_deg: float) -> list[float]:
    """Unit beam direction tilted ``tilt_deg`` off +z towards ``azimuth_deg`` in the x–y plane."""
    t, a = np.radians(tilt_deg), np.radians(azimuth_deg)
    v = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
    v[np.abs(v) < 1e-15] = 0.0  # exact zeros (cos 90° is 6e-17 in floating point)
    return [float(x) for x in v]


def make_rig(kind: str = "rov", color: str = "red") -> Rig:
    """The demo laser scaler (see the module docstring), every beam of ``color``."""
    c = _CORNER
    origins = {"L1": [-c, -c, 0.0], "L2": [c, -c, 0.0], "L3": [c, c, 0.0], "L4": [-c, c, 0.0]}
    if kind == "rov":
        dirs = {"L1": _dir(1.5, 90.0), "L2": _dir(1.5, 90.0), "L3": _dir(2.2, 330.0),
                "L4": _dir(2.8, 160.0)}
        pair_names = [("L1", "L2")]
        name = "synthetic ROV laser scaler (misaligned, config C-like)"
    elif kind == "parallel":
        dirs = {k: [0.0, 0.0, 1.0] for k in origins}
        pair_names = [("L1", "L2"), ("L4", "L3")]
        name = "synthetic parallel laser scaler"
    elif kind == "diverging":
        dirs = {k: _dir(3.0, float(np.degrees(np.arctan2(o[1], o[0])))) for k, o in origins.items()}
        pair_names = []
        name = "synthetic diverging laser scaler"
    else:
        raise InputError(f"unknown demo rig {kind!r} (known: rov, parallel, diverging)")
    lasers = tuple(Laser(name=k, origin=np.array(origins[k]), direction=np.array(dirs[k]),
                         color=color) for k in origins)
    pairs = tuple(Pair(lasers=p, separation=_separation(origins[p[0]], origins[p[1]],
                                                        dirs[p[0]])) for p in pair_names)
    return Rig(name=name, lasers=lasers, pairs=pairs)


def _separation(o1: list[float], o2: list[float], direction: list[float]) -> float:
    """Perpendicular distance between two parallel beams."""
    d = np.asarray(direction) / np.linalg.norm(direction)
    diff = np.asarray(o2) - np.asarray(o1)
    return float(np.linalg.norm(diff - (diff @ d) * d))


# --------------------------------------------------------------------------- poses


def _floor_height(raycaster: SceneRaycaster, xy: F64) -> float:
    """Height of the scene under (x, y) (vertical ray cast from far above)."""
    top = float(raycaster.scene.vertices[:, 2].max()) + 10.0
    hit, ok = raycaster.first_hit(np.array([[xy[0], xy[1], top]]), np.array([[0.0, 0.0, -1.0]]))
    if not ok[0]:
        raise ValueError(f"no scene under {xy}")
    return float(hit[0, 2])


def reference_poses(options: DemoDataOptions, rng: np.random.Generator) -> list[Pose]:
    """Lawnmower survey: lines along x, alternating heading, jittered altitude and tilt."""
    w, h = options.image_size
    fx_m = options.altitude_m * w / options.focal_px  # footprint at nadir, metres
    fy_m = options.altitude_m * h / options.focal_px
    n = options.n_reference
    rows = max(1, int(round(np.sqrt(n))))
    cols = int(np.ceil(n / rows))
    dx, dy = (1 - options.along_overlap) * fx_m, (1 - options.across_overlap) * fy_m
    poses = []
    for k in range(n):
        r, c = divmod(k, cols)
        c_line = c if r % 2 == 0 else cols - 1 - c  # boustrophedon
        x = (c_line - (cols - 1) / 2) * dx + rng.normal(0, 0.05)
        y = (r - (rows - 1) / 2) * dy + rng.normal(0, 0.05)
        z = options.altitude_m + rng.uniform(-0.3, 0.3)
        heading = (0.0 if r % 2 == 0 else 180.0) + rng.uniform(-10, 10)
        tilt = options.reference_tilt_deg
        poses.append(nadir_pose(np.array([x, y, z]), heading, rng.uniform(-tilt, tilt),
                                rng.uniform(-tilt, tilt)))
    return poses


def laser_poses(options: DemoDataOptions, raycaster: SceneRaycaster, reference: list[Pose],
                rng: np.random.Generator) -> list[Pose]:
    """Held-out views inside the survey, at spread distances and tilts up to the maximum."""
    centres = np.array([p.center for p in reference])
    lo, hi = centres[:, :2].min(0), centres[:, :2].max(0)
    mid, half = (lo + hi) / 2, np.maximum((hi - lo) / 2 * 0.7, 0.1)
    n = options.n_laser
    dists = rng.permutation(np.linspace(*options.laser_distance_m, n))
    tilts = rng.permutation(np.linspace(0.0, options.laser_max_tilt_deg, n))
    poses = []
    for k in range(n):
        target_xy = mid + rng.uniform(-1, 1, 2) * half
        target = np.array([*target_xy, _floor_height(raycaster, target_xy)])
        az = rng.uniform(0, 2 * np.pi)
        pitch, roll = tilts[k] * np.cos(az), tilts[k] * np.sin(az)
        heading = rng.uniform(-180, 180)
        probe = nadir_pose(np.zeros(3), heading, pitch, roll)  # orientation only
        axis = probe.R[2]  # optical axis in the world
        poses.append(nadir_pose(target - dists[k] * axis, heading, pitch, roll))
    return poses


def overlapping_pairs(raycaster: SceneRaycaster, camera: Camera, poses: list[Pose],
                      min_overlap: float, grid: int = 12) -> list[tuple[int, int]]:
    """Index pairs (i < j) whose views share at least ``min_overlap`` of a sampled footprint.

    Each view's footprint is a ``grid`` × ``grid`` set of scene points (ray casts); the overlap
    of a pair is the larger fraction of one view's points that project inside the other view.
    """
    u = (np.arange(grid) + 0.5) / grid
    gx, gy = np.meshgrid(u * camera.width, u * camera.height)
    rays_cam = camera.unproject(np.column_stack([gx.ravel(), gy.ravel()]))
    footprints = []
    for pose in poses:
        pts, ok = raycaster.first_hit(np.broadcast_to(pose.center, rays_cam.shape),
                                      rays_cam @ pose.R)
        footprints.append(pts[ok])
    pairs = []
    for i in range(len(poses)):
        for j in range(i + 1, len(poses)):
            frac = max(_inside_fraction(camera, poses[j], footprints[i]),
                       _inside_fraction(camera, poses[i], footprints[j]))
            if frac >= min_overlap:
                pairs.append((i, j))
    return pairs


def _inside_fraction(camera: Camera, pose: Pose, xyz_world: F64) -> float:
    """Fraction of the points in front of the camera that project inside the image."""
    if len(xyz_world) == 0:
        return 0.0
    x_c = pose.transform(xyz_world)
    front = x_c[:, 2] > 1e-6
    if not front.any():
        return 0.0
    xy = camera.project(x_c[front])
    inside = ((xy[:, 0] >= 0) & (xy[:, 0] <= camera.width)
              & (xy[:, 1] >= 0) & (xy[:, 1] <= camera.height))
    return float(inside.sum()) / len(xyz_world)


# --------------------------------------------------------------------------- laser spots


def true_spots(raycaster: SceneRaycaster, camera: Camera, cam_from_world: Pose, rig: Rig,
               margin_px: float = 8.0) -> list[TrueSpot]:
    """Each beam intersected with the scene and projected (visible, unoccluded, in the image)."""
    world_from_cam = cam_from_world.inverse()
    centre = cam_from_world.center
    out = []
    for las in rig.lasers:
        if las.origin is None or las.direction is None:
            out.append(TrueSpot(las.name, False, None, None, np.inf, "uncalibrated beam"))
            continue
        o_w = world_from_cam.transform(las.origin[None, :])
        d_w = las.direction @ cam_from_world.R  # Rᵀ v
        hit, ok = raycaster.first_hit(o_w, d_w[None, :])
        if not ok[0]:
            out.append(TrueSpot(las.name, False, None, None, np.inf, "beam misses the scene"))
            continue
        x_w = hit[0]
        rng_beam = float(np.linalg.norm(x_w - o_w[0]))
        out.append(_visible_spot(raycaster, camera, cam_from_world, centre, las.name, x_w,
                                 rng_beam, margin_px))
    return out


def _visible_spot(raycaster: SceneRaycaster, camera: Camera, cam_from_world: Pose, centre: F64,
                  name: str, x_w: F64, rng_beam: float, margin_px: float) -> TrueSpot:
    """The projection of a beam hit, or the reason it cannot be seen."""
    x_c = cam_from_world.transform(x_w[None, :])[0]
    if x_c[2] <= 0:
        return TrueSpot(name, False, None, x_w, rng_beam, "behind the camera")
    xy = camera.project(x_c[None, :])[0]
    inside = (margin_px <= xy[0] <= camera.width - margin_px
              and margin_px <= xy[1] <= camera.height - margin_px)
    if not inside:
        return TrueSpot(name, False, None, x_w, rng_beam, "outside the image")
    view, ok = raycaster.first_hit(centre[None, :], (x_w - centre)[None, :])
    dist = float(np.linalg.norm(x_w - centre))
    if not ok[0] or float(np.linalg.norm(view[0] - centre)) < dist - 1e-3:
        return TrueSpot(name, False, None, x_w, rng_beam, "occluded from the camera")
    return TrueSpot(name, True, (float(xy[0]), float(xy[1])), x_w, rng_beam)


# --------------------------------------------------------------------------- rendering


def render_reference(raycaster: SceneRaycaster, camera: Camera, pose: Pose,
                     options: DemoDataOptions, rng: np.random.Generator) -> NDArray[np.uint8]:
    """A reference image: rendered, sensor noise, 8-bit encoded (RGB)."""
    img = render_image(raycaster, camera, pose, replace(options.render, noise_std=0.0))
    add_sensor_noise(img, options.noise_std, rng)
    return to_uint8(img, options.gamma)


def render_laser_image(raycaster: SceneRaycaster, camera: Camera, pose: Pose,
                       spots: list[TrueSpot], rig: Rig, options: DemoDataOptions,
                       rng: np.random.Generator) -> NDArray[np.uint8]:
    """A laser image: rendered, visible spots painted at their true positions, noise, 8-bit."""
    img = render_image(raycaster, camera, pose, replace(options.render, noise_std=0.0))
    for spot in spots:
        if not spot.visible or spot.xy_px is None or spot.hit_world is None:
            continue
        depth = float(pose.transform(spot.hit_world[None, :])[0, 2])
        sigma = float(np.clip(camera.focal_px * options.beam_sigma_m / depth, 1.0, 6.0))
        paint_spot(img, spot.xy_px, color=rig.laser(spot.laser).color, sigma_px=sigma,
                   peak=options.spot_peak)
    add_sensor_noise(img, options.noise_std, rng)
    return to_uint8(img, options.gamma)


def _write_png(path: Path, rgb: NDArray[np.uint8]) -> None:
    """Write an RGB uint8 image (OpenCV wants BGR)."""
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1])):
        raise OSError(f"cannot write {path}")


# --------------------------------------------------------------------------- SfM


@contextmanager
def _colmap_log_level(verbose: bool) -> Iterator[None]:
    """Silence COLMAP's INFO log unless ``verbose``."""
    old = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = 2  # ERROR (its CPU-threads warning is noise here)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def run_sfm(images_dir: Path, image_names: list[str], database_path: Path, sparse_dir: Path,
            camera: Camera, pairs_path: Path | None,
            options: DemoDataOptions) -> tuple[pycolmap.Reconstruction, SfmStats,
                                               dict[str, float]]:
    """SIFT + matching + incremental mapping (pycolmap, CPU, the known camera held fixed).

    The camera's model (PINHOLE for the demo, OPENCV for the underwater survey) and
    parameters are given to COLMAP and not refined.

    ``pairs_path``: a COLMAP pair list ("name1 name2" lines) to match; None = exhaustive.
    """
    timings: dict[str, float] = {}
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera.model
    reader.camera_params = ",".join(f"{p:.12g}" for p in camera.params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    extraction.sift.max_num_features = options.max_features
    extraction.sift.first_octave = options.sift_first_octave
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    mapping = mapping_options(options.seed, fixed_intrinsics=True)
    # one step each: SIFT extraction, matching, incremental mapping (pycolmap reports no finer
    # progress); shown only on a terminal and without --quiet (provenance.progress_bar)
    steps = progress_bar(options.progress, "SfM (features, matching, mapping)", total=3)
    with _colmap_log_level(options.colmap_log):
        t0 = time.perf_counter()
        pycolmap.extract_features(database_path, images_dir, image_names=image_names,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        timings["sfm_features"] = time.perf_counter() - t0
        steps.update()
        t0 = time.perf_counter()
        if pairs_path is None:
            pycolmap.match_exhaustive(database_path, matching_options=matching,
                                      device=pycolmap.Device.cpu)
        else:
            pycolmap.match_image_pairs(
                database_path, matching_options=matching,
                pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_path),
                device=pycolmap.Device.cpu)
        timings["sfm_matching"] = time.perf_counter() - t0
        steps.update()
        t0 = time.perf_counter()
        tmp = sparse_dir.parent / (sparse_dir.name + "_all")
        tmp.mkdir(parents=True, exist_ok=True)
        recs = pycolmap.incremental_mapping(database_path, images_dir, tmp, options=mapping)
        timings["sfm_mapping"] = time.perf_counter() - t0
        steps.update()
    steps.close()
    rec, stats = _largest_model(recs, len(image_names))
    sparse_dir.mkdir(parents=True, exist_ok=True)
    rec.write(sparse_dir)
    shutil.rmtree(tmp, ignore_errors=True)
    return rec, stats, timings


def _largest_model(recs: dict[int, pycolmap.Reconstruction],
                   n_images: int) -> tuple[pycolmap.Reconstruction, SfmStats]:
    """The reconstruction with the most registered images; error unless it holds them all."""
    if not recs:
        raise SfmFailedError("SfM produced no model from the rendered reference images")
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    stats = SfmStats(
        n_images=n_images, n_registered=int(rec.num_reg_images()),
        n_points=int(rec.num_points3D()),
        mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
        mean_track_length=float(rec.compute_mean_track_length()), n_models=len(recs),
    )
    if stats.n_registered < n_images:
        raise SfmFailedError(
            f"SfM registered only {stats.n_registered} of {n_images} reference images "
            f"({len(recs)} model(s)); try another seed or more overlap")
    return rec, stats


def model_centres(rec: pycolmap.Reconstruction) -> dict[str, F64]:
    """Image name -> camera centre in the model frame."""
    out = {}
    for image in rec.images.values():
        if image.has_pose:
            out[image.name] = np.asarray(image.projection_center(), dtype=np.float64)
    return out


def align_model(world_centres: dict[str, F64], model_xyz: dict[str, F64]) -> Alignment:
    """``model_from_world`` by Umeyama on the camera centres of the images both hold."""
    names = sorted(set(world_centres) & set(model_xyz))
    if len(names) < 3:
        raise SfmFailedError(f"only {len(names)} cameras to align the model with the world")
    src = np.array([world_centres[n] for n in names])
    dst = np.array([model_xyz[n] for n in names])
    s, R, t = umeyama_sim3(src, dst)
    res = np.linalg.norm(s * src @ R.T + t - dst, axis=1) / s  # metres
    return Alignment(scale=s, R=R, t=t, rms_m=float(np.sqrt(np.mean(res**2))),
                     max_m=float(res.max()))


# --------------------------------------------------------------------------- writers


def vertex_colors(scene: Scene, gamma: float) -> NDArray[np.uint8]:
    """(V, 3) 8-bit colours of the vertices (texture averaged over ~a vertex spacing)."""
    spacing = float(np.median(np.linalg.norm(
        scene.vertices[scene.triangles[:, 1]] - scene.vertices[scene.triangles[:, 0]], axis=1)))
    level = int(np.clip(np.floor(np.log2(max(spacing / scene.texel_size_m, 1.0))), 0, 10))
    tex = scene.texture
    for _ in range(level):
        h, w = tex.shape[:2]
        if min(h, w) < 4:
            break
        tex = cv2.resize(tex, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    h, w = tex.shape[:2]
    cols = np.clip((scene.uv[:, 0] * w).astype(int), 0, w - 1)
    rows = np.clip((scene.uv[:, 1] * h).astype(int), 0, h - 1)
    return to_uint8(tex[rows, cols][:, None, :], gamma)[:, 0, :]


def write_mesh_ply(path: Path, vertices: F64, triangles: NDArray[np.integer],
                   colors: NDArray[np.uint8] | None = None) -> None:
    """Binary little-endian PLY: float64 x y z, optional uchar red green blue, int faces."""
    fields: list[tuple[Any, ...]] = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vert = np.empty(len(vertices), dtype=fields)
    for k, name in enumerate("xyz"):
        vert[name] = vertices[:, k]
    if colors is not None:
        for k, name in enumerate(("red", "green", "blue")):
            vert[name] = colors[:, k]
    faces = np.empty(len(triangles), dtype=[("vertex_indices", "<i4", (3,))])
    faces["vertex_indices"] = triangles
    ply = plyfile.PlyData(
        [plyfile.PlyElement.describe(vert, "vertex"),
         plyfile.PlyElement.describe(faces, "face", len_types={"vertex_indices": "u1"})],
        text=False, byte_order="<",
    )
    ply.write(str(path))


def _pose_json(pose: Pose) -> dict[str, list[float]]:
    return {"rotation_wxyz": [float(v) for v in qvec_from_rotmat(pose.R)],
            "translation": [float(v) for v in pose.t]}


def _spot_json(spot: TrueSpot, align: Alignment) -> dict[str, Any]:
    out: dict[str, Any] = {"laser": spot.laser, "visible": spot.visible, "reason": spot.reason,
                           "x": None, "y": None, "hit_world": None, "hit_model": None,
                           "beam_range_m": None if not np.isfinite(spot.beam_range_m)
                           else spot.beam_range_m}
    if spot.xy_px is not None:
        out["x"], out["y"] = spot.xy_px
    if spot.hit_world is not None:
        out["hit_world"] = [float(v) for v in spot.hit_world]
        out["hit_model"] = [float(v) for v in align.apply(spot.hit_world[None, :])[0]]
    return out


# --------------------------------------------------------------------------- the job


@dataclass
class _Views:
    names: list[str]
    poses: list[Pose]
    spots: list[list[TrueSpot]] = field(default_factory=list)


def _prepare_out_dir(out_dir: Path, overwrite: bool) -> None:
    """Create ``out_dir``; refuse a non-empty one unless ``overwrite`` (then clear our outputs)."""
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("output path exists and is not a folder", out_dir)
    if out_dir.exists() and any(out_dir.iterdir()):
        if not overwrite:
            raise InputError("output folder is not empty (use overwrite)", out_dir)
        for name in (*OUTPUTS, "sparse_all"):
            p = out_dir / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    (out_dir / "laser_images").mkdir(parents=True, exist_ok=True)


def _render_all(raycaster: SceneRaycaster, camera: Camera, ref: _Views, las: _Views, rig: Rig,
                options: DemoDataOptions, out_dir: Path) -> None:
    """Render and write every reference and laser image (fills ``las.spots``)."""
    seeds = np.random.SeedSequence([options.seed, 7]).spawn(len(ref.names) + len(las.names))
    jobs = [(True, k) for k in range(len(ref.names))] + [(False, k) for k in range(len(las.names))]
    for (is_ref, k), seed in progress_bar(options.progress, "render",
                                          iterable=list(zip(jobs, seeds, strict=True))):
        rng = np.random.default_rng(seed)
        if is_ref:
            img = render_reference(raycaster, camera, ref.poses[k], options, rng)
            _write_png(out_dir / "images" / ref.names[k], img)
            continue
        spots = true_spots(raycaster, camera, las.poses[k], rig)
        las.spots.append(spots)
        img = render_laser_image(raycaster, camera, las.poses[k], spots, rig, options, rng)
        _write_png(out_dir / "laser_images" / las.names[k], img)


def _truth(options: DemoDataOptions, camera: Camera, ref: _Views, las: _Views,
           align: Alignment, stats: SfmStats, n_pairs: int, mesh_scale: float) -> dict[str, Any]:
    """The content of truth.json (``mesh_scale``: the mesh's model_from_world scale)."""
    return {
        "true_scale": 1.0 / mesh_scale,
        "true_scale_cameras": 1.0 / align.scale,
        "true_scale_units": "metres per model unit",
        "model_from_world": {"scale": align.scale,
                             "rotation_wxyz": [float(v) for v in qvec_from_rotmat(align.R)],
                             "translation": [float(v) for v in align.t]},
        "alignment_rms_m": align.rms_m, "alignment_max_m": align.max_m,
        "camera": {"model": camera.model, "width": camera.width, "height": camera.height,
                   "params": [float(v) for v in camera.params]},
        "rig": options.rig, "seed": options.seed, "sfm_focal_error": options.sfm_focal_error,
        "sfm": {"n_images": stats.n_images, "n_registered": stats.n_registered,
                "n_points": stats.n_points, "n_models": stats.n_models, "n_pairs": n_pairs,
                "mean_reprojection_error_px": stats.mean_reprojection_error_px,
                "mean_track_length": stats.mean_track_length},
        "reference_images": [{"name": n, "cam_from_world": _pose_json(p)}
                             for n, p in zip(ref.names, ref.poses, strict=True)],
        "laser_images": [
            {"name": n, "cam_from_world": _pose_json(p),
             "cam_from_model": _pose_json(align.cam_from_model(p)),
             "spots": [_spot_json(s, align) for s in spots]}
            for n, p, spots in zip(las.names, las.poses, las.spots, strict=True)],
    }


def _write_spots_csv(path: Path, las: _Views) -> None:
    """The visible true spots as ``image,laser,x,y`` (COLMAP pixel convention)."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(["image", "laser", "x", "y"])
        for name, spots in zip(las.names, las.spots, strict=True):
            for s in spots:
                if s.visible and s.xy_px is not None:
                    writer.writerow([name, s.laser, f"{s.xy_px[0]:.6f}", f"{s.xy_px[1]:.6f}"])


def make_demo_dataset(out_dir: Path, options: DemoDataOptions = DemoDataOptions(),
                      overwrite: bool = False) -> DemoDataset:
    """Render, reconstruct and write the demo data set (see the module docstring)."""
    out_dir = Path(out_dir)
    options = resolve_options(options)
    timings: dict[str, float] = {}
    t_all = t0 = time.perf_counter()
    cpu0 = time.process_time()
    _prepare_out_dir(out_dir, overwrite)
    rng = np.random.default_rng(options.seed)
    scene = make_scene(replace(options.scene, seed=options.seed))
    raycaster = SceneRaycaster(scene)
    timings["scene"] = time.perf_counter() - t0
    camera, rig = demo_camera(options), make_rig(options.rig, options.laser_color)
    ref_poses = reference_poses(options, rng)
    ref = _Views([f"ref_{k:03d}.png" for k in range(len(ref_poses))], ref_poses)
    las_poses = laser_poses(options, raycaster, ref_poses, rng)
    las = _Views([f"laser_{k:03d}.png" for k in range(len(las_poses))], las_poses)
    t0 = time.perf_counter()
    _render_all(raycaster, camera, ref, las, rig, options, out_dir)
    timings["render"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pairs = overlapping_pairs(raycaster, camera, ref.poses, options.min_pair_overlap)
    (out_dir / "pairs.txt").write_text(
        "".join(f"{ref.names[i]} {ref.names[j]}\n" for i, j in pairs), encoding="utf-8")
    timings["pairs"] = time.perf_counter() - t0
    sfm_camera = replace(camera, params=camera.params * np.array(
        [1.0 + options.sfm_focal_error] * 2 + [1.0] * (len(camera.params) - 2)))
    rec, stats, sfm_t = run_sfm(out_dir / "images", ref.names, out_dir / "database.db",
                                out_dir / "sparse" / "0", sfm_camera, out_dir / "pairs.txt",
                                options)
    timings.update(sfm_t)
    t0 = time.perf_counter()
    align = align_model({n: p.center for n, p in zip(ref.names, ref.poses, strict=True)},
                        model_centres(rec))
    mesh_model = align.apply(scene.vertices)
    mesh_scale = align.scale
    if options.sfm_focal_error != 0.0:  # the model is no similarity of the world
        mesh_model = fit_model_warp(rec, camera, dict(zip(ref.names, ref.poses, strict=True))
                                    ).apply(scene.vertices)
        mesh_scale = umeyama_sim3(scene.vertices, mesh_model)[0]
    write_mesh_ply(out_dir / "mesh.ply", mesh_model, scene.triangles,
                   vertex_colors(scene, options.gamma))
    (out_dir / "rig.toml").write_text(rig_to_toml(rig), encoding="utf-8")
    truth = _truth(options, camera, ref, las, align, stats, len(pairs), mesh_scale)
    (out_dir / "truth.json").write_text(json.dumps(truth, indent=2), encoding="utf-8")
    _write_spots_csv(out_dir / "true_spots.csv", las)
    timings["write"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    timings["cpu_total"] = time.process_time() - cpu0  # all threads of this process
    logger.info("demo data set in %s: scale %.6g m/unit, alignment RMS %.3g mm, %.1f s", out_dir,
                truth["true_scale"], 1e3 * align.rms_m, timings["total"])
    return DemoDataset(
        out_dir=out_dir, images_dir=out_dir / "images", laser_images_dir=out_dir / "laser_images",
        database_path=out_dir / "database.db", model_dir=out_dir / "sparse" / "0",
        mesh_path=out_dir / "mesh.ply", rig_path=out_dir / "rig.toml",
        truth_path=out_dir / "truth.json", spots_path=out_dir / "true_spots.csv", rig=rig,
        camera=camera, true_scale=float(truth["true_scale"]), alignment_rms_m=align.rms_m,
        sfm=stats, timings=timings,
    )
