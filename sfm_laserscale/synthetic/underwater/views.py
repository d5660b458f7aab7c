"""One fixed seafloor seen from explicit camera poses: the photographs of a survey.

:func:`.conditions.render_frame` draws a new seafloor, camera and rig for every picture. A
survey needs the opposite: one seafloor in a world frame, one camera, one laser rig, one set
of lamps and camera settings, and many poses. A :class:`SurveyScene` holds them;
:func:`render_view` renders what a pose sees with the physics of a frame, in the same order
(lit seafloor with its clutter, auto-exposure, the water's forward scatter, laser spots and
their glow, the camera: Bayer sensor, processing, JPEG).

World frame (metres): z up, the mean seafloor is the plane z = 0, and the floor point above
(x, y) is (x, y, h(x, y)) with the relief h of :mod:`.surface` in surface coordinates
(s, t) = (x, y). Poses are ``cam_from_world`` (:class:`CameraPose`): X_cam = R X_world + t,
camera frame x right, y down, z forward. For a view, the world seafloor is written in the
camera frame (normal R e_z, in-plane basis R e_x, R e_y, anchor t: the world origin), so the
relief, the texture (a function of (s, t)) and the clutter stay fixed on the floor whatever
the pose.

Pale clutter (shell hash, mineral speckle) is a list of patches fixed on the floor
(:class:`FloorPatch`); each view paints the patches it sees into the albedo as ellipses: the
images of the patch's two axes on the local tangent plane (the affine approximation of the
perspective over a few centimetres).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.synthetic.underwater import beams as beams_mod
from sfm_laserscale.synthetic.underwater import layout, particles, sensor, texture
from sfm_laserscale.synthetic.underwater.beams import Beam, Hit, hit_surface
from sfm_laserscale.synthetic.underwater.conditions import (
    Condition,
    scene_forward_scatter,
    spot_crops,
)
from sfm_laserscale.synthetic.underwater.optics import CameraModel, project_px, unproject_px
from sfm_laserscale.synthetic.underwater.seafloor import Lamp, render_seafloor
from sfm_laserscale.synthetic.underwater.surface import Seafloor, height_m, intersect
from sfm_laserscale.synthetic.underwater.water import WaterType

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]
#: a true spot this close (px) to the image border counts as not visible
SPOT_BORDER_PX = 10.0
#: patches whose image lies farther than this (px) outside the image are not drawn
PATCH_MARGIN_PX = 12.0


@dataclass(frozen=True)
class CameraPose:
    """``cam_from_world``: X_cam = R X_world + t (metres)."""

    R: F64
    t: F64

    @property
    def centre(self) -> F64:
        """Camera centre in the world, -Rᵀ t."""
        return np.asarray(-self.R.T @ self.t, np.float64)

    @property
    def axis(self) -> F64:
        """Optical axis (unit, world frame)."""
        return np.asarray(self.R[2], np.float64)


@dataclass(frozen=True)
class FloorPatch:
    """A flat patch of albedo lying on the floor: centre (x, y) in metres (on the relief),
    diameter of its long axis, short/long axis ratio, angle of the long axis from world x
    (radians) and its albedo (raw camera channels)."""

    x: float
    y: float
    diameter_m: float
    aspect: float
    angle: float
    rgb: tuple[float, float, float]


@dataclass(frozen=True)
class FloorClutter:
    """Patches on the floor and, per patch, five world points: its centre and the ends of
    its long and short axes (centre ± a u, centre ± b v on the local tangent plane)."""

    patches: tuple[FloorPatch, ...]
    points: F64  # (N, 5, 3)

    @staticmethod
    def empty() -> FloorClutter:
        """No clutter."""
        return FloorClutter((), np.zeros((0, 5, 3)))


@dataclass(frozen=True)
class SurveyScene:
    """Everything that stays the same over a survey (see the module docstring).

    ``spots`` is a :class:`.conditions.Condition` read only for the laser spots (peak over
    white, speckle contrast, beam glow). ``exposure_green``: the auto-exposure target (median
    output green, 0-1) of every view.
    """

    cam: CameraModel
    relief: F64  # (k, 4) rows of :mod:`.surface` in world (x, y)
    look: texture.SeabedLook
    bank: texture.NoiseBank
    water: WaterType
    lamps: tuple[Lamp, ...]
    settings: sensor.SensorSettings
    beams: tuple[Beam, ...]
    clutter: FloorClutter
    exposure_green: float
    spots: Condition


@dataclass(frozen=True)
class View:
    """One rendered photograph: the JPEG file's bytes, its decoded pixels, the true spot
    centres per laser (COLMAP pixels; None when not visible), each beam's hit on the floor
    (world metres, None when it misses) and metadata."""

    jpeg: bytes
    image_rgb: U8
    truth: dict[str, tuple[float, float] | None]
    hits_world: dict[str, F64 | None]
    meta: dict[str, Any]


# --------------------------------------------------------------------------- geometry


def world_seafloor(relief: F64) -> Seafloor:
    """The seafloor in the world frame: mean plane z = 0, normal +z, (s, t) = (x, y)."""
    return Seafloor(normal=np.array([0.0, 0.0, 1.0]), anchor_m=np.zeros(3),
                    e1=np.array([1.0, 0.0, 0.0]), e2=np.array([0.0, 1.0, 0.0]),
                    relief=np.asarray(relief, np.float64).reshape(-1, 4))


def seafloor_in_camera(relief: F64, pose: CameraPose) -> Seafloor:
    """The world seafloor written in the camera frame of ``pose`` (same surface coordinates)."""
    R = np.asarray(pose.R, np.float64)
    return Seafloor(normal=R[:, 2].copy(), anchor_m=np.asarray(pose.t, np.float64).copy(),
                    e1=R[:, 0].copy(), e2=R[:, 1].copy(),
                    relief=np.asarray(relief, np.float64).reshape(-1, 4))


def floor_points(relief: F64, x: F64, y: F64) -> F64:
    """(..., 3) world floor points above (x, y)."""
    h, _, _ = height_m(world_seafloor(relief), np.asarray(x, np.float64),
                       np.asarray(y, np.float64))
    return np.stack(np.broadcast_arrays(x, y, h), axis=-1).astype(np.float64)


def pixel_floor_points(relief: F64, cam: CameraModel, pose: CameraPose,
                       xy_px: F64) -> tuple[F64, NDArray[np.bool_]]:
    """(N, 3) world floor points seen at COLMAP pixels ``xy_px`` (N, 2), and which are valid."""
    rays = unproject_px(xy_px, cam)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    dirs = rays @ pose.R  # Rᵀ d per row
    lam, s, t, ok = intersect(world_seafloor(relief), pose.centre, dirs)
    return floor_points(relief, s, t), ok


def project_world(cam: CameraModel, pose: CameraPose, xyz: F64) -> tuple[F64, F64]:
    """(N, 2) COLMAP pixels of world points and their depth (N,) (NaN pixels behind)."""
    pts = np.atleast_2d(xyz) @ pose.R.T + pose.t
    depth = pts[:, 2]
    out = np.full((len(pts), 2), np.nan)
    front = depth > 0.05
    if front.any():
        out[front] = project_px(pts[front], cam)
    return out, depth


def hits_of(scene: SurveyScene, pose: CameraPose) -> dict[str, Hit]:
    """Each beam's hit on the floor in the camera frame of ``pose`` (beams that miss: absent)."""
    sf = seafloor_in_camera(scene.relief, pose)
    return {b.name: h for b in scene.beams if (h := hit_surface(b, sf, scene.cam)) is not None}


