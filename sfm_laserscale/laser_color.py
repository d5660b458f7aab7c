"""A laser's colour as a rig file gives it -> the camera channel it is brightest in and the
expected linear camera response of its light.

A rig's ``color`` may be a name (``"red"``, ``"green"``, ``"blue"``, ``"any"``), a wavelength in
nanometres (``532``, ``"532 nm"``) or a relative RGB triplet (``[0.1, 1.0, 0.2]``, the linear
camera response to the laser, e.g. measured on a calibration image). The detector uses the
*channel* to build its colour response and the *expected response* as colour evidence: the light
a candidate adds over its surroundings is compared with it and with the scene's own colour.

Wavelengths are turned into a response with the sensitivity of a generic CMOS Bayer sensor
(``SENSOR_RGB_BY_NM``: coarse curves, relative; real cameras differ by tens of percent in the
crosstalk, which the colour evidence tolerates; give a triplet measured on your camera for a
better prior).
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from sfm_laserscale.errors import InputError

NAMED = ("red", "green", "blue", "any")
CHANNEL_NAMES = ("red", "green", "blue")
#: wavelengths (nm) a rig file may give
WAVELENGTH_RANGE_NM = (380.0, 780.0)
#: expected linear camera response of a laser of each named colour (max 1): a typical
#: sensor's crosstalk for 638, 532 and 450 nm
DEFAULT_RGB: dict[str, tuple[float, float, float]] = {
    "red": (1.0, 0.10, 0.04),
    "green": (0.12, 1.0, 0.15),
    "blue": (0.04, 0.22, 1.0),
}
#: generic CMOS Bayer sensor sensitivity (R, G, B), relative, every 25 nm from 375 to 775 nm
SENSOR_RGB_BY_NM: tuple[tuple[float, float, float, float], ...] = (
    (375.0, 0.02, 0.02, 0.10),
    (400.0, 0.03, 0.05, 0.45),
    (425.0, 0.02, 0.08, 0.85),
    (450.0, 0.02, 0.16, 1.00),
    (475.0, 0.02, 0.36, 0.85),
    (500.0, 0.03, 0.75, 0.45),
    (525.0, 0.05, 1.00, 0.18),
    (550.0, 0.12, 0.95, 0.07),
    (575.0, 0.55, 0.70, 0.03),
    (600.0, 0.95, 0.35, 0.03),
    (625.0, 1.00, 0.12, 0.03),
    (650.0, 0.85, 0.06, 0.03),
    (675.0, 0.60, 0.04, 0.03),
    (700.0, 0.35, 0.03, 0.02),
    (725.0, 0.20, 0.03, 0.02),
    (750.0, 0.10, 0.02, 0.02),
    (775.0, 0.05, 0.02, 0.02),
)
_NM = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?)\s*(?:nm)?\s*$", re.IGNORECASE)


def rgb_from_wavelength(nm: float) -> tuple[float, float, float]:
    """Expected linear camera response (max 1) of monochromatic light at ``nm`` nanometres."""
    table = np.asarray(SENSOR_RGB_BY_NM)
    rgb = np.array([np.interp(nm, table[:, 0], table[:, k]) for k in (1, 2, 3)])
    rgb = rgb / rgb.max()
    return (float(rgb[0]), float(rgb[1]), float(rgb[2]))


def channel_of(rgb: Sequence[float]) -> str:
    """The channel name a response is brightest in."""
    return CHANNEL_NAMES[int(np.argmax(np.asarray(rgb, dtype=np.float64)))]


def _wavelength(value: float, where: str, path: str) -> float:
    lo, hi = WAVELENGTH_RANGE_NM
    if not lo <= value <= hi:
        raise InputError(f"{where} color: a wavelength must lie in {lo:g}-{hi:g} nm, got "
                         f"{value:g}", path)
    return value


def _triplet(value: Sequence[object], where: str, path: str) -> tuple[float, float, float]:
    if len(value) != 3 or not all(isinstance(v, int | float) and not isinstance(v, bool)
                                  for v in value):
        raise InputError(f"{where} color: an RGB triplet needs 3 numbers, got {value!r}", path)
    rgb = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(rgb)) or rgb.min() < 0 or rgb.max() <= 0:
        raise InputError(f"{where} color: RGB values must be >= 0 and not all 0, got "
                         f"{value!r}", path)
    rgb = rgb / rgb.max()
    return (float(rgb[0]), float(rgb[1]), float(rgb[2]))


def parse_color(value: object, where: str, path: str
                ) -> tuple[str, tuple[float, float, float] | None, str | None]:
    """(channel, expected RGB or None, spec as written or None) of a rig file's ``color``.

    Names give themselves and no RGB (the defaults in ``DEFAULT_RGB`` apply); a wavelength or a
    triplet gives the channel it is brightest in, its response and a label ("532 nm",
    "[0.1, 1, 0.2]"). Anything else is an :class:`InputError` naming the laser.
    """
    if isinstance(value, str) and value.strip().lower() in NAMED:
        return value.strip().lower(), None, None
    if isinstance(value, str) and (m := _NM.match(value)):
        nm = _wavelength(float(m.group(1)), where, path)
        return _from_rgb(rgb_from_wavelength(nm), f"{nm:g} nm")
    if isinstance(value, int | float) and not isinstance(value, bool):
        nm = _wavelength(float(value), where, path)
        return _from_rgb(rgb_from_wavelength(nm), f"{nm:g} nm")
    if isinstance(value, list | tuple):
        rgb = _triplet(value, where, path)
        label = "[" + ", ".join(f"{float(v):g}" for v in value) + "]"
        return _from_rgb(rgb, label)
    raise InputError(f"{where} color must be one of {', '.join(NAMED)}, a wavelength in nm "
                     f"(e.g. 532 or \"532 nm\") or an RGB triplet [r, g, b], got {value!r}", path)


def _from_rgb(rgb: tuple[float, float, float], label: str
              ) -> tuple[str, tuple[float, float, float], str]:
    return channel_of(rgb), rgb, label


def color_toml(channel: str, spec: str | None) -> str:
    """The TOML value that reads back as the same colour."""
    if spec is None:
        return f'"{channel}"'
    if spec.endswith(" nm"):
        return spec[:-3]
    return spec
