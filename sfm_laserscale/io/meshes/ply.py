"""PLY meshes: read (ASCII, binary little/big endian; our own numpy reader) and rewrite with
the vertex positions rescaled, every other byte kept."""

from __future__ import annotations

import mmap
import re
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.meshes.common import (
    Progress,
    _AtomicOutput,
    _bytes_view,
    _copy_range,
    _copy_side_file,
    _distinct_counts,
    _fan_triangulate,
    _no_progress,
    _read_exact,
    _write_all,
)

#: PLY scalar type name -> numpy type code (byte order added per file).
_PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PLY_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_MAX_HEADER_BYTES = 1 << 20
_SCALE_CHUNK = 1 << 22  # bytes of vertex rows scaled at a time
_GATHER_ROWS = 1 << 20  # rows per fancy-index gather (bounds temporary index arrays)


# ----------------------------------------------------------------------------- PLY header


@dataclass(frozen=True)
class _PlyProperty:
    """One PLY property: scalar (count_code None) or list (count_code = length type)."""

    name: str
    code: str  # numpy type code of the value(s), no byte order: 'f4', 'i4', ...
    count_code: str | None = None

    @property
    def is_list(self) -> bool:
        return self.count_code is not None


@dataclass(frozen=True)
class _PlyElement:
    name: str
    count: int
    properties: tuple[_PlyProperty, ...]

    @property
    def has_lists(self) -> bool:
        return any(p.is_list for p in self.properties)

    def prop(self, name: str) -> _PlyProperty | None:
        return next((p for p in self.properties if p.name == name), None)


@dataclass(frozen=True)
class _PlyHeader:
    fmt: str  # ascii | binary_little_endian | binary_big_endian
    elements: tuple[_PlyElement, ...]
    comments: tuple[str, ...]
    data_offset: int  # bytes from the start of the file to the first data byte

    @property
    def byteorder(self) -> str:
        return _PLY_FORMATS[self.fmt]

    def element(self, name: str) -> _PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)

    @property
    def texture_files(self) -> list[str]:
        """Texture file names from ``comment TextureFile <name>`` lines (OpenMVS, MeshLab)."""
        out = []
        for comment in self.comments:
            key, _, rest = comment.partition(" ")
            if key.lower() == "texturefile" and rest.strip():
                out.append(rest.strip())
        return out


def _read_ply_header(path: Path) -> _PlyHeader:
    """Parse the header of a PLY file (any format); InputError when it is not valid PLY."""
    with open(path, "rb") as f:
        first = f.readline(64)
        if first.rstrip(b"\r\n") != b"ply":
            raise InputError("not a PLY file (first line is not 'ply')", path)
        offset, lines = len(first), []
        while True:
            raw = f.readline(_MAX_HEADER_BYTES)
            offset += len(raw)
            if not raw.endswith(b"\n") or offset > _MAX_HEADER_BYTES:
                raise InputError("PLY header has no end_header line (truncated file?)", path)
            line = raw.decode("utf-8", errors="surrogateescape").rstrip("\r\n")
            if line.strip() == "end_header":
                break
            lines.append(line)
    return _parse_ply_header(lines, offset, path)


def _parse_ply_header(lines: list[str], data_offset: int, path: Path) -> _PlyHeader:
    """Header lines (between 'ply' and 'end_header') -> _PlyHeader."""
    fmt: str | None = None
    elements: list[tuple[str, int, list[_PlyProperty]]] = []
    comments: list[str] = []
    for line in lines:
        words = line.split()
        if not words:
            continue
        key = words[0]
        if key == "format":
            if len(words) != 3 or words[1] not in _PLY_FORMATS:
                raise InputError(f"bad PLY format line {line!r}", path)
            fmt = words[1]
        elif key in ("comment", "obj_info"):
            if key == "comment":
                comments.append(line.lstrip()[len("comment"):].strip())
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(f"bad PLY element line {line!r}", path)
            elements.append((words[1], int(words[2]), []))
        elif key == "property":
            if not elements:
                raise InputError(f"PLY property before any element: {line!r}", path)
            elements[-1][2].append(_parse_ply_property(words, line, path))
        else:
            raise InputError(f"unknown PLY header line {line!r}", path)
    if fmt is None:
        raise InputError("PLY header has no format line", path)
    elems = tuple(_PlyElement(n, c, tuple(p)) for n, c, p in elements)
    for e in elems:
        names = [p.name for p in e.properties]
        if len(set(names)) != len(names):
            raise InputError(f"PLY element {e.name!r} repeats a property name", path)
    return _PlyHeader(fmt, elems, tuple(comments), data_offset)


