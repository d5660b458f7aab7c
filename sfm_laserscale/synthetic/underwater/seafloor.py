"""The lit seafloor as the camera sees it: per-pixel geometry, albedo, lamps, water.

Per pixel (COLMAP convention) the camera ray is intersected with the relief surface
(:mod:`.surface`) — exactly on a grid of one node per 8×8 pixels ("level 8", plus a ring of
nodes outside the image) and bilinearly in between (the perspective map is smooth: the
interpolation error is ~1e-3 px) — giving the surface coordinates (s, t) of the albedo
texture (:mod:`.texture`), the range, the normal and the pixel's footprint on the surface.

Radiance (raw camera channels, arbitrary units before exposure)::

    L = albedo · shade · (D_lamps + D_ambient) + V_lamps + V_ambient

- ``D_lamps = Σ_k I_k cone_k(α) max(N·l_k, 0) / d_k² · T(d_k + r) / π``: each lamp (position
  beside the camera, an axis, a Gaussian cone of angular sigma) lights the surface with
  inverse-square falloff and Lambert's cosine; the light is attenuated by the water on the
  whole path lamp → surface → camera, per channel with spectral hardening
  (:func:`.water.transmission_table`);
- ``D_ambient``: downwelling daylight (``WaterType.ambient_level``), attenuated on the way to
  the camera;
- ``V_lamps = Σ_k I_k β_π ∫_{l0}^{r} T(2l) / l² dl · cone_k(ray)``: single-scattering
  backscatter of the lamps' light between the camera and the surface (l0 = 1.0 m: lamps mounted
  away from the camera, no common volume of lamp beam and view closer than that; β at the
  lamps' scattering angles of 150-170° is taken as 0.7 β(π)); ``V_ambient = V∞ (1 - T(r))``;
- ``shade``: small-scale relief (bump map of the texture) lit from the lamps' side;
- natural vignetting cos³ of the off-axis angle.

A strobe *hot spot* is a narrow extra lamp aimed at a chosen surface point; its diffuse term is
returned separately so the caller sets its strength after exposure.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.synthetic.underwater import spectra, texture
from sfm_laserscale.synthetic.underwater import water as water_mod
from sfm_laserscale.synthetic.underwater.optics import CameraModel, unproject_px
from sfm_laserscale.synthetic.underwater.surface import Seafloor, intersect, surface_normals
from sfm_laserscale.synthetic.underwater.water import WaterType

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
#: pixel step of the exact geometry grid
GEOMETRY_STEP = 8
#: coarser grid for the coarsest texture layers
COARSE_STEP = 32
#: start of the lamp/view common volume (m) for backscatter
BACKSCATTER_START_M = 1.0
#: β at the lamps' scattering angles (150-170°) relative to β(180°)
BACKSCATTER_OBLIQUE = 0.7
#: farthest range considered (m): rays beyond are open water
MAX_RANGE_M = 80.0
#: rows per band of the full-resolution work (keeps the temporaries in cache)
BAND_ROWS = 96
#: an in-place painter of the full-resolution albedo (clutter)
AlbedoEdit = Callable[[F32], None]


@dataclass(frozen=True)
class Lamp:
    """A vehicle lamp: position and unit axis (camera frame, m), Gaussian cone sigma (rad),
    intensity (relative, per steradian on the axis)."""

    position_m: F64
    axis: F64
    sigma_rad: float
    intensity: float


@dataclass(frozen=True)
class SceneRender:
    """The seafloor radiance (full resolution, float32 (H, W, 3), raw channels, before
    exposure) and what the rest of the frame needs to know about the scene."""

    radiance: F32  # albedo · shade · (D_lamps + D_ambient) + veil
    hotspot: F32 | None  # albedo · shade · D_hot at unit hot-lamp intensity (None: no hot lamp)
    albedo: F32  # (H, W, 3), clutter included
    grid: Grid  # exact geometry on the step-8 ring grid (for per-pixel look-ups)
    linear_below_m: float  # texture layers finer than this are bilinear (see texture)


def ring_grid_px(cam: CameraModel, step: int) -> tuple[F64, F64]:
    """COLMAP coordinates of the nodes of a grid of one node per step×step pixel block,
    centred on the blocks, with one extra ring of nodes outside the image."""
    nx, ny = -(-cam.width // step), -(-cam.height // step)
    xs = step * (np.arange(nx + 2, dtype=np.float64) - 1.0) + 0.5 * step
    ys = step * (np.arange(ny + 2, dtype=np.float64) - 1.0) + 0.5 * step
    gx, gy = np.meshgrid(xs, ys)
    return gx, gy


def upsample_ring(arr: F32, step_src: int, step_dst: int, cam: CameraModel) -> F32:
    """Bilinear resampling of a ring grid of step ``step_src`` onto the ring grid of step
    ``step_dst`` (or onto the pixels themselves, without ring, when ``step_dst`` is 1)."""
    r = step_src // step_dst
    rows, cols = arr.shape[:2]
    big = cv2.resize(arr, (cols * r, rows * r), interpolation=cv2.INTER_LINEAR)
    j0 = r - 1
    if step_dst == 1:  # a view (row stride > width): OpenCV and numpy accept it as is
        return big[j0 + 1: j0 + 1 + cam.height, j0 + 1: j0 + 1 + cam.width]
    nx, ny = -(-cam.width // step_dst) + 2, -(-cam.height // step_dst) + 2
    return big[j0: j0 + ny, j0: j0 + nx]


def upsample_rows(arr: F32, step: int, cam: CameraModel, r0: int, r1: int) -> F32:
    """Rows [r0, r1) of the full-resolution bilinear upsampling of a ring grid of this step
    (same values as :func:`upsample_ring` to ``step_dst`` = 1, computed on a slab only)."""
    if step == 1:
        return arr[r0:r1]
    k0 = max(int(math.floor((r0 + 0.5) / step + 0.5)) - 1, 0)
    k1 = min(int(math.ceil((r1 - 0.5) / step + 0.5)) + 2, arr.shape[0])
    sub = arr[k0:k1]
    big = cv2.resize(sub, (sub.shape[1] * step, sub.shape[0] * step),
                     interpolation=cv2.INTER_LINEAR)
    j0 = r0 - step * (k0 - 1)
    return big[j0: j0 + (r1 - r0), step: step + cam.width]


def sample_grid(arr: F64 | F32, x_px: F64, y_px: F64, step: int = GEOMETRY_STEP) -> F64:
    """Bilinear look-up of a ring-grid array (any trailing channels) at COLMAP pixel coords."""
    k = np.asarray(x_px, np.float64) / step + 0.5
    m = np.asarray(y_px, np.float64) / step + 0.5
    k0 = np.clip(np.floor(k).astype(int), 0, arr.shape[1] - 2)
    m0 = np.clip(np.floor(m).astype(int), 0, arr.shape[0] - 2)
    fk, fm = k - k0, m - m0
    if arr.ndim == 3:
        fk, fm = fk[..., None], fm[..., None]
    a = np.asarray(arr, np.float64)
    return np.asarray((1 - fm) * ((1 - fk) * a[m0, k0] + fk * a[m0, k0 + 1])
                      + fm * ((1 - fk) * a[m0 + 1, k0] + fk * a[m0 + 1, k0 + 1]), np.float64)


@dataclass(frozen=True)
class Grid:
    """Exact geometry on a ring grid (see :func:`ring_grid_px`)."""

    points_m: F64  # (n, m, 3) surface points (camera frame)
    normals: F64  # (n, m, 3)
    rays: F64  # (n, m, 3) unit ray directions
    s: F32
    t: F32
    range_m: F32
    footprint_m: F32
    valid: NDArray[np.bool_]


def _grid_geometry(cam: CameraModel, sf: Seafloor, step: int) -> Grid:
    gx, gy = ring_grid_px(cam, step)
    rays = unproject_px(np.column_stack([gx.ravel(), gy.ravel()]), cam)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    lam, s, t, valid = intersect(sf, np.zeros(3), rays)
    lam = np.where(valid, np.minimum(lam, MAX_RANGE_M), MAX_RANGE_M)
    nrm = surface_normals(sf, s, t)
    cos_inc = np.clip(np.abs(np.sum(nrm * rays, axis=1)), 0.1, 1.0)
    fp = lam / (cam.focal_px * cos_inc)
    shape = gx.shape
    return Grid(points_m=(rays * lam[:, None]).reshape(*shape, 3),
                 normals=nrm.reshape(*shape, 3), rays=rays.reshape(*shape, 3),
                 s=s.reshape(shape).astype(np.float32), t=t.reshape(shape).astype(np.float32),
                 range_m=lam.reshape(shape).astype(np.float32),
                 footprint_m=fp.reshape(shape).astype(np.float32), valid=valid.reshape(shape))


def texture_levels(cam: CameraModel, base: Grid, coarse: Grid
                   ) -> dict[int, tuple[F32, F32, F32]]:
    """(s, t, footprint) on the texture's coarse ring grids: steps 2, 4 (upsampled from the
    exact step-8 grid), 8 and 32 (exact)."""
    levels: dict[int, tuple[F32, F32, F32]] = {
        GEOMETRY_STEP: (base.s, base.t, base.footprint_m),
        COARSE_STEP: (coarse.s, coarse.t, coarse.footprint_m),
    }
    for g in (2, 4):
        s, t, fp = (upsample_ring(a, GEOMETRY_STEP, g, cam)
                    for a in (base.s, base.t, base.footprint_m))
        levels[g] = (s, t, fp)
    return levels


def _cone(cos_angle: F64, sigma_rad: float) -> F64:
    ang = np.arccos(np.clip(cos_angle, -1.0, 1.0))
    return np.asarray(np.exp(-0.5 * (ang / sigma_rad) ** 2), np.float64)


def lamp_rgb() -> F64:
    """(3,) raw camera response to the lamps' light (white LED), G = 1."""
    rgb = spectra.integrate_rgb(spectra.white_led_spectrum())
    return np.asarray(rgb / rgb[1], np.float64)


