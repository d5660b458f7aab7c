"""Camera spectral sensitivities, light source spectra and the camera response to a laser.

The sensor has three overlapping colour-filter bands (raw R, G, B) modelled as asymmetric
Gaussians (typical of CMOS colour filter arrays) times an IR-cut filter edge at 655 nm, plus
small out-of-band leaks (the red filter's transmission in the violet-blue, the blue filter's
in the far red):

====  =========  =============  ==============  ======
band  centre nm  sigma left nm  sigma right nm  height
====  =========  =============  ==============  ======
R     600        32             28              0.75
G     535        38             40              1.00
B     465        30             33              0.85
====  =========  =============  ==============  ======

A laser is monochromatic, so its raw response is the three sensitivities at its wavelength:
532 nm gives G dominant with R ≈ 8 % and B ≈ 11 % of G; 450 nm B dominant with G ≈ 11 %;
638 nm R dominant with G ≈ 14 % (see :func:`laser_rgb`). Broadband light (lamps, daylight)
is integrated over the grid ``WAVELENGTHS_NM`` (380-720 nm, 1 nm).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
#: wavelength grid of all spectra (nm)
WAVELENGTHS_NM: F64 = np.arange(380.0, 721.0, 1.0)
#: (centre, sigma left, sigma right, height) of the R, G, B colour-filter bands
_BANDS: tuple[tuple[float, float, float, float], ...] = (
    (600.0, 32.0, 28.0, 0.75),
    (535.0, 38.0, 40.0, 1.00),
    (465.0, 30.0, 33.0, 0.85),
)
#: out-of-band leak of each band: (centre nm, sigma nm, height)
_LEAKS: tuple[tuple[float, float, float], ...] = (
    (425.0, 20.0, 0.015),
    (620.0, 40.0, 0.006),
    (680.0, 25.0, 0.010),
)
#: IR-cut filter: 50 % transmission wavelength and edge width (nm)
IR_CUT_NM = (655.0, 8.0)
CHANNEL_NAMES = ("red", "green", "blue")


def _asym_gauss(lam: F64, centre: float, s_left: float, s_right: float) -> F64:
    sigma = np.where(lam < centre, s_left, s_right)
    return np.exp(-0.5 * ((lam - centre) / sigma) ** 2)


def sensitivities(wavelengths_nm: F64 | float) -> F64:
    """(N, 3) raw R, G, B sensitivity of the sensor (colour filters x IR cut) at these
    wavelengths (relative units, G peak = 1)."""
    lam = np.atleast_1d(np.asarray(wavelengths_nm, dtype=np.float64))
    ir_cut = 1.0 / (1.0 + np.exp((lam - IR_CUT_NM[0]) / IR_CUT_NM[1]))
    out = np.empty((lam.size, 3))
    for ch, ((c, sl, sr, h), (lc, ls, lh)) in enumerate(zip(_BANDS, _LEAKS, strict=True)):
        band = h * _asym_gauss(lam, c, sl, sr) + lh * np.exp(-0.5 * ((lam - lc) / ls) ** 2)
        out[:, ch] = band * ir_cut
    return out


def laser_rgb_raw(wavelength_nm: float) -> F64:
    """(3,) raw camera response to one unit of monochromatic light at this wavelength."""
    return sensitivities(float(wavelength_nm))[0]


def laser_rgb(wavelength_nm: float) -> tuple[float, float, float]:
    """Raw camera (R, G, B) of a laser at this wavelength, normalised so the dominant
    channel is 1 (the crosstalk into the other two channels is what remains)."""
    rgb = laser_rgb_raw(wavelength_nm)
    rgb = rgb / float(rgb.max())
    return float(rgb[0]), float(rgb[1]), float(rgb[2])


def dominant_channel(wavelength_nm: float) -> int:
    """Index (0 R, 1 G, 2 B) of the camera channel a laser at this wavelength is brightest in."""
    return int(np.argmax(laser_rgb_raw(wavelength_nm)))


def color_name(wavelength_nm: float) -> str:
    """The rig-file colour name ("red", "green", "blue") of a laser at this wavelength."""
    return CHANNEL_NAMES[dominant_channel(wavelength_nm)]


def white_led_spectrum() -> F64:
    """Relative spectral power of a cool-white phosphor LED lamp on ``WAVELENGTHS_NM``:
    a narrow blue pump at 450 nm and a broad phosphor band centred near 560 nm."""
    lam = WAVELENGTHS_NM
    pump = 1.0 * np.exp(-0.5 * ((lam - 450.0) / 10.0) ** 2)
    phosphor = _asym_gauss(lam, 565.0, 45.0, 65.0)
    return pump + phosphor


def daylight_spectrum() -> F64:
    """Relative spectral power of daylight at the sea surface (smooth, slightly blue-rich)."""
    lam = WAVELENGTHS_NM
    return 1.0 + 0.25 * (550.0 - lam) / 170.0


def integrate_rgb(spectrum: F64) -> F64:
    """(3,) raw camera response to a broadband spectrum sampled on ``WAVELENGTHS_NM``."""
    sens = sensitivities(WAVELENGTHS_NM)
    return np.asarray(np.sum(sens * spectrum[:, None], axis=0) * 1.0, dtype=np.float64)
