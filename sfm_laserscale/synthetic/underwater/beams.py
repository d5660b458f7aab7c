"""Laser spots from physics: Gaussian beams hitting the seafloor, seen through water.

Each beam has an origin and a unit direction in the camera frame (m), a wavelength, a waist
``w0`` (1/e² intensity radius at the exit window) and a far-field divergence half-angle
``θ``: at distance ``a`` along the beam its 1/e² radius is ``w(a) = sqrt(w0² + (θ a)²)`` and
its intensity ``I⊥(ρ) = 2P / (π w²) · exp(-2 ρ² / w²)`` at distance ρ from the axis.

The spot (:func:`render_spot`) is rendered in a crop around the truth, supersampled S×S per
pixel (S = 4, or 8 for spots with sigma < 1 px): every sample's camera ray is intersected with
the relief surface (:mod:`.surface`), the beam irradiance there is ``I⊥ · |N·d|`` (the local
tilted surface: the footprint is elliptical when oblique), attenuated by the water on the way
out (``exp(-c(λ) a)``), reflected with the surface albedo at that point (the texture under the
spot, Lambertian ``ρ / π``), multiplied by *speckle* and attenuated on the way back
(``exp(-c(λ) r)``); the optical PSF (Gaussian) is applied to the supersampled light and the
samples are then averaged per pixel (box integration over the pixel area): blurring before
pixel integration, as optics do, so that narrow spots do not carry the pixel-locking bias of
a sharp pixel-integrated footprint. The spot's light therefore bypasses the sensor's PSF.
The camera's RGB is the laser's raw response (:func:`.spectra.laser_rgb`) times that.

*Truth*: the projection (with the camera model of :mod:`.optics`) of the point where the beam's
axis meets the surface. The image centroid of the footprint differs from it only at second
order: the perspective map of a symmetric pattern on a plane tilted by τ shifts its centroid
by about ``tan τ · σ_px² / f_px`` and the lens distortion by ``~3 k1 r σ_px² / f_px``
(r: normalised radius), both < 0.005 px for spots with σ < 3 px at f > 1400 px; the range
dependence of ``w`` and of the attenuation across the footprint is smaller still. Each
spot's ``geometric_shift_px`` (centroid of the rendered footprint with uniform albedo and no
speckle, minus the truth) is measured and kept in the frame metadata.

*Speckle*: a fully developed speckle field (circular complex Gaussian noise low-passed by a
circular pupil whose cutoff gives grains of ``grain_px`` pixels; intensity exponentially
distributed) mixed with a uniform field to the chosen contrast C (std/mean, 0.1-0.4), drawn
per spot, applied to the core before pixel integration (which lowers the measured contrast).

*Forward-scatter halo*: light scattered by small angles on the two-way path (scattering
coefficient ``b_s = η b_p(λ)``) is not lost but spread around the spot: the halo holds
``exp(b_s L) - 1`` times the direct (core) energy, L = path out + path back. It is drawn as
two concentric Gaussians in the image (sigma ``σ_h = halo_sigma_rad · f`` with 60 % of the
energy, and 3 σ_h with 40 %), centred on the truth, pixel-integrated exactly (erf).

*Beam glow*: the water scatters the beam's light back towards the camera all along its path,
drawn as a line along the beam's image: a camera ray crossing the beam at angle α sees, per
unit of image length across the line, ``∫ L dn = β(π) T_out T_back P f / d⊥`` (d⊥: distance
from the camera centre to the beam's axis), a thin line with the beam's projected width.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.special import erf

from sfm_laserscale.synthetic.underwater import optics, spectra, texture
from sfm_laserscale.synthetic.underwater import water as water_mod
from sfm_laserscale.synthetic.underwater.optics import CameraModel
from sfm_laserscale.synthetic.underwater.surface import (
    Seafloor,
    intersect,
    point_m,
    surface_normals,
)

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
#: share of the halo energy in the inner Gaussian (the outer one is 3x wider)
HALO_INNER_SHARE = 0.6
HALO_OUTER_FACTOR = 3.0
#: ``albedo_at(s_m, t_m, footprint_m) -> (..., 3)`` seabed albedo at surface points
AlbedoFn = Callable[[F32, F32, F32], F32]


@dataclass(frozen=True)
class Beam:
    """One laser beam (camera frame, metres)."""

    name: str
    origin_m: F64
    direction: F64  # unit, z > 0
    wavelength_nm: float
    waist_m: float  # 1/e² intensity radius at the exit
    divergence_rad: float  # far-field half-angle of the 1/e² radius

    def radius_m(self, distance_m: float | F64) -> F64:
        """1/e² intensity radius of the beam (m) at this distance along it."""
        return np.sqrt(self.waist_m ** 2 + (self.divergence_rad * np.asarray(distance_m)) ** 2)


@dataclass(frozen=True)
class Hit:
    """Where a beam's axis meets the seafloor."""

    range_m: float  # along the beam, from its origin
    point_m: F64  # camera frame
    normal: F64  # unit surface normal (towards the camera)
    truth_px: F64  # (2,) COLMAP pixels
    incidence_deg: float  # between the beam and the surface normal
    camera_distance_m: float
    occluded: bool = False  # the camera's ray to the point meets the relief elsewhere first