def _parse_ply_property(words: list[str], line: str, path: Path) -> _PlyProperty:
    """One 'property ...' header line -> _PlyProperty."""
    if len(words) == 5 and words[1] == "list":
        count_code, code = _PLY_TYPES.get(words[2]), _PLY_TYPES.get(words[3])
        if count_code is None or code is None or count_code[0] == "f":
            raise InputError(f"bad PLY list property {line!r}", path)
        return _PlyProperty(words[4], code, count_code)
    if len(words) == 3 and words[1] in _PLY_TYPES:
        return _PlyProperty(words[2], _PLY_TYPES[words[1]])
    raise InputError(f"bad PLY property line {line!r}", path)


def _ply_mesh_props(header: _PlyHeader, path: Path) -> tuple[_PlyElement, _PlyElement, str]:
    """The vertex element, the face element and the face's index list property name."""
    vertex = header.element("vertex")
    if vertex is None:
        raise InputError("PLY file has no 'vertex' element", path)
    for axis in "xyz":
        prop = vertex.prop(axis)
        if prop is None or prop.is_list:
            raise InputError(f"PLY vertex element has no scalar property {axis!r}", path)
    face = header.element("face")
    if face is None or face.count == 0:
        raise InputError("PLY file has no faces (a point cloud?)", path)
    for name in ("vertex_indices", "vertex_index"):
        prop = face.prop(name)
        if prop is not None and prop.is_list:
            return vertex, face, name
    raise InputError("PLY face element has no 'vertex_indices' list property", path)


# ----------------------------------------------------------------------------- PLY binary


def _row_dtype(elem: _PlyElement, counts: Sequence[int], bo: str) -> np.dtype[Any]:
    """Packed numpy dtype of one row whose list properties have the given lengths."""
    fields: list[tuple[Any, ...]] = []
    it = iter(counts)
    for p in elem.properties:
        if p.count_code is None:
            fields.append((p.name, bo + p.code))
        else:
            # ' len' cannot clash with a PLY property name (names have no whitespace)
            fields.append((p.name + " len", bo + p.count_code))
            fields.append((p.name, bo + p.code, (next(it),)))
    return np.dtype(fields)