def _lamp_diffuse(grid: Grid, lamps: tuple[Lamp, ...], table: tuple[F64, F64]) -> F64:
    """(n, m, 3) Σ lamps' irradiance x two-way transmission / π at the grid's surface points."""
    out = np.zeros((*grid.range_m.shape, 3))
    paths, trans = table
    colour = lamp_rgb()
    for lamp in lamps:
        vec = lamp.position_m - grid.points_m
        dist = np.linalg.norm(vec, axis=-1)
        unit = vec / dist[..., None]
        lambert = np.clip(np.sum(grid.normals * unit, axis=-1), 0.0, None)
        cone = _cone(-np.sum(unit * lamp.axis, axis=-1), lamp.sigma_rad)
        irr = lamp.intensity * cone * lambert / dist ** 2
        path = dist + grid.range_m
        for ch in range(3):
            out[..., ch] += colour[ch] * irr * np.interp(path, paths, trans[:, ch]) / math.pi
    return out * grid.valid[..., None]


def _backscatter_table(wat: WaterType, table: tuple[F64, F64]) -> tuple[F64, F64]:
    """(ranges (n,), K (n, 3)): K_ch(r) = ∫_{l0}^{r} T_ch(2l) / l² dl (1/m)."""
    paths, trans = table
    ranges = np.linspace(0.0, MAX_RANGE_M, 2048)
    l_mid = np.maximum(ranges, BACKSCATTER_START_M)
    integrand = np.stack([np.interp(2.0 * l_mid, paths, trans[:, ch]) for ch in range(3)], 1)
    integrand /= l_mid[:, None] ** 2
    integrand[ranges < BACKSCATTER_START_M] = 0.0
    dr = ranges[1] - ranges[0]
    cum = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (integrand[1:] + integrand[:-1]) * dr,
                                                      axis=0)])
    return ranges, cum


