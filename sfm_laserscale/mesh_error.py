"""The mesh's depth error at each laser spot, from how well the mesh agrees with the model's own
3D points around the spot.

A mesh depth error δ along a spot's ray moves its hit by δ and the scale by δ / Z (relative).
The mesh is checked against the registered laser image's inlier model points nearest to the spot
in the image (``neighbours``, within ``max_radius`` of the image diagonal): each point's viewing
ray from the laser camera is cast into the mesh, and δ = (mesh range) − (point range) along it.
With m the median of the δ and ρ = 1.4826 MAD their robust spread (points beyond ``clip`` ρ of m
left out: occlusions, points of other surfaces), and σ_p the points' own σ along their rays (the
model's bundle-adjustment covariance, when known: their share of the spread is the points'
noise, not the mesh's), the spot's mesh σ is

    σ_mesh² = m² + max(min(ρ² − median(σ_p)², γ(d̄)), 0)

m is the mesh's local offset (smoothing, a systematic part at that place), ρ its local
roughness; both stay in σ at full size (one spot sees one place of the mesh, not an average).
The roughness is at most γ(d̄), the semivariogram (below, less the points' noise) at d̄, the
median distance of the spot's hit from its points: what they cannot tell about the spot's own
place. A rough mesh keeps ρ²; where the spread is a smooth trend across the points (a tilt, a
bump) the spot, amid its points, differs from their median by less than their spread.

The spots of one image are a few decimetres apart, and a mesh's error is smooth over such
distances (MVS smoothing, a misfit of the surface): their errors are correlated, so they must not
average down within the image. :func:`mesh_check` estimates the correlation of two spots at
distance d from the same points: the semivariogram γ(d) = ½ E[(δ_i − δ_j)²] of the point pairs
about as far apart (within ``pair_tolerance`` of d), less the points' own noise, against the
points' mean square S (less their noise): ρ(d) = 1 − γ(d) / S, clipped to [0, 1]; without
``min_pairs`` such pairs the nearest distances available are used, and with no pairs at all
ρ = ``default_correlation``. Between images (different places) the term is independent, so
fusion averages it over images — except for the part every place shares: a mesh offset from
its points over the whole survey (:func:`shared_offset`: g, the mean of every spot's local
offset m, with its standard error), a shared term like the rig's. The spots then keep the rest,
σ_local² = (m − g)² + (the roughness term above), and the shared term is √(g² + se²) along every
spot's ray (``model_error.mesh_offset_direction``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.raycast import MeshRaycaster, SpotHit

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class MeshErrorOptions:
    """Options of :func:`spot_mesh_sigma`."""

    enabled: bool = True
    neighbours: int = 30  # inlier points nearest to the spot in the image
    max_radius: float = 0.15  # ... within this fraction of the image diagonal
    min_points: int = 5  # fewer points with a mesh hit: no estimate (σ 0, reported)
    clip: float = 5.0  # points beyond this many robust spreads from the median: left out
    pair_tolerance: float = 0.25  # point pairs within this fraction of the spots' distance
    min_pairs: int = 20  # fewer such pairs: the nearest distances available
    default_correlation: float = 1.0  # no point pairs at all: fully correlated (conservative)


@dataclass(frozen=True)
class SpotMeshError:
    """One spot's mesh check: the σ it gives and its parts (model units)."""

    laser: str
    sigma: float  # σ_mesh (0 when not estimated)
    offset: float  # m, the median mesh − point range difference
    spread: float  # ρ, robust spread of the differences
    point_sigma: float  # median σ of the points along their rays
    n_points: int  # points used


def neighbours(spot_xy: F64, inlier_xy: F64, camera: Camera, options: MeshErrorOptions
               ) -> list[NDArray[np.intp]]:
    """Per spot, the indices of the inlier points nearest to it in the image."""
    radius = options.max_radius * float(np.hypot(camera.width, camera.height))
    out = []
    for xy in np.asarray(spot_xy, dtype=np.float64).reshape(-1, 2):
        dist = np.linalg.norm(inlier_xy - xy, axis=1)
        order = np.argsort(dist, kind="stable")[:options.neighbours]
        out.append(order[dist[order] <= radius].astype(np.intp))
    return out


