"""Small things in the picture: pale clutter, laser-coloured specks, marine snow, glints.

All shapes are drawn with exact-ish pixel coverage (3×3 samples per pixel) in COLMAP pixel
coordinates. Two kinds of drawing:

- *albedo patches* (:func:`paint_albedo_patches`): pale clutter (mineral speckle, shell hash,
  bacterial mat: albedo 0.45-0.85, 2-10 px) and laser-coloured specks (red or green
  organisms). They replace the seabed albedo, so they are lit by the lamps and seen through
  the water like everything on the floor (through green water pale patches read green-cyan
  and may clip the green channel);
- *additive light* (:func:`add_discs`): marine snow (particles in the water column near the
  camera, lit by the lamps, out of focus: uniform discs with a slightly brighter rim,
  3-40 px), particles lit by a laser beam, and specular glints. Their values are given in
  exposed raw units (1 = the sensor's white).

Placement helpers keep things away from the true spots or from the beams' image lines, or
put them near those lines, as the benchmark conditions ask.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
#: samples per pixel side for coverage
COVERAGE_SS = 3


@dataclass(frozen=True)
class Disc:
    """An elliptical patch or disc: centre (COLMAP px), semi-axes (px), angle (rad), RGB
    value (albedo or exposed raw light), and for light: rim brightening (0 = flat)."""

    x: float
    y: float
    a_px: float
    b_px: float
    angle: float
    rgb: tuple[float, float, float]
    rim: float = 0.0


def _coverage(disc: Disc, x0: int, y0: int, w: int, h: int) -> tuple[F64, F64]:
    """(coverage (h, w) in [0, 1], normalised radius² at the pixel centres) of a disc over the
    pixel block [x0, x0+w) × [y0, y0+h)."""
    s = COVERAGE_SS
    xs = x0 + (np.arange(w * s) + 0.5) / s - disc.x
    ys = y0 + (np.arange(h * s) + 0.5) / s - disc.y
    gx, gy = np.meshgrid(xs, ys)
    c, sn = math.cos(disc.angle), math.sin(disc.angle)
    u = (c * gx + sn * gy) / disc.a_px
    v = (-sn * gx + c * gy) / disc.b_px
    q = u * u + v * v
    inside = (q <= 1.0).astype(np.float64)
    cov = inside.reshape(h, s, w, s).mean(axis=(1, 3))
    q_pix = q.reshape(h, s, w, s).mean(axis=(1, 3))
    return cov, q_pix


def _window(disc: Disc, shape: tuple[int, ...]) -> tuple[int, int, int, int] | None:
    r = max(disc.a_px, disc.b_px) + 1.5
    x0, x1 = max(int(math.floor(disc.x - r)), 0), min(int(math.ceil(disc.x + r)), shape[1])
    y0, y1 = max(int(math.floor(disc.y - r)), 0), min(int(math.ceil(disc.y + r)), shape[0])
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1 - x0, y1 - y0


def paint_albedo_patches(albedo: F32, discs: list[Disc]) -> None:
    """In place: each patch replaces the albedo by its own, weighted by pixel coverage."""
    for d in discs:
        win = _window(d, albedo.shape)
        if win is None:
            continue
        x0, y0, w, h = win
        cov, _ = _coverage(d, x0, y0, w, h)
        patch = albedo[y0:y0 + h, x0:x0 + w]
        patch += (cov[..., None] * (np.asarray(d.rgb) - patch)).astype(np.float32)


def add_discs(light: F32, discs: list[Disc]) -> None:
    """In place: add each disc's light (flat, times 1 + rim·r² towards its edge)."""
    for d in discs:
        win = _window(d, light.shape)
        if win is None:
            continue
        x0, y0, w, h = win
        cov, q = _coverage(d, x0, y0, w, h)
        prof = cov * (1.0 + d.rim * np.clip(q, 0.0, 1.0))
        light[y0:y0 + h, x0:x0 + w] += (prof[..., None] * np.asarray(d.rgb)).astype(np.float32)


def distance_to_polylines(xy: F64, polylines: list[F64]) -> F64:
    """(N,) distance (px) from each point to the nearest segment of any polyline."""
    pts = np.atleast_2d(np.asarray(xy, np.float64))
    best = np.full(len(pts), np.inf)
    for line in polylines:
        a, b = line[:-1], line[1:]
        ab = b - a
        denom = np.maximum(np.sum(ab * ab, axis=1), 1e-12)
        t = np.clip(((pts[:, None, :] - a[None]) * ab[None]).sum(-1) / denom[None], 0.0, 1.0)
        proj = a[None] + t[..., None] * ab[None]
        best = np.minimum(best, np.linalg.norm(pts[:, None, :] - proj, axis=-1).min(axis=1))
    return best


def distance_to_points(xy: F64, points: list[tuple[float, float]]) -> F64:
    """(N,) distance (px) from each point to the nearest of ``points`` (inf if none)."""
    pts = np.atleast_2d(np.asarray(xy, np.float64))
    if not points:
        return np.full(len(pts), np.inf)
    ref = np.asarray(points, np.float64)
    return np.asarray(np.linalg.norm(pts[:, None, :] - ref[None], axis=-1).min(axis=1))


