"""COLMAP sparse models written: a lossless rescaled copy of a model folder
(``write_scaled_colmap_model``: only translations and 3D points change, every other byte is
copied) and a :class:`SparseModel` as a COLMAP 3.x binary or text model. The file layouts are
described in :mod:`sfm_laserscale.io.colmap`, which reads them."""

from __future__ import annotations

import logging
import math
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from itertools import islice
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.colmap import (
    _CAMERA_HEAD,
    _IMAGE_HEAD,
    _IMAGE_TVEC_AT,
    _OBS_DTYPE,
    _POINT_HEAD_DTYPE,
    _POINT_HEAD_SIZE,
    _TOKEN,
    _TRACK_DTYPE,
    _U64,
    _camera_model_id,
    _image_lines,
    _is_data,
    _line_error,
    _parse_frames_bin,
    _parse_images_bin,
    _parse_rigs_bin,
    _points3d_offsets,
    _scale_f64_triplets,
    _scatter_rows,
    detect_colmap_format,
)
from sfm_laserscale.model import INVALID_POINT3D_ID, Image, SparseModel

logger = logging.getLogger(__name__)

I64 = NDArray[np.int64]
F64 = NDArray[np.float64]


# --------------------------------------------------------------------------- lossless rescale


def _check_scale(scale: float) -> float:
    s = float(scale)
    if not math.isfinite(s) or s <= 0:
        raise InputError(f"scale must be a positive finite number, got {scale!r}")
    return s


def _mutable(data: bytes | bytearray) -> bytearray:
    """``data`` itself when it is a bytearray (rescaled in place), else a mutable copy."""
    return data if isinstance(data, bytearray) else bytearray(data)


def _read_mutable(path: Path) -> bytearray:
    """A file's bytes in one mutable buffer (``read_bytes`` then ``bytearray`` holds two)."""
    with path.open("rb") as fh:
        data = bytearray(os.fstat(fh.fileno()).st_size)
        n = fh.readinto(data)
    del data[n:]
    return data


def _scale_images_bin(data: bytes | bytearray, path: Path, s: float) -> bytearray:
    out = _mutable(data)
    starts = np.array([r.start + _IMAGE_TVEC_AT for r in _parse_images_bin(data, path)],
                      dtype=np.int64)
    _scale_f64_triplets(out, starts, s)
    return out


def _scale_points3d_bin(data: bytes | bytearray, path: Path, s: float) -> bytearray:
    out = _mutable(data)
    _scale_f64_triplets(out, _points3d_offsets(data, path) + 8, s)
    return out


def _scale_frames_bin(data: bytes | bytearray, path: Path, s: float) -> bytearray:
    out = _mutable(data)
    _scale_f64_triplets(out, np.array(_parse_frames_bin(data, path), dtype=np.int64), s)
    return out


def _scale_rigs_bin(data: bytes | bytearray, path: Path, s: float) -> bytearray:
    out = _mutable(data)
    _scale_f64_triplets(out, np.array(_parse_rigs_bin(data, path), dtype=np.int64), s)
    return out


def _fmt(v: float) -> bytes:
    """Shortest text that reads back as exactly this double."""
    return repr(float(v)).encode("ascii")


def _scale_tokens(line: bytes, first: int, s: float, path: Path, lineno: int) -> bytes:
    """Scale the 3 whitespace-separated fields at token index ``first..first+2``; keep all
    other bytes (separators, other fields, line ending) as they are."""
    spans = [m.span() for m in islice(_TOKEN.finditer(line), first + 3)]
    if len(spans) < first + 3:
        raise _line_error(path, lineno, f"expected at least {first + 3} fields", line)
    parts, last = [], 0
    for a, b in spans[first:]:
        try:
            v = float(line[a:b])
        except ValueError:
            raise _line_error(path, lineno, f"field {line[a:b]!r} is not a number",
                              line) from None
        parts += [line[last:a], _fmt(v * s)]
        last = b
    parts.append(line[last:])
    return b"".join(parts)