@dataclass(frozen=True)
class _BinaryElement:
    """Where the rows of one binary element are: one uniform layout or per-row offsets."""

    elem: _PlyElement
    start: int
    end: int
    bo: str
    dtype: np.dtype[Any] | None  # uniform layout (every row the same size)
    row_offsets: NDArray[np.int64] | None  # variable layout: absolute offset of each row
    list_counts: NDArray[np.int64] | None  # variable layout: (count, n_lists) list lengths

    def groups(self) -> Iterator[tuple[NDArray[np.int64], np.dtype[Any]]]:
        """(row indices, row dtype) for each distinct row layout (variable layout only)."""
        assert self.list_counts is not None  # internal invariant, not an input check
        counts = self.list_counts
        if counts.shape[1] == 1:  # one list per row: a few face sizes, one pass each
            for n in _distinct_counts(counts[:, 0]):
                yield np.flatnonzero(counts[:, 0] == n), _row_dtype(self.elem, [int(n)], self.bo)
            return
        layouts, inverse = np.unique(counts, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        for i, layout in enumerate(layouts):
            yield np.flatnonzero(inverse == i), _row_dtype(self.elem, layout.tolist(), self.bo)


def _truncated(path: Path, elem: _PlyElement) -> InputError:
    return InputError(f"PLY data ends inside element {elem.name!r} (truncated file?)", path)


def _first_row_counts(buf: NDArray[np.uint8], pos: int, elem: _PlyElement, bo: str,
                      path: Path) -> list[int]:
    """List lengths of the row starting at byte ``pos``."""
    counts = []
    for p in elem.properties:
        if p.count_code is None:
            pos += np.dtype(p.code).itemsize
            continue
        size = np.dtype(p.count_code).itemsize
        if pos + size > len(buf):
            raise _truncated(path, elem)
        c = int(buf[pos:pos + size].view(bo + p.count_code)[0])
        if c < 0:
            raise InputError(f"negative list length in PLY element {elem.name!r}", path)
        counts.append(c)
        pos += size + c * np.dtype(p.code).itemsize
    return counts


def _scan_binary_element(buf: NDArray[np.uint8], pos: int, elem: _PlyElement, bo: str,
                         path: Path) -> _BinaryElement:
    """Locate the rows of a binary element starting at byte ``pos`` (vectorised when uniform)."""
    n_lists = sum(p.is_list for p in elem.properties)
    counts = _first_row_counts(buf, pos, elem, bo, path) if elem.count else [0] * n_lists
    dtype = _row_dtype(elem, counts, bo)
    end = pos + elem.count * dtype.itemsize
    if not elem.has_lists or elem.count == 0:
        if end > len(buf):
            raise _truncated(path, elem)
        return _BinaryElement(elem, pos, end, bo, dtype, None, None)
    if end <= len(buf):
        rows = buf[pos:end].view(dtype)
        lists = [p for p in elem.properties if p.is_list]
        # every row has row 0's list lengths => row i really starts at pos + i * itemsize
        if all((rows[p.name + " len"] == c).all() for p, c in zip(lists, counts, strict=True)):
            return _BinaryElement(elem, pos, end, bo, dtype, None, None)
    return _scan_variable_rows(buf, pos, elem, bo, path)


def _scan_variable_rows(buf: NDArray[np.uint8], pos: int, elem: _PlyElement, bo: str,
                        path: Path) -> _BinaryElement:
    """Row offsets of an element whose list lengths vary (sequential by nature: a Python loop)."""
    plan: list[tuple[int, struct.Struct, int]] = []  # (fixed bytes before, count struct, item)
    fixed = 0
    for p in elem.properties:
        if p.count_code is None:
            fixed += np.dtype(p.code).itemsize
        else:
            fmt = bo + np.dtype(p.count_code).char
            plan.append((fixed, struct.Struct(fmt), np.dtype(p.code).itemsize))
            fixed = 0
    start, mem = pos, _bytes_view(buf)
    try:
        if len(plan) == 1 and plan[0][1].size == 1 and plan[0][1].format[-1] == "B":
            offsets, counts, pos = _offsets_one_uchar_list(mem, pos, elem.count, plan[0], fixed)
        else:
            offsets, counts, pos = _offsets_generic(mem, pos, elem.count, plan, fixed)
    except (IndexError, struct.error):
        raise _truncated(path, elem) from None
    if pos > len(buf):
        raise _truncated(path, elem)
    if (counts < 0).any():
        raise InputError(f"negative list length in PLY element {elem.name!r}", path)
    return _BinaryElement(elem, start, pos, bo, None, offsets, counts)


def _offsets_one_uchar_list(mem: memoryview, pos: int, count: int,
                            segment: tuple[int, struct.Struct, int],
                            tail: int) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
    """Row offsets when the only list has a uchar length (the usual face element): fast loop."""
    skip, _, item = segment
    row_size = [skip + 1 + item * c + tail for c in range(256)]
    offsets: list[int] = []
    add = offsets.append
    for _ in range(count):
        add(pos)
        pos += row_size[mem[pos + skip]]
    offsets_array = np.asarray(offsets, dtype=np.int64)
    counts = np.frombuffer(mem, dtype=np.uint8)[offsets_array + skip]
    return offsets_array, counts.astype(np.int64).reshape(-1, 1), pos


def _offsets_generic(mem: memoryview, pos: int, count: int,
                     plan: list[tuple[int, struct.Struct, int]],
                     tail: int) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
    """Row offsets for any combination of list properties (slower loop)."""
    offsets: list[int] = []
    counts: list[int] = []
    for _ in range(count):
        offsets.append(pos)
        for skip, st, item in plan:
            pos += skip
            c = st.unpack_from(mem, pos)[0]
            counts.append(c)
            pos += st.size + max(c, 0) * item
        pos += tail
    counts_array = np.asarray(counts, dtype=np.int64).reshape(count, len(plan))
    return np.asarray(offsets, dtype=np.int64), counts_array, pos


def _gather(buf: NDArray[np.uint8], starts: NDArray[np.int64], nbytes: int,
            dtype: np.dtype[Any]) -> NDArray[Any]:
    """(k, nbytes / itemsize) values of ``dtype`` read at byte offsets ``starts``."""
    if nbytes == 0:
        return np.zeros((len(starts), 0), dtype=dtype)
    out = np.empty((len(starts), nbytes), dtype=np.uint8)
    cols = np.arange(nbytes, dtype=np.int64)
    for a in range(0, len(starts), _GATHER_ROWS):
        out[a:a + _GATHER_ROWS] = buf[starts[a:a + _GATHER_ROWS, None] + cols]
    return out.view(dtype)


def _binary_scalar(buf: NDArray[np.uint8], data: _BinaryElement, name: str) -> NDArray[Any]:
    """(count,) values of scalar property ``name`` (a view when the layout is uniform)."""
    if data.dtype is not None:
        return buf[data.start:data.end].view(data.dtype)[name]
    assert data.row_offsets is not None
    prop = data.elem.prop(name)
    assert prop is not None
    out = np.empty(data.elem.count, dtype=data.bo + prop.code)
    for rows, dtype in data.groups():
        field_dtype, field_offset = dtype.fields[name][:2]  # type: ignore[index]
        out[rows] = _gather(buf, data.row_offsets[rows] + field_offset,
                            field_dtype.itemsize, field_dtype)[:, 0]
    return out


def _binary_lists(buf: NDArray[np.uint8], data: _BinaryElement,
                  name: str) -> list[tuple[NDArray[np.int64] | None, NDArray[Any]]]:
    """List property ``name`` as [(row indices or None for all, (k, n) values)] groups."""
    if data.dtype is not None:
        rows = buf[data.start:data.end].view(data.dtype)
        return [(None, rows[name])]
    assert data.row_offsets is not None
    out: list[tuple[NDArray[np.int64] | None, NDArray[Any]]] = []
    for rows_idx, dtype in data.groups():
        field_dtype, field_offset = dtype.fields[name][:2]  # type: ignore[index]
        base = field_dtype.base
        values = _gather(buf, data.row_offsets[rows_idx] + field_offset,
                         field_dtype.itemsize, base)
        out.append((rows_idx, values))
    return out


def _map_file(path: Path) -> NDArray[np.uint8]:
    """Read-only memory map of a whole file as bytes."""
    return np.memmap(path, dtype=np.uint8, mode="r")


def _drop_pages(buf: NDArray[np.uint8], start: int, end: int) -> None:
    """Release the read pages of ``buf[start:end]`` from this process's resident memory
    (they stay in the page cache); a no-op where madvise is not available."""
    mm = getattr(buf, "_mmap", None)
    if mm is None or not hasattr(mm, "madvise") or not hasattr(mmap, "MADV_DONTNEED"):
        return
    page = mmap.PAGESIZE
    lo = -(-start // page) * page  # whole pages inside the range only
    if end - lo >= page:
        mm.madvise(mmap.MADV_DONTNEED, lo, (end - lo) // page * page)


def _load_ply_binary(path: Path, header: _PlyHeader) -> tuple[NDArray[Any], NDArray[Any]]:
    vertex, face, index_name = _ply_mesh_props(header, path)
    buf = _map_file(path)
    pos, vertices, faces = header.data_offset, None, None
    for elem in header.elements:
        data = _scan_binary_element(buf, pos, elem, header.byteorder, path)
        if elem is vertex:
            codes = {p.code for p in (vertex.prop(a) for a in "xyz") if p is not None}
            vertices = np.empty((elem.count, 3), dtype=np.float32 if codes == {"f4"}
                                else np.float64)  # float32 as stored: exact, half the memory
            for k, axis in enumerate("xyz"):
                vertices[:, k] = _binary_scalar(buf, data, axis)
            _drop_pages(buf, data.start, data.end)
        elif elem is face:
            faces = _fan_triangulate(_binary_lists(buf, data, index_name), elem.count, path)
        pos = data.end
        if vertices is not None and faces is not None:
            break
    assert vertices is not None and faces is not None
    return vertices, faces


# ----------------------------------------------------------------------------- PLY ASCII


def _ascii_body_lines(path: Path, header: _PlyHeader) -> list[str]:
    """Non-blank data lines of an ASCII PLY (one element row per line)."""
    with open(path, "rb") as f:
        f.seek(header.data_offset)
        text = f.read().decode("latin-1")
    return [ln for ln in text.split("\n") if ln.strip()]


def _ascii_table(rows: list[str], elem: _PlyElement, path: Path,
                 ) -> list[tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]]:
    """Rows as groups of equal token count: (row indices, (k, L) values, (k, P) columns).

    columns[:, j] is the token column of property j (for a list: of its length token).
    """
    tokens = [r.split() for r in rows]
    lengths = np.fromiter((len(t) for t in tokens), dtype=np.int64, count=len(tokens))
    out = []
    for length in _distinct_counts(lengths):
        idx = np.flatnonzero(lengths == length)
        try:
            values = np.array([tokens[i] for i in idx], dtype=np.float64).reshape(len(idx), -1)
        except ValueError as exc:
            raise InputError(f"non-numeric value in PLY element {elem.name!r}: {exc}",
                             path) from exc
        cols = np.zeros((len(idx), len(elem.properties)), dtype=np.int64)
        pos = np.zeros(len(idx), dtype=np.int64)
        for j, p in enumerate(elem.properties):
            if (pos >= length).any():
                raise InputError(f"too few values in a row of PLY element {elem.name!r}", path)
            cols[:, j] = pos
            if p.is_list:
                n = values[np.arange(len(idx)), pos]
                if (n < 0).any() or (n != np.round(n)).any():
                    raise InputError(f"bad list length in PLY element {elem.name!r}", path)
                pos = pos + 1 + n.astype(np.int64)
            else:
                pos = pos + 1
        if (pos != length).any():
            raise InputError(f"wrong number of values in a row of PLY element {elem.name!r}",
                             path)
        out.append((idx, values, cols))
    return out


def _load_ply_ascii(path: Path, header: _PlyHeader) -> tuple[NDArray[Any], NDArray[Any]]:
    vertex, face, index_name = _ply_mesh_props(header, path)
    lines = _ascii_body_lines(path, header)
    start, vertices, faces = 0, None, None
    for elem in header.elements:
        rows = lines[start:start + elem.count]
        if len(rows) < elem.count:
            raise _truncated(path, elem)
        if elem is vertex:
            vertices = np.zeros((elem.count, 3))
            for idx, values, cols in _ascii_table(rows, elem, path):
                for k, axis in enumerate("xyz"):
                    prop = vertex.prop(axis)
                    assert prop is not None
                    j = elem.properties.index(prop)
                    # through the property's own type, as a binary file would store it
                    column = values[np.arange(len(idx)), cols[:, j]].astype(prop.code)
                    vertices[idx, k] = column
        elif elem is face:
            faces = _fan_triangulate(_ascii_lists(rows, elem, index_name, path), elem.count, path)
        start += elem.count
    assert vertices is not None and faces is not None
    return vertices, faces


def _ascii_lists(rows: list[str], elem: _PlyElement, name: str,
                 path: Path) -> list[tuple[NDArray[np.int64], NDArray[np.int64]]]:
    """List property ``name`` of ASCII rows as [(row indices, (k, n) ints)] groups."""
    j = [p.name for p in elem.properties].index(name)
    out = []
    for idx, values, cols in _ascii_table(rows, elem, path):
        lengths = values[np.arange(len(idx)), cols[:, j]].astype(np.int64)
        for n in _distinct_counts(lengths):
            sel = np.flatnonzero(lengths == n)
            take = cols[sel, j][:, None] + 1 + np.arange(n)
            ints = values[sel[:, None], take]
            if (ints != np.round(ints)).any():
                raise InputError(f"non-integer vertex index in PLY element {elem.name!r}", path)
            out.append((idx[sel], ints.astype(np.int64)))
    return out


def _load_ply(path: Path) -> tuple[NDArray[Any], NDArray[Any]]:
    header = _read_ply_header(path)
    if header.fmt == "ascii":
        return _load_ply_ascii(path, header)
    return _load_ply_binary(path, header)


# ----------------------------------------------------------------------------- PLY rescale


def _write_scaled_ply(src: Path, dst: Path, scale: float,
                      progress: Progress = _no_progress) -> list[Path]:
    header = _read_ply_header(src)
    vertex = header.element("vertex")
    if vertex is None:
        raise InputError("PLY file has no 'vertex' element", src)
    for axis in "xyz":
        prop = vertex.prop(axis)
        if prop is None or prop.is_list:
            raise InputError(f"PLY vertex element has no scalar property {axis!r}", src)
        if prop.code[0] != "f":
            raise InputError(f"PLY vertex {axis!r} is integer-typed: cannot rescale exactly", src)
    if header.fmt == "ascii":
        _write_scaled_ply_ascii(src, dst, header, vertex, scale)
        progress(src.stat().st_size)
    else:
        _write_scaled_ply_binary(src, dst, header, vertex, scale, progress)
    written = [dst]
    for name in header.texture_files:
        _copy_side_file(name, src.parent, dst.parent, written)
    return written


def _scale_fields(rows: NDArray[Any], scale: float, scratch: NDArray[np.float64]) -> None:
    """Scale fields x, y, z in place: product in float64 (``scratch``), rounded once to own type."""
    for axis in "xyz":
        np.multiply(rows[axis], scale, out=scratch, dtype=np.float64)
        np.copyto(rows[axis], scratch, casting="same_kind")


def _write_scaled_ply_binary(src: Path, dst: Path, header: _PlyHeader, vertex: _PlyElement,
                             scale: float, progress: Progress = _no_progress) -> None:
    """Stream: bytes before the vertex rows, scaled vertex rows in chunks, the rest verbatim.

    Memory: one chunk of rows and one float64 scratch column, reused (fresh allocations
    are what costs most here); the verbatim parts are copied by the kernel.
    """
    buf = _map_file(src)
    pos = header.data_offset
    for elem in header.elements[: header.elements.index(vertex)]:
        pos = _scan_binary_element(buf, pos, elem, header.byteorder, src).end
    data = _scan_binary_element(buf, pos, vertex, header.byteorder, src)
    end = data.end
    for elem in header.elements[header.elements.index(vertex) + 1:]:  # truncated -> InputError
        end = _scan_binary_element(buf, end, elem, header.byteorder, src).end
    size = len(buf)
    del buf
    with open(src, "rb", buffering=0) as fi, _AtomicOutput(dst, buffered=False) as fo:
        progress(data.start)  # the header and the elements before the vertices
        _copy_range(fi, fo, 0, data.start, src)
        fi.seek(data.start)
        if data.dtype is not None:
            rows_per_chunk = max(1, min(vertex.count, _SCALE_CHUNK // max(data.dtype.itemsize, 1)))
            chunk = np.empty(rows_per_chunk, dtype=data.dtype)
            scratch = np.empty(rows_per_chunk, dtype=np.float64)
            for a in range(0, vertex.count, rows_per_chunk):
                n = min(rows_per_chunk, vertex.count - a)
                _read_exact(fi, _bytes_view(chunk[:n]), src)
                _scale_fields(chunk[:n], scale, scratch[:n])
                _write_all(fo, _bytes_view(chunk[:n]))
                progress(n * data.dtype.itemsize)
        else:  # rows of varying size (list properties in the vertex element): whole block
            block = np.empty(data.end - data.start, dtype=np.uint8)
            _read_exact(fi, _bytes_view(block), src)
            _scale_variable_vertex_rows(block, data, scale)
            _write_all(fo, _bytes_view(block))
            progress(len(block))
        _copy_range(fi, fo, data.end, size - data.end, src, progress)


def _scale_variable_vertex_rows(block: NDArray[np.uint8], data: _BinaryElement,
                                scale: float) -> None:
    """Scale x, y, z in a vertex block whose rows differ in size (gather, scale, scatter)."""
    assert data.row_offsets is not None
    starts = data.row_offsets - data.start
    for rows, dtype in data.groups():
        for axis in "xyz":
            field_dtype, field_offset = dtype.fields[axis][:2]  # type: ignore[index]
            at = (starts[rows] + field_offset)[:, None] + np.arange(field_dtype.itemsize)
            values = block[at].view(field_dtype)[:, 0].astype(np.float64) * scale
            block[at] = values.astype(field_dtype)[:, None].view(np.uint8)


def _format_ascii_float(value: float, code: str) -> bytes:
    """Shortest text that reads back to the same float32 ('f4') or float64 ('f8')."""
    text = str(np.float32(value)) if code == "f4" else repr(float(value))
    return text.encode("ascii")


def _write_scaled_ply_ascii(src: Path, dst: Path, header: _PlyHeader, vertex: _PlyElement,
                            scale: float) -> None:
    """Rewrite only the x, y, z tokens of vertex lines (whitespace kept exactly)."""
    raw = src.read_bytes()
    lines = raw[header.data_offset:].split(b"\n")
    i = 0
    for elem in header.elements:
        for _ in range(elem.count):
            while i < len(lines) and not lines[i].strip():
                i += 1
            if i >= len(lines):
                raise _truncated(src, elem)
            if elem is vertex:
                lines[i] = _scale_ascii_vertex_line(lines[i], vertex, scale, src)
            i += 1  # rows of the later elements are counted too: a truncated file is refused
    with _AtomicOutput(dst) as fo:
        fo.write(raw[: header.data_offset])
        fo.write(b"\n".join(lines))


_TOKEN = re.compile(rb"\S+")


def _scale_ascii_vertex_line(line: bytes, vertex: _PlyElement, scale: float, path: Path) -> bytes:
    """One ASCII vertex row with its x, y, z tokens scaled."""
    spans = [m.span() for m in _TOKEN.finditer(line)]
    where: dict[str, int] = {}
    t = 0
    try:
        for p in vertex.properties:
            if p.is_list:
                t += 1 + int(line[slice(*spans[t])])
            else:
                where[p.name] = t
                t += 1
        if t != len(spans):
            raise IndexError
        new = {
            a: _format_ascii_float(float(line[slice(*spans[where[a]])]) * scale,
                                   vertex.prop(a).code)  # type: ignore[union-attr]
            for a in "xyz"
        }
    except (IndexError, ValueError) as exc:
        raise InputError(f"bad PLY vertex row {line.strip()[:80]!r}", path) from exc
    for a in sorted("xyz", key=lambda a: -where[a]):  # replace right to left
        lo, hi = spans[where[a]]
        line = line[:lo] + new[a] + line[hi:]
    return line
