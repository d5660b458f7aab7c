"""Triangle meshes: reading for ray casting, and metric rescaling of mesh files.

Reading (:func:`load_mesh`): PLY (ASCII, binary little/big endian) and OBJ with our own
numpy readers; GLB/glTF, OFF and STL through trimesh. Polygons are fan-triangulated.

Rescaling (:func:`write_scaled_mesh`): PLY, OBJ, OFF and STL keep every byte except the
vertex positions (headers, faces, normals, colours, texture coordinates, custom
properties); textures named by the file (PLY ``comment TextureFile``, OBJ ``mtllib`` ->
``map_*``) are copied beside the output with the same relative paths. Binary positions
are scaled in their own type (product in float64, rounded once); text positions are
written with the shortest repr that reads back exactly. GLB/glTF: the float POSITION
accessors (and morph-target positions) are scaled inside the binary buffers, accessor
min/max and node translations with them; buffer bytes other than
positions are unchanged but the JSON is re-serialised (same content, other formatting);
animations are not scaled. glTF with Draco-compressed, quantised or sparse positions is
refused (InputError).

Why our own PLY/OBJ code: plyfile reads list properties row by row in Python (slow on
millions of faces) and trimesh may merge/reorder vertices and splits OBJ files by
material; both would also make the byte-exact rewrite impossible.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import mmap
import os
import re
import shutil
import struct
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError

logger = logging.getLogger(__name__)

MESH_SUFFIXES = (".ply", ".obj", ".glb", ".gltf", ".off", ".stl")

#: PLY scalar type name -> numpy type code (byte order added per file).
_PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PLY_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_MAX_HEADER_BYTES = 1 << 20
_COPY_CHUNK = 1 << 24  # bytes per read/write when streaming
_SCALE_CHUNK = 1 << 22  # bytes of vertex rows scaled at a time
_GATHER_ROWS = 1 << 20  # rows per fancy-index gather (bounds temporary index arrays)

#: Progress callback of the mesh writers: called with the number of bytes of the source mesh
#: processed since the previous call (the calls of one write add up to the file's size).
Progress = Callable[[int], None]


def _no_progress(nbytes: int) -> None:
    """The default progress callback: nothing."""


@dataclass(frozen=True, eq=False)
class TriangleMesh:
    """Vertices (V, 3) in model units and triangles (F, 3) int32 vertex indices.

    Vertices are float64, or float32 when the file stores float32 (binary PLY): every value is
    then exact and half the memory (120 MB less at 10M vertices); do the maths in float64.
    """

    vertices: NDArray[np.floating]
    triangles: NDArray[np.int32]

    def __post_init__(self) -> None:
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"vertices must be (V, 3), got {self.vertices.shape}")
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3:
            raise ValueError(f"triangles must be (F, 3), got {self.triangles.shape}")

    @property
    def num_vertices(self) -> int:
        """Number of vertices V."""
        return int(self.vertices.shape[0])

    @property
    def num_triangles(self) -> int:
        """Number of triangles F."""
        return int(self.triangles.shape[0])

    @property
    def bounds(self) -> NDArray[np.float64]:
        """(2, 3) axis-aligned bounds [min, max] of the vertices used by triangles (model units)."""
        used_mask = np.zeros(len(self.vertices), dtype=bool)
        used_mask[self.triangles.reshape(-1)] = True
        used = self.vertices[used_mask]
        return np.stack([used.min(axis=0), used.max(axis=0)])

    @property
    def extent(self) -> float:
        """Length of the bounding-box diagonal (model units)."""
        lo, hi = self.bounds
        return float(np.linalg.norm(hi - lo))


# ----------------------------------------------------------------------------- common checks


def _mesh_kind(path: Path) -> str:
    """File kind from the extension ('ply', 'obj', 'glb', ...); InputError when unknown."""
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputError(
            f"unknown mesh extension {path.suffix!r} (expected one of {', '.join(MESH_SUFFIXES)})",
            path,
        )
    return suffix[1:]


def _check_input_file(path: Path) -> None:
    """InputError unless ``path`` is an existing, non-empty regular file."""
    if not path.exists():
        raise InputError("mesh file does not exist", path)
    if not path.is_file():
        raise InputError("mesh path is not a file", path)
    if path.stat().st_size == 0:
        raise InputError("mesh file is empty", path)


def _validated_mesh(vertices: NDArray[Any], faces: NDArray[Any], path: Path) -> TriangleMesh:
    """TriangleMesh after checking: some triangles, finite vertices, indices in range.

    Avoids large temporaries (fresh memory is costly): checks run on the inputs as given and
    each output array is allocated once.
    """
    keep32 = vertices.dtype == np.float32
    vertices = np.ascontiguousarray(vertices, dtype=np.float32 if keep32 else np.float64)
    vertices = vertices.reshape(-1, 3)
    faces = np.asarray(faces).reshape(-1, 3)
    if len(faces) == 0:
        raise InputError("mesh has no triangles (a point cloud?)", path)
    if not np.isfinite(np.sum(vertices)):  # cheap test; the exact one only when it fails
        bad = ~np.isfinite(vertices).all(axis=1)
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise InputError(f"{int(bad.sum())} vertices are not finite (first: vertex {first})",
                             path)
    if faces.dtype.kind not in "iu":
        raise InputError("face vertex indices are not integers", path)
    faces = np.ascontiguousarray(faces, dtype=faces.dtype.newbyteorder("="))  # one pass
    lo, hi = int(faces.min()), int(faces.max())
    if lo < 0 or hi >= len(vertices):
        bad_idx = lo if lo < 0 else hi
        raise InputError(
            f"face vertex index {bad_idx} out of range (mesh has {len(vertices)} vertices)", path
        )
    if len(vertices) > np.iinfo(np.int32).max:
        raise InputError("more than 2^31 - 1 vertices are not supported", path)
    # 4-byte indices now known to be in [0, 2^31): same bits as int32, no second copy
    triangles = faces.view(np.int32) if faces.dtype.itemsize == 4 else faces.astype(np.int32)
    return TriangleMesh(vertices=vertices, triangles=triangles)


def load_mesh(path: str | Path) -> TriangleMesh:
    """Read a triangle mesh (PLY, OBJ, GLB/glTF, OFF, STL); polygons are fan-triangulated."""
    path = Path(path)
    kind = _mesh_kind(path)
    _check_input_file(path)
    if kind == "ply":
        vertices, faces = _load_ply(path)
    elif kind == "obj":
        vertices, faces = _load_obj(path)
    else:
        vertices, faces = _load_with_trimesh(path)
    mesh = _validated_mesh(vertices, faces, path)
    logger.info("read %s: %d vertices, %d triangles", path, mesh.num_vertices, mesh.num_triangles)
    return mesh


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


def _bytes_view(array: NDArray[Any]) -> memoryview:
    """Byte view of a contiguous array for file I/O, no copy (numpy stubs lack Buffer)."""
    return memoryview(array.view(np.uint8))  # type: ignore[arg-type]


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


# ----------------------------------------------------------------------------- OBJ


def _obj_lines(path: Path) -> tuple[list[tuple[int, str]], list[tuple[int, str, int]]]:
    """('v' lines as (line no, text), 'f' lines as (line no, text, vertices defined before))."""
    v_lines: list[tuple[int, str]] = []
    f_lines: list[tuple[int, str, int]] = []
    text = path.read_bytes().decode("latin-1")  # numbers are ASCII; names are not needed here
    for lineno, line in enumerate(text.splitlines(), 1):
        if line[:1] in (" ", "\t"):
            line = line.lstrip()
        head = line[:2]
        if head in ("v ", "v\t"):
            v_lines.append((lineno, line))
        elif head in ("f ", "f\t"):
            f_lines.append((lineno, line, len(v_lines)))
    return v_lines, f_lines


def _obj_vertices(v_lines: list[tuple[int, str]], path: Path) -> NDArray[np.float64]:
    """(V, 3) positions from 'v x y z [w | r g b]' lines."""
    try:
        return np.array([ln.split()[1:4] for _, ln in v_lines], dtype=np.float64).reshape(-1, 3)
    except ValueError:
        for lineno, ln in v_lines:  # find the bad line for the message
            try:
                np.array(ln.split()[1:4], dtype=np.float64).reshape(3)
            except ValueError as exc:
                raise InputError(f"line {lineno}: bad vertex line {ln.strip()!r}", path) from exc
        raise


def _obj_faces(f_lines: list[tuple[int, str, int]], path: Path) -> NDArray[np.int64]:
    """(T, 3) zero-based triangles from 'f' lines (v, v/vt, v//vn, v/vt/vn; negatives ok)."""
    stripped = re.sub(r"/\S*", "", "\n".join(ln[2:] for _, ln, _ in f_lines))
    tokens = [r.split() for r in stripped.split("\n")] if f_lines else []
    lengths = np.fromiter((len(t) for t in tokens), dtype=np.int64, count=len(tokens))
    defined = np.array([n for _, _, n in f_lines], dtype=np.int64)
    groups = []
    for n in _distinct_counts(lengths):
        rows = np.flatnonzero(lengths == n)
        try:
            idx = np.array([tokens[i] for i in rows], dtype=np.int64).reshape(len(rows), n)
        except ValueError as exc:
            bad = next(f_lines[i] for i in rows if not all(_is_int(t) for t in tokens[i]))
            raise InputError(f"line {bad[0]}: bad face line {bad[1].strip()!r}", path) from exc
        if (idx == 0).any():
            lineno = f_lines[int(rows[np.flatnonzero((idx == 0).any(axis=1))[0]])][0]
            raise InputError(f"line {lineno}: face vertex index 0 (OBJ indices start at 1)", path)
        # 1-based; negative = relative to the vertices defined so far (-1 = the last one)
        idx = np.where(idx > 0, idx - 1, idx + defined[rows, None])
        groups.append((rows, idx))
    return _fan_triangulate(groups, len(f_lines), path)


def _is_int(token: str) -> bool:
    try:
        int(token)
    except ValueError:
        return False
    return True


# a literal first character lets the regex engine skip ahead quickly (files get "\n" prepended)
_OBJ_V_REST = re.compile(rb"\nv[ \t]+([^\r\n]*)")
_OBJ_F_REST = re.compile(rb"\nf[ \t]+([^\r\n]*)")
_OBJ_INDENTED = re.compile(rb"\n[ \t]+[vf][ \t]")


def _parse_numbers(text: bytes, dtype: type) -> NDArray[Any] | None:
    """Whitespace-separated numbers parsed in C; None when some token is not a number."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # numpy warns on unparsed data
        try:
            return np.fromstring(text, dtype=dtype, sep=" ")
        except (ValueError, DeprecationWarning):
            return None


def _tokens_per_line(text: bytes) -> NDArray[np.int64]:
    """Number of whitespace-separated tokens on each '\\n'-separated line of ``text``."""
    b = np.frombuffer(text, dtype=np.uint8)
    newline = b == 10
    space = (b == 32) | (b == 9) | (b == 13) | newline
    first = ~space & np.concatenate([[True], space[:-1]])
    line = np.cumsum(newline, dtype=np.int32)
    return np.bincount(line[first], minlength=int(newline.sum()) + 1).astype(np.int64)


def _load_obj_fast(data: bytes) -> tuple[NDArray[Any], NDArray[Any]] | None:
    """Vectorised OBJ reading for well-formed files; None -> use the line-by-line reader."""
    data = b"\n" + data
    if _OBJ_INDENTED.search(data):
        return None
    v_rest, f_rest = _OBJ_V_REST.findall(data), _OBJ_F_REST.findall(data)
    if not v_rest or not f_rest:
        return None
    xyz = _parse_numbers(b"\n".join(v_rest), np.float64)
    if xyz is None or len(xyz) != 3 * len(v_rest):  # w, colours or bad tokens: slow path
        return None
    text = re.sub(rb"/\S*", b"", b"\n".join(f_rest))
    idx = _parse_numbers(text, np.int64)
    sizes = _tokens_per_line(text)
    if idx is None or len(idx) != sizes.sum() or (idx <= 0).any():  # negatives: slow path
        return None
    starts = np.cumsum(sizes) - sizes
    groups = []
    for n in _distinct_counts(sizes):
        rows = np.flatnonzero(sizes == n)
        groups.append((rows, idx[starts[rows, None] + np.arange(n)] - 1))
    return xyz.reshape(-1, 3), _fan_triangulate(groups, len(sizes), Path("obj"))


def _load_obj(path: Path) -> tuple[NDArray[Any], NDArray[Any]]:
    fast = _load_obj_fast(path.read_bytes())
    if fast is not None:
        return fast
    v_lines, f_lines = _obj_lines(path)
    if not v_lines and not f_lines:
        raise InputError("no 'v' or 'f' lines: not an OBJ mesh", path)
    return _obj_vertices(v_lines, path), _obj_faces(f_lines, path)


# ----------------------------------------------------------------------------- trimesh formats


def _load_with_trimesh(path: Path) -> tuple[NDArray[Any], NDArray[Any]]:
    """GLB/glTF/OFF/STL through trimesh (a scene is flattened with its node transforms)."""
    import trimesh

    try:
        scene = trimesh.load_scene(str(path), process=False)
        geoms = [
            g.copy().apply_transform(scene.graph.get(node)[0])
            for node in scene.graph.nodes_geometry
            for g in [scene.geometry[scene.graph.get(node)[1]]]
            if isinstance(g, trimesh.Trimesh)
        ]
    except InputError:
        raise
    except Exception as exc:  # trimesh raises many types for bad files; translate them all
        raise InputError(f"cannot read mesh: {type(exc).__name__}: {exc}", path) from exc
    if not geoms:
        raise InputError("mesh has no triangles (a point cloud?)", path)
    offsets = np.cumsum([0] + [len(g.vertices) for g in geoms])
    vertices = np.concatenate([np.asarray(g.vertices, dtype=np.float64) for g in geoms])
    faces = np.concatenate(
        [np.asarray(g.faces, dtype=np.int64) + o for g, o in zip(geoms, offsets, strict=False)]
    )
    return vertices, faces


# ============================================================================= rescaling


def write_scaled_mesh(src: str | Path, dst_dir: str | Path, scale: float,
                      progress: Progress | None = None) -> list[Path]:
    """Write ``dst_dir/<src.name>`` with vertex positions × ``scale``; returns written files.

    PLY/OBJ/OFF/STL: every other byte unchanged; textures copied with their relative paths.
    glTF/GLB: positions scaled in the buffers (node translations too), JSON re-serialised.
    The input is never modified. ``progress`` (e.g. a tqdm bar's ``update``) receives the
    source bytes processed, as they are (binary PLY and OBJ stream) or at the end (others).
    """
    report = progress or _no_progress
    src, dst_dir = Path(src), Path(dst_dir)
    kind = _mesh_kind(src)
    _check_input_file(src)
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(f"scale must be a positive finite number, got {scale!r}", src)
    if dst_dir.exists() and not dst_dir.is_dir():
        raise InputError("output path exists and is not a folder", dst_dir)
    if dst_dir.resolve() == src.parent.resolve():
        raise InputError("output folder must differ from the mesh's folder", dst_dir)
    dst_dir.mkdir(parents=True, exist_ok=True)
    dst = dst_dir / src.name
    if kind == "ply":
        written = _write_scaled_ply(src, dst, float(scale), report)
    elif kind == "obj":
        written = _write_scaled_obj(src, dst, float(scale), report)
    else:
        if kind in ("glb", "gltf"):
            written = _write_scaled_gltf(src, dst, float(scale))
        elif kind == "off":
            written = _write_scaled_off(src, dst, float(scale))
        else:
            written = _write_scaled_stl(src, dst, float(scale))
        report(src.stat().st_size)
    logger.info("wrote %s (scale %.9g) and %d side files", dst, scale, len(written) - 1)
    return written


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


# ----------------------------------------------------------------------------- OBJ rescale

def _xyz_pattern(prefix: bytes) -> re.Pattern[bytes]:
    """Regex for a text line '<prefix> x y z ...' capturing the three tokens and separators."""
    return re.compile(rb"^([ \t]*" + prefix + rb")(\S+)([ \t]+)(\S+)([ \t]+)(\S+)")


_OBJ_V = _xyz_pattern(rb"v[ \t]+")
_STL_VERTEX = _xyz_pattern(rb"vertex[ \t]+")
_OFF_VERTEX = _xyz_pattern(b"")


# patterns start with a literal "\n" (blocks get one prepended): much faster than "^" + re.M
_OBJ_V_LINE = re.compile(rb"(\n[ \t]*v[ \t]+)(\S+)([ \t]+)(\S+)([ \t]+)(\S+)")
_OBJ_V_ANY = re.compile(rb"\n[ \t]*v[ \t]")
_OBJ_MTLLIB = re.compile(rb"\n[ \t]*mtllib[ \t]+([^\r\n]*)")


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


def _write_scaled_obj(src: Path, dst: Path, scale: float,
                      progress: Progress = _no_progress) -> list[Path]:
    """Rewrite only the x y z of 'v' lines; copy the MTL files and their textures."""
    mtllibs: list[str] = []

    def scaled(m: re.Match[bytes]) -> bytes:
        # %r: shortest repr that reads back exactly; float() raises ValueError on a bad token
        return b"%s%r%s%r%s%r" % (m[1], float(m[2]) * scale, m[3], float(m[4]) * scale,
                                  m[5], float(m[6]) * scale)

    first_line, n_vertices = 1, 0
    with open(src, "rb") as fi, _AtomicOutput(dst) as fo:
        for block in _line_blocks(fi):
            block = b"\n" + block
            try:
                out, n_scaled = _OBJ_V_LINE.subn(scaled, block)
            except ValueError:
                n_scaled = -1
            if n_scaled != len(_OBJ_V_ANY.findall(block)):
                _raise_bad_xyz_line(block[1:], _OBJ_V, first_line, src)
            n_vertices += n_scaled
            fo.write(out[1:])
            progress(len(block) - 1)
            mtllibs += [m.decode("utf-8", "surrogateescape").strip()
                        for m in _OBJ_MTLLIB.findall(block)]
            first_line += block.count(b"\n") - 1
        if n_vertices == 0:
            raise InputError("no 'v' lines: not an OBJ mesh", src)
    written = [dst]
    for entry in mtllibs:
        for name in _mtllib_names(entry, src.parent):
            _copy_side_file(name, src.parent, dst.parent, written)
            for tex in _mtl_textures(src.parent / name):
                rel = (Path(name).parent / tex).as_posix() if not Path(tex).is_absolute() else tex
                _copy_side_file(rel, src.parent, dst.parent, written)
    return written


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


def _mtllib_names(entry: str, obj_dir: Path) -> list[str]:
    """File names in an 'mtllib' entry: the whole entry if such a file exists, else its words."""
    return [entry] if (obj_dir / entry).is_file() else entry.split()


#: MTL texture options and how many arguments they take (-o/-s/-t take 1 to 3 numbers).
_MTL_OPTION_ARGS = {
    "-blendu": 1, "-blendv": 1, "-boost": 1, "-cc": 1, "-clamp": 1, "-imfchan": 1,
    "-texres": 1, "-type": 1, "-bm": 1, "-mm": 2, "-o": 3, "-s": 3, "-t": 3,
}
_MTL_MAP_KEYS = {"bump", "disp", "decal", "refl", "norm"}


def _mtl_textures(mtl: Path) -> list[str]:
    """Texture file names referenced by an MTL file (map_*, bump, disp, decal, refl, norm)."""
    if not mtl.is_file():
        return []
    out = []
    for line in mtl.read_bytes().decode("utf-8", "surrogateescape").splitlines():
        words = line.split()
        if not words or not (words[0].lower().startswith("map_") or
                             words[0].lower() in _MTL_MAP_KEYS):
            continue
        name = _mtl_map_filename(words[1:], mtl.parent)
        if name:
            out.append(name)
    return out


def _mtl_map_filename(args: list[str], mtl_dir: Path) -> str | None:
    """The file name of a texture statement after its options (names may contain spaces)."""
    i = 0
    while i < len(args) and args[i].startswith("-") and not _is_number(args[i]):
        n = _MTL_OPTION_ARGS.get(args[i].lower(), 1)
        i += 1
        if n == 3:  # 1 to 3 numbers
            k = 0
            while k < 3 and i < len(args) - 1 and _is_number(args[i]):
                i, k = i + 1, k + 1
        else:
            i += n
    rest = args[i:]
    if not rest:
        return None
    whole = " ".join(rest)
    if len(rest) > 1 and not (mtl_dir / whole).is_file():
        return rest[-1]
    return whole


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


# ----------------------------------------------------------------------------- glTF / GLB

_GLB_MAGIC = b"glTF"
_GLB_JSON, _GLB_BIN = 0x4E4F534A, 0x004E4942
_GLTF_FLOAT = 5126


def _read_glb(path: Path) -> tuple[dict[str, Any], bytearray | None]:
    """GLB -> (JSON dict, BIN chunk or None)."""
    raw = path.read_bytes()
    if len(raw) < 20 or raw[:4] != _GLB_MAGIC:
        raise InputError("not a GLB file (bad magic)", path)
    version, length = struct.unpack_from("<II", raw, 4)
    if version != 2 or length > len(raw):
        raise InputError(f"unsupported or truncated GLB (version {version})", path)
    pos, doc, binary = 12, None, None
    while pos + 8 <= length:
        size, kind = struct.unpack_from("<II", raw, pos)
        chunk = raw[pos + 8: pos + 8 + size]
        if len(chunk) != size:
            raise InputError("truncated GLB chunk", path)
        if kind == _GLB_JSON and doc is None:
            doc = _parse_json(chunk, path)
        elif kind == _GLB_BIN and binary is None:
            binary = bytearray(chunk)
        pos += 8 + size
    if doc is None:
        raise InputError("GLB has no JSON chunk", path)
    return doc, binary


def _parse_json(raw: bytes, path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"invalid glTF JSON: {exc}", path) from exc
    if not isinstance(doc, dict):
        raise InputError("invalid glTF JSON: not an object", path)
    return doc


def _glb_bytes(doc: dict[str, Any], binary: bytearray | None) -> bytes:
    """Assemble a GLB from its JSON and BIN chunk (4-byte padding: spaces / zeros)."""
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<II", len(js), _GLB_JSON) + js
    if binary is not None:
        data = bytes(binary) + b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(data), _GLB_BIN) + data
    return _GLB_MAGIC + struct.pack("<II", 2, 12 + len(chunks)) + chunks


def _gltf_position_accessors(doc: dict[str, Any]) -> list[int]:
    """Indices of accessors holding positions (primitive POSITION and morph-target POSITION)."""
    found: set[int] = set()
    for mesh in doc.get("meshes", []):
        for prim in mesh.get("primitives", []):
            for attrs in [prim.get("attributes", {}), *prim.get("targets", [])]:
                if "POSITION" in attrs:
                    found.add(int(attrs["POSITION"]))
    return sorted(found)


def _gltf_can_scale_buffers(doc: dict[str, Any]) -> bool:
    """True when every position accessor is plain float VEC3 data in a buffer view."""
    if "KHR_draco_mesh_compression" in doc.get("extensionsUsed", []):
        return False
    accessors = doc.get("accessors", [])
    for i in _gltf_position_accessors(doc):
        acc = accessors[i]
        if (acc.get("componentType") != _GLTF_FLOAT or acc.get("type") != "VEC3"
                or "sparse" in acc or "bufferView" not in acc):
            return False
    return True


def _scale_gltf_doc(doc: dict[str, Any], buffers: list[bytearray], scale: float) -> None:
    """Scale positions in ``buffers`` (in place), accessor min/max and node translations."""
    accessors, views = doc["accessors"], doc.get("bufferViews", [])
    done: set[tuple[int, int, int, int]] = set()
    for i in _gltf_position_accessors(doc):
        acc = accessors[i]
        view = views[acc["bufferView"]]
        offset = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
        stride = int(view.get("byteStride", 12))
        key = (int(view["buffer"]), offset, stride, int(acc["count"]))
        if key not in done:  # two accessors on the same bytes: scale once
            done.add(key)
            arr = np.ndarray((key[3], 3), dtype="<f4", buffer=buffers[key[0]], offset=offset,
                             strides=(stride, 4))
            arr[...] = arr.astype(np.float64) * scale
        for bound in ("min", "max"):
            if bound in acc:
                acc[bound] = [float(np.float32(v * scale)) for v in acc[bound]]
    for node in doc.get("nodes", []):
        if "translation" in node:
            node["translation"] = [v * scale for v in node["translation"]]
        if "matrix" in node:  # column-major 4x4: translation is elements 12..14
            node["matrix"] = [v * scale if k in (12, 13, 14) else v
                              for k, v in enumerate(node["matrix"])]


def _write_scaled_gltf(src: Path, dst: Path, scale: float) -> list[Path]:
    """glTF/GLB: scale position data in the buffers; other buffer bytes and images unchanged."""
    try:
        if src.suffix.lower() == ".glb":
            doc, binary = _read_glb(src)
            buffers = _gltf_buffers(doc, src, binary)
        else:
            doc, binary = _parse_json(src.read_bytes(), src), None
            buffers = _gltf_buffers(doc, src, None)
        if not _gltf_can_scale_buffers(doc):
            raise InputError("glTF with compressed, quantised or sparse positions is not "
                             "supported: export the mesh as PLY", src)
        _scale_gltf_doc(doc, buffers, scale)
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"invalid glTF structure: {type(exc).__name__}: {exc}", src) from exc
    return _write_gltf_outputs(src, dst, doc, buffers, src.suffix.lower() == ".glb", binary)


def _gltf_buffers(doc: dict[str, Any], src: Path, binary: bytearray | None) -> list[bytearray]:
    """Contents of every glTF buffer (GLB BIN chunk, data: URI or external file)."""
    out = []
    for i, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if uri is None:
            if i != 0 or binary is None:
                raise InputError(f"glTF buffer {i} has no data", src)
            out.append(binary)
        elif uri.startswith("data:"):
            out.append(bytearray(base64.b64decode(uri.split(",", 1)[1])))
        else:
            file = src.parent / _unquote(uri)
            if not file.is_file():
                raise InputError(f"glTF buffer file {uri!r} not found", src)
            out.append(bytearray(file.read_bytes()))
    return out


def _unquote(uri: str) -> str:
    from urllib.parse import unquote

    return unquote(uri)


def _write_gltf_outputs(src: Path, dst: Path, doc: dict[str, Any], buffers: list[bytearray],
                        glb: bool, binary: bytearray | None) -> list[Path]:
    """Write the scaled glTF/GLB, its external buffers (scaled) and its images (copied)."""
    written = [dst]
    for i, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if uri is None:
            continue
        if uri.startswith("data:"):
            head = uri.split(",", 1)[0]
            buf["uri"] = head + "," + base64.b64encode(bytes(buffers[i])).decode("ascii")
        else:
            target = dst.parent / _unquote(uri)
            if not target.resolve().is_relative_to(dst.parent.resolve()):
                raise InputError(f"glTF buffer {uri!r} points outside the mesh folder", src)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(bytes(buffers[i]))
            written.append(target)
    with _AtomicOutput(dst) as fo:
        if glb:
            first = doc.get("buffers", [{}])[0] if doc.get("buffers") else {}
            fo.write(_glb_bytes(doc, buffers[0] if buffers and "uri" not in first else binary))
        else:
            fo.write(json.dumps(doc, indent=2).encode("utf-8"))
    for image in doc.get("images", []):
        uri = image.get("uri")
        if uri and not uri.startswith("data:"):
            _copy_side_file(_unquote(uri), src.parent, dst.parent, written)
    return written


# ----------------------------------------------------------------------------- OFF / STL


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