def _scale_text_fixed(first: int) -> Callable[[bytes, Path, float], bytes]:
    """Rescaler for a text file whose data lines hold a translation at token ``first``."""

    def scale(data: bytes, path: Path, s: float) -> bytes:
        out = []
        for lineno, line in enumerate(data.splitlines(keepends=True), start=1):
            out.append(_scale_tokens(line, first, s, path, lineno) if _is_data(line) else line)
        return b"".join(out)

    return scale


def _scale_images_txt(data: bytes, path: Path, s: float) -> bytes:
    lines = data.splitlines(keepends=True)
    out = []
    for lineno, line, kind in _image_lines(lines):
        out.append(_scale_tokens(line, 5, s, path, lineno) if kind == "pose" else line)
    return b"".join(out)


def _rig_translation_tokens(tok: list[bytes], path: Path, lineno: int, line: bytes) -> list[int]:
    """Token indices where each posed sensor's TX starts on a rigs.txt line."""
    try:
        n_sensors, k, firsts = int(tok[1]), 4, []
        for _ in range(max(n_sensors - 1, 0)):
            if tok[k + 2] == b"1":
                firsts.append(k + 3 + 4)
                k += 10
            else:
                k += 3
    except (IndexError, ValueError):
        raise _line_error(path, lineno, "cannot parse rig line", line) from None
    if k > len(tok) or (n_sensors == 0 and len(tok) != 2):
        raise _line_error(path, lineno, "cannot parse rig line", line)
    return firsts


def _scale_rigs_txt(data: bytes, path: Path, s: float) -> bytes:
    out = []
    for lineno, line in enumerate(data.splitlines(keepends=True), start=1):
        if _is_data(line):
            for first in _rig_translation_tokens(line.split(), path, lineno, line):
                line = _scale_tokens(line, first, s, path, lineno)
        out.append(line)
    return b"".join(out)


_RESCALERS: dict[str, Callable[..., bytes | bytearray]] = {  # (data, path, scale)
    "images.bin": _scale_images_bin,
    "points3D.bin": _scale_points3d_bin,
    "frames.bin": _scale_frames_bin,
    "rigs.bin": _scale_rigs_bin,
    "images.txt": _scale_images_txt,
    "points3D.txt": _scale_text_fixed(1),  # POINT3D_ID X Y Z ...
    "frames.txt": _scale_text_fixed(6),  # FRAME_ID RIG_ID QW QX QY QZ TX TY TZ ...
    "rigs.txt": _scale_rigs_txt,
}


def write_scaled_colmap_model(src_dir: str | Path, dst_dir: str | Path, scale: float) -> list[Path]:
    """Copy a model folder with every translation and 3D point multiplied by ``scale``.

    Lossless and in the input's format: only the tvec / xyz doubles (binary) or those
    fields (text, printed with ``repr`` precision) change; every other byte and every other
    file of the folder is copied as is. Model files of both formats are rescaled when a
    folder holds both. Returns the written files.
    """
    src, dst = Path(src_dir), Path(dst_dir)
    s = _check_scale(scale)
    detect_colmap_format(src)
    if dst.exists() and dst.resolve() == src.resolve():
        raise InputError("refusing to write the rescaled model over its source", dst)
    dst.mkdir(parents=True, exist_ok=True)
    written = []
    for f in sorted(src.iterdir()):
        if not f.is_file():
            continue
        target = dst / f.name
        rescale = _RESCALERS.get(f.name)
        if rescale is None:
            shutil.copyfile(f, target)
        else:
            data = _read_mutable(f) if f.suffix == ".bin" else f.read_bytes()
            target.write_bytes(rescale(data, f, s))  # binary files: rescaled in place
            del data
        written.append(target)
    logger.info("wrote model rescaled by %.9g to %s (%d files)", s, dst, len(written))
    return written


