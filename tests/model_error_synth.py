"""A synthetic nadir survey with known answers for the model-error tests.

Metric units (1 model unit = 1 m). A relief surface z = h(x, y), a 3 × 3 grid of nadir PINHOLE
cameras at altitude H, its points observed with Gaussian pixel noise: a SparseModel with
observations, as an SfM would give. For nadir cameras at one altitude a focal error ε is an
exact ambiguity: the same images come from the cameras at H and every point's depth below them
stretched by (1 + ε), z' = z − ε (H − z). A laser camera at the same altitude then sees its hit's
depth Z stretched too, and FCM's estimate of a beam of origin O and lateral direction v_lat moves
by γ = Z (v_lat · O) / |O|² per unit ε (docs/DESIGN.md §4): the known answers.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.model import Camera, Image, Pose, SparseModel
from sfm_laserscale.raycast import SpotHit
from sfm_laserscale.rig import Rig, rig_from_dict
from sfm_laserscale.uncertainty import ImageObservation

F64 = NDArray[np.float64]
H = 3.0  # camera altitude (m)
CAMERA = Camera(1, "PINHOLE", 800, 600, np.array([700.0, 700.0, 400.0, 300.0]))
NADIR = np.diag([1.0, -1.0, -1.0])  # camera x = world x, y = −world y, z (forward) = −world z


def height(xy: F64) -> F64:
    """Relief of the surface (m)."""
    x, y = xy[..., 0], xy[..., 1]
    return np.asarray(0.15 * np.sin(1.3 * x) * np.cos(0.9 * y) + 0.05 * x, dtype=np.float64)


def normal(xy: F64) -> F64:
    """Unit upward normal of the surface."""
    x, y = float(xy[0]), float(xy[1])
    gx = 0.15 * 1.3 * np.cos(1.3 * x) * np.cos(0.9 * y) + 0.05
    gy = -0.15 * 0.9 * np.sin(1.3 * x) * np.sin(0.9 * y)
    n = np.array([-gx, -gy, 1.0])
    return np.asarray(n / np.linalg.norm(n), dtype=np.float64)


def nadir_pose(cx: float, cy: float) -> Pose:
    """cam_from_world of a nadir camera at (cx, cy, H)."""
    c = np.array([cx, cy, H])
    return Pose(NADIR.copy(), -NADIR @ c)


def survey(seed: int = 0, noise_px: float = 0.3) -> SparseModel:
    """The survey's SparseModel: 9 nadir images, ~1500 points, noisy observations."""
    rng = np.random.default_rng(seed)
    g = np.linspace(-2.0, 2.0, 40)
    xy = np.array([(x, y) for x in g for y in g]) + rng.uniform(-0.04, 0.04, (len(g) ** 2, 2))
    pts = np.column_stack([xy, height(xy)])
    ids = np.arange(1, len(pts) + 1, dtype=np.uint64)
    images = {}
    for k, (cx, cy) in enumerate((x, y) for x in (-0.8, 0.0, 0.8) for y in (-0.8, 0.0, 0.8)):
        pose = nadir_pose(cx, cy)
        px = CAMERA.project(pose.transform(pts))
        inside = (px[:, 0] > 0) & (px[:, 0] < CAMERA.width) & (px[:, 1] > 0) & (
            px[:, 1] < CAMERA.height)
        obs = px[inside] + rng.normal(scale=noise_px, size=(int(inside.sum()), 2))
        images[k + 1] = Image(k + 1, f"ref_{k}.png", 1, pose, obs, ids[inside])
    return SparseModel({1: CAMERA}, images, ids, pts)


def beam_hit(origin_w: F64, direction_w: F64) -> F64:
    """First intersection of a downward beam with the surface (bisection on the height)."""
    lo, hi = 0.0, 2 * H
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        p = origin_w + mid * direction_w
        if p[2] > float(height(p[:2])):
            lo = mid
        else:
            hi = mid
    return np.asarray(origin_w + lo * direction_w, dtype=np.float64)


def diverging_rig(tilt_deg: float = 3.0) -> Rig:
    """One laser at O = (0.15, 0, 0) m, tilted tilt_deg outwards (towards +x)."""
    t = np.radians(tilt_deg)
    return rig_from_dict({"name": "diverging", "laser": [
        {"name": "L1", "origin": [0.15, 0.0, 0.0], "direction": [np.sin(t), 0.0, np.cos(t)]}]})


def laser_view(rig: Rig, cx: float = 0.1, cy: float = -0.2
               ) -> tuple[ImageObservation, F64, F64, float]:
    """A nadir laser image at the survey's altitude: its observation (exact spot), and the
    model points it sees as (pixels, xyz), and the hit's depth Z (m)."""
    pose = nadir_pose(cx, cy)
    las = rig.lasers[0]
    assert las.origin is not None and las.direction is not None
    world_from_cam = pose.inverse()
    o_w = world_from_cam.transform(np.asarray(las.origin)[None])[0]
    v_w = world_from_cam.R @ np.asarray(las.direction)
    hit = beam_hit(o_w, v_w)
    hit_cam = pose.transform(hit[None])[0]
    xy = CAMERA.project(hit_cam[None])[0]
    spot = SpotHit("L1", xy, 0.3, hit, normal(hit[:2]))
    obs = ImageObservation("laser", CAMERA, pose, None, (spot,))
    g = np.linspace(-1.2, 1.2, 25)
    pts_xy = np.array([(cx + x, cy + y) for x in g for y in g])
    pts = np.column_stack([pts_xy, height(pts_xy)])
    return obs, CAMERA.project(pose.transform(pts)), pts, float(hit_cam[2])


def analytic_gamma(rig: Rig, depth_m: float) -> float:
    """γ = Z (v_lat · O) / |O|² of the rig's one beam."""
    las = rig.lasers[0]
    assert las.origin is not None and las.direction is not None
    v = np.asarray(las.direction) / las.direction[2]
    o = np.asarray(las.origin)
    return float(depth_m * (v[:2] @ o[:2]) / (o[:2] @ o[:2]))
