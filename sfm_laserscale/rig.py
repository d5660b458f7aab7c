"""Laser rig file (TOML, docs/RIG.md) -> validated :class:`Rig`.

All lengths are metres in the camera frame (x right, y down, z forward).
Unknown keys are errors; origins are moved along their beam onto the laser
plane z = 0.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.laser_color import DEFAULT_RGB, NAMED, color_toml, parse_color

#: named laser colours: the camera channel a laser is brightest in, or "any" (search all three);
#: a rig file may also give a wavelength or an RGB triplet (laser_color.parse_color)
COLORS = NAMED
_TOP_KEYS = {"name", "laser", "pair"}
_LASER_KEYS = {"name", "origin", "direction", "color", "sigma_origin", "sigma_direction"}
_PAIR_KEYS = {"lasers", "separation"}
#: |v·c_z| below this (beam within ~0.6° of the laser plane) makes FCM undefined.
MIN_DIRECTION_Z = 0.01
#: origins closer than this to the camera centre (metres) make FCM undefined.
MIN_ORIGIN_NORM = 1e-4


@dataclass(frozen=True)
class Laser:
    """One beam: origin on z = 0 and unit direction (both None for a PCM-only beam)."""

    name: str
    origin: NDArray[np.float64] | None  # (3,) metres, origin[2] == 0
    direction: NDArray[np.float64] | None  # (3,) unit, direction[2] > 0
    color: str = "any"  # the channel it is brightest in: red | green | blue | any
    sigma_origin: float = 0.0  # metres, per axis
    sigma_direction: float = 0.0  # radians
    #: expected linear camera response (R, G, B), max 1; None: the default of ``color``
    color_rgb: tuple[float, float, float] | None = None
    #: the colour as the rig file gave it ("green", "532 nm", "[0.1, 1, 0.2]"); None: ``color``
    color_spec: str | None = None

    @property
    def expected_rgb(self) -> tuple[float, float, float] | None:
        """Expected linear camera response of the spot's light (max 1); None for "any"."""
        if self.color_rgb is not None:
            return self.color_rgb
        return DEFAULT_RGB.get(self.color)

    @property
    def color_label(self) -> str:
        """The colour as written in the rig file (for messages and reports)."""
        return self.color_spec or self.color

    @property
    def calibrated(self) -> bool:
        """True when origin and direction are known (FCM usable)."""
        return self.origin is not None and self.direction is not None


@dataclass(frozen=True)
class Pair:
    """Two parallel beams at a known perpendicular separation (metres), for PCM."""

    lasers: tuple[str, str]
    separation: float


@dataclass(frozen=True)
class Rig:
    """A validated laser scaler."""

    name: str
    lasers: tuple[Laser, ...]
    pairs: tuple[Pair, ...] = ()

    def laser(self, name: str) -> Laser:
        """The laser with this name (KeyError if none)."""
        for las in self.lasers:
            if las.name == name:
                return las
        raise KeyError(name)

    @property
    def names(self) -> list[str]:
        """Laser names in file order."""
        return [las.name for las in self.lasers]

    @property
    def has_fcm(self) -> bool:
        """True when at least one laser is fully calibrated."""
        return any(las.calibrated for las in self.lasers)


def _vec3(value: Any, what: str, path: str) -> NDArray[np.float64]:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a list of three numbers, got {value!r}", path) from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise InputError(f"{what} must be a list of three finite numbers, got {value!r}", path)
    return arr