def hit_surface(beam: Beam, sf: Seafloor, cam: CameraModel) -> Hit | None:
    """Intersect the beam's axis with the relief surface (Newton on the height field);
    None when it misses (points above the horizon)."""
    lam, s, t, valid = intersect(sf, beam.origin_m, beam.direction[None, :])
    if not valid[0]:
        return None
    p = point_m(sf, s, t)[0]
    nrm = surface_normals(sf, s, t)[0]
    if p[2] <= 0.05:
        return None
    cos_inc = abs(float(nrm @ beam.direction))
    dist = float(np.linalg.norm(p))
    lam_cam, _, _, ok = intersect(sf, np.zeros(3), (p / dist)[None, :])
    return Hit(range_m=float(lam[0]), point_m=p, normal=nrm,
               truth_px=optics.project_px(p[None, :], cam)[0],
               incidence_deg=math.degrees(math.acos(min(cos_inc, 1.0))),
               camera_distance_m=dist,
               occluded=not ok[0] or abs(float(lam_cam[0]) - dist) > 1e-4)


def beam_polyline_px(beam: Beam, cam: CameraModel, a_min_m: float, a_max_m: float,
                     samples: int = 48) -> F64:
    """(n, 2) image of the beam between these distances along it (geometric spacing),
    points with z <= 0.05 m dropped."""
    a = np.geomspace(a_min_m, a_max_m, samples)
    pts = beam.origin_m[None, :] + a[:, None] * beam.direction[None, :]
    pts = pts[pts[:, 2] > 0.05]
    return optics.project_px(pts, cam) if len(pts) else np.zeros((0, 2))


@dataclass(frozen=True)
class SpotRender:
    """A rendered spot: light (raw units, before exposure scaling: multiply by ``scale``)
    in a crop whose top-left pixel is (x0, y0), and measurements of it."""

    x0: int
    y0: int
    light: F32  # (h, w, 3) core + halo, unit laser power
    scale: float  # factor that makes the peak (after the optical PSF) = peak_over_white
    meta: dict[str, float] = field(default_factory=dict)


def _speckle(rng: np.random.Generator, shape: tuple[int, int], grain_samples: float,
             contrast: float) -> F64:
    """Multiplicative speckle (mean 1, std ``contrast`` before pixel integration)."""
    noise = rng.standard_normal(shape) + 1j * rng.standard_normal(shape)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.fftfreq(shape[1])[None, :]
    pupil = (fx * fx + fy * fy) <= (0.5 / grain_samples) ** 2
    field_c = np.fft.ifft2(np.fft.fft2(noise) * pupil)
    inten = np.abs(field_c) ** 2
    inten /= inten.mean()
    return np.asarray(1.0 + contrast * (inten - 1.0), np.float64)


def _pixel_gauss_1d(coords: F64, centre: float, sigma: float) -> F64:
    """Integral over each unit pixel [c-0.5, c+0.5) of a unit 1-D Gaussian (erf)."""
    lo = (coords - 0.5 - centre) / (math.sqrt(2.0) * sigma)
    hi = (coords + 0.5 - centre) / (math.sqrt(2.0) * sigma)
    return np.asarray(0.5 * (erf(hi) - erf(lo)), np.float64)


def halo_image(x0: int, y0: int, w: int, h: int, centre: F64, sigma_px: float) -> F64:
    """(h, w) pixel-integrated two-Gaussian halo kernel of unit energy centred at ``centre``."""
    xs = x0 + np.arange(w, dtype=np.float64) + 0.5
    ys = y0 + np.arange(h, dtype=np.float64) + 0.5
    out = np.zeros((h, w))
    for share, sig in ((HALO_INNER_SHARE, sigma_px),
                       (1.0 - HALO_INNER_SHARE, HALO_OUTER_FACTOR * sigma_px)):
        out += share * np.outer(_pixel_gauss_1d(ys, centre[1], sig),
                                _pixel_gauss_1d(xs, centre[0], sig))
    return out


