"""The paper's synthetic experiments (Istenič et al. 2020), run through the code of ``scale``.

Every trial goes through the same functions as a real laser image in ``pipeline.py``:

1. a true view of the metric scene (see *Views*);
2. ``n_points`` (1500) model points: random pixels cast into the mesh from the true camera (so
   every point is visible), projected, plus N(0, σ_f²) per axis; a fraction ``outlier_ratio`` is
   replaced by uniformly random pixels. Descriptors are skipped: the 2D–3D correspondences are
   given, matching is not what is simulated;
3. ``registration.estimate_pose``: pycolmap LO-RANSAC P3P + refinement, our acceptance rule and
   pose covariance (one thread, seeded);
4. laser spots: each beam's exact first hit on the mesh, projected when it is inside the image
   and not occluded from the camera, plus N(0, σ_l²) per axis; the detector's σ is σ_l;
5. ``raycast.cast_spots`` (MeshRaycaster with the ESTIMATED pose, the depth-edge check of
   ``scale``) → ``uncertainty.estimate_image`` (FCM per laser, PCM and Direct 3D per pair,
   first-order σ) →
   ``fusion.fuse`` per view; ``methods.pcm_joint.estimate_pcm_joint`` over groups of views;
   ``methods.baselines.davis_tusting_scale`` for four beams parallel to the optical axis.

Frames and units: the scene (``make_scene``, or any metric mesh) is in metres; the model is the
world divided by ``true_scale`` (metres per model unit, default 1), so the truth of every
estimate is ``true_scale``. Errors are reported relative to it, in percent.

Views: a target point on the surface and its local normal n (plane fitted to the surface within
``area_radius_m``). The camera starts looking straight down the normal (image x along the
world x axis projected on the local plane), is turned by ``pitch`` about its x axis and
``roll`` about its y axis (``synthetic.render.nadir_pose``'s convention), and is placed on its
new optical axis so that it looks at the target from an ALTITUDE ``distance`` above the local
plane, measured along n: range to the target = distance / (cos pitch · cos roll).

Areas: ``smooth`` and ``rough`` are the windows of the central half of the scene with the
smallest and the largest relief (RMS height about the local plane, ``area_radius_m`` window),
the paper's areas A and B.

Modes: ``grid`` — pitch and roll from −40° to 40° in 5° steps (289 views) over both areas at each
distance, ``trials`` noise draws per view; ``random`` — ``trials`` random surface points of the
central half with random pitch and roll within ±40°, distances taken in turn; ``noise-table`` —
the camera straight above the smooth area, ``trials`` draws per cell of σ_f × σ_l × distance.
With ``antithetic`` every draw is paired with its mirror image (all Gaussian noise negated, same
feature points, outliers and RANSAC seed): the mean of a pair cancels the first-order error
and leaves the estimator's bias, measurable per view from one pair.

Camera: PINHOLE 1920 × 1080, f = 1500 px (principal point at the centre) — the paper's camera
parameters are not given in our sources; FCM's spread scales as depth / (f · ‖O_L‖).

Reported methods (results.json, per setting): ``fcm`` / ``pcm`` / ``direct3d`` single estimates
(pooled, and per laser / pair as ``fcm:L1`` …); ``<m>_fused``: ``fusion.fuse`` of one view, with
the σ and interval the pipeline reports; ``<m>_fused_gls``: the same value with the σ before the
Birge inflation (interval ±1.96 σ); ``pcm_joint``: ``estimate_pcm_joint`` over ``group_size``
views; ``pcm_group``: the midpoint PCM fused over the same views; ``pcm_joint_view``: each
view's scale with the jointly fitted beam direction; ``davis_tusting``. Every method drops
the spots ``scale`` drops (``raycast.on_depth_edge``: the mesh is not planar within 3 σ of the
spot); ``fcm_unchecked``, ``fcm_fused_unchecked``, ``pcm_unchecked`` keep them, to show
what the check removes. PCM-joint is not run in the noise table (identical views
leave the beam direction undetermined).
"""

from __future__ import annotations

import csv
import gzip
import json
import logging
import math
import multiprocessing
import sys
import time
from array import array
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from sfm_laserscale import __version__
from sfm_laserscale.errors import InputError
from sfm_laserscale.fusion import FusedScale, FusionOptions, fuse
from sfm_laserscale.methods.baselines import davis_tusting_scale
from sfm_laserscale.methods.pcm_joint import PcmJointOptions, estimate_pcm_joint
from sfm_laserscale.model import Camera, Pose, Spot
from sfm_laserscale.raycast import (
    MeshRaycaster,
    SpotCastOptions,
    cast_spots,
    pixel_rays,
)
from sfm_laserscale.registration.options import PoseOptions
from sfm_laserscale.registration.pose import estimate_pose
from sfm_laserscale.rig import Rig, rig_from_dict
from sfm_laserscale.synthetic.dataset import make_rig
from sfm_laserscale.uncertainty import (
    METHODS,
    EstimationOptions,
    ImageEstimates,
    ImageObservation,
    estimate_image,
)

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
MODES = ("grid", "random", "noise-table")
CONFIGS = ("A", "B", "C")
AREAS = ("smooth", "rough")
Z95 = 1.959963984540054  # two-sided 95 % normal quantile
#: Defaults per mode: configurations, trials, σ_f (px), σ_l (px).
MODE_DEFAULTS: dict[str, dict[str, Any]] = {
    "grid": {"configs": ("A", "B", "C"), "trials": 1, "sigma_f": (0.5,), "sigma_l": (0.25,)},
    "random": {"configs": ("A", "B", "C"), "trials": 10000, "sigma_f": (0.5,),
               "sigma_l": (0.25,)},
    "noise-table": {"configs": ("B", "C"), "trials": 500, "sigma_f": (0.5, 1.0),
                    "sigma_l": (0.25, 0.5)},
}
#: Spots closer than this to the image border are not visible (pixels).
SPOT_MARGIN_PX = 8.0
#: Davis & Tusting query points: a 5 × 5 grid over the central half of the image.
DT_GRID = 5
def pinhole_camera(width: int, height: int, focal_px: float) -> Camera:
    """PINHOLE camera with the principal point at the image centre."""
    if width < 16 or height < 16 or not focal_px > 0:
        raise InputError(f"camera needs width, height >= 16 px and a positive focal length, "
                         f"got {width} {height} {focal_px}")
    return Camera(1, "PINHOLE", int(width), int(height),
                  np.array([focal_px, focal_px, width / 2.0, height / 2.0]))


def default_camera() -> Camera:
    """PINHOLE 1920 × 1080, f = 1500 px, principal point at the image centre."""
    return pinhole_camera(1920, 1080, 1500.0)


# --------------------------------------------------------------------------- configurations


def _unit(v: Sequence[float]) -> list[float]:
    a = np.asarray(v, dtype=np.float64)
    return [float(x) for x in a / np.linalg.norm(a)]


def _rig(name: str, origins: dict[str, tuple[float, float, float]],
         dirs: dict[str, list[float]], pairs: list[tuple[str, str, float]]) -> Rig:
    lasers = [{"name": k, "origin": list(o), "direction": dirs[k], "color": "red"}
              for k, o in origins.items()]
    return rig_from_dict({"name": name, "laser": lasers,
                          "pair": [{"lasers": [a, b], "separation": s} for a, b, s in pairs]},
                         f"<configuration {name}>")


