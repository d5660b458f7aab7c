"""OFF and STL meshes rewritten with only their vertex positions rescaled (OFF text and ASCII
STL: the x y z tokens; binary STL: the triangle corners in float32)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.meshes.common import (
    _COPY_CHUNK,
    _AtomicOutput,
    _bytes_view,
    _scale_xyz_line,
    _xyz_pattern,
)

_STL_VERTEX = _xyz_pattern(rb"vertex[ \t]+")
_OFF_VERTEX = _xyz_pattern(b"")


def _write_scaled_off(src: Path, dst: Path, scale: float) -> list[Path]:
    """OFF/COFF/NOFF/4OFF text: only the x y z of the vertex lines change."""
    lines = src.read_bytes().split(b"\n")
    i, n_vertices = _off_header(lines, src)
    done = 0
    while done < n_vertices:
        if i >= len(lines):
            raise InputError("OFF file ends inside the vertex list (truncated?)", src)
        body = lines[i].split(b"#", 1)[0]
        if body.strip():
            scaled = _scale_xyz_line(body, _OFF_VERTEX, scale, i + 1, src)
            lines[i] = scaled + lines[i][len(body):]
            done += 1
        i += 1
    with _AtomicOutput(dst) as fo:
        fo.write(b"\n".join(lines))
    return [dst]


def _off_header(lines: list[bytes], path: Path) -> tuple[int, int]:
    """(index of the first line after the counts, number of vertices) of a text OFF file."""
    words: list[bytes] = []
    i = 0
    while len(words) < 2 and i < len(lines):  # keyword, then "V F E" (maybe on the same line)
        words += lines[i].split(b"#", 1)[0].split()
        i += 1
    keyword = words[0] if words else b""
    if not keyword.endswith(b"OFF") or keyword.startswith(b"n") or b"BINARY" in b" ".join(words):
        raise InputError("not a text OFF file (or an unsupported nOFF / binary variant)", path)
    counts = words[1:]
    while not counts and i < len(lines):
        counts = lines[i].split(b"#", 1)[0].split()
        i += 1
    try:
        return i, int(counts[0])
    except (IndexError, ValueError) as exc:
        raise InputError("OFF file has no vertex count line", path) from exc


_STL_DTYPE = np.dtype([("normal", "<f4", (3,)), ("xyz", "<f4", (3, 3)), ("attr", "<u2")])


def _write_scaled_stl(src: Path, dst: Path, scale: float) -> list[Path]:
    """STL: binary -> triangle corners scaled (normals, attributes, header kept); ASCII -> text."""
    size = src.stat().st_size
    with open(src, "rb") as fi:
        head = fi.read(84)
    n = struct.unpack_from("<I", head, 80)[0] if len(head) == 84 else -1
    if size == 84 + n * _STL_DTYPE.itemsize:
        with open(src, "rb") as fi, _AtomicOutput(dst) as fo:
            fo.write(fi.read(84))
            rows_per_chunk = _COPY_CHUNK // _STL_DTYPE.itemsize
            for a in range(0, n, rows_per_chunk):
                rows = np.empty(min(rows_per_chunk, n - a), dtype=_STL_DTYPE)
                fi.readinto(_bytes_view(rows))
                rows["xyz"] = rows["xyz"].astype(np.float64) * scale
                fo.write(_bytes_view(rows))
        return [dst]
    if not head.lstrip().startswith(b"solid"):
        raise InputError("not an STL file (neither binary size nor 'solid')", src)
    with open(src, "rb") as fi, _AtomicOutput(dst) as fo:
        for lineno, line in enumerate(fi, 1):
            if line.lstrip()[:6] == b"vertex":
                line = _scale_xyz_line(line, _STL_VERTEX, scale, lineno, src)
            fo.write(line)
    return [dst]
