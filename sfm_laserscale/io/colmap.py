"""COLMAP sparse models: read (binary or text, COLMAP 3.x and 4.x), write, rescale losslessly.

Formats (little-endian binary, as COLMAP's ``reconstruction_io_binary.cc`` writes them):

- ``cameras.bin``: u64 count; per camera u32 id, i32 model id, u64 width, u64 height,
  f64 params[n(model)].
- ``images.bin``: u64 count; per image u32 id, f64 qw qx qy qz tx ty tz (cam_from_world),
  u32 camera id, NUL-terminated name, u64 n; n × (f64 x, f64 y, u64 point3D id).
- ``points3D.bin``: u64 count; per point u64 id, f64 xyz, u8 rgb, f64 error, u64 track
  length L; L × (u32 image id, u32 point2D index).
- COLMAP 4.x also writes ``rigs`` (sensor_from_rig poses) and ``frames`` (rig_from_world
  poses). ``images`` still holds every image's composed cam_from_world and camera id, so
  reading ignores rigs/frames; rescaling scales their translations too.

The readers are written here with ``struct``/numpy rather than pycolmap so that every
problem becomes one clear ``InputError`` line and rescaled copies are byte-for-byte lossless.
"""

from __future__ import annotations

import array
import logging
import re
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pycolmap
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.geometry import rotmat_from_qvec
from sfm_laserscale.model import (
    CAMERA_MODEL_IDS,
    CAMERA_MODEL_NAMES,
    CAMERA_MODEL_NUM_PARAMS,
    INVALID_POINT3D_ID,
    Camera,
    Image,
    Pose,
    SparseModel,
)

logger = logging.getLogger(__name__)

MODEL_STEMS = ("cameras", "images", "points3D")
_FORMATS = {".bin": "colmap-binary", ".txt": "colmap-text"}

_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
_U8 = struct.Struct("<B")
_RIG_HEAD = struct.Struct("<II")  # rig_id, number of sensors
_CAMERA_HEAD = struct.Struct("<IiQQ")  # camera_id, model_id, width, height
_IMAGE_HEAD = struct.Struct("<I7dI")  # image_id, qw qx qy qz tx ty tz, camera_id
_IMAGE_TVEC_AT = 4 + 4 * 8  # byte offset of tx inside an images.bin record
_POINT_HEAD_SIZE = 51  # u64 id, 3 f64 xyz, 3 u8 rgb, f64 error, u64 track length
_POINT_TRACK_LEN_AT = 43
_OBS_DTYPE = np.dtype([("x", "<f8"), ("y", "<f8"), ("point3D_id", "<u8")])  # 24 bytes
_TRACK_DTYPE = np.dtype([("image_id", "<u4"), ("point2D_idx", "<u4")])  # 8 bytes
_POINT_HEAD_DTYPE = np.dtype(
    [("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8"),
     ("track_length", "<u8")]
)  # packed: 51 bytes
_CHUNK_ROWS = 1 << 16  # rows per gather/scatter block (bounds the index matrices' memory)
_TOKEN = re.compile(rb"\S+")
_MAX_POINT_ID = 2**64 - 1  # exclusive: 2^64 - 1 is INVALID_POINT3D_ID

I64 = NDArray[np.int64]
F64 = NDArray[np.float64]
T = TypeVar("T")


# --------------------------------------------------------------------------- camera models


@cache
def _pycolmap_models() -> dict[str, tuple[int, int]]:
    """Model name -> (id, number of params) for every model pycolmap knows."""
    table: dict[str, tuple[int, int]] = {}
    for name, model_id in pycolmap.CameraModelId.__members__.items():
        if name == "INVALID":
            continue
        try:
            cam = pycolmap.Camera.create_from_model_id(0, model_id, 1.0, 1, 1)
            table[name] = (int(model_id), len(cam.params))
        except Exception:  # a model pycolmap cannot build stays unknown
            continue
    return table