def config_rig(name: str) -> Rig:
    """The paper's laser configurations A, B, C (metres, camera frame).

    A: four beams parallel to the optical axis, origins 10 cm from the camera centre on the x
    and y axes; pairs (L1, L2) and (L3, L4), 0.2 m apart. B: two pairs of parallel beams 0.1 m
    apart, origins (±0.05, ∓0.10); pair L1+L2 tilted 2° towards −y, pair L3+L4 3° towards +y
    (tilts in the y–z plane keep the camera equidistant from both beams of a pair). C: the
    demo's misaligned ROV scaler (``dataset.make_rig("rov")``): origins 16.5 cm from the centre,
    directions 1.5–2.8° off the axis, one parallel pair L1+L2.
    """
    if name == "A":
        axis = [0.0, 0.0, 1.0]
        return _rig("A", {"L1": (0.1, 0.0, 0.0), "L2": (-0.1, 0.0, 0.0),
                          "L3": (0.0, 0.1, 0.0), "L4": (0.0, -0.1, 0.0)},
                    dict.fromkeys(("L1", "L2", "L3", "L4"), axis),
                    [("L1", "L2", 0.2), ("L3", "L4", 0.2)])
    if name == "B":
        a, b = np.radians(2.0), np.radians(3.0)
        va, vb = _unit([0.0, -np.sin(a), np.cos(a)]), _unit([0.0, np.sin(b), np.cos(b)])
        return _rig("B", {"L1": (-0.05, -0.10, 0.0), "L2": (0.05, -0.10, 0.0),
                          "L3": (-0.05, 0.10, 0.0), "L4": (0.05, 0.10, 0.0)},
                    {"L1": va, "L2": va, "L3": vb, "L4": vb},
                    [("L1", "L2", 0.1), ("L3", "L4", 0.1)])
    if name == "C":
        return make_rig("rov")
    raise InputError(f"unknown laser configuration {name!r} (known: {', '.join(CONFIGS)})")


def check_rig(rig: Rig, where: str) -> None:
    """Simulation needs the true beams: every laser must have an origin and a direction."""
    missing = [las.name for las in rig.lasers if not las.calibrated]
    if missing:
        raise InputError(f"simulation needs every laser's origin and direction; "
                         f"{', '.join(missing)} have none", where)


def is_parallel_axis_rig(rig: Rig) -> bool:
    """True for four calibrated beams parallel to the optical axis (Davis & Tusting)."""
    return len(rig.lasers) == 4 and all(
        las.direction is not None and float(las.direction[2]) > 1 - 1e-9 for las in rig.lasers)


# --------------------------------------------------------------------------- options


@dataclass(frozen=True)
class SimulationOptions:
    """What ``simulate`` runs. ``None`` fields take the mode's default (``MODE_DEFAULTS``)."""

    mode: str = "grid"
    configs: tuple[str, ...] | None = None  # A | B | C (ignored when a rig file is given)
    distances_m: tuple[float, ...] = (2.0, 3.0, 4.0)  # altitude above the local surface
    trials: int | None = None  # grid: per view; random: views in all; noise-table: per cell
    sigma_f_px: tuple[float, ...] | None = None  # feature noise, per axis
    sigma_l_px: tuple[float, ...] | None = None  # spot noise, per axis
    outlier_ratio: float = 0.1  # fraction of features moved to random pixels
    n_points: int = 1500
    group_size: int = 5  # views per PCM-joint estimate
    max_angle_deg: float = 40.0
    angle_step_deg: float = 5.0
    area_radius_m: float = 0.5
    areas: tuple[str, ...] = AREAS  # grid mode: which areas
    antithetic: bool = False
    camera: Camera = field(default_factory=default_camera)
    true_scale: float = 1.0  # metres per model unit
    scene_seed: int = 0  # make_scene's seed (the demo's scene)
    seed: int = 0
    workers: int = 1
    progress: bool = True
    pose: PoseOptions = field(default_factory=PoseOptions)
    spot_cast: SpotCastOptions = field(default_factory=SpotCastOptions)
    estimation: EstimationOptions = field(default_factory=EstimationOptions)
    fusion: FusionOptions = field(default_factory=FusionOptions)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise InputError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        for c in self.configs or ():
            if c not in CONFIGS:
                raise InputError(f"configuration must be A, B or C, got {c!r}")
        if not self.distances_m or min(self.distances_m) <= 0:
            raise InputError("distances must be positive metres")
        if self.trials is not None and self.trials < 1:
            raise InputError(f"trials must be >= 1, got {self.trials}")
        noise = (*(self.sigma_f_px or ()), *(self.sigma_l_px or ()))
        if any(not (math.isfinite(s) and s >= 0) for s in noise):
            raise InputError("noise sigmas must be finite and >= 0 pixels")
        if not 0 <= self.outlier_ratio < 0.9:
            raise InputError(f"outlier ratio must be in [0, 0.9), got {self.outlier_ratio}")
        if not self.areas or any(a not in AREAS for a in self.areas):
            raise InputError(f"areas must be among {', '.join(AREAS)}, got {self.areas}")
        if self.n_points < 10 or self.group_size < 3 or self.workers < 1:
            raise InputError("need n_points >= 10, group_size >= 3 and workers >= 1")
        if not (0 < self.max_angle_deg < 80 and self.angle_step_deg > 0 and self.true_scale > 0
                and self.area_radius_m > 0):
            raise InputError("need 0 < max angle < 80°, a positive angle step, true scale and "
                             "area radius")

    def resolved(self, key: str) -> Any:
        """The mode's default for configs / trials / sigma_f / sigma_l when unset."""
        value = {"configs": self.configs, "trials": self.trials, "sigma_f": self.sigma_f_px,
                 "sigma_l": self.sigma_l_px}[key]
        return MODE_DEFAULTS[self.mode][key] if value is None else value


@dataclass(frozen=True)
class SimulationInputs:
    """Optional files: a rig replacing the configurations, a metric mesh replacing the scene."""

    rig: Path | None = None
    mesh: Path | None = None


# --------------------------------------------------------------------------- scene and areas


@dataclass(frozen=True)
class Area:
    """A surface window: centre (a surface point, metres), local plane normal, relief."""

    name: str
    centre: F64  # (3,) metres
    normal: F64  # (3,) unit, on the side the views come from
    relief_m: float  # RMS height about the local plane within the window
    slope_deg: float  # angle between the local normal and the scene's up axis


@dataclass(frozen=True)
class SimScene:
    """The metric scene, its up axis and surface samples, and the smooth and rough areas."""

    vertices: F64  # (V, 3) metres
    triangles: NDArray[np.int64]  # (F, 3)
    up: F64  # (3,) area-weighted mean face normal
    basis: F64  # (2, 3) unit axes of the plane perpendicular to up
    samples: F64  # (N, 3) area-uniform surface samples, metres
    central: tuple[F64, F64]  # (lo (2,), hi (2,)) central half of the scene, plane coordinates
    areas: dict[str, Area]
    source: str


def _surface_samples(vertices: F64, triangles: NDArray[np.int64], n: int,
                     rng: np.random.Generator) -> F64:
    """(n, 3) points uniformly distributed over the mesh area."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    tri = rng.choice(len(triangles), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    return np.asarray(a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri]))


def _up_axis(vertices: F64, triangles: NDArray[np.int64]) -> tuple[F64, F64]:
    """Unit up axis (area-weighted mean face normal) and a (2, 3) basis of its plane."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    up = np.cross(b - a, c - a).sum(axis=0)
    norm = float(np.linalg.norm(up))
    if norm <= 0:
        raise InputError("the mesh has no dominant facing direction (closed or degenerate?)")
    up = up / norm
    ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e_u = ref - (ref @ up) * up
    e_u /= np.linalg.norm(e_u)
    return up, np.array([e_u, np.cross(up, e_u)])


def local_plane(samples: F64, tree: cKDTree, basis: F64, up: F64, uv: F64,
                radius: float) -> tuple[F64, F64, float] | None:
    """(centroid, unit normal facing up, RMS height) of the surface within radius of uv."""
    idx = tree.query_ball_point(uv, radius)
    if len(idx) < 30:
        return None
    pts = samples[idx]
    centroid = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    normal = vt[2] if vt[2] @ up > 0 else -vt[2]
    return centroid, normal, float(np.std((pts - centroid) @ normal))


