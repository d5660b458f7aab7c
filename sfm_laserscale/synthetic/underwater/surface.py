"""The seafloor's shape: a tilted plane with smooth relief (a height field), in the camera frame.

A surface point is ``X = anchor + s·e1 + t·e2 + h(s, t)·n`` (metres, camera frame: x right,
y down, z forward) where ``n`` is the unit normal of the mean plane pointing towards the
camera, ``anchor`` a point of the mean plane (for single frames (0, 0, D), its point on the
optical axis; a seafloor fixed in a world frame and seen from several poses keeps its world
origin as anchor, :mod:`.views`), (e1, e2) an orthonormal basis of the plane and ``h`` a sum
of a few long-wavelength sinusoids (the relief). (s, t) are the
surface coordinates used by the albedo texture. Rays from the camera centre are intersected
with the height field by Newton's method on ``g(λ) = n·(λ r - anchor) - h(s(λ), t(λ))``,
started at the mean plane; the same code serves the whole-frame geometry and the laser beams
(which start at their own origin).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
#: most Newton iterations of ray/height-field intersection (the relief is smooth: 3-5 do)
NEWTON_ITERATIONS = 8


@dataclass(frozen=True)
class Seafloor:
    """Mean plane (unit normal towards the camera, anchor point, in-plane basis) + relief.

    ``relief`` rows are (amplitude m, wave number along e1 rad/m, along e2 rad/m, phase rad).
    """

    normal: F64
    anchor_m: F64
    e1: F64
    e2: F64
    relief: F64

    @property
    def distance_m(self) -> float:
        """Distance from the camera centre to the mean plane along the optical axis (m)."""
        if self.anchor_m[0] == 0.0 and self.anchor_m[1] == 0.0:  # anchor on the axis
            return float(self.anchor_m[2])
        return float(self.normal @ self.anchor_m / self.normal[2])


def height_m(sf: Seafloor, s_m: F64, t_m: F64) -> tuple[F64, F64, F64]:
    """Relief height (m, along the normal) and its partial derivatives dh/ds, dh/dt."""
    h = np.zeros_like(s_m)
    hs = np.zeros_like(s_m)
    ht = np.zeros_like(s_m)
    for amp, ks, kt, phase in sf.relief:
        arg = ks * s_m + kt * t_m + phase
        h += amp * np.sin(arg)
        cos = amp * np.cos(arg)
        hs += ks * cos
        ht += kt * cos
    return h, hs, ht


def surface_normals(sf: Seafloor, s_m: F64, t_m: F64) -> F64:
    """(..., 3) unit normals of the relief surface (towards the camera) at surface coords."""
    _, hs, ht = height_m(sf, s_m, t_m)
    nrm = (sf.normal[None, :] - hs.reshape(-1, 1) * sf.e1[None, :]
           - ht.reshape(-1, 1) * sf.e2[None, :])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return nrm.reshape(*np.shape(s_m), 3)


def intersect(sf: Seafloor, origins_m: F64, dirs: F64) -> tuple[F64, F64, F64, NDArray[np.bool_]]:
    """Intersect rays ``origin + λ·dir`` (λ > 0; (N, 3) or (3,) origins, (N, 3) dirs) with the
    surface. Returns (λ (N,), s (N,), t (N,), valid (N,)): invalid rays miss the mean plane
    (they look above the horizon) or do not converge."""
    dirs = np.atleast_2d(np.asarray(dirs, np.float64))
    org = np.broadcast_to(np.asarray(origins_m, np.float64), dirs.shape)
    rel = org - sf.anchor_m[None, :]
    n_r = dirs @ sf.normal
    n_o = rel @ sf.normal
    e1_r, e2_r = dirs @ sf.e1, dirs @ sf.e2
    e1_o, e2_o = rel @ sf.e1, rel @ sf.e2
    valid = n_r < -1e-3
    lam = np.where(valid, -n_o / np.where(valid, n_r, -1.0), 0.0)
    for _ in range(NEWTON_ITERATIONS):
        s, t = e1_o + lam * e1_r, e2_o + lam * e2_r
        h, hs, ht = height_m(sf, s, t)
        g = n_o + lam * n_r - h
        dg = n_r - hs * e1_r - ht * e2_r
        step = np.where(dg < -1e-6, g / np.where(dg < -1e-6, dg, -1.0), 0.0)
        lam = lam - np.clip(step, -5.0, 5.0)
        if float(np.max(np.abs(step), initial=0.0)) < 1e-10:
            break
    s, t = e1_o + lam * e1_r, e2_o + lam * e2_r
    h, _, _ = height_m(sf, s, t)
    residual = np.abs(n_o + lam * n_r - h)
    valid &= (lam > 0) & (residual < 1e-9 + 1e-7 * np.abs(lam))
    return lam, s, t, valid


def point_m(sf: Seafloor, s_m: F64, t_m: F64) -> F64:
    """(..., 3) camera-frame surface point at surface coordinates (s, t)."""
    h, _, _ = height_m(sf, s_m, t_m)
    s3, t3, h3 = (np.asarray(a)[..., None] for a in (s_m, t_m, h))
    return np.asarray(sf.anchor_m + s3 * sf.e1 + t3 * sf.e2 + h3 * sf.normal, np.float64)


def make_seafloor(distance_m: float, tilt_deg: float, azimuth_rad: float, relief: F64) -> Seafloor:
    """A seafloor whose mean plane crosses the optical axis at ``distance_m`` and whose normal
    is tilted by ``tilt_deg`` from the optical axis: the plane's depth grows along the image
    direction (cos azimuth, sin azimuth) (0: the right side is farther; -π/2: the top is
    farther, as for a forward-looking camera over a seabed)."""
    tilt = math.radians(tilt_deg)
    normal = np.array([math.sin(tilt) * math.cos(azimuth_rad),
                       math.sin(tilt) * math.sin(azimuth_rad), -math.cos(tilt)])
    helper = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, normal)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    return Seafloor(normal=normal, anchor_m=np.array([0.0, 0.0, float(distance_m)]),
                    e1=e1, e2=e2, relief=np.asarray(relief, np.float64).reshape(-1, 4))


def random_relief(rng: np.random.Generator, max_slope: float = 0.25, count: int = 4) -> F64:
    """(count, 4) smooth relief: wavelengths 1.5-8 m, random directions and phases, amplitudes
    scaled so the summed slope stays below ``max_slope`` (peak-to-peak up to ~0.5 m)."""
    wavelength = np.exp(rng.uniform(math.log(1.5), math.log(8.0), count))
    k = 2.0 * math.pi / wavelength
    ang = rng.uniform(0.0, 2.0 * math.pi, count)
    amp = rng.uniform(0.3, 1.0, count) * max_slope / count / k
    rows = np.column_stack([amp, k * np.cos(ang), k * np.sin(ang),
                            rng.uniform(0.0, 2.0 * math.pi, count)])
    return np.asarray(rows, np.float64)
