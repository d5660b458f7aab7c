"""The mismatch settings of ``simulate --mode mismatch``: data that carry errors the estimator is
not told about, made here independently of the estimators (docs/SIMULATE.md, "Mismatch").

Each setting switches on one effect of real data and says what the estimator is told:

- ``focal``: the SfM model's focal length off by ε. A nadir survey at one altitude cannot tell
  focal length from altitude: with a focal f (1 + ε) the model is the world with every depth
  below the survey's camera plane stretched by 1 + ε (exact for those cameras). The model's
  points and mesh are stretched so, the laser images are registered with f (1 + ε). ε is drawn
  per survey, N(0, σ²) (``focal_sigma``, the estimator is told that σ, as a bundle-adjustment
  covariance would tell it) or ±``focal_fixed`` (told ``focal_told``: σ cannot cover it);
- ``mesh``: the mesh off the surface: a smooth random field along the up axis (RMS
  ``mesh_noise_m``, correlation length ``mesh_length_m``) after ``mesh_smooth`` Laplacian
  smoothing passes over the relief (a systematic error at crests and troughs); the estimator
  sees only its mesh check against the model's points;
- ``spots``: spot noise ``spot_scale`` × the σ_l told (understated), ``elongated`` (the noise
  ``elongation`` × larger along a random axis per spot) or ``speckled`` (with probability
  ``speckle_rate`` an extra offset of ``speckle_scale`` σ_l);
- ``rig``: the rig's beams off their calibration by draws at its stated σ (origin per axis,
  direction per axis), common to the survey; told the σ.

The model's points carry their own noise (``point_sigma_m``, told to the mesh check as the
points' σ), as SfM points do.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from sfm_laserscale.rig import Laser, Rig

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Mismatch:
    """One mismatch setting: what the data carry and what the estimator is told."""

    name: str
    focal_sigma: float = 0.0  # ε ~ N(0, σ²), told σ
    focal_fixed: float = 0.0  # ε = ± this (random sign), told focal_told
    focal_told: float = 0.0
    mesh_noise_m: float = 0.0
    mesh_length_m: float = 0.1
    mesh_smooth: int = 0
    spot_scale: float = 1.0
    elongation: float = 1.0
    speckle_rate: float = 0.0
    speckle_scale: float = 3.0
    rig_sigma_origin_m: float = 0.0  # drawn AND told
    rig_sigma_direction_rad: float = 0.0
    covered: bool = True  # does the told σ claim to cover the effect?

    @property
    def told_focal_sigma(self) -> float:
        """σ(δf / f) the estimator is told."""
        return self.focal_sigma if self.focal_sigma > 0 else self.focal_told


#: The settings of the mismatch table (docs/SIMULATE.md).
SETTINGS: tuple[Mismatch, ...] = (
    Mismatch("none"),
    Mismatch("focal σ 0.05 %", focal_sigma=5e-4),
    Mismatch("focal σ 0.15 %", focal_sigma=1.5e-3),
    Mismatch("focal off 0.5 %, told 0.1 %", focal_fixed=5e-3, focal_told=1e-3, covered=False),
    Mismatch("mesh 2 mm, smoothed", mesh_noise_m=0.002, mesh_smooth=3),
    Mismatch("mesh 20 mm, smoothed", mesh_noise_m=0.02, mesh_smooth=3),
    Mismatch("σ_l understated 2×", spot_scale=2.0, covered=False),
    Mismatch("elongated spots (3:1)", elongation=3.0, covered=False),
    Mismatch("speckled spots", speckle_rate=0.3, speckle_scale=4.0, covered=False),
    Mismatch("rig error at its σ", rig_sigma_origin_m=5e-4, rig_sigma_direction_rad=3e-4),
)


def setting(name: str) -> Mismatch:
    """The setting of this name."""
    for s in SETTINGS:
        if s.name == name:
            return s
    raise KeyError(name)


# --------------------------------------------------------------------------- focal


def focal_error(m: Mismatch, rng: np.random.Generator) -> float:
    """This survey's ε."""
    if m.focal_sigma > 0:
        return float(m.focal_sigma * rng.standard_normal())
    if m.focal_fixed > 0:
        return float(m.focal_fixed * (1 if rng.random() < 0.5 else -1))
    return 0.0