def random_positions(rng: np.random.Generator, n: int, width: int, height: int,
                     keep: Callable[[F64], NDArray[np.bool_]] | None = None,
                     tries: int = 20) -> F64:
    """(≤ n, 2) uniform image positions, rejecting those for which ``keep(xy) -> bool mask``
    is False (up to ``tries`` rounds)."""
    out: list[F64] = []
    need = n
    for _ in range(tries):
        xy = np.column_stack([rng.uniform(0, width, need * 2), rng.uniform(0, height, need * 2)])
        if keep is not None:
            xy = xy[keep(xy)]
        out.append(xy[:need])
        need -= len(out[-1])
        if need <= 0:
            break
    return np.concatenate(out) if out else np.zeros((0, 2))


def points_near_polylines(rng: np.random.Generator, n: int, polylines: list[F64],
                          max_offset_px: float) -> F64:
    """(n, 2) points along random polylines (uniform in arc length) offset sideways by up to
    ``max_offset_px``."""
    if not polylines or n <= 0:
        return np.zeros((0, 2))
    out = np.zeros((n, 2))
    for i in range(n):
        line = polylines[int(rng.integers(len(polylines)))]
        seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        at = rng.uniform(0.0, cum[-1])
        k = min(int(np.searchsorted(cum, at, side="right")) - 1, len(seg) - 1)
        frac = (at - cum[k]) / max(seg[k], 1e-9)
        p = line[k] + frac * (line[k + 1] - line[k])
        tangent = (line[k + 1] - line[k]) / max(seg[k], 1e-9)
        normal = np.array([-tangent[1], tangent[0]])
        out[i] = p + normal * rng.uniform(-max_offset_px, max_offset_px)
    return out


def pale_clutter(rng: np.random.Generator, xy: F64) -> list[Disc]:
    """Pale patches (albedo 0.45-0.85, slightly warm or cool white), diameter 2-10 px."""
    discs = []
    for x, y in xy:
        d = math.exp(rng.uniform(math.log(2.0), math.log(10.0)))
        ratio = rng.uniform(0.4, 1.0)
        level = rng.uniform(0.45, 0.85)
        tint = rng.uniform(-0.05, 0.05)
        rgb = (level * (1 + tint), level, level * (1 - tint) * rng.uniform(0.9, 1.0))
        discs.append(Disc(float(x), float(y), 0.5 * d, 0.5 * d * ratio,
                          rng.uniform(0, math.pi), (rgb[0], rgb[1], rgb[2])))
    return discs


def coloured_specks(rng: np.random.Generator, xy: F64, dominant: int) -> list[Disc]:
    """Organisms the colour of the laser (albedo 0.6-0.85 in its channel, 0.05-0.25 in the
    others), diameter 3-10 px."""
    discs = []
    for x, y in xy:
        d = rng.uniform(3.0, 10.0)
        rgb = [float(rng.uniform(0.05, 0.25)) for _ in range(3)]
        rgb[dominant] = float(rng.uniform(0.6, 0.85))
        discs.append(Disc(float(x), float(y), 0.5 * d, 0.5 * d * rng.uniform(0.5, 1.0),
                          rng.uniform(0, math.pi), (rgb[0], rgb[1], rgb[2])))
    return discs


def marine_snow(rng: np.random.Generator, xy: F64, colour_rgb: F64,
                peak_range: tuple[float, float] = (0.03, 0.6)) -> list[Disc]:
    """Out-of-focus lit particles: discs of diameter 3-40 px (log-uniform), peak brightness
    log-uniform in ``peak_range`` (exposed raw units) and dimmer for larger discs (the same
    scattered light spread over a larger blur disc), whitish ``colour_rgb`` (max 1)."""
    discs = []
    for x, y in xy:
        d = math.exp(rng.uniform(math.log(3.0), math.log(40.0)))
        peak = math.exp(rng.uniform(*np.log(peak_range))) * min(1.0, (8.0 / d) ** 0.7)
        rgb = np.asarray(colour_rgb) * peak
        rim = 0.0 if d < 8 else float(rng.uniform(0.0, 0.5))
        discs.append(Disc(float(x), float(y), 0.5 * d, 0.5 * d * rng.uniform(0.85, 1.0),
                          rng.uniform(0, math.pi), (float(rgb[0]), float(rgb[1]),
                                                    float(rgb[2])), rim))
    return discs


def glints(rng: np.random.Generator, xy: F64, colour_rgb: F64) -> list[Disc]:
    """Specular glints of the lamps on wet rock: small (2-8 px), very bright (0.8-4 x white,
    so they clip), in the lamps' colour."""
    discs = []
    for x, y in xy:
        d = rng.uniform(2.0, 8.0)
        peak = math.exp(rng.uniform(math.log(0.8), math.log(4.0)))
        rgb = np.asarray(colour_rgb) * peak
        discs.append(Disc(float(x), float(y), 0.5 * d, 0.5 * d * rng.uniform(0.4, 1.0),
                          rng.uniform(0, math.pi), (float(rgb[0]), float(rgb[1]),
                                                    float(rgb[2]))))
    return discs