def surface_point(caster: MeshRaycaster, point: F64, normal: F64, k: float) -> F64 | None:
    """The surface point below ``point`` along −normal (metres), or None."""
    start = (point + 100.0 * normal) / k
    res = caster.cast(start[None], -normal[None])
    return None if not res.hit[0] else np.asarray(res.xyz[0] * k)


def _candidate_grid(central: tuple[F64, F64], step: float) -> F64:
    lo, hi = central
    us = np.arange(lo[0], hi[0] + 1e-9, step)
    vs = np.arange(lo[1], hi[1] + 1e-9, step)
    return np.array([(u, v) for u in us for v in vs]).reshape(-1, 2)


def find_areas(scene: SimScene, caster: MeshRaycaster, radius: float, k: float
               ) -> dict[str, Area]:
    """The smoothest and the roughest window of the central half (RMS height about a plane)."""
    tree = cKDTree(scene.samples @ scene.basis.T)
    found: list[tuple[float, F64, F64]] = []
    for uv in _candidate_grid(scene.central, radius / 2):
        plane = local_plane(scene.samples, tree, scene.basis, scene.up, uv, radius)
        if plane is not None:
            found.append((plane[2], plane[0], plane[1]))
    if not found:
        raise InputError("no surface window with enough area in the mesh's central half")
    out = {}
    for name, pick in (("smooth", min), ("rough", max)):
        relief, centroid, normal = pick(found, key=lambda f: f[0])
        centre = surface_point(caster, centroid, normal, k)
        if centre is None:
            raise InputError(f"no surface under the {name} area's centre")
        slope = float(np.degrees(np.arccos(np.clip(normal @ scene.up, -1, 1))))
        out[name] = Area(name, centre, normal, relief, slope)
    return out


def build_scene(vertices: F64, triangles: NDArray[np.integer], source: str,
                options: SimulationOptions) -> tuple[SimScene, MeshRaycaster]:
    """Scene geometry (metres), up axis, surface samples, central region and the two areas."""
    verts = np.asarray(vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64)
    up, basis = _up_axis(verts, tris)
    rng = np.random.default_rng(np.random.SeedSequence([options.scene_seed, 17]))
    samples = _surface_samples(verts, tris, 200_000, rng)
    uv = samples @ basis.T
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    central = (lo + 0.25 * (hi - lo), hi - 0.25 * (hi - lo))
    caster = MeshRaycaster(verts / options.true_scale, tris)
    scene = SimScene(verts, tris, up, basis, samples, central, {}, source)
    areas = find_areas(scene, caster, options.area_radius_m, options.true_scale)
    return replace(scene, areas=areas), caster


def load_scene(inputs: SimulationInputs, options: SimulationOptions
               ) -> tuple[SimScene, MeshRaycaster]:
    """The demo's seafloor (make_scene) or the metric mesh given."""
    if inputs.mesh is not None:
        from sfm_laserscale.io.meshes.mesh import load_mesh

        mesh = load_mesh(inputs.mesh)
        return build_scene(np.asarray(mesh.vertices, dtype=np.float64), mesh.triangles,
                           str(inputs.mesh), options)
    from sfm_laserscale.synthetic.scene import SceneOptions, make_scene

    # the texture is not needed: a tiny one leaves the geometry (drawn first) unchanged
    scene = make_scene(SceneOptions(seed=options.scene_seed, texture_px=64))
    return build_scene(scene.vertices, scene.triangles,
                       f"synthetic seafloor (make_scene, seed {options.scene_seed})", options)


def load_settings(inputs: SimulationInputs, options: SimulationOptions
                  ) -> tuple[LaserSetting, ...]:
    """(configuration, rig, σ_l) of every laser setting to simulate."""
    if inputs.rig is not None:
        from sfm_laserscale.rig import load_rig

        rig = load_rig(inputs.rig)
        check_rig(rig, str(inputs.rig))
        rigs = [(Path(inputs.rig).stem, rig)]
    else:
        rigs = [(c, config_rig(c)) for c in options.resolved("configs")]
    return tuple(LaserSetting(name, rig, float(s)) for name, rig in rigs
                 for s in options.resolved("sigma_l"))


# --------------------------------------------------------------------------- views


@dataclass(frozen=True)
class LaserSetting:
    """One laser rig with one spot noise level."""

    config: str
    rig: Rig
    sigma_l_px: float


@dataclass(frozen=True)
class ViewJob:
    """One trial: a true view and its noise draw."""

    index: int  # unique view id (antithetic twins share it)
    area: str  # smooth | rough | random
    distance_m: float  # altitude above the local plane
    pitch_deg: float
    roll_deg: float
    sigma_f_px: float
    round: int  # grid: noise draw number; otherwise 0
    sign: int  # +1, or −1 for the antithetic twin (all Gaussian noise negated)
    seed: int  # noise seed (shared by antithetic twins)
    cam_from_world: Pose  # true pose, metres


def _rot(axis: int, angle_rad: float) -> F64:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    i, j = [a for a in range(3) if a != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def view_pose(target: F64, normal: F64, altitude_m: float, pitch_deg: float,
              roll_deg: float) -> Pose:
    """cam_from_world (metres) looking at ``target`` from ``altitude_m`` above its plane.

    Straight down −normal with image x along world x (projected), then pitch about the camera
    x axis and roll about its y axis (``render.nadir_pose``'s convention).
    """
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ n) * n
    x /= np.linalg.norm(x)
    z = -n
    base = np.array([x, np.cross(z, x), z])
    R = (_rot(0, np.radians(pitch_deg)) @ _rot(1, np.radians(roll_deg))).T @ base
    axis = R[2]
    centre = np.asarray(target, dtype=np.float64) - altitude_m / float(axis @ -n) * axis
    return Pose(R, -R @ centre)


def grid_angles(options: SimulationOptions) -> F64:
    """Pitch/roll values of the grid, degrees (−40 … 40 in 5° steps by default)."""
    m, step = options.max_angle_deg, options.angle_step_deg
    n = int(round(m / step))
    return np.asarray(np.linspace(-n * step, n * step, 2 * n + 1), dtype=np.float64)


def _seed(options: SimulationOptions, index: int) -> int:
    ss = np.random.SeedSequence([options.seed, MODES.index(options.mode), index])
    return int(ss.generate_state(1, dtype=np.uint32)[0])


def _twins(job: ViewJob, options: SimulationOptions) -> list[ViewJob]:
    return [job, replace(job, sign=-1)] if options.antithetic else [job]


def grid_jobs(scene: SimScene, options: SimulationOptions) -> list[ViewJob]:
    """Pitch × roll grid over both areas at every distance and σ_f, ``trials`` draws each."""
    jobs: list[ViewJob] = []
    angles = grid_angles(options)
    i = 0
    for area in options.areas:
        a = scene.areas[area]
        for d in options.distances_m:
            for sf in options.resolved("sigma_f"):
                for rnd in range(options.resolved("trials")):
                    for p in angles:
                        for r in angles:
                            pose = view_pose(a.centre, a.normal, d, p, r)
                            jobs += _twins(ViewJob(i, area, d, float(p), float(r), float(sf), rnd,
                                                   1, _seed(options, i), pose), options)
                            i += 1
    return jobs


def noise_table_jobs(scene: SimScene, options: SimulationOptions) -> list[ViewJob]:
    """The camera straight above the smooth area: ``trials`` draws per distance and σ_f."""
    a = scene.areas["smooth"]
    jobs: list[ViewJob] = []
    i = 0
    for d in options.distances_m:
        pose = view_pose(a.centre, a.normal, d, 0.0, 0.0)
        for sf in options.resolved("sigma_f"):
            for _ in range(options.resolved("trials")):
                job = ViewJob(i, "smooth", d, 0.0, 0.0, float(sf), 0, 1, _seed(options, i), pose)
                jobs += _twins(job, options)
                i += 1
    return jobs