# --------------------------------------------------------------------------- writers


@dataclass(frozen=True)
class _Tracks:
    """Every point's track rebuilt from the observations, points in increasing id order."""

    order: I64  # (M,) rows of ``model.points_xyz`` sorted by point id
    lengths: I64  # (M,) track length of point ``order[k]``
    image_ids: NDArray[np.uint32]  # (T,) grouped by k, then sorted by image id, index
    point2d_idx: NDArray[np.uint32]  # (T,)


def _tracks(model: SparseModel) -> _Tracks:
    """Track elements (image id, point2D index) of every 3D point, from the images."""
    order = np.argsort(model.point3D_ids, kind="stable").astype(np.int64)
    sorted_ids = model.point3D_ids[order]
    ks, img, idx = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for im in model.images.values():
        j = np.flatnonzero(im.point3D_ids != INVALID_POINT3D_ID)
        if len(order) == 0 or len(j) == 0:
            continue
        k = np.minimum(np.searchsorted(sorted_ids, im.point3D_ids[j]), len(order) - 1)
        found = sorted_ids[k] == im.point3D_ids[j]
        ks.append(k[found])
        img.append(np.full(int(found.sum()), im.image_id, dtype=np.int64))
        idx.append(j[found])
    k_all, i_all, j_all = np.concatenate(ks), np.concatenate(img), np.concatenate(idx)
    srt = np.lexsort((j_all, i_all, k_all))
    lengths = np.bincount(k_all, minlength=len(order)).astype(np.int64)
    return _Tracks(order, lengths, i_all[srt].astype(np.uint32), j_all[srt].astype(np.uint32))


def _sorted_images(model: SparseModel) -> list[Image]:
    return [model.images[k] for k in sorted(model.images)]


def _qvec_wxyz(R: F64) -> F64:
    """Unit quaternion (w, x, y, z), w >= 0, of rotation matrix R (COLMAP's convention).

    scipy, not ``geometry.qvec_from_rotmat``: that one returns the conjugate quaternion
    (the inverse rotation) at the time of writing.
    """
    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    q = np.array([w, x, y, z], dtype=np.float64)
    return q if q[0] >= 0 else -q


def _qt(im: Image) -> tuple[F64, F64]:
    return _qvec_wxyz(im.cam_from_world.R), np.asarray(im.cam_from_world.t, np.float64)


def write_colmap_model_text(model: SparseModel, dst_dir: str | Path) -> list[Path]:
    """Write ``model`` as a COLMAP 3.x text model (colour 128 grey, error 0); returns files."""
    dst = Path(dst_dir)
    dst.mkdir(parents=True, exist_ok=True)
    cam_lines = ["# Camera list with one line of data per camera:\n",
                 "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n",
                 f"# Number of cameras: {len(model.cameras)}\n"]
    for cid in sorted(model.cameras):
        c = model.cameras[cid]
        params = " ".join(repr(float(p)) for p in c.params)
        cam_lines.append(f"{cid} {c.model} {c.width} {c.height} {params}\n")
    img_lines = ["# Image list with two lines of data per image:\n",
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)\n",
                 f"# Number of images: {len(model.images)}\n"]
    for im in _sorted_images(model):
        q, t = _qt(im)
        pose = " ".join(repr(float(v)) for v in (*q, *t))
        img_lines.append(f"{im.image_id} {pose} {im.camera_id} {im.name}\n")
        ids = im.point3D_ids.astype(np.uint64).view(np.int64)  # 2^64 - 1 prints as -1
        img_lines.append(" ".join(f"{x!r} {y!r} {p}" for x, y, p in zip(
            im.xy_px[:, 0].tolist(), im.xy_px[:, 1].tolist(), ids.tolist(), strict=True)) + "\n")
    tr = _tracks(model)
    ends = np.cumsum(tr.lengths)
    pairs = np.column_stack([tr.image_ids, tr.point2d_idx]).astype(str)
    pt_lines = ["# 3D point list with one line of data per point:\n",
                "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
                f"# Number of points: {len(model.point3D_ids)}\n"]
    for k, row in enumerate(tr.order):
        x, y, z = model.points_xyz[row].tolist()
        track = " ".join(" ".join(p) for p in pairs[ends[k] - tr.lengths[k]:ends[k]])
        pt_lines.append(f"{model.point3D_ids[row]} {x!r} {y!r} {z!r} 128 128 128 0 {track}\n")
    files = {"cameras.txt": cam_lines, "images.txt": img_lines, "points3D.txt": pt_lines}
    for name, lines in files.items():
        (dst / name).write_text("".join(lines), encoding="utf-8", errors="surrogateescape")
    return [dst / name for name in files]


