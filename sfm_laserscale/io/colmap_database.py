"""Keypoints and SIFT descriptors from a COLMAP database, read without ever modifying it.

``pycolmap.Database.open`` upgrades an old schema in place (docs/DESIGN.md §6), and even SQLite's
read-only mode writes the ``-shm`` index of a WAL database beside the file. So:

- no pending journal (``-wal`` / ``-journal`` absent or empty; the usual case, and the
  fixture's): the file holds every committed row, open it with ``immutable=1``: SQLite then
  takes no locks and creates or writes no file at all;
- otherwise (a WAL with frames not yet checkpointed, or a hot journal): copy the database
  and its journal into a private temporary folder and read the copy, where SQLite may
  recover the WAL / roll back the journal freely.

Both schemas work: COLMAP 3.x (no rigs/frames tables) and COLMAP/pycolmap 4.x (a ``type``
column in ``descriptors``).
"""

from __future__ import annotations

import logging
import shutil
import sqlite3
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from contextlib import closing, contextmanager
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import ImageFeatures

logger = logging.getLogger(__name__)

_SQLITE_MAGIC = b"SQLite format 3\x00"
_JOURNALS = ("-wal", "-journal")
_REQUIRED_TABLES = ("images", "keypoints", "descriptors")
_SIFT_TYPES = (-1, 0)  # FeatureExtractorType UNDEFINED (legacy) and SIFT in COLMAP 4.x


def _check_file(path: Path) -> None:
    """The path is an existing SQLite 3 file (InputError otherwise)."""
    if not path.exists():
        raise InputError("COLMAP database not found", path)
    if not path.is_file():
        raise InputError("not a file (expected a COLMAP database)", path)
    try:
        with path.open("rb") as f:
            magic = f.read(len(_SQLITE_MAGIC))
    except OSError as e:
        raise InputError(f"cannot read COLMAP database: {e.strerror}", path) from e
    if magic != _SQLITE_MAGIC:
        raise InputError("not a SQLite database (expected a COLMAP database)", path)


def _pending_journals(path: Path) -> list[Path]:
    """Non-empty ``-wal`` / ``-journal`` files beside the database."""
    found = [path.with_name(path.name + suffix) for suffix in _JOURNALS]
    return [p for p in found if p.is_file() and p.stat().st_size > 0]


@contextmanager
def open_database_readonly(db_path: str | Path) -> Iterator[sqlite3.Connection]:
    """A read-only SQLite connection that sees every committed row and writes nothing
    beside ``db_path`` (see the module docstring)."""
    path = Path(db_path)
    _check_file(path)
    journals = _pending_journals(path)
    if not journals:
        uri = f"{path.resolve().as_uri()}?mode=ro&immutable=1"
        with closing(sqlite3.connect(uri, uri=True)) as con:
            yield con
        return
    logger.info("%s has a pending %s: reading a temporary copy", path,
                ", ".join(p.name for p in journals))
    with tempfile.TemporaryDirectory(prefix="sfm_laserscale_db_") as tmp:
        copy = Path(tmp) / "database.db"
        try:
            shutil.copyfile(path, copy)
            for j in journals:
                shutil.copyfile(j, Path(tmp) / (copy.name + j.name[len(path.name):]))
        except OSError as e:
            raise InputError(f"cannot copy the COLMAP database: {e.strerror}", path) from e
        with closing(sqlite3.connect(copy)) as con:
            yield con


