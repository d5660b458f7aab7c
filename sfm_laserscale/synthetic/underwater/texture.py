"""Procedural seabed albedo in surface coordinates (metres): sediment, ripples, rocks, gravel.

Every layer is built from *value noise*: one 2048×2048 lattice of smoothed Gaussian random
values per image, sampled bicubically (``cv2.remap``) at the surface coordinates scaled by
the layer's feature size ("wavelength"), rotated and offset differently per layer (slot).
Evaluating the noise at each pixel's surface point makes the texture perspective-correct;
the same functions evaluated at sub-pixel points give the albedo under a laser footprint
(:class:`PointSampler`). For whole frames, :class:`LevelSampler` evaluates coarse layers on
coarser pixel grids (≥ 8 grid nodes per feature everywhere) and upsamples them bilinearly,
band by band (:class:`BandSampler`).
Each layer is faded out where the pixel's footprint on the surface approaches its wavelength
(anti-aliasing: weight 0 at λ = 0.75 footprints, 1 at λ = 1.75 footprints).

Layers (albedo in raw camera channels): a sediment colour modulated by fBm (12 octaves,
1.6 m down to 0.8 mm, persistence 0.88, metre-scale octaves damped; log-normal modulation)
and, on sand, ripples; rock outcrops (thresholded low-frequency noise) with their own
colour, rough fine texture and dark pits; gravel (bright and dark pebbles, 5-30 mm);
greenish biofilm patches. A bump field (for shading) comes with it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

F32 = NDArray[np.float32]
LATTICE = 2048
#: fBm octaves of the sediment: wavelength of octave k is SEDIMENT_BASE_M * 0.5**k
SEDIMENT_BASE_M = 1.6
SEDIMENT_OCTAVES = 12
PERSISTENCE = 0.88
#: the first octaves (metre scale) are damped so the large-scale albedo stays moderate
LOW_OCTAVE_DAMPING = (0.45, 0.55, 0.7)
#: slots of the other layers (after the sediment octaves) and the total
_ROCK, _PITS, _PEBBLE, _BIOFILM, _RIPPLE = 12, 14, 16, 19, 20
BANK_SIZE = 22
#: a layer goes on a pixel grid of step g when its wavelength spans >= this many nodes
NODES_PER_WAVELENGTH = 8.0


@dataclass(frozen=True)
class NoiseBank:
    """The random lattice and per-slot rotation/offset of the value noise (one per image)."""

    lattice: F32  # (LATTICE, LATTICE), unit variance
    rotations: NDArray[np.float64]  # (BANK_SIZE, 2, 2)
    offsets: NDArray[np.float64]  # (BANK_SIZE, 2) lattice cells


@dataclass(frozen=True)
class SeabedLook:
    """Colours (raw-channel albedo) and proportions of one seabed."""

    sediment_rgb: tuple[float, float, float]
    rock_rgb: tuple[float, float, float]
    biofilm_rgb: tuple[float, float, float]
    rock_cover: float  # 0..1 fraction of rock outcrop
    gravel: float  # 0..1 density of pebbles
    contrast: float  # amplitude of the sediment fBm (relative albedo)
    biofilm: float  # 0..1 opacity of the biofilm patches
    ripples: float  # 0..1 amplitude of sand ripples
    ripple_wavelength_m: float


def make_noise_bank(rng: np.random.Generator) -> NoiseBank:
    """A fresh lattice (smoothed white noise, unit variance) and slot transforms for one image."""
    lat = rng.standard_normal((LATTICE, LATTICE), dtype=np.float32)
    lat = ndimage.gaussian_filter(lat, 0.7, mode="wrap")
    lat /= float(lat.std()) + 1e-6
    ang = rng.uniform(0.0, 2.0 * math.pi, BANK_SIZE)
    rot = np.stack([np.stack([np.cos(ang), -np.sin(ang)], -1),
                    np.stack([np.sin(ang), np.cos(ang)], -1)], 1)
    return NoiseBank(lat.astype(np.float32), rot, rng.uniform(0.0, LATTICE, (BANK_SIZE, 2)))


def random_look(rng: np.random.Generator) -> SeabedLook:
    """A seabed: sand, mud or silt, with more or less rock, gravel, ripples and biofilm."""
    kind = int(rng.integers(3))
    base = [(0.46, 0.40, 0.30), (0.26, 0.24, 0.19), (0.33, 0.32, 0.29)][kind]
    tint = rng.uniform(0.85, 1.15, 3)
    sediment = tuple(float(c * t) for c, t in zip(base, tint, strict=True))
    grey = float(rng.uniform(0.12, 0.25))
    return SeabedLook(
        sediment_rgb=(sediment[0], sediment[1], sediment[2]),
        rock_rgb=(grey * 1.05, grey, grey * float(rng.uniform(0.8, 1.0))),
        biofilm_rgb=(float(rng.uniform(0.14, 0.2)), 0.2, float(rng.uniform(0.08, 0.14))),
        biofilm=float(rng.uniform(0.0, 0.6)),
        rock_cover=float(rng.uniform(0.05, 0.45)),
        gravel=float(rng.uniform(0.2, 1.0)),
        contrast=float(rng.uniform(0.35, 0.55)),
        ripples=float(rng.uniform(0.3, 1.0)) if kind == 0 else float(rng.uniform(0.0, 0.3)),
        ripple_wavelength_m=float(rng.uniform(0.06, 0.2)),
    )


def sample_noise(bank: NoiseBank, slot: int, s_m: F32, t_m: F32, wavelength_m: float,
                 linear: bool = False) -> F32:
    """Value noise of one slot at surface coordinates (2-D arrays), feature size
    ``wavelength_m``, bicubic (or bilinear: faster, for layers only a few pixels wide). The
    lattice coordinates are shifted by whole periods so that the array's centre lies in the
    lattice (cv2.remap wraps only one period)."""
    rot, off = bank.rotations[slot], bank.offsets[slot]
    inv = 1.0 / wavelength_m
    mx = cv2.addWeighted(s_m, rot[0, 0] * inv, t_m, rot[0, 1] * inv, off[0])
    my = cv2.addWeighted(s_m, rot[1, 0] * inv, t_m, rot[1, 1] * inv, off[1])
    ci, cj = s_m.shape[0] // 2, s_m.shape[1] // 2
    for m in (mx, my):
        shift = LATTICE * math.floor(float(m[ci, cj]) / LATTICE)
        if shift:
            m -= np.float32(shift)
    interp = cv2.INTER_LINEAR if linear else cv2.INTER_CUBIC
    return np.asarray(cv2.remap(bank.lattice, mx, my, interp, borderMode=cv2.BORDER_WRAP),
                      np.float32)


def aa_weight(wavelength_m: float, inv_footprint: F32) -> F32:
    """Anti-aliasing weight of a layer: 0 at λ <= 0.75 footprints, 1 at λ >= 1.75 footprints
    (``inv_footprint`` = 1 / pixel footprint on the surface, 1/m; a lattice of cell λ
    interpolated cubically has little energy above 1/(2λ) cycles per metre)."""
    w = cv2.addWeighted(inv_footprint, wavelength_m, inv_footprint, 0.0, -0.75)
    return np.clip(w, 0.0, 1.0, out=w)


class PointSampler:
    """Noise at given surface points (2-D arrays), e.g. the sub-pixel samples of a spot.

    Layers finer than ``linear_below_m`` are interpolated bilinearly (as the frame sampler
    does at full resolution, so that a spot's albedo matches the frame's)."""

    def __init__(self, bank: NoiseBank, s_m: F32, t_m: F32, footprint_m: F32,
                 linear_below_m: float = 0.0) -> None:
        self.bank = bank
        self.linear_below_m = linear_below_m
        self.s = np.asarray(s_m, np.float32)
        self.t = np.asarray(t_m, np.float32)
        self.inv_fp = cv2.divide(1.0, np.maximum(np.asarray(footprint_m, np.float32), 1e-6))
        self.shape: tuple[int, ...] = self.s.shape
        self.min_footprint_m = float(1.0 / self.inv_fp.max())

    def noise(self, slot: int, wavelength_m: float, antialias: bool = True) -> F32:
        """Layer ``slot`` at feature size ``wavelength_m`` (faded out below the pixel scale)."""
        val = sample_noise(self.bank, slot, self.s, self.t, wavelength_m,
                           wavelength_m < self.linear_below_m)
        return val * aa_weight(wavelength_m, self.inv_fp) if antialias else val


class LevelSampler:
    """Noise for a whole frame, computed in bands of rows (cache-friendly).

    Each layer is evaluated on the coarsest of a few pixel grids ("levels", steps g) that
    still gives ≥ 8 nodes per wavelength at the 95th-percentile footprint, and upsampled
    bilinearly to full resolution; layers left at full resolution are interpolated
    bilinearly from the lattice (``linear_below_m``). ``levels`` maps g > 1 to the (s, t,
    footprint) arrays of that grid; ``upsample_rows(array, g, r0, r1)`` gives rows
    [r0, r1) of the full-resolution upsampling of a level-g array; full-resolution surface
    coordinates are upsampled from level ``base_step``.
    """

    def __init__(self, bank: NoiseBank, levels: dict[int, tuple[F32, F32, F32]],
                 base_step: int, upsample_rows: Callable[[F32, int, int, int], F32]) -> None:
        self.bank = bank
        self.base_step = base_step
        self.raw_levels = levels
        fp = levels[base_step][2]
        self.fp95 = float(np.percentile(fp, 95))
        self.min_footprint_m = float(fp.min())
        self.linear_below_m = NODES_PER_WAVELENGTH * 2 * self.fp95
        self.levels = {g: PointSampler(bank, *arrs, linear_below_m=self.linear_below_m)
                       for g, arrs in levels.items()}
        self.upsample_rows = upsample_rows
        self._cache: dict[tuple[int, float, bool], F32] = {}

    def level_for(self, wavelength_m: float) -> int:
        """Grid step on which a layer of this wavelength is evaluated (1 = full resolution)."""
        g = 1
        for cand in sorted(self.levels):
            if wavelength_m >= NODES_PER_WAVELENGTH * cand * self.fp95:
                g = cand
        return g

    def coarse_noise(self, slot: int, wavelength_m: float, antialias: bool) -> F32:
        """A layer on its (coarse) level grid, computed once per frame."""
        key = (slot, wavelength_m, antialias)
        if key not in self._cache:
            g = self.level_for(wavelength_m)
            self._cache[key] = self.levels[g].noise(slot, wavelength_m, antialias)
        return self._cache[key]

    def band(self, r0: int, r1: int) -> BandSampler:
        """A sampler of full-resolution rows [r0, r1)."""
        return BandSampler(self, r0, r1)


class BandSampler(PointSampler):
    """Full-resolution rows [r0, r1) of a :class:`LevelSampler`."""

    def __init__(self, parent: LevelSampler, r0: int, r1: int) -> None:
        g = parent.base_step
        s, t, fp = (parent.upsample_rows(a, g, r0, r1) for a in parent.raw_levels[g])
        super().__init__(parent.bank, s, t, fp, parent.linear_below_m)
        self.parent = parent
        self.rows = (r0, r1)
        self.min_footprint_m = parent.min_footprint_m

    def noise(self, slot: int, wavelength_m: float, antialias: bool = True) -> F32:
        """Layer ``slot`` at feature size ``wavelength_m`` (faded out below the pixel scale)."""
        g = self.parent.level_for(wavelength_m)
        if g == 1:
            return super().noise(slot, wavelength_m, antialias)
        coarse = self.parent.coarse_noise(slot, wavelength_m, antialias)
        return self.parent.upsample_rows(coarse, g, *self.rows)


Sampler = PointSampler


def _smoothstep(x: F32, lo: float, hi: float) -> F32:
    y = np.clip((x - np.float32(lo)) * np.float32(1.0 / (hi - lo)), 0.0, 1.0)
    return y * y * (np.float32(3.0) - np.float32(2.0) * y)


def _octave_weight(k: int) -> float:
    damp = LOW_OCTAVE_DAMPING[k] if k < len(LOW_OCTAVE_DAMPING) else 1.0
    return float(PERSISTENCE ** k * damp)


def _fbm(sampler: Sampler, split: int = 4) -> tuple[F32, F32]:
    """Sediment fBm (amplitude PERSISTENCE^k per octave, the first octaves damped, normalised
    to unit variance) over all octaves, and over octaves >= ``split`` only (the fine part,
    for rock texture)."""
    full = np.zeros(sampler.shape, np.float32)
    fine = np.zeros(sampler.shape, np.float32)
    norm_all = math.sqrt(sum(_octave_weight(k) ** 2 for k in range(SEDIMENT_OCTAVES)))
    norm_fine = math.sqrt(sum(_octave_weight(k) ** 2 for k in range(split, SEDIMENT_OCTAVES)))
    for k in range(SEDIMENT_OCTAVES):
        lam = SEDIMENT_BASE_M * 0.5 ** k
        if lam < 0.75 * sampler.min_footprint_m:
            break
        octave = sampler.noise(k, lam)
        full = cv2.scaleAdd(octave, _octave_weight(k) / norm_all, full)
        if k >= split:
            fine = cv2.scaleAdd(octave, _octave_weight(k) / norm_fine, fine)
    return full, fine


def albedo_rgb(sampler: Sampler, look: SeabedLook) -> tuple[F32, F32]:
    """(albedo (..., 3) float32 in [0.02, 0.95], bump (...) float32) where the sampler is."""
    fbm, fbm_fine = _fbm(sampler)
    rock_field = (sampler.noise(_ROCK, 1.2) + 0.6 * sampler.noise(_ROCK + 1, 0.35)
                  + np.float32(0.25) * fbm)
    thresh = float(np.interp(look.rock_cover, [0.0, 1.0], [2.0, -1.2]))
    rock = _smoothstep(rock_field, thresh, thresh + 0.2)
    pits = _smoothstep(sampler.noise(_PITS, 0.01) + 0.5 * fbm_fine, 1.6, 2.2)
    peb = sampler.noise(_PEBBLE, 0.018) + 0.7 * sampler.noise(_PEBBLE + 1, 0.008)
    pebble = _smoothstep(peb, 2.6 - 0.9 * look.gravel, 3.0 - 0.9 * look.gravel)
    tone = sampler.noise(_PEBBLE + 2, 0.05, False)
    ripple_phase = sampler.noise(_RIPPLE, 0.6, False) * np.float32(1.5)
    ripple = _ripples(sampler, look, ripple_phase)
    bio = _smoothstep(sampler.noise(_BIOFILM, 0.5), 1.5, 2.1) * np.float32(look.biofilm)
    sed = np.exp(np.float32(look.contrast) * fbm) * (np.float32(1.0) + ripple)
    rock_tex = np.exp(np.float32(0.5) * fbm_fine) * (np.float32(1.0) - np.float32(0.6) * pits)
    out = np.empty((*sampler.shape, 3), np.float32)
    peb_val = np.float32(0.28) + np.float32(0.14) * tone + np.float32(0.1) * fbm_fine
    for ch in range(3):
        val = np.float32(look.sediment_rgb[ch]) * sed
        val += bio * (np.float32(look.biofilm_rgb[ch]) - val)
        val += rock * (np.float32(look.rock_rgb[ch]) * rock_tex - val)
        val += pebble * (1.0 - rock) * (peb_val - val)
        out[..., ch] = val
    bump = (np.float32(0.5) * rock + np.float32(0.05) * fbm + np.float32(0.3) * pebble
            + np.float32(0.25) * fbm_fine + np.float32(0.3) * ripple)
    return np.clip(out, 0.02, 0.95), bump


def _ripples(sampler: Sampler, look: SeabedLook, phase: F32) -> F32:
    """Sand ripples: a sinusoid across the crests (direction from the bank), its phase
    perturbed by low-frequency noise, faded out below the pixel scale."""
    if look.ripples <= 0.0:
        return np.zeros(sampler.shape, np.float32)
    lam = look.ripple_wavelength_m
    rot = sampler.bank.rotations[_RIPPLE + 1]
    k = 2.0 * math.pi / lam
    arg = cv2.addWeighted(sampler.s, rot[0, 0] * k, sampler.t, rot[0, 1] * k, 0.0)
    arg += phase * np.float32(2.0 * math.pi)
    wave = np.sin(arg) * aa_weight(lam, sampler.inv_fp)
    return wave * np.float32(0.08 * look.ripples)