def visible_truth(hit: Hit | None, cam: CameraModel) -> tuple[float, float] | None:
    """The spot centre if it is in the image (``SPOT_BORDER_PX`` from its edges) and seen."""
    if hit is None or hit.occluded:
        return None
    x, y = float(hit.truth_px[0]), float(hit.truth_px[1])
    b = SPOT_BORDER_PX
    if not (b <= x <= cam.width - b and b <= y <= cam.height - b):
        return None
    return x, y


# --------------------------------------------------------------------------- clutter


def floor_clutter(relief: F64, patches: tuple[FloorPatch, ...]) -> FloorClutter:
    """The patches with their centres and axis ends on the floor (see :class:`FloorClutter`)."""
    if not patches:
        return FloorClutter.empty()
    x = np.array([p.x for p in patches])
    y = np.array([p.y for p in patches])
    centre = floor_points(relief, x, y)
    _, hs, ht = height_m(world_seafloor(relief), x, y)
    tx = np.column_stack([np.ones_like(x), np.zeros_like(x), hs])
    ty = np.column_stack([np.zeros_like(x), np.ones_like(x), ht])
    tx /= np.linalg.norm(tx, axis=1, keepdims=True)
    ty /= np.linalg.norm(ty, axis=1, keepdims=True)
    ang = np.array([p.angle for p in patches])[:, None]
    u = np.cos(ang) * tx + np.sin(ang) * ty
    v = -np.sin(ang) * tx + np.cos(ang) * ty
    a = np.array([0.5 * p.diameter_m for p in patches])[:, None]
    b = a * np.array([p.aspect for p in patches])[:, None]
    points = np.stack([centre, centre + a * u, centre - a * u, centre + b * v, centre - b * v],
                      axis=1)
    return FloorClutter(patches, np.asarray(points, np.float64))