def lamp_backscatter_rgb(wat: WaterType) -> F64:
    """(3,) β(π) per channel (1/m/sr) for the lamp's spectrum."""
    lam = spectra.WAVELENGTHS_NM
    weights = spectra.sensitivities(lam) * spectra.white_led_spectrum()[:, None]
    beta = water_mod.BACKSCATTER_PHASE_PI * wat.backscattering_per_m(lam)
    return np.asarray((weights * beta[:, None]).sum(0) / weights.sum(0), np.float64)


def _veil(grid: Grid, lamps: tuple[Lamp, ...], wat: WaterType,
          table: tuple[F64, F64]) -> F64:
    """(n, m, 3) veiling light: lamp backscatter along each ray + ambient water colour."""
    ranges, k_tab = _backscatter_table(wat, table)
    beta = BACKSCATTER_OBLIQUE * lamp_backscatter_rgb(wat) * lamp_rgb()
    paths, trans = table
    out = np.zeros((*grid.range_m.shape, 3))
    amb = wat.ambient_level * water_mod.veiling_rgb_inf(wat) * AMBIENT_SCALE
    for lamp in lamps:
        cone = _cone(np.sum(grid.rays * lamp.axis, axis=-1), lamp.sigma_rad)
        for ch in range(3):
            out[..., ch] += lamp.intensity * beta[ch] * cone * np.interp(
                grid.range_m, ranges, k_tab[:, ch])
    for ch in range(3):
        out[..., ch] += amb[ch] * (1.0 - np.interp(grid.range_m, paths, trans[:, ch]))
    return out