def _tables(con: sqlite3.Connection) -> dict[str, set[str]]:
    """Table name -> column names."""
    names = [r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")]
    quoted = {n: n.replace('"', '""') for n in names}
    return {n: {r[1] for r in con.execute(f'PRAGMA table_info("{q}")')} for n, q in quoted.items()}


def _keypoints(row: tuple[int, int, bytes | None] | None, name: str,
               path: Path) -> NDArray[np.float64]:
    """(N, 2) float64 x, y (COLMAP pixel convention) from a keypoints row."""
    if row is None:
        raise InputError(f"image {name!r} has no keypoints in the database", path)
    rows, cols, blob = row
    blob = blob or b""
    if cols not in (2, 4, 6) or len(blob) != 4 * rows * cols:
        raise InputError(
            f"corrupt keypoints of image {name!r}: {rows}x{cols} float32 expected "
            f"({4 * rows * cols} bytes), blob has {len(blob)} bytes", path)
    kp = np.frombuffer(blob, dtype="<f4").reshape(rows, cols)
    return kp[:, :2].astype(np.float64)


def _descriptors(row: tuple[int, int, int, bytes | None] | None, name: str,
                 path: Path) -> NDArray[np.uint8]:
    """(N, 128) uint8 SIFT descriptors from a descriptors row (type, rows, cols, data)."""
    if row is None:
        raise InputError(f"image {name!r} has no descriptors in the database", path)
    dtype, rows, cols, blob = row
    blob = blob or b""
    if dtype not in _SIFT_TYPES:
        raise InputError(f"descriptors of image {name!r} are not SIFT (type {dtype})", path)
    if cols != 128 or len(blob) != rows * cols:
        raise InputError(
            f"corrupt descriptors of image {name!r}: {rows}x128 uint8 expected, found "
            f"{rows}x{cols} and {len(blob)} bytes", path)
    return np.frombuffer(blob, dtype=np.uint8).reshape(rows, 128).copy()


def _catalogue(con: sqlite3.Connection, path: Path,
               image_names: Iterable[str] | None) -> tuple[list[str], dict[str, int], str]:
    """(image names to read, name -> image_id, descriptor type column) of a database."""
    tables = _tables(con)
    missing = [t for t in _REQUIRED_TABLES if t not in tables]
    if missing:
        raise InputError(f"not a COLMAP database with features: no table {', '.join(missing)}",
                         path)
    type_col = "type" if "type" in tables["descriptors"] else "-1"
    ids = dict(con.execute("SELECT name, image_id FROM images").fetchall())
    if image_names is None:
        names = [r[0] for r in con.execute(
            "SELECT images.name FROM images JOIN keypoints USING (image_id) "
            "JOIN descriptors USING (image_id) ORDER BY images.image_id")]
    else:
        names = list(image_names)
        unknown = [n for n in names if n not in ids]
        if unknown:
            shown = ", ".join(repr(n) for n in unknown[:5])
            more = f" and {len(unknown) - 5} more" if len(unknown) > 5 else ""
            raise InputError(f"image(s) not in the database: {shown}{more}", path)
    return names, ids, type_col


class DatabaseFeatures(Mapping[str, ImageFeatures]):
    """Image name -> keypoints and SIFT descriptors, read from an open database on each
    access: one image's features in memory at a time (``open_database_features``)."""

    def __init__(self, con: sqlite3.Connection, path: Path,
                 image_names: Iterable[str] | None) -> None:
        self._con, self._path = con, path
        self._names, self._ids, self._type_col = _catalogue(con, path, image_names)
        self._known = set(self._names)

    def __getitem__(self, name: str) -> ImageFeatures:
        if name not in self._known:
            raise KeyError(name)
        try:
            return self._read(name, self._ids[name])
        except sqlite3.DatabaseError as e:
            raise InputError(f"cannot read COLMAP database: {e}", self._path) from e

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def _read(self, name: str, image_id: int) -> ImageFeatures:
        con, path = self._con, self._path
        kp = _keypoints(con.execute("SELECT rows, cols, data FROM keypoints WHERE image_id=?",
                                    (image_id,)).fetchone(), name, path)
        desc = _descriptors(con.execute(
            f"SELECT {self._type_col}, rows, cols, data FROM descriptors WHERE image_id=?",
            (image_id,)).fetchone(), name, path)
        if len(kp) != len(desc):
            raise InputError(f"image {name!r} has {len(kp)} keypoints but {len(desc)} "
                             "descriptors", path)
        return ImageFeatures(kp, desc)


@contextmanager
def open_database_features(db_path: str | Path, image_names: Iterable[str] | None = None
                           ) -> Iterator[DatabaseFeatures]:
    """The features of the named images (or all with features) as a lazy mapping, valid
    inside the ``with`` block; the database (and its folder) is never written."""
    path = Path(db_path)
    try:
        with open_database_readonly(path) as con:
            features = DatabaseFeatures(con, path, image_names)
            yield features
    except sqlite3.DatabaseError as e:
        raise InputError(f"cannot read COLMAP database: {e}", path) from e


def read_database_features(db_path: str | Path,
                           image_names: Iterable[str] | None = None) -> dict[str, ImageFeatures]:
    """Image name -> keypoints (x, y) and SIFT descriptors, for the named images or all with
    features; the database (and its folder) is never written."""
    with open_database_features(db_path, image_names) as lazy:
        features = dict(lazy.items())
    logger.info("read features of %d images from %s", len(features), db_path)
    return features