def _centroid(img: F64, x0: int, y0: int) -> tuple[F64, F64]:
    """(centroid (2,), covariance (2, 2)) of an image block in COLMAP coordinates."""
    h, w = img.shape
    gx, gy = np.meshgrid(x0 + np.arange(w) + 0.5, y0 + np.arange(h) + 0.5)
    return _weighted_moments(img, gx, gy)


@dataclass(frozen=True)
class SpotOptions:
    """How one spot is rendered (see the module docstring)."""

    peak_over_white: float = 5.0
    speckle_contrast: float = 0.25
    speckle_grain_px: float = 1.5
    halo: bool = True
    psf_sigma_px: float = 0.6
    supersample: int | None = None  # None: 4, or 8 for spots with sigma < 1 px


def footprint_sigma_px(beam: Beam, hit: Hit, cam: CameraModel) -> float:
    """Approximate major-axis sigma (px) of the footprint's image (w/2 stretched by 1/cos)."""
    w = float(beam.radius_m(hit.range_m))
    cos_inc = max(math.cos(math.radians(hit.incidence_deg)), 0.2)
    return 0.5 * w / cos_inc * cam.focal_px / hit.camera_distance_m


def render_spot(beam: Beam, hit: Hit, cam: CameraModel, sf: Seafloor,
                albedo_at: AlbedoFn, wat: water_mod.WaterType, opts: SpotOptions,
                rng: np.random.Generator) -> SpotRender:
    """Render one spot's light (see the module docstring); ``albedo_at(s, t, footprint_m)``
    gives the seabed albedo (..., 3) at surface points."""
    sig_px = footprint_sigma_px(beam, hit, cam)
    ss = opts.supersample or (8 if sig_px < 1.0 else 4)
    r_core = int(math.ceil(4.5 * sig_px + 3.0 * opts.psf_sigma_px + 3.0))
    tx, ty = hit.truth_px
    x0, y0 = int(math.floor(tx)) - r_core, int(math.floor(ty)) - r_core
    n = 2 * r_core + 1
    gx, gy = optics.pixel_centres_px(x0, y0, n, n, ss)
    rays = optics.unproject_px(np.column_stack([gx.ravel(), gy.ravel()]), cam)
    lam, s, t, valid = intersect(sf, np.zeros(3), rays)
    pts = rays * lam[:, None]
    rel = pts - beam.origin_m[None, :]
    along = rel @ beam.direction
    rho2 = np.maximum(np.sum(rel * rel, axis=1) - along ** 2, 0.0)
    w2 = beam.radius_m(along) ** 2
    nrm = surface_normals(sf, s, t)
    cos_inc = np.abs(nrm @ beam.direction)
    c_l = float(wat.attenuation_per_m(beam.wavelength_nm)[0])
    geo = (2.0 / (math.pi * w2) * np.exp(-2.0 * rho2 / w2) * cos_inc
           * np.exp(-c_l * (along + np.linalg.norm(pts, axis=1))) / math.pi)
    geo = np.where(valid, geo, 0.0).reshape(gx.shape)
    view = hit.point_m / hit.camera_distance_m
    cos_view = max(abs(float(hit.normal @ view)), 0.1)
    fp = np.full(gx.shape, hit.camera_distance_m / (cam.focal_px * cos_view), np.float32)
    dom = spectra.dominant_channel(beam.wavelength_nm)
    alb = albedo_at(s.reshape(gx.shape).astype(np.float32),
                    t.reshape(gx.shape).astype(np.float32), fp)[..., dom]
    speck = _speckle(rng, gx.shape, opts.speckle_grain_px * ss, opts.speckle_contrast)

    def to_pixels(sub: F64) -> F64:
        """Optical PSF on the supersampled light, then integration over each pixel."""
        if opts.psf_sigma_px > 0.0:
            sub = cv2.GaussianBlur(sub, (0, 0), opts.psf_sigma_px * ss,
                                   borderType=cv2.BORDER_CONSTANT)
        return optics.bin_supersamples(sub, ss)

    lit = geo * alb.astype(np.float64)
    core = to_pixels(lit * speck)
    core_mean_albedo = to_pixels(lit)
    g_c, g_cov = _weighted_moments(geo, gx, gy)
    p_c, _ = _centroid(to_pixels(geo), x0, y0)
    o_c, _ = _centroid(core, x0, y0)
    sp_pix = optics.bin_supersamples(speck, ss)
    inside = optics.bin_supersamples(geo, ss) > 0.3 * optics.bin_supersamples(geo, ss).max()
    eig = np.linalg.eigvalsh(g_cov)
    meta = {"geometric_shift_px": float(np.hypot(*(g_c - hit.truth_px))),
            "geometric_shift_x_px": float(g_c[0] - tx), "geometric_shift_y_px": float(g_c[1] - ty),
            "pixel_centroid_shift_px": float(np.hypot(*(p_c - hit.truth_px))),
            "oracle_shift_px": float(np.hypot(*(o_c - hit.truth_px))),
            "sigma_major_px": float(math.sqrt(eig[1])),
            "sigma_minor_px": float(math.sqrt(max(eig[0], 0.0))),
            "speckle_contrast_pixel": float(np.std(sp_pix[inside]) / np.mean(sp_pix[inside])),
            "supersample": float(ss)}
    light, hx0, hy0, meta_h = _with_halo(core, core_mean_albedo, x0, y0, beam, hit, cam, wat,
                                         opts)
    meta.update(meta_h)
    rgb = np.asarray(spectra.laser_rgb(beam.wavelength_nm), np.float64)
    light_rgb = (light[..., None] * rgb[None, None, :]).astype(np.float32)
    scale = opts.peak_over_white / float(light_rgb[..., dom].max())
    meta["peak_over_white"] = opts.peak_over_white
    return SpotRender(x0=hx0, y0=hy0, light=light_rgb, scale=scale, meta=meta)