def camera_model_num_params(name: str) -> int | None:
    """Number of parameters of a COLMAP camera model, or None if unknown."""
    if name in CAMERA_MODEL_NUM_PARAMS:
        return CAMERA_MODEL_NUM_PARAMS[name]
    entry = _pycolmap_models().get(name)  # newer models (e.g. SIMPLE_FISHEYE) than model.py
    return None if entry is None else entry[1]


def camera_model_name(model_id: int) -> str | None:
    """COLMAP camera model name for a binary model id, or None if unknown."""
    if model_id in CAMERA_MODEL_NAMES:
        return CAMERA_MODEL_NAMES[model_id]
    for name, (mid, _) in _pycolmap_models().items():
        if mid == model_id:
            return name
    return None


def _camera_model_id(name: str) -> int:
    """Binary model id of a camera model name (ValueError if unknown)."""
    if name in CAMERA_MODEL_IDS:
        return CAMERA_MODEL_IDS[name]
    if name in _pycolmap_models():
        return _pycolmap_models()[name][0]
    raise ValueError(f"unknown COLMAP camera model {name!r}")


# --------------------------------------------------------------------------- folder layout


def _existing(folder: Path, suffix: str) -> list[str]:
    return [s for s in MODEL_STEMS if (folder / f"{s}{suffix}").is_file()]


def detect_colmap_format(path: str | Path) -> str:
    """``"colmap-binary"`` or ``"colmap-text"`` for a model folder (binary wins if both)."""
    folder = Path(path)
    if not folder.exists():
        raise InputError("COLMAP model folder not found", folder)
    if not folder.is_dir():
        raise InputError(
            "not a folder (expected a COLMAP model folder with cameras/images/points3D "
            ".bin or .txt)", folder)
    found = {suffix: _existing(folder, suffix) for suffix in _FORMATS}
    for suffix, fmt in _FORMATS.items():
        if len(found[suffix]) == len(MODEL_STEMS):
            return fmt
    suffix = max(_FORMATS, key=lambda k: len(found[k]))
    if found[suffix]:
        missing = [f"{s}{suffix}" for s in MODEL_STEMS if s not in found[suffix]]
        raise InputError(f"incomplete COLMAP model: missing {', '.join(missing)}", folder)
    hint = [p.name for p in sorted(folder.iterdir()) if p.is_dir() and _is_model_dir(p)]
    more = f" (a model is in subfolder {hint[0]!r})" if hint else ""
    raise InputError(
        f"no COLMAP model here: cameras, images and points3D .bin or .txt not found{more}",
        folder)


def _is_model_dir(folder: Path) -> bool:
    return any(len(_existing(folder, s)) == len(MODEL_STEMS) for s in _FORMATS)


# --------------------------------------------------------------------------- byte helpers


def _gather_rows(u8: NDArray[np.uint8], starts: I64, width: int) -> NDArray[np.uint8]:
    """(n, width) bytes copied from ``u8[starts[i] : starts[i] + width]`` (vectorised)."""
    out = np.empty((len(starts), width), dtype=np.uint8)
    cols = np.arange(width, dtype=np.int64)
    for a in range(0, len(starts), _CHUNK_ROWS):
        out[a:a + _CHUNK_ROWS] = u8[starts[a:a + _CHUNK_ROWS, None] + cols]
    return out


def _scatter_rows(u8: NDArray[np.uint8], starts: I64, rows: NDArray[np.uint8]) -> None:
    """Write ``rows[i]`` (n, width) bytes at ``u8[starts[i]:]`` (vectorised)."""
    cols = np.arange(rows.shape[1], dtype=np.int64)
    for a in range(0, len(starts), _CHUNK_ROWS):
        u8[starts[a:a + _CHUNK_ROWS, None] + cols] = rows[a:a + _CHUNK_ROWS]


def _scale_f64_triplets(out: bytearray, starts: I64, scale: float) -> None:
    """Multiply in place the three little-endian doubles at each byte offset in ``starts``."""
    if len(starts) == 0:
        return
    u8 = np.frombuffer(out, dtype=np.uint8)
    vals = _gather_rows(u8, starts, 24).view("<f8") * scale
    _scatter_rows(u8, starts, np.ascontiguousarray(vals).view(np.uint8).reshape(-1, 24))