def stretch(xyz: F64, up: F64, camera_height: float, eps: float) -> F64:
    """Depths below the plane (up · X = camera_height) stretched by 1 + ε (metres)."""
    depth = camera_height - xyz @ up
    return np.asarray(xyz - eps * depth[:, None] * up[None], dtype=np.float64)


# --------------------------------------------------------------------------- mesh


def _field(uv: F64, rms: float, length: float, rng: np.random.Generator, modes: int = 48) -> F64:
    """A smooth random field over plane coordinates uv (N, 2): random Fourier modes of
    wavelengths around 2π ``length``, scaled to RMS ``rms``."""
    k = rng.normal(scale=1.0 / length, size=(modes, 2))
    phase = rng.uniform(0, 2 * np.pi, modes)
    f = np.cos(uv @ k.T + phase).sum(axis=1)
    return np.asarray(f * rms / max(float(np.std(f)), 1e-12), dtype=np.float64)


def _laplacian_smooth(vertices: F64, triangles: NDArray[np.int64], passes: int) -> F64:
    """``passes`` uniform Laplacian smoothing passes (λ = 0.5) over the vertices."""
    n = len(vertices)
    i = np.concatenate([triangles[:, a] for a in (0, 1, 2, 1, 2, 0)])
    j = np.concatenate([triangles[:, b] for b in (1, 2, 0, 0, 1, 2)])
    adj = sparse.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    deg = np.asarray(adj.sum(axis=1)).ravel()
    v = vertices.copy()
    for _ in range(passes):
        mean = (adj @ v) / np.maximum(deg, 1)[:, None]
        v = v + 0.5 * (mean - v)
    return np.asarray(v, dtype=np.float64)


def mesh_with_error(vertices: F64, triangles: NDArray[np.int64], up: F64, basis: F64,
                    m: Mismatch, rng: np.random.Generator) -> F64:
    """The mesh an MVS would give (metres): smoothed relief plus a smooth field along up."""
    v = _laplacian_smooth(vertices, triangles, m.mesh_smooth) if m.mesh_smooth else vertices
    if m.mesh_noise_m > 0:
        v = v + _field(vertices @ basis.T, m.mesh_noise_m, m.mesh_length_m, rng)[:, None] * up
    return np.asarray(v, dtype=np.float64)


# --------------------------------------------------------------------------- spots, rig


def spot_offsets(m: Mismatch, sigma_px: float, n: int, rng: np.random.Generator) -> F64:
    """(n, 2) pixel errors of n spots."""
    e = rng.normal(scale=sigma_px * m.spot_scale, size=(n, 2))
    if m.elongation > 1:
        ang = rng.uniform(0, np.pi, n)
        axis = np.column_stack([np.cos(ang), np.sin(ang)])
        along = rng.normal(scale=sigma_px * (m.elongation - 1), size=n)
        e += along[:, None] * axis
    if m.speckle_rate > 0:
        hit = rng.random(n) < m.speckle_rate
        e[hit] += rng.normal(scale=sigma_px * m.speckle_scale, size=(int(hit.sum()), 2))
    return np.asarray(e, dtype=np.float64)


def _tilted(direction: F64, a: float, b: float) -> F64:
    """The unit direction turned by small angles a, b about two axes perpendicular to it."""
    d = np.asarray(direction, dtype=np.float64)
    ref = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(ref, d)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    v = d + a * e1 + b * e2
    return np.asarray(v / np.linalg.norm(v), dtype=np.float64)


def rigs(rig: Rig, m: Mismatch, rng: np.random.Generator) -> tuple[Rig, Rig]:
    """(the true rig of this survey, the rig the estimator is told)."""
    so, sd = m.rig_sigma_origin_m, m.rig_sigma_direction_rad
    told = Rig(rig.name, tuple(replace(la, sigma_origin=so, sigma_direction=sd)
                               for la in rig.lasers), rig.pairs)
    if so == 0 and sd == 0:
        return rig, told
    lasers: list[Laser] = []
    for la in rig.lasers:
        if la.origin is None or la.direction is None:
            lasers.append(la)
            continue
        o = np.asarray(la.origin, dtype=np.float64).copy()
        o[:2] += rng.normal(scale=so, size=2)
        d = _tilted(np.asarray(la.direction), *rng.normal(scale=sd, size=2))
        o = o - (o[2] / d[2]) * d  # back onto z = 0 along the beam
        lasers.append(replace(la, origin=o, direction=d))
    return Rig(rig.name, tuple(lasers), rig.pairs), told