def check_rays(pose: Pose, inlier_xyz: F64, idx: Sequence[NDArray[np.intp]]) -> tuple[F64, F64]:
    """Origins and unit directions (N, 3) of the rays camera -> every neighbour point."""
    rows = np.unique(np.concatenate([*idx, np.zeros(0, np.intp)]))
    centre = pose.center
    d = inlier_xyz[rows] - centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    return np.repeat(centre[None], len(rows), axis=0), d


def _one(laser: str, delta: F64, sigma_p: F64, options: MeshErrorOptions,
         gamma_spot: float = float("nan")) -> SpotMeshError:
    """The mesh σ of one spot from its points' range differences and their own σ, its local
    roughness at most ``gamma_spot`` (the semivariogram at the spot's distance from them)."""
    ok = np.isfinite(delta)
    delta, sigma_p = delta[ok], sigma_p[ok]
    if len(delta) < options.min_points:
        return SpotMeshError(laser, 0.0, float("nan"), float("nan"), float("nan"), len(delta))
    m = float(np.median(delta))
    rho = 1.4826 * float(np.median(np.abs(delta - m)))
    if rho > 0:
        keep = np.abs(delta - m) <= options.clip * rho
        delta, sigma_p = delta[keep], sigma_p[keep]
        m = float(np.median(delta))
        rho = 1.4826 * float(np.median(np.abs(delta - m)))
    sp = float(np.median(sigma_p))
    rough = rho * rho - sp * sp
    if np.isfinite(gamma_spot):  # what the neighbours cannot tell about the spot's own place
        rough = min(rough, gamma_spot)
    sigma = float(np.sqrt(m * m + max(rough, 0.0)))
    return SpotMeshError(laser, sigma, m, rho, sp, len(delta))


@dataclass(frozen=True)
class MeshCheck:
    """An image's mesh check: each spot's σ and the correlation of the spots' mesh errors."""

    spots: tuple[SpotMeshError, ...]
    correlation: F64  # (K, K)


@dataclass(frozen=True)
class _Pairs:
    """The point pairs of an image's mesh check (points of other surfaces left out, as for
    each spot): their δ differences and distances, and the points' noise and mean square."""

    diff2: F64  # (P,) (δ_i − δ_j)²
    dist: F64  # (P,) distance of the two points (model units)
    noise: float  # mean σ_p² of the points
    mean_square: float  # mean δ² of the points, less their noise (S)


def _pairs(xyz: F64, delta: F64, sigma_p: F64, options: MeshErrorOptions) -> _Pairs | None:
    """:class:`_Pairs` of the points with a δ (None with fewer than two)."""
    ok = np.isfinite(delta)
    if ok.sum() >= 2:
        med = float(np.median(delta[ok]))
        rho = 1.4826 * float(np.median(np.abs(delta[ok] - med)))
        ok &= ~(np.abs(delta - med) > options.clip * rho) if rho > 0 else ok
    xyz, delta, sigma_p = xyz[ok], delta[ok], sigma_p[ok]
    if len(delta) < 2:
        return None
    i, j = np.triu_indices(len(delta), 1)
    noise = float(np.mean(sigma_p**2))
    return _Pairs((delta[i] - delta[j]) ** 2, np.linalg.norm(xyz[i] - xyz[j], axis=1), noise,
                  float(np.mean(delta**2)) - noise)


def _semivariogram(pairs: _Pairs, d: float, options: MeshErrorOptions) -> float:
    """γ(d) of the mesh error less the points' noise, from the pairs about d apart (at least
    ``min_pairs``: else the nearest distances)."""
    off = np.abs(pairs.dist - d)
    near = np.flatnonzero(off <= options.pair_tolerance * d)
    if len(near) < options.min_pairs:
        near = np.argsort(off, kind="stable")[:options.min_pairs]
    return 0.5 * float(np.mean(pairs.diff2[near])) - pairs.noise


def _correlation(pairs: _Pairs | None, d: float, options: MeshErrorOptions) -> float:
    """ρ(d) = 1 − γ(d) / S of the mesh error (module docstring)."""
    if pairs is None or not pairs.mean_square > 0:
        return options.default_correlation
    return float(np.clip(1.0 - _semivariogram(pairs, d, options) / pairs.mean_square, 0.0, 1.0))


def _spot_gamma(hit_xyz: F64, own_xyz: F64, pairs: _Pairs | None,
                options: MeshErrorOptions) -> float:
    """γ(d̄) less the points' noise, d̄ the median distance of the spot's hit from its own
    points (``own_xyz``, those with a δ): how much the mesh error at the spot may differ from
    theirs (NaN if unknown)."""
    if pairs is None or len(own_xyz) == 0:
        return float("nan")
    d = float(np.median(np.linalg.norm(own_xyz - hit_xyz, axis=1)))
    return _semivariogram(pairs, d, options) if d > 0 else float("nan")