class _Cursor:
    """Bounds-checked reads over a binary model file; every failure is an InputError."""

    def __init__(self, data: bytes | bytearray, path: Path) -> None:
        self.data, self.path, self.pos = data, path, 0

    def fail(self, what: str) -> InputError:
        return InputError(
            f"truncated or corrupt file: it ends at byte {len(self.data)} while reading {what}",
            self.path)

    def take(self, n: int, what: str) -> int:
        """Skip n bytes; return where they start."""
        if n < 0 or self.pos + n > len(self.data):
            raise self.fail(what)
        start, self.pos = self.pos, self.pos + n
        return start

    def unpack(self, st: struct.Struct, what: str) -> tuple[Any, ...]:
        return st.unpack_from(self.data, self.take(st.size, what))

    def count(self, what: str, min_record_bytes: int) -> int:
        """Leading u64 record count, checked against the bytes that follow."""
        (n,) = self.unpack(_U64, f"the number of {what}")
        room = (len(self.data) - self.pos) // max(min_record_bytes, 1)
        if n > room:
            raise InputError(
                f"truncated or corrupt file: header says {n} {what} but the file "
                f"({len(self.data)} bytes) can hold at most {room}", self.path)
        return int(n)

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise self.fail(what)
        raw, self.pos = self.data[self.pos:end], end + 1
        return raw.decode("utf-8", errors="surrogateescape")

    def finish(self) -> None:
        extra = len(self.data) - self.pos
        if extra:
            raise InputError(
                f"corrupt file: {extra} unexpected bytes after the last record "
                "(trailing garbage or a wrong record count)", self.path)


# --------------------------------------------------------------------------- binary parsing


@dataclass(frozen=True)
class _ImageRecord:
    image_id: int
    qvec: tuple[float, float, float, float]
    tvec: tuple[float, float, float]
    camera_id: int
    name: str
    start: int  # byte offset of the record
    obs_start: int  # byte offset of the first (x, y, point3D id) observation
    num_points2d: int


#: larger image sides (pixels) are taken for corruption (a flipped high bit of a uint64 width).
_MAX_IMAGE_SIDE = 2**20


def _parse_cameras_bin(data: bytes, path: Path) -> dict[int, Camera]:
    cur = _Cursor(data, path)
    n = cur.count("cameras", _CAMERA_HEAD.size)
    cameras: dict[int, Camera] = {}
    for i in range(n):
        what = f"camera {i + 1} of {n}"
        cam_id, model_id, width, height = cur.unpack(_CAMERA_HEAD, what)
        name = camera_model_name(model_id)
        if name is None:
            raise InputError(f"corrupt file: unknown camera model id {model_id} in {what}", path)
        n_params = camera_model_num_params(name)
        assert n_params is not None  # a known name always has a parameter count
        at = cur.take(8 * n_params, f"the {n_params} parameters of {what} ({name})")
        params = np.frombuffer(data, "<f8", n_params, at).astype(np.float64)
        if not (0 < width <= _MAX_IMAGE_SIDE and 0 < height <= _MAX_IMAGE_SIDE):
            raise InputError(f"corrupt file: {what} has an implausible size {width}x{height}", path)
        if not np.isfinite(params).all():
            raise InputError(f"corrupt file: {what} has non-finite parameters {params}", path)
        _put_unique(cameras, cam_id, Camera(cam_id, name, int(width), int(height), params),
                    "camera", path)
    cur.finish()
    return cameras


