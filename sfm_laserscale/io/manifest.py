"""The ``batch`` manifest: a CSV with a header, one model per row (docs/BATCH.md).

Columns: ``name`` (unique; the model's output folder), ``laser_images`` (files and/or folders,
several separated by ``;``) and ``rig`` are required; the model is one of ``model`` + ``mesh``
(+ optional ``database``, ``images``, ``features``), ``colmap_workspace`` or ``openmvg_project``;
``spots`` and ``method`` (fcm | pcm | all) are optional. Paths are relative to the manifest's
folder. Everything is checked before any work: a bad manifest raises one InputError naming the
manifest, the row (its line in the file) and the column.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

from sfm_laserscale.errors import InputError

REQUIRED = ("name", "laser_images", "rig")
PATHS = ("model", "mesh", "database", "images", "features", "spots", "colmap_workspace",
         "openmvg_project")
COLUMNS = (*REQUIRED, *PATHS, "method")
METHODS = ("fcm", "pcm", "all")
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]*$")


@dataclass(frozen=True)
class ManifestRow:
    """One model of the manifest, paths resolved against the manifest's folder."""

    line: int  # its line in the file (the header is line 1)
    name: str
    laser_images: tuple[Path, ...]
    rig: Path
    model: Path | None = None
    mesh: Path | None = None
    database: Path | None = None
    images: Path | None = None
    features: Path | None = None
    spots: Path | None = None
    colmap_workspace: Path | None = None
    openmvg_project: Path | None = None
    method: str | None = None


def _error(manifest: Path, line: int, column: str | None, problem: str) -> InputError:
    where = f"line {line} (row {line - 1})" if line > 1 else "line 1 (header)"
    col = f", column {column!r}" if column else ""
    return InputError(f"{where}{col}: {problem}", manifest)


def _read_rows(manifest: Path) -> tuple[list[str], list[tuple[int, dict[str, str]]]]:
    """Header and (line, row) pairs; InputError when unreadable or malformed."""
    try:
        text = manifest.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError("manifest not found", manifest) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the manifest: {exc}", manifest) from None
    reader = csv.reader(text.splitlines())
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise InputError("empty manifest (a header and one row per model expected)",
                         manifest) from None
    except csv.Error as exc:
        raise _error(manifest, 1, None, f"not CSV ({exc})") from None
    rows: list[tuple[int, dict[str, str]]] = []
    try:
        for fields in reader:
            line = reader.line_num
            if not any(f.strip() for f in fields):
                continue
            if len(fields) > len(header):
                raise _error(manifest, line, None, f"{len(fields)} fields for {len(header)} "
                             "columns")
            rows.append((line, {h: (fields[k].strip() if k < len(fields) else "")
                                for k, h in enumerate(header)}))
    except csv.Error as exc:
        raise _error(manifest, reader.line_num, None, f"not CSV ({exc})") from None
    return header, rows


def _check_header(manifest: Path, header: list[str]) -> None:
    for column in REQUIRED:
        if column not in header:
            raise _error(manifest, 1, column, "missing column (required: "
                         f"{', '.join(REQUIRED)})")
    for column in header:
        if column not in COLUMNS:
            raise _error(manifest, 1, column, f"unknown column (known: {', '.join(COLUMNS)})")
    dupes = sorted({h for h in header if header.count(h) > 1})
    if dupes:
        raise _error(manifest, 1, dupes[0], "column given twice")


def _path(manifest: Path, line: int, column: str, value: str, kind: str) -> Path:
    """The path of one field, resolved and checked to exist (``kind``: file | dir | any)."""
    path = Path(value).expanduser()
    path = path if path.is_absolute() else manifest.parent / path
    ok = {"file": path.is_file(), "dir": path.is_dir(), "any": path.exists()}[kind]
    if not ok:
        what = {"file": "file", "dir": "folder", "any": "file or folder"}[kind]
        raise _error(manifest, line, column, f"{what} not found: {path}")
    return path


def _model_fields(manifest: Path, line: int, row: dict[str, str]) -> dict[str, Path | None]:
    given = [c for c in ("model", "colmap_workspace", "openmvg_project") if row.get(c)]
    if len(given) != 1:
        problem = ("no model: give model + mesh, colmap_workspace or openmvg_project"
                   if not given else f"give one model, not {' and '.join(given)}")
        raise _error(manifest, line, given[1] if len(given) > 1 else "model", problem)
    if row.get("model") and not row.get("mesh"):
        raise _error(manifest, line, "mesh", "empty: a model needs its mesh")
    if row.get("mesh") and not row.get("model"):
        raise _error(manifest, line, "model", "empty: a mesh goes with model")
    kinds = {"model": "any", "mesh": "file", "database": "file", "images": "dir",
             "features": "dir", "spots": "file", "colmap_workspace": "dir",
             "openmvg_project": "dir"}
    return {c: (_path(manifest, line, c, row[c], kinds[c]) if row.get(c) else None)
            for c in PATHS}


def _row(manifest: Path, line: int, row: dict[str, str]) -> ManifestRow:
    for column in REQUIRED:
        if not row.get(column):
            raise _error(manifest, line, column, "empty (required)")
    name = row["name"]
    if not _SAFE_NAME.match(name) or name in ("summary.csv", "summary.html"):
        raise _error(manifest, line, "name", f"{name!r} cannot name an output folder (letters, "
                     "digits, '.', '_', '+', '-'; not starting with '.')")
    method = row.get("method") or None
    if method is not None and method not in METHODS:
        raise _error(manifest, line, "method", f"{method!r} is not one of {', '.join(METHODS)}")
    lasers = tuple(_path(manifest, line, "laser_images", v.strip(), "any")
                   for v in row["laser_images"].split(";") if v.strip())
    return ManifestRow(line=line, name=name, laser_images=lasers,
                       rig=_path(manifest, line, "rig", row["rig"], "file"), method=method,
                       **_model_fields(manifest, line, row))


def read_manifest(manifest: Path) -> tuple[ManifestRow, ...]:
    """Every row, checked (InputError naming the row and column of the first problem)."""
    header, raw = _read_rows(manifest)
    _check_header(manifest, header)
    if not raw:
        raise InputError("the manifest has no row (one per model expected)", manifest)
    rows: list[ManifestRow] = []
    first: dict[str, int] = {}
    for line, row in raw:
        parsed = _row(manifest, line, row)
        key = parsed.name.lower()  # one folder per name, on case-insensitive file systems too
        if key in first:
            raise _error(manifest, line, "name", f"duplicate name {parsed.name!r} (first on "
                         f"line {first[key]})")
        first[key] = line
        rows.append(parsed)
    return tuple(rows)
