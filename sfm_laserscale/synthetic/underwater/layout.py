"""The geometry of one picture: seafloor, laser rig, beams and where their spots land.

Rig: an ROV-like 4-beam scaler, origins on the plane z = 0 at 0.10-0.25 m from the camera
centre (corners of a square, or a diamond, turned by up to ±10°, each origin jittered by up to
5 mm), beams 0.5-3° off the optical axis (random azimuth, per laser), 1/e² waist radius
1.0-2.5 mm and divergence half-angle 0.3-1.0 mrad. The rig given to the detector is the true
one plus a calibration error (origin: N(0, ``SIGMA_ORIGIN_M``) per axis in the plane z = 0;
direction: rotated by N(0, ``SIGMA_DIRECTION_RAD``) about two axes normal to it).

Spots are redrawn (camera distance, tilt, relief and rig together) until every switched-on
laser's spot lies in the image at least ``border_px`` from its edges (2-12 px exactly, for
border conditions), spots are at least ``MIN_SEPARATION_PX`` apart (scaled down for images
narrower than 1920 px), no spot is hidden from the camera by the relief, and every beam hits
the floor between 0.6 and 9.8 m along it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.synthetic.underwater import optics
from sfm_laserscale.synthetic.underwater.beams import Beam, Hit, hit_surface
from sfm_laserscale.synthetic.underwater.optics import CameraModel
from sfm_laserscale.synthetic.underwater.surface import (
    Seafloor,
    intersect,
    make_seafloor,
    point_m,
    random_relief,
)

F64 = NDArray[np.float64]
LASER_NAMES = ("L1", "L2", "L3", "L4")
MIN_SEPARATION_PX = 30.0
#: calibration error of the rig given to the detector
SIGMA_ORIGIN_M = 0.001
SIGMA_DIRECTION_RAD = math.radians(0.05)
MIN_HIT_RANGE_M, MAX_HIT_RANGE_M = 0.6, 9.8
MAX_TRIES = 400


@dataclass(frozen=True)
class GeometrySpec:
    """What a condition asks of the geometry."""

    distance_m: tuple[float, float] = (1.5, 6.0)
    tilt_deg: tuple[float, float] = (0.0, 40.0)
    off_axis_deg: tuple[float, float] = (0.5, 3.0)
    border_px: float = 10.0
    at_border: bool = False  # spots 2-12 px from the border (one per edge)
    lasers_off: tuple[int, int] = (0, 0)  # how many lasers are switched off (min, max)


@dataclass(frozen=True)
class Layout:
    """A sampled picture geometry."""

    seafloor: Seafloor
    tilt_deg: float
    beams: tuple[Beam, ...]
    on: dict[str, bool]
    hits: dict[str, Hit]  # every beam that hits the floor (on or off)


def _direction(theta: float, phi: float) -> F64:
    return np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi),
                     math.cos(theta)])


def _origins(rng: np.random.Generator) -> list[F64]:
    radius = rng.uniform(0.10, 0.25)
    start = (math.pi / 4 if rng.random() < 0.5 else 0.0) + math.radians(rng.uniform(-10, 10))
    out = []
    for k in range(4):
        ang = start + k * math.pi / 2
        jit = rng.uniform(-0.005, 0.005, 2)
        out.append(np.array([radius * math.cos(ang) + jit[0], radius * math.sin(ang) + jit[1],
                             0.0]))
    return out


def _beam(name: str, origin: F64, direction: F64, wavelength_nm: float,
          rng: np.random.Generator) -> Beam:
    return Beam(name=name, origin_m=origin, direction=direction / np.linalg.norm(direction),
                wavelength_nm=wavelength_nm, waist_m=float(rng.uniform(1.0e-3, 2.5e-3)),
                divergence_rad=float(rng.uniform(0.3e-3, 1.0e-3)))


def random_beams(rng: np.random.Generator, wavelength_nm: float,
                 off_axis_deg: tuple[float, float] = (0.5, 3.0)) -> tuple[Beam, ...]:
    """A rig of four beams as :func:`sample_layout` draws it (origins, directions off the
    optical axis by ``off_axis_deg`` at random azimuths, waists, divergences), without a
    seafloor: for a rig that stays the same over many pictures (a survey)."""
    origins = _origins(rng)
    dirs = [_direction(math.radians(rng.uniform(*off_axis_deg)), rng.uniform(-math.pi, math.pi))
            for _ in origins]
    return tuple(_beam(n, o, d, wavelength_nm, rng)
                 for n, o, d in zip(LASER_NAMES, origins, dirs, strict=True))


def _border_targets(rng: np.random.Generator, cam: CameraModel) -> list[F64]:
    """One pixel per edge (left, right, top, bottom), 2-12 px inside it, 20-80 % along it."""
    m = rng.uniform(2.0, 12.0, 4)
    u = rng.uniform(0.2, 0.8, 4)
    w, h = cam.width, cam.height
    return [np.array([m[0], u[0] * h]), np.array([w - m[1], u[1] * h]),
            np.array([u[2] * w, m[2]]), np.array([u[3] * w, h - m[3]])]


def _aimed(origin: F64, target_px: F64, sf: Seafloor, cam: CameraModel) -> F64 | None:
    """Direction from ``origin`` to the floor point seen at ``target_px``."""
    ray = optics.unproject_px(target_px[None, :], cam)
    _, s, t, ok = intersect(sf, np.zeros(3), ray / np.linalg.norm(ray))
    if not ok[0]:
        return None
    d = point_m(sf, s, t)[0] - origin
    return d / np.linalg.norm(d)


def _spots_ok(hits: dict[str, Hit], on: dict[str, bool], cam: CameraModel,
              spec: GeometrySpec) -> bool:
    xy = []
    for name, is_on in on.items():
        if not is_on:
            continue
        hit = hits.get(name)
        if (hit is None or hit.occluded
                or not MIN_HIT_RANGE_M <= hit.range_m <= MAX_HIT_RANGE_M):
            return False
        x, y = hit.truth_px
        margin = 2.0 if spec.at_border else spec.border_px
        if not (margin <= x <= cam.width - margin and margin <= y <= cam.height - margin):
            return False
        if spec.at_border and min(x, y, cam.width - x, cam.height - y) > 12.0:
            return False
        xy.append(hit.truth_px)
    pts = np.asarray(xy)
    if len(pts) > 1:
        dist = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(len(pts)) * 1e9
        if dist.min() < MIN_SEPARATION_PX * min(1.0, cam.width / 1920.0):
            return False
    return True


def sample_layout(rng: np.random.Generator, cam: CameraModel, spec: GeometrySpec,
                  wavelength_nm: float) -> Layout:
    """Draw seafloor and rig until the spots satisfy ``spec`` (see the module docstring)."""
    for _ in range(MAX_TRIES):
        tilt = float(rng.uniform(*spec.tilt_deg))
        azimuth = (-math.pi / 2 + rng.uniform(-1.0, 1.0) if rng.random() < 0.7
                   else rng.uniform(-math.pi, math.pi))
        sf = make_seafloor(float(rng.uniform(*spec.distance_m)), tilt, azimuth,
                           random_relief(rng, max_slope=0.2))
        origins = _origins(rng)
        if spec.at_border:
            dirs = [_aimed(o, p, sf, cam) for o, p in zip(origins, _border_targets(rng, cam),
                                                           strict=True)]
            if any(d is None for d in dirs):
                continue
        else:
            dirs = [_direction(math.radians(rng.uniform(*spec.off_axis_deg)),
                               rng.uniform(-math.pi, math.pi)) for _ in origins]
        beams = tuple(_beam(n, o, d, wavelength_nm, rng)  # type: ignore[arg-type]
                      for n, o, d in zip(LASER_NAMES, origins, dirs, strict=True))
        n_off = int(rng.integers(spec.lasers_off[0], spec.lasers_off[1] + 1))
        off = set(rng.choice(LASER_NAMES, size=n_off, replace=False).tolist())
        on = {n: n not in off for n in LASER_NAMES}
        hits = {b.name: h for b in beams if (h := hit_surface(b, sf, cam)) is not None}
        if _spots_ok(hits, on, cam, spec):
            return Layout(seafloor=sf, tilt_deg=tilt, beams=beams, on=on, hits=hits)
    raise RuntimeError(f"no layout satisfying {spec} in {MAX_TRIES} tries")


def _perturbed(beam: Beam, rng: np.random.Generator, error_scale: float = 1.0
               ) -> tuple[F64, F64]:
    """(origin, direction) with the calibration error of the rig file (its draws times
    ``error_scale``: 1 the calibration error of the module docstring, 0 the true beam)."""
    origin = beam.origin_m + error_scale * np.array([*rng.normal(0.0, SIGMA_ORIGIN_M, 2), 0.0])
    d = beam.direction
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    e = error_scale * rng.normal(0.0, SIGMA_DIRECTION_RAD, 2)
    d2 = d + e[0] * u + e[1] * v
    return origin, d2 / np.linalg.norm(d2)


def rig_toml(beams: tuple[Beam, ...], color: str, rng: np.random.Generator,
             name: str = "underwater benchmark rig", error_scale: float = 1.0) -> str:
    """The rig as given to the detector: true beams plus calibration error (scaled by
    ``error_scale``; the sigmas written are always the module's), in the rig-file TOML format
    (colour name per laser; the wavelength goes in the frame metadata)."""
    lines = [f'name = "{name}"']
    for beam in beams:
        origin, direction = _perturbed(beam, rng, error_scale)
        lines += ["", "[[laser]]", f'name = "{beam.name}"',
                  "origin = [" + ", ".join(repr(float(v)) for v in origin) + "]",
                  "direction = [" + ", ".join(repr(float(v)) for v in direction) + "]",
                  f'color = "{color}"', f"sigma_origin = {SIGMA_ORIGIN_M!r}",
                  f"sigma_direction = {SIGMA_DIRECTION_RAD!r}"]
    return "\n".join(lines) + "\n"