def _parse_images_bin(data: bytes | bytearray, path: Path) -> list[_ImageRecord]:
    cur = _Cursor(data, path)
    n = cur.count("images", _IMAGE_HEAD.size + 1 + 8)
    records = []
    for i in range(n):
        what = f"image {i + 1} of {n}"
        start = cur.pos
        image_id, qw, qx, qy, qz, tx, ty, tz, cam_id = cur.unpack(_IMAGE_HEAD, what)
        name = cur.cstring(f"the name of {what}")
        (npts,) = cur.unpack(_U64, f"the number of observations of {what} ({name})")
        obs = cur.take(24 * npts, f"the {npts} observations of {what} ({name})")
        records.append(_ImageRecord(image_id, (qw, qx, qy, qz), (tx, ty, tz), cam_id, name,
                                    start, obs, int(npts)))
    cur.finish()
    return records


def _points3d_offsets(data: bytes | bytearray, path: Path) -> I64:
    """Byte offset of every points3D.bin record: one tight pass over the track lengths.

    Records have variable length, so each offset depends on the previous one; this single
    ``struct`` pass (about 0.5 s per million points) is the only per-point Python loop, all
    field reads and writes are then vectorised.
    """
    cur = _Cursor(data, path)
    n = cur.count("3D points", _POINT_HEAD_SIZE)
    offsets = array.array("q")
    append, unpack, pos = offsets.append, _U64.unpack_from, cur.pos
    try:
        for _ in range(n):
            append(pos)
            pos += _POINT_HEAD_SIZE + 8 * unpack(data, pos + _POINT_TRACK_LEN_AT)[0]
    except (struct.error, OverflowError):
        raise cur.fail(f"3D point {len(offsets)} of {n}") from None
    if pos > len(data):
        raise cur.fail(f"the track of 3D point {n} of {n}")
    cur.pos = pos
    cur.finish()
    return np.frombuffer(offsets, dtype=np.int64).copy()


def _parse_frames_bin(data: bytes | bytearray, path: Path) -> list[int]:
    """Byte offsets of every frame's rig_from_world translation (COLMAP 4.x frames.bin)."""
    cur = _Cursor(data, path)
    n = cur.count("frames", 4 + 4 + 56 + 4)
    t_offsets = []
    for i in range(n):
        what = f"frame {i + 1} of {n}"
        start = cur.take(4 + 4 + 56, what)
        t_offsets.append(start + 8 + 32)
        (n_data,) = cur.unpack(_U32, f"the number of data ids of {what}")
        cur.take(16 * n_data, f"the data ids of {what}")
    cur.finish()
    return t_offsets


def _parse_rigs_bin(data: bytes | bytearray, path: Path) -> list[int]:
    """Byte offsets of every sensor_from_rig translation (COLMAP 4.x rigs.bin)."""
    cur = _Cursor(data, path)
    n = cur.count("rigs", 8)
    t_offsets = []
    for i in range(n):
        what = f"rig {i + 1} of {n}"
        _, n_sensors = cur.unpack(_RIG_HEAD, what)
        if n_sensors > 0:
            cur.take(8, f"the reference sensor of {what}")
        for j in range(max(n_sensors - 1, 0)):
            cur.take(8, f"sensor {j + 2} of {what}")
            (has_pose,) = cur.unpack(_U8, f"sensor {j + 2} of {what}")
            if has_pose:
                t_offsets.append(cur.take(56, f"the pose of sensor {j + 2} of {what}") + 32)
    cur.finish()
    return t_offsets


def _read_binary(folder: Path) -> SparseModel:
    cameras = _parse_cameras_bin((folder / "cameras.bin").read_bytes(), folder / "cameras.bin")
    img_path = folder / "images.bin"
    img_data = img_path.read_bytes()
    images: dict[int, Image] = {}
    for r in _parse_images_bin(img_data, img_path):
        obs = np.frombuffer(img_data, _OBS_DTYPE, r.num_points2d, r.obs_start)
        xy = np.column_stack([obs["x"], obs["y"]]).astype(np.float64).reshape(-1, 2)
        pose = _pose(r.qvec, r.tvec, img_path, f"image {r.image_id} ({r.name})")
        image = Image(r.image_id, r.name, r.camera_id, pose, xy,
                      obs["point3D_id"].astype(np.uint64))
        _put_unique(images, r.image_id, image, "image", img_path)
    pts_path = folder / "points3D.bin"
    pts_data = pts_path.read_bytes()
    offsets = _points3d_offsets(pts_data, pts_path)
    u8 = np.frombuffer(pts_data, dtype=np.uint8)
    ids = _gather_rows(u8, offsets, 8).view("<u8").reshape(-1).astype(np.uint64)
    xyz = _gather_rows(u8, offsets + 8, 24).view("<f8").reshape(-1, 3).astype(np.float64)
    return SparseModel(cameras, images, ids, xyz, source_format="colmap-binary")


