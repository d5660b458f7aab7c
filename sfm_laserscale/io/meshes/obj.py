"""Wavefront OBJ meshes: read (our own numpy reader, polygons fan-triangulated) and rewrite
with only the x y z of the ``v`` lines rescaled; MTL files and their textures are copied."""

from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.meshes.common import (
    Progress,
    _AtomicOutput,
    _copy_side_file,
    _distinct_counts,
    _fan_triangulate,
    _line_blocks,
    _no_progress,
    _raise_bad_xyz_line,
    _xyz_pattern,
)

# ----------------------------------------------------------------------------- OBJ read


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


# ----------------------------------------------------------------------------- OBJ rescale


_OBJ_V = _xyz_pattern(rb"v[ \t]+")


# patterns start with a literal "\n" (blocks get one prepended): much faster than "^" + re.M
_OBJ_V_LINE = re.compile(rb"(\n[ \t]*v[ \t]+)(\S+)([ \t]+)(\S+)([ \t]+)(\S+)")
_OBJ_V_ANY = re.compile(rb"\n[ \t]*v[ \t]")
_OBJ_MTLLIB = re.compile(rb"\n[ \t]*mtllib[ \t]+([^\r\n]*)")


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