def patch_discs(scene: SurveyScene, pose: CameraPose) -> list[particles.Disc]:
    """The floor patches that ``pose`` sees, as image ellipses (albedo patches): the images of
    each patch's two axes, turned into semi-axes and angle (SVD of the 2 x 2 axis matrix)."""
    clutter = scene.clutter
    if not clutter.patches:
        return []
    n = len(clutter.patches)
    px, _ = project_world(scene.cam, pose, clutter.points.reshape(-1, 3))
    px = px.reshape(n, 5, 2)
    m, cam = PATCH_MARGIN_PX, scene.cam
    with np.errstate(invalid="ignore"):
        ok = (np.isfinite(px).all(axis=(1, 2)) & (px[:, 0, 0] >= -m)
              & (px[:, 0, 0] <= cam.width + m) & (px[:, 0, 1] >= -m)
              & (px[:, 0, 1] <= cam.height + m))
    idx = np.nonzero(ok)[0]
    if not len(idx):
        return []
    axes = np.stack([(px[idx, 1] - px[idx, 2]) / 2.0, (px[idx, 3] - px[idx, 4]) / 2.0], axis=2)
    U, S, _ = np.linalg.svd(axes)
    angle = np.arctan2(U[:, 1, 0], U[:, 0, 0])
    return [particles.Disc(float(px[i, 0, 0]), float(px[i, 0, 1]), float(max(S[k, 0], 0.05)),
                           float(max(S[k, 1], 0.05)), float(angle[k]), clutter.patches[i].rgb)
            for k, i in enumerate(idx)]


def random_patches(rng: np.random.Generator, bounds: tuple[F64, F64], per_m2: float,
                   diameter_m: tuple[float, float],
                   keep_away: Sequence[tuple[F64, float]] = ()) -> tuple[FloorPatch, ...]:
    """Pale patches on the floor: ``per_m2`` over the (x, y) rectangle ``bounds`` (min, max),
    diameters log-uniform in ``diameter_m``, aspect 0.4-1, albedo 0.45-0.85 (slightly warm or
    cool white, as :func:`.particles.pale_clutter`). Patches closer than its radius plus
    ``clearance`` to a ``keep_away`` point ((x, y), clearance) are dropped."""
    lo, hi = np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64)
    n = int(round(per_m2 * float(np.prod(hi - lo))))
    xy = lo + rng.random((n, 2)) * (hi - lo)
    diam = np.exp(rng.uniform(math.log(diameter_m[0]), math.log(diameter_m[1]), n))
    aspect = rng.uniform(0.4, 1.0, n)
    angle = rng.uniform(0.0, math.pi, n)
    level = rng.uniform(0.45, 0.85, n)
    tint = rng.uniform(-0.05, 0.05, n)
    blue = rng.uniform(0.9, 1.0, n)
    out = []
    for i in range(n):
        if any(float(np.hypot(*(xy[i] - np.asarray(p)[:2]))) < 0.5 * diam[i] + clear
               for p, clear in keep_away):
            continue
        rgb = (float(level[i] * (1 + tint[i])), float(level[i]),
               float(level[i] * (1 - tint[i]) * blue[i]))
        out.append(FloorPatch(float(xy[i, 0]), float(xy[i, 1]), float(diam[i]),
                              float(aspect[i]), float(angle[i]), rgb))
    return tuple(out)