# --------------------------------------------------------------------------- text parsing


def _line_error(path: Path, lineno: int, problem: str, line: bytes) -> InputError:
    text = line.strip().decode("utf-8", errors="replace")
    snippet = text if len(text) <= 60 else text[:57] + "..."
    return InputError(f"line {lineno}: {problem}: {snippet!r}", path)


def _is_data(line: bytes) -> bool:
    s = line.strip()
    return bool(s) and not s.startswith(b"#")


def _text_lines(path: Path) -> list[bytes]:
    """Lines of a text file with their line endings (exact bytes)."""
    return path.read_bytes().splitlines(keepends=True)


def _image_lines(lines: Iterable[bytes]) -> Iterator[tuple[int, bytes, str]]:
    """(line number, line, role) for images.txt; role is ``skip``, ``pose`` or ``points``.

    As in COLMAP, the line after a pose line is always its observation line, even if blank.
    """
    after_pose = False
    for lineno, line in enumerate(lines, start=1):
        if after_pose:
            after_pose = False
            yield lineno, line, "points"
        elif _is_data(line):
            after_pose = True
            yield lineno, line, "pose"
        else:
            yield lineno, line, "skip"


def _parse_camera_line(line: bytes, path: Path, lineno: int) -> Camera:
    tok = line.split()
    try:
        cam_id, model = int(tok[0]), tok[1].decode("ascii")
        width, height = int(tok[2]), int(tok[3])
        params = np.array([float(t) for t in tok[4:]], dtype=np.float64)
    except (IndexError, ValueError, UnicodeDecodeError):
        raise _line_error(path, lineno, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]",
                          line) from None
    if not (0 <= cam_id < 2**32 and 0 < width <= _MAX_IMAGE_SIDE
            and 0 < height <= _MAX_IMAGE_SIDE and np.isfinite(params).all()):
        raise _line_error(path, lineno, "CAMERA_ID, WIDTH, HEIGHT or a parameter out of range",
                          line)
    n_params = camera_model_num_params(model)
    if n_params is None:
        raise _line_error(path, lineno, f"unknown camera model {model!r}", line)
    if len(params) != n_params:
        raise _line_error(
            path, lineno, f"{model} needs {n_params} parameters, found {len(params)}", line)
    return Camera(cam_id, model, width, height, params)


def _read_cameras_text(path: Path) -> dict[int, Camera]:
    cameras: dict[int, Camera] = {}
    for lineno, line in enumerate(_text_lines(path), start=1):
        if _is_data(line):
            cam = _parse_camera_line(line, path, lineno)
            _put_unique(cameras, cam.camera_id, cam, "camera", path, lineno)
    return cameras


def _parse_pose_line(line: bytes, path: Path, lineno: int) -> tuple[int, Pose, int, str]:
    tok = line.split(maxsplit=9)
    try:
        image_id, camera_id = int(tok[0]), int(tok[8])
        q = tuple(float(v) for v in tok[1:5])
        t = tuple(float(v) for v in tok[5:8])
        name = tok[9].strip().decode("utf-8", errors="surrogateescape")
    except (IndexError, ValueError):
        raise _line_error(path, lineno, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME",
                          line) from None
    if not (0 <= image_id < 2**32 and 0 <= camera_id < 2**32):
        raise _line_error(path, lineno, "IMAGE_ID or CAMERA_ID out of range", line)
    return image_id, _pose(q, t, path, f"line {lineno}"), camera_id, name