def _weighted_moments(weights: F64, gx: F64, gy: F64) -> tuple[F64, F64]:
    """(centroid (2,), covariance (2, 2)) of point weights at coordinates (gx, gy)."""
    tot = float(weights.sum())
    cx, cy = float((weights * gx).sum() / tot), float((weights * gy).sum() / tot)
    dx, dy = gx - cx, gy - cy
    cov = np.array([[(weights * dx * dx).sum(), (weights * dx * dy).sum()],
                    [(weights * dx * dy).sum(), (weights * dy * dy).sum()]]) / tot
    return np.array([cx, cy]), cov


def _with_halo(core: F64, core_mean: F64, x0: int, y0: int, beam: Beam, hit: Hit,
               cam: CameraModel, wat: water_mod.WaterType, opts: SpotOptions
               ) -> tuple[F64, int, int, dict[str, float]]:
    """Core plus forward-scatter halo (its kernel widened by the PSF) on a crop large enough
    for the halo."""
    path = hit.range_m + hit.camera_distance_m
    b_s = float(wat.small_angle_scattering_per_m(beam.wavelength_nm)[0])
    ratio = math.expm1(b_s * path) if opts.halo else 0.0
    sigma_h = math.hypot(wat.halo_sigma_rad * cam.focal_px, opts.psf_sigma_px)
    meta = {"halo_energy_ratio": ratio, "halo_sigma_px": sigma_h}
    if ratio <= 0.0:
        return core, x0, y0, meta
    r_h = int(math.ceil(3.5 * HALO_OUTER_FACTOR * sigma_h))
    tx, ty = hit.truth_px
    hx0, hy0 = min(int(math.floor(tx)) - r_h, x0), min(int(math.floor(ty)) - r_h, y0)
    size = max(2 * r_h + 1, x0 + core.shape[1] - hx0, y0 + core.shape[0] - hy0)
    out = ratio * float(core_mean.sum()) * halo_image(hx0, hy0, size, size, hit.truth_px,
                                                      sigma_h)
    out[y0 - hy0: y0 - hy0 + core.shape[0], x0 - hx0: x0 - hx0 + core.shape[1]] += core
    meta["halo_peak_over_core_peak"] = ratio * float(core_mean.sum()) * (
        HALO_INNER_SHARE / (2 * math.pi * sigma_h ** 2)) / max(float(core.max()), 1e-30)
    return out, hx0, hy0, meta