def mesh_check(caster: MeshRaycaster, camera: Camera, pose: Pose, hits: Sequence[SpotHit],
               inlier_xy: F64, inlier_xyz: F64, point_sigma: F64, options: MeshErrorOptions
               ) -> MeshCheck:
    """Each hit's mesh depth σ from the registered image's inlier points around its spot, and
    the correlation of the hits' mesh errors.

    ``point_sigma`` (N,): the inlier points' σ along their viewing rays (0 where unknown).
    """
    k = len(hits)
    if not options.enabled or len(inlier_xyz) == 0:
        return MeshCheck(tuple(SpotMeshError(h.laser, 0.0, float("nan"), float("nan"),
                                             float("nan"), 0) for h in hits), np.eye(k))
    xy = np.array([np.asarray(h.xy_px, np.float64).reshape(2) for h in hits]).reshape(-1, 2)
    idx = neighbours(xy, inlier_xy, camera, options)
    rows = np.unique(np.concatenate([*idx, np.zeros(0, np.intp)]))
    origins, dirs = check_rays(pose, inlier_xyz, idx)
    delta = np.full(len(inlier_xyz), np.nan)
    if len(rows):
        res = caster.cast(origins, dirs)
        rng = np.linalg.norm(inlier_xyz[rows] - pose.center, axis=1)
        delta[rows] = np.where(res.hit, res.distance - rng, np.nan)
    sig_p = np.asarray(point_sigma, np.float64)
    pairs = _pairs(inlier_xyz[rows], delta[rows], sig_p[rows], options)
    hit_xyz = np.array([np.asarray(h.hit_world, np.float64).reshape(3) for h in hits])
    spots = tuple(
        _one(h.laser, delta[i], sig_p[i], options,
             _spot_gamma(hit_xyz[a], inlier_xyz[i[np.isfinite(delta[i])]], pairs, options))
        for a, (h, i) in enumerate(zip(hits, idx, strict=True)))
    corr = np.eye(k)
    for a in range(k):
        for b in range(a + 1, k):
            d = float(np.linalg.norm(hit_xyz[a] - hit_xyz[b]))
            corr[a, b] = corr[b, a] = _correlation(pairs, d, options)
    return MeshCheck(spots, corr)


@dataclass(frozen=True)
class SharedOffset:
    """The mesh's offset from its points common to every spot of the run (model units)."""

    offset: float  # g, the mean of the spots' local offsets
    stderr: float  # its standard error
    n_spots: int

    @property
    def sigma(self) -> float:
        """σ of the shared term: √(g² + se²)."""
        return float(np.hypot(self.offset, self.stderr)) if self.n_spots else 0.0


def shared_offset(spots: Sequence[SpotMeshError]) -> SharedOffset:
    """g and its standard error from every spot's local offset (spots with an estimate)."""
    m = np.array([s.offset for s in spots if s.n_points > 0 and np.isfinite(s.offset)])
    if len(m) == 0:
        return SharedOffset(0.0, 0.0, 0)
    se = float(np.std(m, ddof=1) / np.sqrt(len(m))) if len(m) > 1 else float(abs(m[0]))
    return SharedOffset(float(np.mean(m)), se, len(m))


def local_sigma(spot: SpotMeshError, shared: SharedOffset | None) -> float:
    """The spot's mesh σ without the shared offset: √((m − g)² + max(ρ² − σ_p², 0))."""
    if shared is None or shared.n_spots == 0 or spot.n_points == 0:
        return spot.sigma
    rest = max(spot.sigma**2 - spot.offset**2, 0.0)
    return float(np.sqrt((spot.offset - shared.offset) ** 2 + rest))


def spot_mesh_sigma(caster: MeshRaycaster, camera: Camera, pose: Pose, hits: Sequence[SpotHit],
                    inlier_xy: F64, inlier_xyz: F64, point_sigma: F64,
                    options: MeshErrorOptions) -> tuple[SpotMeshError, ...]:
    """Each hit's mesh depth σ (:func:`mesh_check` without the correlation)."""
    return mesh_check(caster, camera, pose, hits, inlier_xy, inlier_xyz, point_sigma,
                      options).spots
