"""Named water types: spectral absorption and scattering, and what they do to light.

Inherent optical properties (per metre) are built from the usual constituents:

- pure water absorption ``a_w(λ)`` (tabulated after Pope & Fry 1997 / Smith & Baker 1981) and
  scattering ``b_w(λ) = 0.0022 (500/λ)^4.32``;
- phytoplankton absorption ``0.06·Chl^0.65`` at 440 nm (blue peak, red peak at 676 nm);
- CDOM (yellow substance) ``a_g(440)·exp(-0.015(λ-440))`` and non-algal particles (sediment)
  ``a_d(440)·exp(-0.011(λ-440))``;
- particle scattering ``b_p(550)·(550/λ)^γ`` with backscattering ratio ``B_p``.

Then ``c = a + b`` (beam attenuation: what the direct, unscattered light suffers),
``b_b = b_w/2 + B_p·b_p`` (backscattering), ``β(π) ≈ 0.175·b_b`` per steradian (the
volume scattering function near 180°, Fournier-Forand-like), and a fraction ``η`` of the
particle scattering goes into small angles (the forward-scatter halo of a laser spot, the
glow of a lamp; angular width ``halo_sigma_rad``). Broadband light (lamps, daylight) seen
through a path of length L has per-channel transmission
``T_ch(L) = ∫ S_ch E exp(-c L) dλ / ∫ S_ch E dλ`` (spectral hardening included), tabulated by
:func:`transmission_table`; a laser at λ simply gets ``exp(-c(λ) L)``.

The four types (numbers in :data:`WATER_TYPES`; effective lamp-light c_R/c_G/c_B and c at
450/532/638 nm in 1/m) are in the range of the Jerlov classes:

- ``neutral`` ~ oceanic II-III, mild blue-green cast: c_RGB 0.35/0.26/0.24,
  c(450/532/638) 0.25/0.24/0.50, no daylight (lamps only);
- ``blue_oceanic`` ~ oceanic IB-II, red dies fast: c_RGB 0.22/0.13/0.10, c 0.10/0.10/0.36;
- ``green_coastal`` ~ coastal 3-5, green-cyan (chlorophyll + daylight from 6 m above):
  c_RGB 0.50/0.43/0.49, c 0.53/0.40/0.64;
- ``turbid_brown`` ~ coastal 7-9 with suspended sediment and CDOM, strong backscatter
  (b_b(532) = 0.023/m) and forward scatter (b_s(532) = 0.39/m): c_RGB 1.37/1.41/1.82,
  c 1.98/1.41/1.42.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.synthetic.underwater import spectra

F64 = NDArray[np.float64]
#: pure water absorption (1/m) every 20 nm from 380 to 720 nm
_AW_NM = np.arange(380.0, 721.0, 20.0)
_AW_PER_M = np.array([0.0114, 0.0066, 0.0045, 0.0064, 0.0092, 0.0145, 0.0204, 0.0417, 0.0503,
                      0.0619, 0.0896, 0.2224, 0.2755, 0.3231, 0.4100, 0.4550, 0.6240, 1.0000])
#: β(180°) / b_b (1/sr) of a Fournier-Forand-like phase function
BACKSCATTER_PHASE_PI = 0.175


@dataclass(frozen=True)
class WaterType:
    """Constituents of a water body, and the light field it sits in.

    ``ambient_level`` is the downwelling daylight at the scene relative to the vehicle's lamps
    (0: deep or night dive), filtered by ``ambient_depth_m`` of this water; ``halo_sigma_rad``
    is the angular sigma (radians, as seen from the camera) of the inner Gaussian of the
    forward-scatter halo kernel (an outer one, 3x wider, carries 40 % of it).
    """

    name: str
    description: str
    chl_mg_m3: float
    cdom_440_per_m: float
    nap_440_per_m: float
    bp_550_per_m: float
    bp_exponent: float
    backscatter_ratio: float
    small_angle_fraction: float
    halo_sigma_rad: float
    ambient_level: float
    ambient_depth_m: float

    def absorption_per_m(self, wavelength_nm: F64 | float) -> F64:
        """Total absorption coefficient a(λ) (1/m)."""
        lam = np.atleast_1d(np.asarray(wavelength_nm, dtype=np.float64))
        a_w = np.interp(lam, _AW_NM, _AW_PER_M)
        shape = (np.exp(-0.5 * ((lam - 440.0) / 35.0) ** 2)
                 + 0.45 * np.exp(-0.5 * ((lam - 676.0) / 12.0) ** 2)
                 + 0.10 * np.exp(-0.5 * ((lam - 620.0) / 25.0) ** 2))
        a_ph = 0.06 * self.chl_mg_m3 ** 0.65 * shape
        a_g = self.cdom_440_per_m * np.exp(-0.015 * (lam - 440.0))
        a_d = self.nap_440_per_m * np.exp(-0.011 * (lam - 440.0))
        return np.asarray(a_w + a_ph + a_g + a_d, dtype=np.float64)

    def particle_scattering_per_m(self, wavelength_nm: F64 | float) -> F64:
        """Particle scattering coefficient b_p(λ) (1/m)."""
        lam = np.atleast_1d(np.asarray(wavelength_nm, dtype=np.float64))
        return np.asarray(self.bp_550_per_m * (550.0 / lam) ** self.bp_exponent, np.float64)

    def scattering_per_m(self, wavelength_nm: F64 | float) -> F64:
        """Total scattering coefficient b(λ) = b_w + b_p (1/m)."""
        lam = np.atleast_1d(np.asarray(wavelength_nm, dtype=np.float64))
        b_w = 0.0022 * (500.0 / lam) ** 4.32
        return np.asarray(b_w + self.particle_scattering_per_m(lam), np.float64)

    def attenuation_per_m(self, wavelength_nm: F64 | float) -> F64:
        """Beam attenuation coefficient c(λ) = a + b (1/m)."""
        return self.absorption_per_m(wavelength_nm) + self.scattering_per_m(wavelength_nm)

    def backscattering_per_m(self, wavelength_nm: F64 | float) -> F64:
        """Backscattering coefficient b_b(λ) (1/m)."""
        lam = np.atleast_1d(np.asarray(wavelength_nm, dtype=np.float64))
        b_w = 0.0022 * (500.0 / lam) ** 4.32
        return np.asarray(0.5 * b_w + self.backscatter_ratio
                          * self.particle_scattering_per_m(lam), np.float64)

    def small_angle_scattering_per_m(self, wavelength_nm: F64 | float) -> F64:
        """Part of the scattering (1/m) that stays within a few degrees (the halo)."""
        return self.small_angle_fraction * self.particle_scattering_per_m(wavelength_nm)


def _types() -> dict[str, WaterType]:
    rows = [
        WaterType("neutral", "mild blue-green cast (oceanic II-III)",
                  chl_mg_m3=0.2, cdom_440_per_m=0.015, nap_440_per_m=0.01, bp_550_per_m=0.18,
                  bp_exponent=0.3, backscatter_ratio=0.012, small_angle_fraction=0.25,
                  halo_sigma_rad=0.012, ambient_level=0.0, ambient_depth_m=20.0),
        WaterType("blue_oceanic", "clear blue oceanic water, red dies fast (Jerlov IB-II)",
                  chl_mg_m3=0.08, cdom_440_per_m=0.008, nap_440_per_m=0.005,
                  bp_550_per_m=0.05, bp_exponent=1.2, backscatter_ratio=0.010,
                  small_angle_fraction=0.25, halo_sigma_rad=0.015, ambient_level=0.3,
                  ambient_depth_m=15.0),
        WaterType("green_coastal", "green-cyan coastal water (Jerlov coastal 3-5)",
                  chl_mg_m3=2.5, cdom_440_per_m=0.05, nap_440_per_m=0.03, bp_550_per_m=0.32,
                  bp_exponent=0.4, backscatter_ratio=0.015, small_angle_fraction=0.3,
                  halo_sigma_rad=0.010, ambient_level=0.8, ambient_depth_m=6.0),
        WaterType("turbid_brown", "turbid brown coastal water, suspended sediment and CDOM "
                  "(Jerlov coastal 7-9)",
                  chl_mg_m3=1.5, cdom_440_per_m=0.45, nap_440_per_m=0.35, bp_550_per_m=1.1,
                  bp_exponent=0.4, backscatter_ratio=0.020, small_angle_fraction=0.35,
                  halo_sigma_rad=0.008, ambient_level=0.15, ambient_depth_m=3.0),
    ]
    return {w.name: w for w in rows}


#: the named water types
WATER_TYPES: dict[str, WaterType] = _types()


def attenuation_rgb_per_m(water: WaterType, illuminant: F64 | None = None) -> F64:
    """(3,) effective per-channel (raw R, G, B) attenuation coefficient (1/m) of broadband
    light (default: the white LED lamp) over short paths: the sensitivity-weighted mean of
    c(λ). Longer paths attenuate less than this (spectral hardening; see
    :func:`transmission_table`)."""
    spec = spectra.white_led_spectrum() if illuminant is None else illuminant
    weights = spectra.sensitivities(spectra.WAVELENGTHS_NM) * spec[:, None]
    c = water.attenuation_per_m(spectra.WAVELENGTHS_NM)
    return np.asarray((weights * c[:, None]).sum(0) / weights.sum(0), np.float64)


def transmission_table(water: WaterType, max_path_m: float = 60.0, samples: int = 512,
                       illuminant: F64 | None = None, coefficient: str = "c"
                       ) -> tuple[F64, F64]:
    """(paths_m (n,), T (n, 3)): per-channel raw transmission of broadband light (default the
    lamp) along a path, for np.interp. ``coefficient`` "c" uses the beam attenuation (direct
    light), "a+bb" the diffuse attenuation (downwelling light, scattered light fields)."""
    spec = spectra.white_led_spectrum() if illuminant is None else illuminant
    lam = spectra.WAVELENGTHS_NM
    weights = spectra.sensitivities(lam) * spec[:, None]
    if coefficient == "c":
        k = water.attenuation_per_m(lam)
    else:
        k = water.absorption_per_m(lam) + water.backscattering_per_m(lam)
    paths = np.linspace(0.0, max_path_m, samples)
    trans = np.exp(-np.outer(paths, k)) @ weights / weights.sum(0)
    return paths, np.asarray(trans, np.float64)


def downwelling_rgb(water: WaterType) -> F64:
    """(3,) raw camera response to the daylight reaching ``ambient_depth_m`` (unit daylight at
    the surface), attenuated with the diffuse coefficient K ≈ 1.1 (a + b_b)."""
    lam = spectra.WAVELENGTHS_NM
    k_d = 1.1 * (water.absorption_per_m(lam) + water.backscattering_per_m(lam))
    spec = spectra.daylight_spectrum() * np.exp(-k_d * water.ambient_depth_m)
    ref = float(spectra.integrate_rgb(spectra.daylight_spectrum())[1])
    return spectra.integrate_rgb(spec) / ref


def veiling_rgb_inf(water: WaterType) -> F64:
    """(3,) raw radiance of the ambient veiling light at infinite range, per unit of
    :func:`downwelling_rgb`'s reference: the single-scattering water colour ``b_b / c``
    weighted by the downwelling spectrum (what the open water column looks like)."""
    lam = spectra.WAVELENGTHS_NM
    k_d = 1.1 * (water.absorption_per_m(lam) + water.backscattering_per_m(lam))
    spec = spectra.daylight_spectrum() * np.exp(-k_d * water.ambient_depth_m)
    colour = spec * water.backscattering_per_m(lam) / water.attenuation_per_m(lam)
    ref = float(spectra.integrate_rgb(spectra.daylight_spectrum())[1])
    return spectra.integrate_rgb(colour) / ref


def describe(water: WaterType) -> dict[str, float]:
    """Headline numbers of a water type (for docs and frame metadata)."""
    c_rgb = attenuation_rgb_per_m(water)
    return {
        "c_R_per_m": float(c_rgb[0]), "c_G_per_m": float(c_rgb[1]), "c_B_per_m": float(c_rgb[2]),
        "c_450_per_m": float(water.attenuation_per_m(450.0)[0]),
        "c_532_per_m": float(water.attenuation_per_m(532.0)[0]),
        "c_638_per_m": float(water.attenuation_per_m(638.0)[0]),
        "b_532_per_m": float(water.scattering_per_m(532.0)[0]),
        "bb_532_per_m": float(water.backscattering_per_m(532.0)[0]),
        "small_angle_532_per_m": float(water.small_angle_scattering_per_m(532.0)[0]),
        "beta_pi_532_per_m_sr": BACKSCATTER_PHASE_PI * float(
            water.backscattering_per_m(532.0)[0]),
    }
