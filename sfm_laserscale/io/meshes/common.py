"""What the mesh formats share: the progress callback, streamed byte copies, atomic output
files, side files (textures, MTL), text vertex lines, fan triangulation."""

from __future__ import annotations

import io
import logging
import os
import re
import shutil
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError

logger = logging.getLogger(__name__)

_COPY_CHUNK = 1 << 24  # bytes per read/write when streaming

#: Progress callback of the mesh writers: called with the number of bytes of the source mesh
#: processed since the previous call (the calls of one write add up to the file's size).
Progress = Callable[[int], None]


def _no_progress(nbytes: int) -> None:
    """The default progress callback: nothing."""


# ----------------------------------------------------------------------------- fan triangulation


def _fan_triangulate(
    groups: Sequence[tuple[NDArray[np.int64] | None, NDArray[Any]]], n_rows: int, path: Path
) -> NDArray[Any]:
    """(T, 3) triangles in face order from polygon groups [(row indices, (k, n) indices)].

    Row indices None: the group is every row in order. All-triangle input is returned as is.
    """
    if len(groups) == 1 and (groups[0][0] is None or len(groups[0][0]) == n_rows):
        polys = groups[0][1]
        n = polys.shape[1]
        if n == 3:
            return polys
        if n > 3:  # one polygon size everywhere: (F, n - 2, 3) fans without fancy indexing
            tris = np.empty((len(polys), n - 2, 3), dtype=polys.dtype)
            tris[:, :, 0] = polys[:, :1]
            tris[:, :, 1] = polys[:, 1:-1]
            tris[:, :, 2] = polys[:, 2:]
            return tris.reshape(-1, 3)
    sizes = np.zeros(n_rows, dtype=np.int64)
    for rows, polys in groups:
        sizes[slice(None) if rows is None else rows] = polys.shape[1]
    n_tri = np.maximum(sizes - 2, 0)
    if (sizes < 3).any():
        logger.warning("%s: skipped %d faces with fewer than 3 vertices",
                       path, int((sizes < 3).sum()))
    first = np.cumsum(n_tri) - n_tri
    out = np.empty((int(n_tri.sum()), 3), dtype=np.int64)
    for rows, polys in groups:
        at = first if rows is None else first[rows]
        for k in range(polys.shape[1] - 2):  # loop over polygon corners, not faces
            out[at + k] = polys[:, [0, k + 1, k + 2]]
    return out


def _distinct_counts(counts: NDArray[Any]) -> NDArray[np.int64]:
    """Sorted distinct values of an array of small non-negative counts (face sizes).

    ``np.bincount`` when the values are small: ``np.unique`` hashes and took ~1 s for the 20M
    face sizes of a large mesh; large (corrupt) values go through ``np.unique`` instead of
    allocating a huge count table.
    """
    a = np.asarray(counts).ravel()
    if a.size and a.dtype.kind in "iu" and int(a.min()) >= 0 and int(a.max()) < (1 << 16):
        return np.flatnonzero(np.bincount(a.astype(np.int64, copy=False)))
    return np.unique(a).astype(np.int64)


# ----------------------------------------------------------------------------- bytes and streams


def _bytes_view(array: NDArray[Any]) -> memoryview:
    """Byte view of a contiguous array for file I/O, no copy (numpy stubs lack Buffer)."""
    return memoryview(array.view(np.uint8))  # type: ignore[arg-type]


def _read_exact(fi: io.RawIOBase | io.BufferedIOBase, target: memoryview, path: Path) -> None:
    """Fill ``target`` from ``fi`` (raw reads may return fewer bytes)."""
    done = 0
    while done < len(target):
        n = fi.readinto(target[done:])
        if not n:
            raise InputError("file ended early (truncated?)", path)
        done += n


def _write_all(fo: BinaryIO, data: memoryview) -> None:
    """Write all of ``data`` (raw writes may write fewer bytes)."""
    done = 0
    while done < len(data):
        done += fo.write(data[done:]) or 0