def _random_view(scene: SimScene, caster: MeshRaycaster, tree: cKDTree, rng: np.random.Generator,
                 options: SimulationOptions) -> tuple[F64, F64, float, float] | None:
    """(target, local normal, pitch, roll) of a random view, or None when the draw misses."""
    lo, hi = scene.central
    m = options.max_angle_deg
    uv = rng.uniform(lo, hi)
    pitch, roll = rng.uniform(-m, m, 2)
    plane = local_plane(scene.samples, tree, scene.basis, scene.up, uv, options.area_radius_m)
    if plane is None:
        return None
    point = plane[0] + (uv - plane[0] @ scene.basis.T) @ scene.basis
    target = surface_point(caster, point, plane[1], options.true_scale)
    return None if target is None else (target, plane[1], float(pitch), float(roll))


def random_jobs(scene: SimScene, caster: MeshRaycaster, options: SimulationOptions
                ) -> list[ViewJob]:
    """Random surface points of the central half, random pitch and roll, distances in turn."""
    rng = np.random.default_rng(np.random.SeedSequence([options.seed, 99]))
    tree = cKDTree(scene.samples @ scene.basis.T)
    dists = options.distances_m
    jobs: list[ViewJob] = []
    i = n = misses = 0
    while n < options.resolved("trials"):
        view = _random_view(scene, caster, tree, rng, options)
        if view is None:
            misses += 1
            if misses > 1000 + 10 * n:
                raise InputError("random views: the mesh's central half has too little surface")
            continue
        target, normal, pitch, roll = view
        d = dists[n % len(dists)]
        pose = view_pose(target, normal, d, pitch, roll)
        for sf in options.resolved("sigma_f"):
            jobs += _twins(ViewJob(i, "random", d, pitch, roll, float(sf), 0, 1,
                                   _seed(options, i), pose), options)
            i += 1
        n += 1
    return jobs


def make_jobs(scene: SimScene, caster: MeshRaycaster, options: SimulationOptions
              ) -> list[ViewJob]:
    """The trials of the options' mode."""
    if options.mode == "grid":
        return grid_jobs(scene, options)
    if options.mode == "noise-table":
        return noise_table_jobs(scene, options)
    return random_jobs(scene, caster, options)


# --------------------------------------------------------------------------- one trial


@dataclass(frozen=True)
class TrueSpot:
    """Where a beam meets the mesh in one true view (model units) and whether it is seen."""

    laser: str
    xy_px: F64 | None  # (2,) exact projection, COLMAP convention; None when not visible
    hit: F64 | None  # (3,) first hit of the beam, model units (None: the beam misses)
    reason: str | None  # why the spot is not visible


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


def true_spots(caster: MeshRaycaster, camera: Camera, true_model: Pose, rig: Rig, k: float
               ) -> list[TrueSpot]:
    """Each beam's first mesh hit (model units), projected if in the image and unoccluded."""
    world_from_cam = true_model.inverse()
    origins = world_from_cam.transform(np.array([las.origin for las in rig.lasers]) / k)
    dirs = np.array([las.direction for las in rig.lasers]) @ true_model.R  # rows: Rᵀ v
    beams = caster.cast(origins, dirs)
    centre = true_model.center
    sight = caster.cast(np.repeat(centre[None], len(dirs), axis=0),
                        np.where(beams.hit[:, None], beams.xyz - centre, dirs))
    out = []
    for i, las in enumerate(rig.lasers):
        if not beams.hit[i]:
            out.append(TrueSpot(las.name, None, None, "beam misses the mesh"))
            continue
        hit = beams.xyz[i]
        rng_ = float(np.linalg.norm(hit - centre))
        xy = camera.project(true_model.transform(hit[None]))[0]
        inside = (SPOT_MARGIN_PX <= xy[0] <= camera.width - SPOT_MARGIN_PX
                  and SPOT_MARGIN_PX <= xy[1] <= camera.height - SPOT_MARGIN_PX)
        seen = bool(sight.hit[i]) and abs(float(sight.distance[i]) - rng_) <= 1e-6 * rng_ + 1e-9
        reason = None if inside and seen else ("spot outside the image" if not inside
                                               else "spot hidden by the terrain")
        out.append(TrueSpot(las.name, xy if reason is None else None, hit, reason))
    return out


def _depth_differences(rig: Rig, spots: Sequence[TrueSpot], true_model: Pose, k: float
                       ) -> dict[str, float]:
    """Per pair with both beams hitting: (X_2 − X_1)·v of the true hits, metres."""
    by = {s.laser: s for s in spots}
    out = {}
    for pair in rig.pairs:
        a, b = by[pair.lasers[0]], by[pair.lasers[1]]
        v = rig.laser(pair.lasers[0]).direction
        if a.hit is not None and b.hit is not None and v is not None:
            out["+".join(pair.lasers)] = float(((b.hit - a.hit) @ (true_model.R.T @ v)) * k)
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
    reasons = {t.laser: t.reason for t in truth if t.reason is not None}
    cast = cast_spots(spots, ctx.camera, pose, ctx.caster, ctx.options.spot_cast)
    edges = tuple(h.laser for h in cast.edge_hits)
    reasons.update({las: why for las, why in cast.reasons.items() if las not in edges})
    k = ctx.options.true_scale
    depth = _depth_differences(setting.rig, truth,
                               Pose(job.cam_from_world.R, job.cam_from_world.t / k), k)
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
            truths[s.config] = true_spots(ctx.caster, ctx.camera, true_model, s.rig, k)
        outcomes.append(evaluate_setting(ctx, i, truths[s.config], job, pose, res.covariance,
                                         z[i]))
    rot, centre = _pose_errors(true_model, pose, k)
    return TrialRecord(job, True, None, res.num_inliers, rot, centre, tuple(outcomes),
                       time.process_time() - cpu0)


# --------------------------------------------------------------------------- running trials

_WORKER: TrialContext | None = None


def _init_worker(vertices: F64, triangles: NDArray[np.int64], camera: Camera,
                 settings: tuple[LaserSetting, ...], options: SimulationOptions) -> None:
    global _WORKER
    _WORKER = TrialContext(MeshRaycaster(vertices, triangles), camera, settings, options)


def _work(job: ViewJob) -> TrialRecord:
    if _WORKER is None:  # pragma: no cover - the pool's initializer always runs first
        raise RuntimeError("worker not initialised")
    return run_trial(_WORKER, job)


def _group_work(task: GroupTask) -> GroupResult:
    return joint_group(task)


Mapper = Callable[[Callable[[Any], Any], Sequence[Any]], Iterator[Any]]