def _parse_points2d_line(line: bytes, path: Path, lineno: int) -> tuple[F64, NDArray[np.uint64]]:
    tok = line.split()
    if len(tok) % 3:
        raise _line_error(path, lineno, "expected (X Y POINT3D_ID) triplets", line)
    try:
        arr = np.array(tok, dtype=np.bytes_).reshape(-1, 3)
        xy = arr[:, :2].astype(np.float64)
        ids = arr[:, 2].astype(np.int64)  # -1 (no 3D point) becomes 2^64 - 1 below
    except (ValueError, OverflowError):
        raise _line_error(path, lineno, "cannot parse (X Y POINT3D_ID) triplets", line) from None
    if np.any(ids < -1):
        raise _line_error(path, lineno, "negative POINT3D_ID other than -1", line)
    return xy.reshape(-1, 2), ids.view(np.uint64)


def _read_images_text(path: Path) -> dict[int, Image]:
    lines = _text_lines(path)
    images: dict[int, Image] = {}
    head: tuple[int, Pose, int, str, int] | None = None
    for lineno, line, kind in _image_lines(lines):
        if kind == "pose":
            head = (*_parse_pose_line(line, path, lineno), lineno)
        elif kind == "points":
            assert head is not None  # a points line always follows a pose line
            xy, ids = _parse_points2d_line(line, path, lineno)
            _add_text_image(images, head, xy, ids, path)
            head = None
    if head is not None:  # last pose line without an observation line: no observations
        _add_text_image(images, head, np.zeros((0, 2)), np.zeros(0, np.uint64), path)
    return images


def _add_text_image(images: dict[int, Image], head: tuple[int, Pose, int, str, int],
                    xy: F64, ids: NDArray[np.uint64], path: Path) -> None:
    image_id, pose, camera_id, name, lineno = head
    _put_unique(images, image_id, Image(image_id, name, camera_id, pose, xy, ids),
                "image", path, lineno)


def _parse_point_line(line: bytes, path: Path, lineno: int) -> tuple[int, float, float, float]:
    tok = line.split()
    ok = len(tok) >= 8 and len(tok) % 2 == 0 and b"".join(tok[4:7] + tok[8:]).isdigit()
    try:  # R G B and the track are unsigned integers (checked above), ERROR any number
        pid, x, y, z = int(tok[0]), float(tok[1]), float(tok[2]), float(tok[3])
        float(tok[7])
    except (IndexError, ValueError):
        ok = False
    if not ok:
        raise _line_error(path, lineno, "expected POINT3D_ID X Y Z R G B ERROR TRACK[] "
                          "(IMAGE_ID POINT2D_IDX pairs)", line)
    if not 0 <= pid < _MAX_POINT_ID:
        raise _line_error(path, lineno, "POINT3D_ID out of range", line)
    return pid, x, y, z


def _read_points_text(path: Path) -> tuple[NDArray[np.uint64], F64]:
    rows = [_parse_point_line(line, path, n)
            for n, line in enumerate(_text_lines(path), start=1) if _is_data(line)]
    if not rows:
        return np.zeros(0, np.uint64), np.zeros((0, 3))
    ids = np.array([r[0] for r in rows], dtype=np.uint64)
    xyz = np.array([r[1:] for r in rows], dtype=np.float64).reshape(-1, 3)
    return ids, xyz


def _read_text(folder: Path) -> SparseModel:
    cameras = _read_cameras_text(folder / "cameras.txt")
    images = _read_images_text(folder / "images.txt")
    ids, xyz = _read_points_text(folder / "points3D.txt")
    return SparseModel(cameras, images, ids, xyz, source_format="colmap-text")


# --------------------------------------------------------------------------- checks


def _put_unique(table: dict[int, T], key: int, value: T, what: str, path: Path,
                lineno: int | None = None) -> None:
    if key in table:
        where = f"line {lineno}: " if lineno else ""
        raise InputError(f"{where}duplicate {what} id {key}", path)
    table[key] = value