#: irradiance of full ambient daylight (ambient_level = 1) relative to a lamp of unit
#: intensity at 1 m: sets the balance of daylight and lamps
AMBIENT_SCALE = 0.08


def _ambient_diffuse(grid: Grid, wat: WaterType, sf: Seafloor,
                     table: tuple[F64, F64]) -> F64:
    """(n, m, 3) downwelling daylight reflected towards the camera / π (before albedo)."""
    paths, trans = table
    down = wat.ambient_level * AMBIENT_SCALE * water_mod.downwelling_rgb(wat)
    facing = 0.6 + 0.4 * np.clip(np.sum(grid.normals * sf.normal, axis=-1), 0.0, 1.0)
    out = np.stack([down[ch] * facing * np.interp(grid.range_m, paths, trans[:, ch])
                    for ch in range(3)], -1) / math.pi
    return out * grid.valid[..., None]


def _shade(bump: F32, light_dir_px: tuple[float, float], strength: float) -> F32:
    """Bump shading: 1 + strength · (∇bump · light direction in the image), clipped (one
    3x3 filter: the light-direction combination of the Sobel kernels, /8)."""
    sob_x = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], np.float32) / 8.0
    kernel = strength * (light_dir_px[0] * sob_x + light_dir_px[1] * sob_x.T)
    shade = cv2.filter2D(bump, cv2.CV_32F, kernel.astype(np.float32), delta=1.0,
                         borderType=cv2.BORDER_REFLECT)
    return np.clip(shade, 0.35, 1.8, out=shade)


def _vignetting(cam: CameraModel, grid: Grid) -> F64:
    """cos³ of the angle between each ray and the optical axis (natural vignetting)."""
    return np.asarray(np.clip(grid.rays[..., 2], 0.0, 1.0) ** 3, np.float64)


def render_seafloor(cam: CameraModel, sf: Seafloor, look: texture.SeabedLook,
                    bank: texture.NoiseBank, lamps: tuple[Lamp, ...],
                    hot_lamps: tuple[Lamp, ...], wat: WaterType,
                    albedo_edit: AlbedoEdit | None = None) -> SceneRender:
    """The seafloor radiance for this camera (see the module docstring), computed in bands of
    ``BAND_ROWS`` rows. ``albedo_edit(albedo)`` may paint into the full-resolution albedo
    (clutter) in place before lighting."""
    base = _grid_geometry(cam, sf, GEOMETRY_STEP)
    coarse = _grid_geometry(cam, sf, COARSE_STEP)
    sampler = texture.LevelSampler(
        bank, texture_levels(cam, base, coarse), GEOMETRY_STEP,
        lambda a, g, r0, r1: upsample_rows(a, g, cam, r0, r1))
    h, w = cam.height, cam.width
    albedo = np.empty((h, w, 3), np.float32)
    bump = np.empty((h, w), np.float32)
    for r0 in range(0, h, BAND_ROWS):
        r1 = min(r0 + BAND_ROWS, h)
        albedo[r0:r1], bump[r0:r1] = texture.albedo_rgb(sampler.band(r0, r1), look)
    if albedo_edit is not None:
        albedo_edit(albedo)
    shade = _shade(bump, (0.25, -0.97), 4.0)
    del bump
    table = water_mod.transmission_table(wat)
    vig = _vignetting(cam, base)[..., None]
    diffuse = ((_lamp_diffuse(base, lamps, table) + _ambient_diffuse(base, wat, sf, table))
               * vig).astype(np.float32)
    veil = (_veil(base, lamps, wat, table) * vig).astype(np.float32)
    hot = (_lamp_diffuse(base, hot_lamps, table) * vig).astype(np.float32) if hot_lamps else None
    radiance = np.empty((h, w, 3), np.float32)
    hot_rad = np.empty((h, w, 3), np.float32) if hot is not None else None
    for r0 in range(0, h, BAND_ROWS):
        r1 = min(r0 + BAND_ROWS, h)
        lit = albedo[r0:r1] * shade[r0:r1, :, None]
        radiance[r0:r1] = lit * upsample_rows(diffuse, GEOMETRY_STEP, cam, r0, r1)
        radiance[r0:r1] += upsample_rows(veil, GEOMETRY_STEP, cam, r0, r1)
        if hot is not None and hot_rad is not None:
            hot_rad[r0:r1] = lit * upsample_rows(hot, GEOMETRY_STEP, cam, r0, r1)
    return SceneRender(radiance=radiance, hotspot=hot_rad, albedo=albedo, grid=base,
                       linear_below_m=sampler.linear_below_m)