def _copy_range(fi: io.RawIOBase | io.BufferedIOBase, fo: BinaryIO, offset: int, count: int,
                path: Path, progress: Progress = _no_progress) -> None:
    """Append bytes [offset, offset + count) of ``fi`` to ``fo`` (in the kernel if possible)."""
    done = 0
    try:
        while done < count:  # sendfile: no user-space copy, no fresh memory
            sent = os.sendfile(fo.fileno(), fi.fileno(), offset + done,
                               min(count - done, _COPY_CHUNK))
            if sent == 0:
                raise InputError("file ended early (truncated?)", path)
            done += sent
            progress(sent)
    except (AttributeError, OSError):  # no sendfile here: copy through a reused buffer
        buffer = memoryview(bytearray(min(_COPY_CHUNK, max(count - done, 1))))
        fi.seek(offset + done)
        while done < count:
            part = buffer[: min(len(buffer), count - done)]
            _read_exact(fi, part, path)
            _write_all(fo, part)
            done += len(part)
            progress(len(part))


def _line_blocks(f: BinaryIO) -> Iterator[bytes]:
    """The file in blocks of whole lines (about _COPY_CHUNK bytes each)."""
    carry = b""
    while block := f.read(_COPY_CHUNK):
        block = carry + block
        cut = block.rfind(b"\n") + 1
        carry, block = block[cut:], block[:cut]
        if block:
            yield block
    if carry:
        yield carry


# ----------------------------------------------------------------------------- output files


class _AtomicOutput:
    """Write to ``<dst>.partial`` and rename onto ``dst`` only when the block succeeds."""

    def __init__(self, dst: Path, buffered: bool = True) -> None:
        self.dst = dst
        self.tmp = dst.with_name(dst.name + ".partial")
        self.buffering = -1 if buffered else 0

    def __enter__(self) -> BinaryIO:
        self.file: BinaryIO = open(self.tmp, "wb", buffering=self.buffering)  # noqa: SIM115
        return self.file

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.file.close()
        if exc_type is None:
            os.replace(self.tmp, self.dst)
        else:
            self.tmp.unlink(missing_ok=True)


def _copy_side_file(rel: str, src_dir: Path, dst_dir: Path, written: list[Path]) -> None:
    """Copy ``src_dir/rel`` to ``dst_dir/rel`` (texture, MTL); warn when it cannot be done."""
    candidates = [rel, rel.replace("\\", "/")]
    rel_path = next((Path(c) for c in candidates if (src_dir / c).is_file()), None)
    if rel_path is None:
        logger.warning("%s: referenced file %r not found; not copied", src_dir, rel)
        return
    if rel_path.is_absolute():
        logger.info("%s: %r is an absolute path; left where it is", src_dir, rel)
        return
    target = dst_dir / rel_path
    if not target.resolve().is_relative_to(dst_dir.resolve()):
        logger.warning("%s: %r points outside the mesh folder; not copied", src_dir, rel)
        return
    if target in written:
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src_dir / rel_path, target)
    written.append(target)


# ----------------------------------------------------------------------------- text vertex lines


def _xyz_pattern(prefix: bytes) -> re.Pattern[bytes]:
    """Regex for a text line '<prefix> x y z ...' capturing the three tokens and separators."""
    return re.compile(rb"^([ \t]*" + prefix + rb")(\S+)([ \t]+)(\S+)([ \t]+)(\S+)")


def _raise_bad_xyz_line(block: bytes, pattern: re.Pattern[bytes], first_line: int,
                        path: Path) -> None:
    """Raise the InputError (with its line number) for the first bad vertex line of a block."""
    for i, line in enumerate(block.split(b"\n")):
        if line.lstrip(b" \t")[:2] in (b"v ", b"v\t"):
            _scale_xyz_line(line, pattern, 1.0, first_line + i, path)
    raise InputError(f"bad vertex line near line {first_line}", path)


def _scale_xyz_line(line: bytes, pattern: re.Pattern[bytes], scale: float, lineno: int,
                    path: Path) -> bytes:
    """A text line with its x y z tokens scaled (float64, shortest repr); rest kept verbatim."""
    m = pattern.match(line)
    try:
        if m is None:
            raise ValueError("fewer than 3 coordinates")
        xyz = [repr(float(m.group(k)) * scale).encode("ascii") for k in (2, 4, 6)]
    except ValueError as exc:
        text = line.strip().decode("latin-1")[:80]
        raise InputError(f"line {lineno}: bad vertex line {text!r}", path) from exc
    return b"".join([m.group(1), xyz[0], m.group(3), xyz[1], m.group(5), xyz[2],
                     line[m.end():]])
