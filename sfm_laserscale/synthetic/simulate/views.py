"""The true views of each mode: the pitch × roll grid over both areas, the noise table above
the smooth area, random views of the central half (``make_jobs``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Pose
from sfm_laserscale.raycast import MeshRaycaster
from sfm_laserscale.synthetic.simulate.areas import SimScene, local_plane, surface_point
from sfm_laserscale.synthetic.simulate.configs import MODES, SimulationOptions

F64 = NDArray[np.float64]


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