def _cameras_bin(model: SparseModel) -> bytes:
    parts = [_U64.pack(len(model.cameras))]
    for cid in sorted(model.cameras):
        c = model.cameras[cid]
        parts.append(_CAMERA_HEAD.pack(cid, _camera_model_id(c.model), c.width, c.height))
        parts.append(np.asarray(c.params, dtype="<f8").tobytes())
    return b"".join(parts)


def _images_bin(model: SparseModel) -> bytes:
    parts = [_U64.pack(len(model.images))]
    for im in _sorted_images(model):
        q, t = _qt(im)
        parts.append(_IMAGE_HEAD.pack(im.image_id, *q.tolist(), *t.tolist(), im.camera_id))
        parts.append(im.name.encode("utf-8", errors="surrogateescape") + b"\0")
        obs = np.empty(len(im.xy_px), dtype=_OBS_DTYPE)
        obs["x"], obs["y"], obs["point3D_id"] = im.xy_px[:, 0], im.xy_px[:, 1], im.point3D_ids
        parts.append(_U64.pack(len(obs)) + obs.tobytes())
    return b"".join(parts)


def _points3d_bin(model: SparseModel) -> bytes:
    """points3D.bin bytes, records sorted by id, built with vectorised scatters."""
    tr = _tracks(model)
    head = np.zeros(len(tr.order), dtype=_POINT_HEAD_DTYPE)
    head["id"], head["xyz"] = model.point3D_ids[tr.order], model.points_xyz[tr.order]
    head["rgb"], head["track_length"] = 128, tr.lengths
    sizes = _POINT_HEAD_SIZE + 8 * tr.lengths
    starts = 8 + np.cumsum(sizes) - sizes
    out = np.zeros(8 + int(sizes.sum()), dtype=np.uint8)
    out[:8] = np.frombuffer(_U64.pack(len(tr.order)), dtype=np.uint8)
    _scatter_rows(out, starts, head.view(np.uint8).reshape(-1, _POINT_HEAD_SIZE))
    firsts = np.cumsum(tr.lengths) - tr.lengths  # first track element of each point
    rank = np.arange(len(tr.image_ids)) - np.repeat(firsts, tr.lengths)
    elem_at = np.repeat(starts + _POINT_HEAD_SIZE, tr.lengths) + 8 * rank
    track = np.empty(len(tr.image_ids), dtype=_TRACK_DTYPE)
    track["image_id"], track["point2D_idx"] = tr.image_ids, tr.point2d_idx
    _scatter_rows(out, elem_at.astype(np.int64), track.view(np.uint8).reshape(-1, 8))
    return out.tobytes()


def write_colmap_model_binary(model: SparseModel, dst_dir: str | Path) -> list[Path]:
    """Write ``model`` as a COLMAP 3.x binary model (colour 128 grey, error 0); returns files."""
    dst = Path(dst_dir)
    dst.mkdir(parents=True, exist_ok=True)
    files = {"cameras.bin": _cameras_bin(model), "images.bin": _images_bin(model),
             "points3D.bin": _points3d_bin(model)}
    for name, data in files.items():
        (dst / name).write_bytes(data)
    return [dst / name for name in files]