# --------------------------------------------------------------------------- rendering


def _tilt_deg(sf: Seafloor) -> float:
    """Angle between the optical axis and the floor's mean normal (degrees)."""
    return math.degrees(math.acos(min(1.0, abs(float(sf.normal[2])))))


def _truth(scene: SurveyScene, pose: CameraPose, hits: dict[str, Hit]
           ) -> tuple[dict[str, tuple[float, float] | None], dict[str, F64 | None]]:
    """True spot centres (None when not visible) and hit points (world) of every beam."""
    truth = {b.name: visible_truth(hits.get(b.name), scene.cam) for b in scene.beams}
    world: dict[str, F64 | None] = {}
    for b in scene.beams:
        hit = hits.get(b.name)
        world[b.name] = None if hit is None else np.asarray(pose.R.T @ (hit.point_m - pose.t))
    return truth, world


def render_view(scene: SurveyScene, pose: CameraPose, lasers_on: bool,
                rng: np.random.Generator) -> View:
    """The photograph ``pose`` takes of the scene (see the module docstring), lasers on or off.

    Every random draw of the frame (speckle, spot peaks, sensor noise) comes from ``rng``.
    """
    cam, wat = scene.cam, scene.water
    sf = seafloor_in_camera(scene.relief, pose)
    discs = patch_discs(scene, pose)
    lit = render_seafloor(cam, sf, scene.look, scene.bank, scene.lamps, (), wat,
                          lambda alb: particles.paint_albedo_patches(alb, discs))
    radiance = lit.radiance
    exposure = sensor.auto_exposure(radiance, scene.settings, scene.exposure_green)
    radiance *= np.float32(exposure)
    fs = scene_forward_scatter(radiance, wat, sf.distance_m, cam.focal_px)
    hits = hits_of(scene, pose) if lasers_on else {}
    crops: list[sensor.Crop] = []
    spot_meta: dict[str, dict[str, float]] = {}
    if lasers_on:
        lay = layout.Layout(seafloor=sf, tilt_deg=_tilt_deg(sf), beams=scene.beams,
                            on={b.name: True for b in scene.beams}, hits=hits)
        albedo_at = beams_mod.albedo_function(scene.bank, scene.look, lit.linear_below_m)
        crops, spot_meta = spot_crops(scene.spots, cam, lay, wat, albedo_at, scene.settings, rng)
    del lit
    rgb8 = sensor.capture(radiance, replace(scene.settings, jpeg=False), rng, crops)
    jpeg = sensor.encode_jpeg(rgb8, scene.settings.jpeg_quality, scene.settings.chroma_420)
    truth, hits_world = _truth(scene, pose, hits) if lasers_on else ({}, {})
    meta: dict[str, Any] = {
        "exposure": exposure, "distance_m": sf.distance_m, "tilt_deg": _tilt_deg(sf),
        "scene_forward_scatter_fraction": fs, "pale_patches_drawn": len(discs),
        "spots": spot_meta}
    return View(jpeg=jpeg, image_rgb=sensor.decode_jpeg(jpeg), truth=truth,
                hits_world=hits_world, meta=meta)