def glow_line(beam: Beam, hit: Hit, cam: CameraModel, wat: water_mod.WaterType,
              psf_sigma_px: float = 0.0, a_min_m: float = 0.05) -> tuple[int, int, F32] | None:
    """(x0, y0, light (h, w, 3)) of the beam's in-water glow for unit laser power, in the same
    radiance units as :func:`render_spot`'s light (see the module docstring), the optical PSF
    included; None when the visible part of the line is empty."""
    lam_nm = beam.wavelength_nm
    beta = water_mod.BACKSCATTER_PHASE_PI * float(wat.backscattering_per_m(lam_nm)[0])
    c_l = float(wat.attenuation_per_m(lam_nm)[0])
    d_perp = float(np.linalg.norm(np.cross(beam.origin_m, beam.direction)))
    a = np.geomspace(a_min_m, hit.range_m, 4000)
    pts = beam.origin_m[None, :] + a[:, None] * beam.direction[None, :]
    keep = pts[:, 2] > 0.05
    a, pts = a[keep], pts[keep]
    xy = optics.project_px(pts, cam)
    inside = ((xy[:, 0] > -5) & (xy[:, 0] < cam.width + 5) & (xy[:, 1] > -5)
              & (xy[:, 1] < cam.height + 5))
    if inside.sum() < 2 or d_perp < 1e-3:
        return None
    a, pts, xy = a[inside], pts[inside], xy[inside]
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    dist = np.linalg.norm(pts, axis=1)
    dens = beta * np.exp(-c_l * (a + dist)) * cam.focal_px / d_perp
    weights = 0.5 * (dens[1:] + dens[:-1]) * seg
    mid = 0.5 * (xy[1:] + xy[:-1])
    # the line's sigma: half the beam's projected 1/e² radius (wide near the camera)
    sigma = np.hypot(np.maximum(0.5 * beam.radius_m(a) * cam.focal_px / dist, 0.35),
                     psf_sigma_px)
    sigma = 0.5 * (sigma[1:] + sigma[:-1])
    pad = int(math.ceil(4 * sigma.max() + 2))
    x0 = max(int(math.floor(mid[:, 0].min())) - pad, 0)
    y0 = max(int(math.floor(mid[:, 1].min())) - pad, 0)
    x1 = min(int(math.ceil(mid[:, 0].max())) + pad, cam.width)
    y1 = min(int(math.ceil(mid[:, 1].max())) + pad, cam.height)
    if x1 <= x0 or y1 <= y0:
        return None
    img = np.zeros((y1 - y0, x1 - x0), np.float32)
    edges = np.geomspace(sigma.min(), sigma.max() * 1.0001 + 1e-9, 6)
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (sigma >= lo) & (sigma < hi) if hi < edges[-1] else (sigma >= lo)
        if not sel.any():
            continue
        part = _splat(mid[sel] - [x0, y0], weights[sel], img.shape, float(seg[sel].max()))
        img += cv2.GaussianBlur(part, (0, 0), float(math.sqrt(lo * hi)))
    rgb = np.asarray(spectra.laser_rgb(lam_nm), np.float32)
    return x0, y0, (img[..., None] * rgb[None, None, :]).astype(np.float32)


def _splat(xy_local: F64, weights: F64, shape: tuple[int, int], max_step: float) -> F32:
    """Bilinear splat of weighted points (subdivided so that steps are <= 0.5 px)."""
    sub = max(1, int(math.ceil(max_step / 0.5)))
    if sub > 1:
        xy_local = np.repeat(xy_local, sub, axis=0)
        weights = np.repeat(weights / sub, sub)
    img = np.zeros(shape, np.float64)
    x = xy_local[:, 0] - 0.5
    y = xy_local[:, 1] - 0.5
    i0, j0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = y - i0, x - j0
    for di, dj, wgt in ((0, 0, (1 - fy) * (1 - fx)), (0, 1, (1 - fy) * fx),
                        (1, 0, fy * (1 - fx)), (1, 1, fy * fx)):
        ii, jj = i0 + di, j0 + dj
        ok = (ii >= 0) & (ii < shape[0]) & (jj >= 0) & (jj < shape[1])
        np.add.at(img, (ii[ok], jj[ok]), (weights * wgt)[ok])
    return img.astype(np.float32)


def albedo_function(bank: texture.NoiseBank, look: texture.SeabedLook,
                    linear_below_m: float) -> AlbedoFn:
    """``albedo_at(s, t, footprint_m)``: the seabed albedo at surface points, identical to the
    frame's texture (same noise bank and interpolation choices)."""
    def albedo_at(s: F32, t: F32, footprint_m: F32) -> F32:
        """Albedo (..., 3) at surface coordinates (s, t) seen with this pixel footprint."""
        sampler = texture.PointSampler(bank, s, t, footprint_m, linear_below_m)
        return texture.albedo_rgb(sampler, look)[0]
    return albedo_at

