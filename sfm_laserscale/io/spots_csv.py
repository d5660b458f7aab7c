"""Laser spots CSV (``--spots`` input and ``spots.csv`` output), docs/OUTPUTS.md.

Columns: ``image,laser,x,y`` required; ``score``, ``sigma_px`` and ``source`` optional
(header case-insensitive, surrounding whitespace ignored; any other column is an error).
x, y are pixels in COLMAP's convention (centre of the top-left pixel is (0.5, 0.5)).
Rows without a ``source`` value are hand-given spots: ``source="manual"``, score 1.0
unless given. Blank lines and lines whose first cell starts with ``#`` are skipped.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path, PurePosixPath, PureWindowsPath

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Spot

logger = logging.getLogger(__name__)

REQUIRED_COLUMNS = ("image", "laser", "x", "y")
OPTIONAL_COLUMNS = ("score", "sigma_px", "source")
WRITE_COLUMNS = ("image", "laser", "x", "y", "score", "sigma_px", "source")
SOURCES = ("detected", "guided", "manual")


def _basename(name: str) -> str:
    """Last component of a POSIX or Windows style path."""
    return PureWindowsPath(PurePosixPath(name).name).name


class _ImageMatcher:
    """Maps a CSV image entry to a model image name.

    Exact name first; otherwise the entry's base name (a path's last component) must equal
    the base name of exactly one model image (``dir/03.jpg`` and ``03.jpg`` both match a model
    image ``03.jpg``; ``03.jpg`` matches a model image ``sub/03.jpg`` if no other image has
    that base name).
    """

    def __init__(self, names: Collection[str]) -> None:
        self.names = set(names)
        self.by_base: dict[str, list[str]] = {}
        for name in sorted(self.names):
            self.by_base.setdefault(_basename(name), []).append(name)

    def match(self, entry: str) -> str | None | list[str]:
        """The model image name, None when none matches, or the candidates when ambiguous."""
        if entry in self.names:
            return entry
        found = self.by_base.get(_basename(entry), [])
        if len(found) == 1:
            return found[0]
        return found or None


def _header(row: list[str], path: Path) -> list[str]:
    """Normalised column names; InputError on missing, unknown or repeated columns."""
    columns = [c.strip().lower() for c in row]
    unknown = [c for c in columns if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    if unknown:
        raise InputError(f"line 1: unknown column(s) {', '.join(map(repr, unknown))} "
                         f"(allowed: {', '.join(REQUIRED_COLUMNS + OPTIONAL_COLUMNS)})", path)
    missing = [c for c in REQUIRED_COLUMNS if c not in columns]
    if missing:
        raise InputError(f"line 1: missing column(s) {', '.join(missing)} "
                         f"(the header must be {','.join(REQUIRED_COLUMNS)})", path)
    if len(set(columns)) != len(columns):
        raise InputError("line 1: a column appears twice", path)
    return columns


def _number(text: str, column: str, line: int, path: Path, default: float | None = None) -> float:
    """A finite float from a cell (``default`` when blank and a default exists)."""
    text = text.strip()
    if not text and default is not None:
        return default
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"line {line}: {column} is not a number: {text!r}", path) from None
    if not math.isfinite(value):
        raise InputError(f"line {line}: {column} is not finite: {text!r}", path)
    return value


def _spot(cells: dict[str, str], line: int, path: Path) -> Spot:
    """One validated Spot from a row's cells."""
    x = _number(cells["x"], "x", line, path)
    y = _number(cells["y"], "y", line, path)
    score = _number(cells.get("score", ""), "score", line, path, default=1.0)
    sigma = _number(cells.get("sigma_px", ""), "sigma_px", line, path, default=0.3)
    source = cells.get("source", "").strip() or "manual"
    if not 0.0 <= score <= 1.0:
        raise InputError(f"line {line}: score must be in [0, 1], got {score!r}", path)
    if sigma <= 0.0:
        raise InputError(f"line {line}: sigma_px must be positive, got {sigma!r}", path)
    if source not in SOURCES:
        raise InputError(f"line {line}: source must be one of {SOURCES}, got {source!r}", path)
    return Spot(laser=cells["laser"].strip(), x=x, y=y, score=score, sigma_px=sigma,
                source=source)


def _image_name(entry: str, matcher: _ImageMatcher | None, line: int, path: Path) -> str:
    """The model image a CSV entry names (the entry itself when no names are given)."""
    if not entry:
        raise InputError(f"line {line}: empty image name", path)
    if matcher is None:
        return entry
    found = matcher.match(entry)
    if found is None:
        raise InputError(f"line {line}: image {entry!r} is not one of the laser images", path)
    if isinstance(found, list):
        raise InputError(f"line {line}: image {entry!r} is ambiguous: matches "
                         f"{', '.join(found)}; give the full name", path)
    return found


def read_spots_csv(path: str | Path, image_names: Collection[str] | None,
                   laser_names: Collection[str]) -> dict[str, list[Spot]]:
    """Read spots per image (keys: model image names; spots in file order); see module doc."""
    path = Path(path)
    if not path.is_file():
        raise InputError("spots file does not exist", path)
    matcher = None if image_names is None else _ImageMatcher(image_names)
    lasers = set(laser_names)
    out: dict[str, list[Spot]] = {}
    seen: dict[tuple[str, str], int] = {}
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            columns = None
            for row in reader:
                if not any(c.strip() for c in row) or row[0].lstrip().startswith("#"):
                    continue
                if columns is None:
                    columns = _header(row, path)
                    continue
                line = reader.line_num
                if len(row) != len(columns):
                    raise InputError(f"line {line}: {len(row)} fields, expected "
                                     f"{len(columns)} ({','.join(columns)})", path)
                cells = dict(zip(columns, row, strict=True))
                image = _image_name(cells["image"].strip(), matcher, line, path)
                spot = _spot(cells, line, path)
                if spot.laser not in lasers:
                    raise InputError(f"line {line}: laser {spot.laser!r} is not in the rig "
                                     f"({', '.join(sorted(lasers))})", path)
                if (image, spot.laser) in seen:
                    raise InputError(f"line {line}: image {image!r} laser {spot.laser!r} "
                                     f"already given on line {seen[image, spot.laser]}", path)
                seen[image, spot.laser] = line
                out.setdefault(image, []).append(spot)
    except UnicodeDecodeError as exc:
        raise InputError(f"not a UTF-8 text file: {exc}", path) from exc
    except csv.Error as exc:
        raise InputError(f"bad CSV: {exc}", path) from exc
    if columns is None:
        raise InputError(f"empty spots file (expected a header {','.join(REQUIRED_COLUMNS)})",
                         path)
    logger.info("read %d spots for %d images from %s", len(seen), len(out), path)
    return out


def write_spots_csv(path: str | Path, spots_by_image: Mapping[str, Sequence[Spot]]) -> None:
    """Write image,laser,x,y,score,sigma_px,source (floats in repr: reads back exactly)."""
    with open(Path(path), "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(WRITE_COLUMNS)
        for image, spots in spots_by_image.items():
            for s in spots:
                # float(...) first: repr of a numpy scalar would be 'np.float64(...)'
                writer.writerow([image, s.laser, repr(float(s.x)), repr(float(s.y)),
                                 repr(float(s.score)), repr(float(s.sigma_px)), s.source])
