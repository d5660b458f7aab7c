"""Synthetic laser images with known truth for the uncertainty and fusion tests.

A planar scene in front of a PINHOLE camera, a 4-laser rig (two parallel pairs), a known scale
K_TRUE (metres per model unit) and a non-trivial world frame. Observations are generated
exactly: noisy spot pixels and a noisy pose, the ray through each pixel intersected with the
true plane (no linearisation). The pose noise follows the documented convention
R' = exp([δ]ₓ) R, t' = t + δt, implemented here independently of the package (Rodrigues).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.rig import Rig, rig_from_dict
from sfm_laserscale.uncertainty import ImageObservation, SpotHit

F64 = NDArray[np.float64]
K_TRUE = 0.37  # metres per model unit


def rodrigues(rotvec: F64) -> F64:
    """Rotation matrix exp([w]ₓ) (hand-written, independent of scipy)."""
    w = np.asarray(rotvec, dtype=np.float64)
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * kx @ kx


def make_camera() -> Camera:
    """PINHOLE 1024×768, f = 900 px."""
    return Camera(1, "PINHOLE", 1024, 768, np.array([900.0, 900.0, 512.0, 384.0]))


def _unit(v: list[float]) -> F64:
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a)


def _separation(o1: F64, o2: F64, v: F64) -> float:
    d = o2 - o1
    return float(np.linalg.norm(d - (d @ v) * v))


def make_rig(sigma_origin: float = 0.0, sigma_direction: float = 0.0) -> Rig:
    """4 lasers, origins 0.165 m from the camera, directions 1–3° off the axis, 2 parallel pairs."""
    va = _unit([np.tan(np.radians(2.0)), np.tan(np.radians(1.0)), 1.0])
    vb = _unit([np.tan(np.radians(-1.0)), np.tan(np.radians(3.0)), 1.0])
    origins = {"L1": [0.165, 0.0, 0.0], "L2": [-0.165, 0.01, 0.0],
               "L3": [0.01, 0.165, 0.0], "L4": [0.0, -0.165, 0.0]}
    dirs = {"L1": va, "L2": va, "L3": vb, "L4": vb}
    lasers = [{"name": n, "origin": o, "direction": list(dirs[n]),
               "sigma_origin": sigma_origin, "sigma_direction": sigma_direction}
              for n, o in origins.items()]
    o = {n: np.asarray(v) for n, v in origins.items()}
    pairs = [{"lasers": ["L1", "L2"], "separation": _separation(o["L1"], o["L2"], va)},
             {"lasers": ["L3", "L4"], "separation": _separation(o["L3"], o["L4"], vb)}]
    return rig_from_dict({"name": "synthetic", "laser": lasers, "pair": pairs})


@dataclass(frozen=True)
class Scene:
    """Camera, rig, true pose (model units) and the scene plane in world model units."""

    camera: Camera
    rig: Rig
    pose: Pose  # true cam_from_world, model units
    plane_point: F64  # world, model units
    plane_normal: F64  # world, unit
    k: float  # metres per model unit


def make_scene(rig: Rig, distance_m: float = 3.0, tilt_deg: float = 20.0,
               tilt_axis: tuple[float, float, float] = (0.3, 1.0, 0.0), k: float = K_TRUE,
               world_rotvec: tuple[float, float, float] = (0.4, -1.1, 0.3),
               world_t: tuple[float, float, float] = (2.0, -1.0, 5.0)) -> Scene:
    """Plane at distance_m on the axis, tilted by tilt_deg; camera pose arbitrary in the world."""
    axis = _unit(list(tilt_axis))
    n_cam = rodrigues(axis * np.radians(tilt_deg)) @ np.array([0.0, 0.0, -1.0])
    p_cam_model = np.array([0.0, 0.0, distance_m]) / k
    R = rodrigues(np.asarray(world_rotvec))
    t = np.asarray(world_t, dtype=np.float64)
    return Scene(make_camera(), rig, Pose(R, t), R.T @ (p_cam_model - t), R.T @ n_cam, k)


def true_hits_cam_m(scene: Scene) -> dict[str, F64]:
    """Exact metric camera-frame hit of every calibrated beam on the plane."""
    R, t = scene.pose.R, scene.pose.t
    n_c = R @ scene.plane_normal
    p_c = (R @ scene.plane_point + t) * scene.k
    out = {}
    for las in scene.rig.lasers:
        assert las.origin is not None and las.direction is not None
        r = n_c @ (p_c - las.origin) / (n_c @ las.direction)
        out[las.name] = las.origin + r * las.direction
    return out


def true_pixels(scene: Scene) -> dict[str, F64]:
    """Exact spot pixels of every beam."""
    hits = true_hits_cam_m(scene)
    px = scene.camera.project(np.array(list(hits.values())))
    return dict(zip(hits, px, strict=True))


def intersect(scene: Scene, pose: Pose, xy: F64) -> F64:
    """World hit (model units) of the ray through pixels xy (N, 2) from pose on the plane."""
    rays_w = scene.camera.unproject(xy) @ pose.R  # rows: Rᵀ ray
    c = pose.center
    lam = ((scene.plane_point - c) @ scene.plane_normal) / (rays_w @ scene.plane_normal)
    return c + lam[:, None] * rays_w


def pose_covariance(rng: np.random.Generator, sigma_rot: float = 3e-4,
                    sigma_t_m: float = 0.002, k: float = K_TRUE) -> F64:
    """A correlated 6×6 pose covariance [rot rad, trans model units]."""
    a = rng.normal(size=(6, 6))
    cov = a @ a.T + 3 * np.eye(6)
    d = np.sqrt(np.diag(cov))
    corr = cov / np.outer(d, d)
    s = np.array([sigma_rot] * 3 + [sigma_t_m / k] * 3)
    return np.asarray(corr * np.outer(s, s), dtype=np.float64)


def observe(scene: Scene, rng: np.random.Generator, sigma_px: float, pose_cov: F64 | None,
            lasers: tuple[str, ...] = ("L1", "L2", "L3", "L4"), name: str = "img",
            px_offset: dict[str, F64] | None = None, pose_noise: bool = True,
            sigma_claimed: float | None = None) -> ImageObservation:
    """One noisy observation: noisy pixels and pose, exact ray–plane hits.

    ``pose_noise`` False keeps the true pose (the covariance is still reported);
    ``sigma_claimed`` is the spot σ written into the hits (default: sigma_px).
    """
    pose = scene.pose
    if pose_cov is not None and pose_noise:
        d = np.linalg.cholesky(pose_cov) @ rng.normal(size=6)
        pose = Pose(rodrigues(d[:3]) @ pose.R, pose.t + d[3:])
    px = true_pixels(scene)
    xy = np.array([px[n] for n in lasers]) + rng.normal(scale=sigma_px, size=(len(lasers), 2))
    if px_offset:
        xy += np.array([px_offset.get(n, np.zeros(2)) for n in lasers])
    hits = intersect(scene, pose, xy)
    claimed = sigma_px if sigma_claimed is None else sigma_claimed
    spots = tuple(SpotHit(n, xy[i], claimed, hits[i], scene.plane_normal)
                  for i, n in enumerate(lasers))
    return ImageObservation(name, scene.camera, pose, pose_cov, spots)


def rodrigues_batch(rotvecs: F64) -> F64:
    """(N, 3) rotation vectors -> (N, 3, 3) matrices exp([w]ₓ)."""
    w = np.asarray(rotvecs, dtype=np.float64)
    th = np.linalg.norm(w, axis=1)
    k = w / np.where(th > 0, th, 1.0)[:, None]
    kx = np.zeros((len(w), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx -= np.transpose(kx, (0, 2, 1))
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3)[None] + s * kx + (1 - c) * kx @ kx


def sample_hits_cam(scene: Scene, rng: np.random.Generator, n: int, sigma_px: float,
                    pose_cov: F64 | None, lasers: tuple[str, ...] = ("L1", "L2", "L3", "L4"),
                    ) -> F64:
    """(n, L, 3) exact hits in the OBSERVED camera frame (model units) of n noisy observations.

    Pixels get N(0, σ²) noise, the pose the convention's left noise; each noisy ray is
    intersected with the true plane. PINHOLE unprojection written out (independent of pycolmap).
    """
    fx, fy, cx, cy = scene.camera.params
    px = true_pixels(scene)
    xy = np.array([px[name] for name in lasers])[None] + rng.normal(
        scale=sigma_px, size=(n, len(lasers), 2))
    rays = np.stack([(xy[..., 0] - cx) / fx, (xy[..., 1] - cy) / fy,
                     np.ones(xy.shape[:2])], axis=-1)
    d = (rng.multivariate_normal(np.zeros(6), pose_cov, size=n) if pose_cov is not None
         else np.zeros((n, 6)))
    R = rodrigues_batch(d[:, :3]) @ scene.pose.R
    t = scene.pose.t[None] + d[:, 3:]
    n_c = R @ scene.plane_normal  # (n, 3)
    p_c = R @ scene.plane_point + t
    lam = np.sum(n_c * p_c, axis=1)[:, None] / np.einsum("nj,nlj->nl", n_c, rays)
    return np.asarray(rays * lam[..., None], dtype=np.float64)


def perturbed_rig(rig: Rig, rng: np.random.Generator, sigma_origin: float,
                  sigma_direction: float) -> Rig:
    """A 'true' rig drawn from the nominal one's calibration σ (origin x/y, isotropic tilt)."""
    lasers = []
    for las in rig.lasers:
        if las.origin is None or las.direction is None:
            lasers.append(las)
            continue
        v = las.direction
        tilt = (np.eye(3) - np.outer(v, v)) @ rng.normal(scale=sigma_direction, size=3)
        origin = las.origin + np.r_[rng.normal(scale=sigma_origin, size=2), 0.0]
        lasers.append(replace(las, origin=origin, direction=(v + tilt) / np.linalg.norm(v + tilt)))
    return replace(rig, lasers=tuple(lasers))
