"""The metric scene of the experiments (the demo's seafloor or a given mesh), its up axis and
surface samples, and the smooth and rough areas the views look at."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from sfm_laserscale.errors import InputError
from sfm_laserscale.raycast import MeshRaycaster
from sfm_laserscale.synthetic.simulate.configs import SimulationInputs, SimulationOptions

F64 = NDArray[np.float64]


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