@contextmanager
def worker_pool(caster: MeshRaycaster, settings: tuple[LaserSetting, ...],
                options: SimulationOptions, n_jobs: int) -> Iterator[Mapper]:
    """An ordered ``map`` for trials and groups: in this process, or in ``options.workers``
    spawned processes (each builds its own ray caster once). Spawned processes import the
    caller's main module: a script calling this with workers > 1 needs the usual
    ``if __name__ == "__main__":`` guard (without it the pool never starts)."""
    global _WORKER
    if options.workers == 1 or n_jobs < 8 * options.workers:
        previous = _WORKER
        _WORKER = TrialContext(caster, options.camera, settings, options)
        try:
            yield lambda fn, items: map(fn, items)
        finally:
            _WORKER = previous
        return
    quiet = replace(options, progress=False)
    with ProcessPoolExecutor(options.workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_init_worker,
                             initargs=(caster.vertices, caster.triangles, options.camera,
                                       settings, quiet)) as pool:
        def pmap(fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[Any]:
            chunk = max(1, min(16, len(items) // (8 * options.workers)))
            return pool.map(fn, items, chunksize=chunk)

        yield pmap


def _progress(items: Iterable[Any], total: int, desc: str, options: SimulationOptions
              ) -> Iterator[Any]:
    from tqdm import tqdm

    yield from tqdm(items, total=total, desc=desc, unit="view", leave=False,
                    disable=not options.progress or not sys.stderr.isatty())


def run_trials(pmap: Mapper, jobs: Sequence[ViewJob], options: SimulationOptions
               ) -> Iterator[TrialRecord]:
    """Every job's record, in job order."""
    yield from _progress(pmap(_work, jobs), len(jobs), f"simulate {options.mode}", options)


# --------------------------------------------------------------------------- collecting


class SettingKey(NamedTuple):
    """What one row of results.json aggregates over."""

    config: str
    area: str
    distance_m: float
    sigma_f_px: float
    sigma_l_px: float


class SampleTable:
    """Column store of every estimate: one row per (view, method, laser or pair)."""

    FLOATS = ("value", "sigma", "lo", "hi", "pitch", "roll", "depth")
    INTS = ("key", "view", "round", "sign", "method", "sub", "edge")

    def __init__(self) -> None:
        self.keys: list[SettingKey] = []
        self.vocab: list[str] = []
        self._key_ids: dict[SettingKey, int] = {}
        self._codes: dict[str, int] = {}
        self._f = {c: array("d") for c in self.FLOATS}
        self._i = {c: array("q") for c in self.INTS}

    def key_id(self, key: SettingKey) -> int:
        """Index of a setting key (added when new)."""
        if key not in self._key_ids:
            self._key_ids[key] = len(self.keys)
            self.keys.append(key)
        return self._key_ids[key]

    def code(self, text: str) -> int:
        """Integer code of a method or laser name."""
        if text not in self._codes:
            self._codes[text] = len(self.vocab)
            self.vocab.append(text)
        return self._codes[text]

    def add(self, key: SettingKey, method: str, sub: str, value: float, sigma: float,
            interval: tuple[float, float], view: tuple[int, int, int, float, float],
            depth: float = float("nan"), edge: int = 0) -> None:
        """One estimate; view = (view id, round, sign, pitch, roll); edge: 0 normal, 1 only
        without the depth-edge check (it uses an edge spot), −1 only with it (as ``scale``)."""
        floats = (value, sigma, interval[0], interval[1], view[3], view[4], depth)
        for c, v in zip(self.FLOATS, floats, strict=True):
            self._f[c].append(float(v))
        ints = (self.key_id(key), view[0], view[1], view[2], self.code(method), self.code(sub),
                edge)
        for c, n in zip(self.INTS, ints, strict=True):
            self._i[c].append(int(n))

    def __len__(self) -> int:
        return len(self._f["value"])

    def arrays(self) -> dict[str, NDArray[Any]]:
        """Every column as a numpy array (methods and subs as integer codes)."""
        out: dict[str, NDArray[Any]] = {c: np.frombuffer(a, dtype=np.float64)
                                        for c, a in self._f.items()}
        out.update({c: np.frombuffer(a, dtype=np.int64) for c, a in self._i.items()})
        return out


@dataclass
class Collected:
    """Trial records turned into estimate rows, rejection counts and PCM-joint groups."""

    table: SampleTable = field(default_factory=SampleTable)
    rejected: Counter[tuple[SettingKey, str]] = field(default_factory=Counter)
    groups: dict[tuple[SettingKey, int, int], list[tuple[ViewJob, LaserOutcome]]] = field(
        default_factory=lambda: defaultdict(list))
    views: int = 0
    failed: Counter[str] = field(default_factory=Counter)
    rotation_error_deg: list[float] = field(default_factory=list)
    centre_error_m: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)  # per trial


def _view(job: ViewJob) -> tuple[int, int, int, float, float]:
    return (job.index, job.round, job.sign, job.pitch_deg, job.roll_deg)


def _interval(value: float, sigma: float) -> tuple[float, float]:
    return (value - Z95 * sigma, value + Z95 * sigma)


def _ingest_fused(col: Collected, key: SettingKey, v: tuple[int, int, int, float, float],
                  out: LaserOutcome) -> None:
    """Per-view fusions (pipeline σ and σ without Birge inflation), with and without the edge
    spots when the view has any."""
    variants = [(out.fused, -1 if out.edge_spots else 0)]
    if out.edge_spots:
        variants.append((out.fused_unchecked, 1))
    for fused, edge in variants:
        for m, (value, std, lo, hi, gls) in fused.items():
            if not math.isfinite(value):
                col.rejected[(key, f"{m}_fused")] += edge <= 0
                continue
            col.table.add(key, f"{m}_fused", "", value, std, (lo, hi), v, edge=edge)
            col.table.add(key, f"{m}_fused_gls", "", value, gls, _interval(value, gls), v,
                          edge=edge)


def _ingest_outcome(col: Collected, key: SettingKey, job: ViewJob, out: LaserOutcome) -> None:
    """Rows of one laser setting in one view: singles, per-view fusions, Davis & Tusting."""
    t, v = col.table, _view(job)
    for laser in out.spot_reasons:
        col.rejected[(key, f"spot:{laser}")] += 1
    for laser in out.edge_spots:
        col.rejected[(key, f"edge:{laser}")] += 1
    if out.estimates is not None:
        for e in out.estimates.estimates:
            if e.rejected or not (math.isfinite(e.scale) and math.isfinite(e.sigma)):
                col.rejected[(key, e.method)] += 1
                continue
            depth = abs(out.depth_difference_m.get(e.laser, float("nan")))
            edge = int(any(las in out.edge_spots for las in e.laser.split("+")))
            t.add(key, e.method, e.laser, e.scale, e.sigma, _interval(e.scale, e.sigma), v,
                  depth, edge)
    _ingest_fused(col, key, v, out)
    if math.isfinite(out.davis_tusting):
        t.add(key, "davis_tusting", "", out.davis_tusting, float("nan"), (np.nan, np.nan), v)
    if out.observation is not None and out.estimates is not None:
        col.groups[(key, job.round, job.sign)].append((job, out))


def collect(records: Iterable[TrialRecord], settings: Sequence[LaserSetting]) -> Collected:
    """Turn trial records into estimate rows (and remember the views for PCM-joint)."""
    col = Collected()
    for rec in records:
        col.views += 1
        col.cpu_s.append(rec.cpu_s)
        job = rec.job
        if not rec.registered:
            col.failed[rec.reason or "registration failed"] += 1
            for s in settings:
                key = SettingKey(s.config, job.area, job.distance_m, job.sigma_f_px, s.sigma_l_px)
                col.rejected[(key, "registration")] += 1
            continue
        col.rotation_error_deg.append(rec.rotation_error_deg)
        col.centre_error_m.append(rec.centre_error_m)
        for out in rec.outcomes:
            s = settings[out.setting]
            key = SettingKey(s.config, job.area, job.distance_m, job.sigma_f_px, s.sigma_l_px)
            _ingest_outcome(col, key, job, out)
    return col


@dataclass(frozen=True)
class GroupTask:
    """A group of views of one setting for PCM-joint (sent to a worker)."""

    key: SettingKey
    gid: int
    views: tuple[tuple[int, int, int, float, float], ...]  # _view of each member
    depths: tuple[dict[str, float], ...]
    observations: tuple[ImageObservation, ...]
    estimates: tuple[ImageEstimates, ...]
    rig: Rig
    options: SimulationOptions


Row = tuple[str, str, float, float, tuple[float, float], tuple[int, int, int, float, float],
            float]


@dataclass(frozen=True)
class GroupResult:
    """Rows (method, laser/pair, value, σ, interval, view, depth) and rejected methods."""

    key: SettingKey
    rows: tuple[Row, ...]
    rejected: tuple[str, ...]


def joint_group(task: GroupTask) -> GroupResult:
    """PCM-joint over one group of views, the midpoint PCM fused over the same views, and
    each view's scale with the joint beam direction."""
    opts = task.options
    res = estimate_pcm_joint(task.observations, task.rig,
                             PcmJointOptions(estimation=opts.estimation, fusion=opts.fusion))
    nan = float("nan")
    first = task.views[0]
    gview = (task.gid, first[1], first[2], nan, nan)
    rows: list[Row] = []
    rejected = []
    f = res.fused
    if res.joint and math.isfinite(f.value):
        rows.append(("pcm_joint", "", f.value, f.std, f.ci95, gview, nan))
    else:
        rejected.append("pcm_joint")
    mid = fuse(task.estimates, "pcm", opts.fusion)
    if math.isfinite(mid.value):
        rows.append(("pcm_group", "", mid.value, mid.std, mid.ci95, gview, nan))
    member = {o.image: i for i, o in enumerate(task.observations)}
    for fit in res.pairs if res.joint else ():
        for im in fit.images:
            if im.rejected or im.image not in member:
                continue
            i = member[im.image]
            rows.append(("pcm_joint_view", fit.pair, im.implied_scale, im.implied_sigma,
                         _interval(im.implied_scale, im.implied_sigma), task.views[i],
                         abs(task.depths[i].get(fit.pair, nan))))
    return GroupResult(task.key, tuple(rows), tuple(rejected))


def group_tasks(col: Collected, settings: Sequence[LaserSetting], options: SimulationOptions
                ) -> list[GroupTask]:
    """Random groups of ``group_size`` views of one setting, noise draw and sign (none for the
    noise table: its views are identical, which leaves the beam direction undetermined)."""
    if options.mode == "noise-table":
        return []
    rigs = {s.config: s.rig for s in settings}
    tasks: list[GroupTask] = []
    for n, ((key, _, _), items) in enumerate(sorted(col.groups.items(), key=lambda kv: kv[0])):
        rig = rigs[key.config]
        if not rig.pairs or len(items) < options.group_size:
            continue
        rng = np.random.default_rng(np.random.SeedSequence([options.seed, 5, n]))
        order = rng.permutation(len(items))
        for idx in np.array_split(order, len(items) // options.group_size):
            members = [items[i] for i in idx]
            tasks.append(GroupTask(
                key, len(tasks), tuple(_view(j) for j, _ in members),
                tuple(o.depth_difference_m for _, o in members),
                tuple(o.observation for _, o in members if o.observation is not None),
                tuple(o.estimates for _, o in members if o.estimates is not None), rig,
                options))
    return tasks


def add_groups(col: Collected, results: Iterable[GroupResult]) -> None:
    """Add the PCM-joint rows of every group (and forget the views kept for grouping)."""
    for res in results:
        for method, sub, value, sigma, interval, view, depth in res.rows:
            col.table.add(res.key, method, sub, value, sigma, interval, view, depth)
        for method in res.rejected:
            col.rejected[(res.key, method)] += 1
    col.groups.clear()


# --------------------------------------------------------------------------- statistics

#: Methods in the order of tables and figures.
METHOD_ORDER = ("fcm", "fcm_unchecked", "fcm_fused", "fcm_fused_unchecked", "fcm_fused_gls",
                "pcm", "pcm_unchecked", "pcm_fused", "pcm_fused_gls", "pcm_group", "pcm_joint",
                "pcm_joint_view", "direct3d", "direct3d_fused", "direct3d_fused_gls",
                "davis_tusting")
UNCHECKED = "_unchecked"


def method_rows(t: SampleTable, a: dict[str, NDArray[Any]], method: str) -> NDArray[np.bool_]:
    """Rows of a reported method; ``<m>_unchecked`` is ``<m>`` with the depth-edge spots."""
    unchecked = method.endswith(UNCHECKED)
    base = method[: -len(UNCHECKED)] if unchecked else method
    if base not in t.vocab:
        return np.zeros(len(a["value"]), dtype=bool)
    edge_ok = a["edge"] >= 0 if unchecked else a["edge"] <= 0
    return np.asarray((a["method"] == t.code(base)) & edge_ok)
#: Methods with a laser or pair name per row (also reported per laser / pair).
PER_SUB = ("fcm", "pcm", "direct3d", "pcm_joint_view")


def method_stats(value: F64, sigma: F64, lo: F64, hi: F64, truth: float) -> dict[str, float]:
    """Error statistics of n estimates of ``truth``: bias, std, RMSE, mean σ (all in % of the
    truth), std / mean σ, mean and RMS of the normalised error z = (s − truth) / σ, and the
    fraction of 95 % intervals holding the truth. NaN where undefined."""
    e = value / truth - 1.0
    n = len(e)
    nan = float("nan")
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(sigma > 0, (value - truth) / sigma, np.nan)
    has_sigma = np.isfinite(z)
    has_ci = np.isfinite(lo) & np.isfinite(hi)
    std = float(np.std(e, ddof=1)) * 100 if n > 1 else nan
    pred = float(np.mean(sigma[has_sigma] / truth)) * 100 if has_sigma.any() else nan
    return {
        "n": n,
        "bias": float(np.mean(e)) * 100 if n else nan,
        "std": std,
        "rmse": float(np.sqrt(np.mean(e**2))) * 100 if n else nan,
        "predicted_sigma": pred,
        "ratio": std / pred if pred > 0 else nan,
        "z_mean": float(np.mean(z[has_sigma])) if has_sigma.any() else nan,
        "z_rms": float(np.sqrt(np.mean(z[has_sigma] ** 2))) if has_sigma.any() else nan,
        "coverage95": float(np.mean((lo[has_ci] <= truth) & (truth <= hi[has_ci])))
        if has_ci.any() else nan,
    }


def antithetic_pairs(a: dict[str, NDArray[Any]], rows: NDArray[np.bool_]
                     ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Row indices (plus, minus) of the antithetic twins among ``rows`` (same key, view, draw,
    laser or pair; both present)."""
    plus: dict[tuple[int, int, int, int], int] = {}
    minus: dict[tuple[int, int, int, int], int] = {}
    for i in np.flatnonzero(rows):
        k = (int(a["key"][i]), int(a["view"][i]), int(a["round"][i]), int(a["sub"][i]))
        (plus if a["sign"][i] > 0 else minus)[k] = int(i)
    both = [k for k in plus if k in minus]
    return (np.array([plus[k] for k in both], dtype=np.int64),
            np.array([minus[k] for k in both], dtype=np.int64))


def pair_bias(a: dict[str, NDArray[Any]], rows: NDArray[np.bool_], truth: float
              ) -> tuple[float, float, int]:
    """Antithetic pairs: max and mean of |pair-mean error| / σ, and the number of pairs."""
    p, m = antithetic_pairs(a, rows & np.isfinite(a["sigma"]))
    if len(p) == 0:
        return float("nan"), float("nan"), 0
    b = np.abs(0.5 * (a["value"][p] + a["value"][m]) - truth) / (
        0.5 * (a["sigma"][p] + a["sigma"][m]))
    return float(np.max(b)), float(np.mean(b)), len(b)


def _stats_for(a: dict[str, NDArray[Any]], rows: NDArray[np.bool_], options: SimulationOptions
               ) -> dict[str, float]:
    k = options.true_scale
    out = method_stats(a["value"][rows], a["sigma"][rows], a["lo"][rows], a["hi"][rows], k)
    if options.antithetic:
        mx, mean, n = pair_bias(a, rows, k)
        out.update(pair_bias_max_sigma=mx, pair_bias_mean_sigma=mean, n_pairs=n)
    return out


def _counts(col: Collected, key: SettingKey, prefix: str) -> dict[str, int]:
    """Per laser, how often a counter starting with ``prefix`` fired for this setting."""
    return {name[len(prefix):]: n for (k, name), n in col.rejected.items()
            if k == key and name.startswith(prefix)}


def summarize(col: Collected, options: SimulationOptions) -> list[dict[str, Any]]:
    """results.json ``settings``: per setting key, statistics per method (and laser / pair)."""
    t = col.table
    a = t.arrays()
    out = []
    for kid, key in enumerate(t.keys):
        in_key = a["key"] == kid
        methods: dict[str, Any] = {}
        for m in METHOD_ORDER:
            rows = in_key & method_rows(t, a, m)
            if rows.any():
                methods[m] = {**_stats_for(a, rows, options), "n_rejected": col.rejected[(key, m)]}
            subs = sorted({t.vocab[c] for c in a["sub"][rows]}) if m in PER_SUB else []
            for sub in subs if len(subs) > 1 else []:
                sub_rows = rows & (a["sub"] == t.code(sub))
                methods[f"{m}:{sub}"] = _stats_for(a, sub_rows, options)
        out.append({"setting": key._asdict(), "methods": methods,
                    "registration_failures": col.rejected[(key, "registration")],
                    "spots_not_visible": _counts(col, key, "spot:"),
                    "edge_spots": _counts(col, key, "edge:")})
    return out


def overall(col: Collected, options: SimulationOptions) -> dict[str, dict[str, Any]]:
    """Per configuration and method, pooled over every setting: n, mean and RMS of z, coverage."""
    t = col.table
    a = t.arrays()
    out: dict[str, dict[str, Any]] = {}
    for config in sorted({key.config for key in t.keys}):
        in_config = np.isin(a["key"], [i for i, key in enumerate(t.keys) if key.config == config])
        per: dict[str, Any] = {}
        for m in METHOD_ORDER:
            rows = in_config & method_rows(t, a, m)
            if rows.any():
                s = _stats_for(a, rows, options)
                per[m] = {k: s[k] for k in ("n", "z_mean", "z_rms", "coverage95",
                                            "pair_bias_max_sigma") if k in s}
        out[config] = per
    return out


#: Methods drawn in the grid heatmaps.
MAP_METHODS = ("fcm_fused", "fcm", "pcm", "pcm_joint_view", "direct3d", "davis_tusting")


def grid_maps(col: Collected, options: SimulationOptions
              ) -> dict[tuple[str, float], dict[str, dict[str, F64]]]:
    """(config, distance) -> area -> method -> (n, n) mean error % over [pitch, roll] (grid)."""
    t = col.table
    a = t.arrays()
    angles = grid_angles(options)
    n = len(angles)
    out: dict[tuple[str, float], dict[str, dict[str, F64]]] = defaultdict(dict)
    for kid, key in enumerate(t.keys):
        maps: dict[str, F64] = {}
        for m in MAP_METHODS:
            rows = (a["key"] == kid) & method_rows(t, a, m)
            if not rows.any():
                continue
            ip = np.clip(np.round((a["pitch"][rows] - angles[0]) / options.angle_step_deg), 0,
                         n - 1).astype(int)
            ir = np.clip(np.round((a["roll"][rows] - angles[0]) / options.angle_step_deg), 0,
                         n - 1).astype(int)
            total, count = np.zeros((n, n)), np.zeros((n, n))
            np.add.at(total, (ip, ir), 100 * (a["value"][rows] / options.true_scale - 1))
            np.add.at(count, (ip, ir), 1)
            with np.errstate(invalid="ignore"):
                maps[m] = total / count
        out[(key.config, key.distance_m)].setdefault(key.area, {}).update(maps)
    return dict(out)


# --------------------------------------------------------------------------- tables

def method_label(method: str, group_size: int) -> str:
    """Human name of a reported method."""
    return {
        "fcm": "FCM single laser", "fcm_fused": "FCM fused (per view)",
        "fcm_unchecked": "FCM single laser, depth-edge spots kept",
        "fcm_fused_unchecked": "FCM fused, depth-edge spots kept",
        "pcm_unchecked": "PCM, depth-edge spots kept",
        "fcm_fused_gls": "FCM fused, σ without Birge inflation",
        "pcm": "PCM (midpoint)", "pcm_fused": "PCM fused (per view)",
        "pcm_fused_gls": "PCM fused, σ without Birge inflation",
        "direct3d_fused_gls": "Direct 3D fused, σ without Birge inflation",
        "pcm_group": f"PCM fused over {group_size} views",
        "pcm_joint": f"PCM-joint ({group_size} views)",
        "pcm_joint_view": "PCM-joint direction, per view",
        "direct3d": "Direct 3D", "direct3d_fused": "Direct 3D fused (per view)",
        "davis_tusting": "Davis & Tusting",
    }.get(method, method)


def _fmt(x: Any, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    if isinstance(x, int):
        return str(x)
    return f"{x:.{digits}f}"


#: Methods of the compact (paper-like) table, per mode.
TABLE_METHODS = {
    "noise-table": ("fcm", "fcm_fused", "pcm", "direct3d"),
    "grid": ("fcm", "fcm_fused", "pcm", "pcm_group", "pcm_joint", "direct3d", "davis_tusting"),
    "random": ("fcm", "fcm_fused", "pcm", "pcm_group", "pcm_joint", "pcm_joint_view",
               "direct3d", "davis_tusting"),
}


def pivot_table(stats: Sequence[dict[str, Any]], mode: str, group_size: int) -> list[str]:
    """The paper's layout: rows configuration × method × noise, columns area × distance;
    cells "std (bias)" in % of the scale."""
    cols = sorted({(s["setting"]["area"], s["setting"]["distance_m"]) for s in stats},
                  key=lambda c: (AREAS.index(c[0]) if c[0] in AREAS else 9, c[1]))
    head = ["config", "method", "σ_f px", "σ_l px"] + [
        f"{d:g} m" if mode == "noise-table" else f"{a} {d:g} m" for a, d in cols]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    rows = sorted({(s["setting"]["config"], s["setting"]["sigma_f_px"], s["setting"]["sigma_l_px"])
                   for s in stats})
    cell = {(s["setting"]["config"], s["setting"]["sigma_f_px"], s["setting"]["sigma_l_px"],
             s["setting"]["area"], s["setting"]["distance_m"]): s["methods"] for s in stats}
    for config, sf, sl in rows:
        for m in TABLE_METHODS[mode]:
            vals = [cell.get((config, sf, sl, a, d), {}).get(m) for a, d in cols]
            if not any(vals):
                continue
            txt = [f"{_fmt(v['std'], 2)} ({_fmt(v['bias'], 2)})" if v else "–" for v in vals]
            lines.append(f"| {config} | {method_label(m, group_size)} | {sf:g} | {sl:g} | "
                         + " | ".join(txt) + " |")
    return lines


def calibration_table(stats: Sequence[dict[str, Any]], group_size: int) -> list[str]:
    """Every setting and method with a σ: n, bias, std, mean σ, std/σ, RMS z, coverage."""
    head = ["config", "area", "d m", "σ_f", "σ_l", "method", "n", "bias %", "std %",
            "mean σ %", "std/σ", "RMS z", "cover95"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in stats:
        k = s["setting"]
        for m, v in s["methods"].items():
            if ":" in m or not (v.get("predicted_sigma") or 0) > 0:
                continue
            lines.append("| " + " | ".join([
                k["config"], k["area"], f"{k['distance_m']:g}", f"{k['sigma_f_px']:g}",
                f"{k['sigma_l_px']:g}", method_label(m, group_size), str(v["n"]),
                _fmt(v["bias"]), _fmt(v["std"]), _fmt(v["predicted_sigma"]), _fmt(v["ratio"], 2),
                _fmt(v["z_rms"], 2), _fmt(v["coverage95"], 3)]) + " |")
    return lines


def markdown_report(results: dict[str, Any], options: SimulationOptions) -> str:
    """table.md: the paper-like table, then the calibration table."""
    cam = results["camera"]
    g = options.group_size
    lines = [f"# sfm-laserscale simulate — {options.mode}", "",
             f"Camera {cam['model']} {cam['width']}×{cam['height']}, f = {cam['params'][0]:g} px; "
             f"{results['trials']} trial(s) {results['trials_unit']}; outliers "
             f"{options.outlier_ratio:g}; {options.n_points} model points per view.", "",
             "## Spread and bias", "",
             "Cells: std (bias) of the estimates in % of the true scale.", ""]
    lines += pivot_table(results["settings"], options.mode, g)
    lines += ["", "## Calibration of the reported σ", "",
              "std/σ: Monte-Carlo spread over the mean reported σ; RMS z: RMS of (estimate − "
              "truth) / reported σ (1 when calibrated, also when views differ); cover95: "
              "fraction of 95 % intervals holding the truth.", ""]
    lines += calibration_table(results["settings"], g)
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- result, writer


@dataclass(frozen=True)
class SimulationResult:
    """Everything a simulation produced (results.json's content, the tables, the rows)."""

    options: SimulationOptions
    settings: tuple[LaserSetting, ...]
    scene: SimScene
    collected: Collected
    results: dict[str, Any]
    table_md: str
    timings: dict[str, float]
    summary: str


def _jsonable(x: Any) -> Any:
    """Plain JSON values: arrays to lists, NaN/inf to None, dataclasses and tuples unpacked."""
    if hasattr(x, "__dataclass_fields__") and not isinstance(x, type):
        return {k: _jsonable(v) for k, v in asdict(x).items()}
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _rig_json(rig: Rig) -> dict[str, Any]:
    return {"name": rig.name,
            "lasers": [{"name": las.name, "origin_m": las.origin, "direction": las.direction}
                       for las in rig.lasers],
            "pairs": [{"lasers": list(p.lasers), "separation_m": p.separation}
                      for p in rig.pairs]}


def _maps_json(col: Collected, options: SimulationOptions) -> list[dict[str, Any]]:
    if options.mode != "grid":
        return []
    angles = grid_angles(options).tolist()
    return [{"config": c, "distance_m": d, "area": area, "method": m, "angles_deg": angles,
             "mean_error_percent": arr}
            for (c, d), areas in grid_maps(col, options).items()
            for area, maps in areas.items() for m, arr in maps.items()]


def build_results(scene: SimScene, settings: Sequence[LaserSetting], col: Collected,
                  options: SimulationOptions, timings: dict[str, float]) -> dict[str, Any]:
    """The content of results.json (plain JSON values)."""
    unit = {"grid": "per view", "random": "views in all", "noise-table": "per cell"}[options.mode]
    rot, centre = np.asarray(col.rotation_error_deg), np.asarray(col.centre_error_m)
    return _jsonable({
        "version": __version__, "mode": options.mode, "true_scale": options.true_scale,
        "units": "bias, std, rmse, predicted_sigma: % of the true scale; ratio = std / "
                 "predicted_sigma; z = (estimate − truth) / reported sigma; coverage95: "
                 "fraction of 95 % intervals holding the truth",
        "trials": options.resolved("trials"), "trials_unit": unit,
        "camera": options.camera, "group_size": options.group_size,
        "outlier_ratio": options.outlier_ratio, "n_points": options.n_points,
        "antithetic": options.antithetic, "seed": options.seed,
        "scene": {"source": scene.source, "areas": scene.areas},
        "configs": {s.config: _rig_json(s.rig) for s in settings},
        "registration": {"views": col.views, "failed": sum(col.failed.values()),
                         "reasons": dict(col.failed),
                         "rotation_error_deg_median": float(np.median(rot)) if len(rot) else None,
                         "centre_error_mm_median": float(np.median(centre)) * 1e3
                         if len(centre) else None},
        "settings": summarize(col, options), "overall": overall(col, options),
        "grid_maps": _maps_json(col, options), "timings_s": timings,
    })


def _summary_line(results: dict[str, Any], seconds: float) -> str:
    reg = results["registration"]
    parts = [f"simulate {results['mode']}: {reg['views']} views ({reg['failed']} not "
             f"registered) in {seconds:.0f} s"]
    for config, per in results["overall"].items():
        for m in ("fcm", "fcm_fused", "pcm", "pcm_joint"):
            v = per.get(m)
            if v and v.get("z_rms") is not None:
                parts.append(f"{config} {m}: RMS z {v['z_rms']:.2f}, 95 % coverage "
                             f"{v['coverage95']:.3f} (n {v['n']})")
    return "\n".join(parts)


def simulate(inputs: SimulationInputs, options: SimulationOptions,
             prepared: tuple[SimScene, MeshRaycaster] | None = None) -> SimulationResult:
    """Run the experiments of ``options.mode`` (no files written). ``prepared``: a scene from
    :func:`load_scene` / :func:`build_scene` with the same ``true_scale`` (else it is loaded)."""
    timings: dict[str, float] = {}
    t_all = t0 = time.perf_counter()
    scene, caster = prepared if prepared is not None else load_scene(inputs, options)
    settings = load_settings(inputs, options)
    timings["scene"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    jobs = make_jobs(scene, caster, options)
    timings["views"] = time.perf_counter() - t0
    with worker_pool(caster, settings, options, len(jobs)) as pmap:
        t0 = time.perf_counter()
        col = collect(run_trials(pmap, jobs, options), settings)
        timings["trials"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        tasks = group_tasks(col, settings, options)
        add_groups(col, pmap(_group_work, tasks))
        timings["pcm_joint"] = time.perf_counter() - t0
    timings["trial_cpu_ms_mean"] = 1e3 * float(np.mean(col.cpu_s)) if col.cpu_s else 0.0
    timings["total"] = time.perf_counter() - t_all
    timings["workers"] = float(options.workers)
    results = build_results(scene, settings, col, options, timings)
    logger.info("simulation done: %d views, %d estimates", col.views, len(col.table))
    return SimulationResult(options, settings, scene, col, results,
                            markdown_report(results, options), timings,
                            _summary_line(results, timings["total"]))


def _trial_rows(col: Collected) -> Iterator[list[Any]]:
    t = col.table
    a = t.arrays()
    for i in range(len(t)):
        key = t.keys[int(a["key"][i])]
        yield [key.config, key.area, f"{key.distance_m:g}", f"{key.sigma_f_px:g}",
               f"{key.sigma_l_px:g}", t.vocab[int(a["method"][i])], t.vocab[int(a["sub"][i])],
               int(a["view"][i]), int(a["round"][i]), int(a["sign"][i]), int(a["edge"][i]),
               *(f"{float(a[c][i]):.10g}" for c in ("pitch", "roll", "value", "sigma", "lo",
                                                   "hi", "depth"))]


def write_trials_csv(path: Path, col: Collected) -> None:
    """Every estimate, one row each (gzip-compressed CSV)."""
    with gzip.open(path, "wt", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["config", "area", "distance_m", "sigma_f_px", "sigma_l_px", "method",
                    "laser", "view", "round", "sign", "edge", "pitch_deg", "roll_deg", "scale",
                    "sigma", "ci95_lo", "ci95_hi", "depth_difference_m"])
        w.writerows(_trial_rows(col))


def write_simulation(out_dir: Path, result: SimulationResult, overwrite: bool) -> None:
    """results.json, table.md, trials.csv.gz and the figures, staged then moved into place."""
    from sfm_laserscale.io.outputs import staged_output_dir
    from sfm_laserscale.report.simulate_plots import simulation_figures

    with staged_output_dir(out_dir, overwrite) as tmp:
        t0 = time.perf_counter()
        for name, png in simulation_figures(result).items():
            (tmp / name).write_bytes(png)
        result.timings["figures"] = time.perf_counter() - t0
        write_trials_csv(tmp / "trials.csv.gz", result.collected)
        (tmp / "table.md").write_text(result.table_md, encoding="utf-8")
        result.results["timings_s"] = _jsonable(result.timings)
        (tmp / "results.json").write_text(json.dumps(result.results, indent=1,
                                                     allow_nan=False), encoding="utf-8")


def run_simulation(inputs: SimulationInputs, out_dir: Path,
                   options: SimulationOptions = SimulationOptions(),  # noqa: B008
                   overwrite: bool = False) -> SimulationResult:
    """The ``simulate`` command: run the experiments and write every output into ``out_dir``."""
    from sfm_laserscale.io.outputs import check_output_dir

    check_output_dir(out_dir, overwrite)
    result = simulate(inputs, options)
    write_simulation(out_dir, result, overwrite)
    return result