def _number(value: Any, what: str, path: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise InputError(f"{what} must be a number, got {value!r}", path)
    if positive and value <= 0:
        raise InputError(f"{what} must be positive, got {value!r}", path)
    if value < 0:
        raise InputError(f"{what} must not be negative, got {value!r}", path)
    return float(value)


def _check_keys(table: dict[str, Any], allowed: set[str], where: str, path: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise InputError(
            f"unknown key(s) {', '.join(map(repr, unknown))} in {where} "
            f"(allowed: {', '.join(sorted(allowed))})",
            path,
        )


def _beam(raw: dict[str, Any], where: str, path: str) -> tuple[NDArray[np.float64] | None, ...]:
    if ("origin" in raw) != ("direction" in raw):
        raise InputError(f"{where} needs both origin and direction, or neither (PCM only)", path)
    if "origin" not in raw:
        return None, None
    origin = _vec3(raw["origin"], f"{where} origin", path)
    direction = _vec3(raw["direction"], f"{where} direction", path)
    norm = float(np.linalg.norm(direction))
    if norm < 1e-12:
        raise InputError(f"{where} direction is the zero vector", path)
    direction = direction / norm
    if abs(direction[2]) < MIN_DIRECTION_Z:
        raise InputError(f"{where} beam is parallel to the laser plane (direction z ~ 0)", path)
    if direction[2] < 0:
        direction = -direction
    origin = origin - (origin[2] / direction[2]) * direction  # onto z = 0 along the beam
    if float(np.linalg.norm(origin)) < MIN_ORIGIN_NORM:
        raise InputError(f"{where} origin is at the camera centre (FCM undefined)", path)
    return origin, direction


def _laser(raw: Any, index: int, path: str) -> Laser:
    if not isinstance(raw, dict):
        raise InputError(f"[[laser]] #{index + 1} must be a table", path)
    _check_keys(raw, _LASER_KEYS, f"[[laser]] #{index + 1}", path)
    name = raw.get("name")
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"[[laser]] #{index + 1} needs a non-empty string 'name'", path)
    where = f"laser {name!r}"
    origin, direction = _beam(raw, where, path)
    color, rgb, spec = parse_color(raw.get("color", "any"), where, path)
    return Laser(
        name=name,
        origin=origin,
        direction=direction,
        color=color,
        color_rgb=rgb,
        color_spec=spec,
        sigma_origin=_number(raw.get("sigma_origin", 0.0), f"{where} sigma_origin", path),
        sigma_direction=_number(raw.get("sigma_direction", 0.0), f"{where} sigma_direction", path),
    )


def _pair(raw: Any, index: int, names: list[str], path: str) -> Pair:
    where = f"[[pair]] #{index + 1}"
    if not isinstance(raw, dict):
        raise InputError(f"{where} must be a table", path)
    _check_keys(raw, _PAIR_KEYS, where, path)
    lasers = raw.get("lasers")
    if (
        not isinstance(lasers, list)
        or len(lasers) != 2
        or not all(isinstance(x, str) for x in lasers)
    ):
        raise InputError(f"{where} 'lasers' must name exactly two lasers", path)
    for name in lasers:
        if name not in names:
            raise InputError(
                f"{where} names unknown laser {name!r} (known: {', '.join(names)})", path
            )
    if lasers[0] == lasers[1]:
        raise InputError(f"{where} names the same laser twice", path)
    if "separation" not in raw:
        raise InputError(f"{where} has no 'separation' (metres between the beams)", path)
    sep = _number(raw["separation"], f"{where} separation", path, positive=True)
    return Pair(lasers=(lasers[0], lasers[1]), separation=sep)


def rig_from_dict(data: dict[str, Any], path: str = "<rig>") -> Rig:
    """Validate a parsed rig table (the TOML's content)."""
    _check_keys(data, _TOP_KEYS, "the rig file", path)
    raw_lasers = data.get("laser", [])
    if not isinstance(raw_lasers, list) or not raw_lasers:
        raise InputError("no [[laser]] tables", path)
    lasers = tuple(_laser(raw, i, path) for i, raw in enumerate(raw_lasers))
    names = [las.name for las in lasers]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise InputError(f"duplicate laser name(s): {', '.join(dupes)}", path)
    raw_pairs = data.get("pair", [])
    if not isinstance(raw_pairs, list):
        raise InputError("[[pair]] must be an array of tables", path)
    pairs = tuple(_pair(raw, i, names, path) for i, raw in enumerate(raw_pairs))
    rig = Rig(name=str(data.get("name", "laser rig")), lasers=lasers, pairs=pairs)
    for las in lasers:
        if not las.calibrated and not any(las.name in p.lasers for p in pairs):
            raise InputError(f"laser {las.name!r} has no origin/direction and is in no pair", path)
    return rig


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig TOML file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("rig file not found", p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read rig file ({exc.__class__.__name__})", p) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", p) from None
    return rig_from_dict(data, str(p))


def rig_to_toml(rig: Rig) -> str:
    """Serialise a rig back to TOML (docs/RIG.md layout)."""

    def fmt(v: NDArray[np.float64]) -> str:
        return "[" + ", ".join(f"{x:.9g}" for x in v) + "]"

    lines = [
        "# all lengths in metres, camera frame (x right, y down, z forward)",
        f"name = {rig.name!r}".replace("'", '"'),
        "",
    ]
    for las in rig.lasers:
        lines += ["[[laser]]", f'name = "{las.name}"']
        if las.origin is not None and las.direction is not None:
            lines += [f"origin = {fmt(las.origin)}", f"direction = {fmt(las.direction)}"]
        lines.append(f"color = {color_toml(las.color, las.color_spec)}")
        if las.sigma_origin:
            lines.append(f"sigma_origin = {las.sigma_origin:.9g}")
        if las.sigma_direction:
            lines.append(f"sigma_direction = {las.sigma_direction:.9g}")
        lines.append("")
    for pair in rig.pairs:
        lines += [
            "[[pair]]",
            f'lasers = ["{pair.lasers[0]}", "{pair.lasers[1]}"]',
            f"separation = {pair.separation:.9g}",
            "",
        ]
    return "\n".join(lines)