def _pose(q: tuple[float, ...], t: tuple[float, ...], path: Path, where: str) -> Pose:
    qv, tv = np.array(q, dtype=np.float64), np.array(t, dtype=np.float64)
    norm = float(np.linalg.norm(qv))
    if not (np.all(np.isfinite(qv)) and np.all(np.isfinite(tv))) or norm < 1e-12:
        raise InputError(f"{where}: invalid pose (quaternion {q}, translation {t})", path)
    return Pose(rotmat_from_qvec(qv), tv)


def _check_model(model: SparseModel, folder: Path, suffix: str) -> None:
    """Cross-file consistency: cameras exist, observed 3D points exist, model not empty."""
    images_file = folder / f"images{suffix}"
    if not model.images:
        raise InputError("empty model: no registered images", images_file)
    known = np.sort(model.point3D_ids)  # (np.unique hashes: 30x slower at 1M points)
    if np.any(known[1:] == known[:-1]):
        raise InputError("duplicate 3D point ids", folder / f"points3D{suffix}")
    for im in model.images.values():
        if im.camera_id not in model.cameras:
            raise InputError(
                f"image {im.image_id} ({im.name}) refers to camera {im.camera_id}, "
                f"which is not in cameras{suffix}", images_file)
        obs = im.point3D_ids[im.point3D_ids != INVALID_POINT3D_ID]
        pos = np.minimum(np.searchsorted(known, obs), max(len(known) - 1, 0))
        bad = known[pos] != obs if len(known) else np.ones(len(obs), dtype=bool)
        if np.any(bad):
            raise InputError(
                f"image {im.image_id} ({im.name}) observes 3D point {int(obs[bad][0])}, "
                f"which is not in points3D{suffix}", images_file)


def read_colmap_model(path: str | Path) -> SparseModel:
    """Read a COLMAP sparse model folder (binary or text, COLMAP 3.x or 4.x)."""
    folder = Path(path)
    fmt = detect_colmap_format(folder)
    suffix = ".bin" if fmt == "colmap-binary" else ".txt"
    try:
        model = _read_binary(folder) if suffix == ".bin" else _read_text(folder)
    except OSError as e:
        raise InputError(f"cannot read model file: {e.strerror}", e.filename or folder) from e
    _check_model(model, folder, suffix)
    logger.info("read %s model %s: %d cameras, %d images, %d points", fmt, folder,
                len(model.cameras), len(model.images), len(model.points_xyz))
    return model


# --------------------------------------------------------------------------- hold-out


def model_without_images(model: SparseModel, names: Iterable[str]) -> SparseModel:
    """The model without the named images; 3D points left with < 2 observations are removed
    (and their remaining observations become INVALID_POINT3D_ID)."""
    drop = set(names)
    present = {im.name for im in model.images.values()}
    missing = sorted(drop - present)
    if missing:
        raise InputError(f"cannot hold out images not in the model: {', '.join(missing)}")
    kept = {k: im for k, im in model.images.items() if im.name not in drop}
    obs = [im.point3D_ids[im.point3D_ids != INVALID_POINT3D_ID] for im in kept.values()]
    all_obs = np.concatenate(obs) if obs else np.zeros(0, np.uint64)
    uniq, counts = np.unique(all_obs, return_counts=True)
    keep_ids = uniq[counts >= 2]
    keep_rows = np.isin(model.point3D_ids, keep_ids)
    images = {}
    for k, im in kept.items():
        ids = im.point3D_ids.copy()
        ids[~np.isin(ids, model.point3D_ids[keep_rows])] = INVALID_POINT3D_ID
        images[k] = Image(im.image_id, im.name, im.camera_id, im.cam_from_world,
                          im.xy_px.copy(), ids)
    return SparseModel(dict(model.cameras), images, model.point3D_ids[keep_rows].copy(),
                       model.points_xyz[keep_rows].copy(), source_format=model.source_format)
