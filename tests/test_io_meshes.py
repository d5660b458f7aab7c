"""Mesh reading and byte-preserving rescaling (sfm_laserscale.io.meshes).

Test files are written with plyfile / trimesh / by hand (independent writers); the checks
parse the outputs independently of the code under test.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh
from plyfile import PlyData, PlyElement

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.meshes.mesh import TriangleMesh, load_mesh, write_scaled_mesh

SCALE = 2.5
TEXTURE_BYTES = b"\x89PNG fake texture \x00\x01\x02"

VERTEX_DTYPE = [
    ("x", "f4"), ("y", "f4"), ("z", "f4"), ("nx", "f4"), ("ny", "f4"), ("nz", "f4"),
    ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1"), ("quality", "f4"),
]


def _vertices(n: int = 12, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = np.zeros(n, dtype=VERTEX_DTYPE)
    for name in ("x", "y", "z", "nx", "ny", "nz", "quality"):
        v[name] = rng.normal(size=n) * 3.1
    for name in ("red", "green", "blue", "alpha"):
        v[name] = rng.integers(0, 256, size=n)
    return v


def _faces(polygons: list[list[int]], seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = np.empty(len(polygons), dtype=[("vertex_indices", "O"), ("texcoord", "O")])
    for i, poly in enumerate(polygons):
        f[i] = (np.array(poly, dtype=np.int32), rng.random(2 * len(poly)).astype(np.float32))
    return f


TRIANGLES = [[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 7, 8], [8, 9, 10], [10, 11, 0], [1, 3, 5]]
QUADS = [[0, 1, 2, 3], [3, 4, 5, 6], [6, 7, 8, 9], [9, 10, 11, 0]]
MIXED = [[0, 1, 2, 3], [3, 4, 5], [5, 6, 7, 8, 9], [9, 10, 11], [11, 0, 1]]


def _fan(polygons: list[list[int]]) -> np.ndarray:
    return np.array([[p[0], p[k], p[k + 1]] for p in polygons for k in range(1, len(p) - 1)])


def _write_ply(path: Path, fmt: str, polygons: list[list[int]] = TRIANGLES,
               vertex_first: bool = True) -> np.ndarray:
    """OpenMVS-style PLY (vertex_indices + texcoord lists, TextureFile comment)."""
    v = _vertices()
    vert = PlyElement.describe(v, "vertex")
    face = PlyElement.describe(
        _faces(polygons), "face",
        len_types={"vertex_indices": "u1", "texcoord": "u1"},
        val_types={"vertex_indices": "i4", "texcoord": "f4"},
    )
    elements = [vert, face] if vertex_first else [face, vert]
    byte_order = {"le": "<", "be": ">", "ascii": "="}[fmt]
    PlyData(elements, text=fmt == "ascii", byte_order=byte_order,
            comments=["TextureFile tex.png", "made by the test"]).write(str(path))
    (path.parent / "tex.png").write_bytes(TEXTURE_BYTES)
    return v


def _header_len(raw: bytes) -> int:
    return raw.index(b"end_header\n") + len(b"end_header\n")


# ----------------------------------------------------------------------------- load_mesh


@pytest.mark.parametrize("fmt", ["le", "be", "ascii"])
@pytest.mark.parametrize("vertex_first", [True, False])
@pytest.mark.parametrize("polygons", [TRIANGLES, QUADS, MIXED], ids=["tris", "quads", "mixed"])
def test_load_ply(tmp_path: Path, fmt: str, vertex_first: bool,
                  polygons: list[list[int]]) -> None:
    v = _write_ply(tmp_path / "m.ply", fmt, polygons, vertex_first)
    mesh = load_mesh(tmp_path / "m.ply")
    assert isinstance(mesh, TriangleMesh)
    # binary float32 files keep float32 vertices (exact); ASCII ones are parsed to float64
    assert mesh.vertices.dtype == (np.float64 if fmt == "ascii" else v["x"].dtype)
    assert mesh.triangles.dtype == np.int32
    expected = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    np.testing.assert_array_equal(mesh.vertices, expected)
    np.testing.assert_array_equal(mesh.triangles, _fan(polygons))
    np.testing.assert_array_equal(mesh.bounds, [expected.min(0), expected.max(0)])
    assert mesh.extent == pytest.approx(np.linalg.norm(np.ptp(expected, axis=0)))


def test_load_and_rescale_ply_with_list_property_in_vertex(tmp_path: Path) -> None:
    """Variable-size vertex rows (a list property before x) are read and rescaled right.

    Written by hand: plyfile 1.1.5 writes the scalar fields of big-endian elements that
    have list properties in native (little-endian) order.
    """
    header = (b"ply\nformat binary_big_endian 1.0\nelement vertex 3\n"
              b"property list uchar short tags\nproperty double x\nproperty double y\n"
              b"property double z\nelement face 1\nproperty list uchar int vertex_indices\n"
              b"end_header\n")
    xyz = [[0.5, 0.0, 0.0], [1.5, -1.0, 2.0], [2.5, -2.0, 4.0]]
    rows = [struct.pack(f">B{i + 1}h3d", i + 1, *range(i + 1), *xyz[i]) for i in range(3)]
    faces = struct.pack(">B3i", 3, 0, 1, 2)
    (tmp_path / "in").mkdir()
    src = tmp_path / "in" / "v.ply"
    src.write_bytes(header + b"".join(rows) + faces)
    mesh = load_mesh(src)
    np.testing.assert_array_equal(mesh.vertices, xyz)
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2]])
    out = write_scaled_mesh(src, tmp_path / "out", SCALE)
    new_rows = [struct.pack(f">B{i + 1}h3d", i + 1, *range(i + 1), *(np.array(xyz[i]) * SCALE))
                for i in range(3)]
    assert out[0].read_bytes() == header + b"".join(new_rows) + faces


OBJ_TEXT = """# test OBJ
mtllib materials.mtl
o thing
v 0.0 0.0 0.0
v 1.0  0.0 0.0 1.0
v 1.0 1.0 0.0 0.5 0.25 0.125
v\t0.0 1.0 0.0
v 0.5 0.5 1.25
vt 0.0 0.0
vt 1.0 0.0
vt 1.0 1.0
vn 0.0 0.0 1.0
usemtl mat1
f 1/1/1 2/2/1 3/3/1 4/1/1
f -1//1 -5//1 -4//1
s off
f 2 3 5
l 1 2
"""

MTL_TEXT = """newmtl mat1
Kd 1 1 1
map_Kd -s 1 1 1 -o 0 0 textures/diffuse.png
map_Bump -bm 0.5 bump map.png
norm normals.png
map_Ks missing.png
"""


def _write_obj(folder: Path, crlf: bool = False) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    text = OBJ_TEXT.replace("\n", "\r\n") if crlf else OBJ_TEXT
    (folder / "mesh.obj").write_bytes(text.encode())
    (folder / "materials.mtl").write_text(MTL_TEXT)
    (folder / "textures").mkdir(exist_ok=True)
    (folder / "textures" / "diffuse.png").write_bytes(TEXTURE_BYTES + b"d")
    (folder / "bump map.png").write_bytes(TEXTURE_BYTES + b"b")
    (folder / "normals.png").write_bytes(TEXTURE_BYTES + b"n")
    return folder / "mesh.obj"


OBJ_VERTICES = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1.25]]
OBJ_TRIANGLES = [[0, 1, 2], [0, 2, 3], [4, 0, 1], [1, 2, 4]]


def test_load_obj_triangulates_quads_and_resolves_negative_indices(tmp_path: Path) -> None:
    mesh = load_mesh(_write_obj(tmp_path / "in"))
    np.testing.assert_array_equal(mesh.vertices, OBJ_VERTICES)
    np.testing.assert_array_equal(mesh.triangles, OBJ_TRIANGLES)


def test_load_obj_matches_trimesh(tmp_path: Path) -> None:
    """Same triangles (as vertex positions) as trimesh's independent OBJ reader.

    (trimesh 5.2 fails on OBJ_TEXT's mix of face formats, so a plainer file is used.)
    """
    rng = np.random.default_rng(3)
    verts = rng.normal(size=(9, 3))
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in verts.tolist()]
    lines += ["f 1 2 3 4", "f 4 5 6", "f 6 7 8 9 1", "f 2 9 5"]
    path = tmp_path / "plain.obj"
    path.write_text("\n".join(lines) + "\n")
    ours = load_mesh(path)
    theirs = trimesh.load_mesh(str(path), process=False)
    assert ours.num_triangles == len(theirs.faces) == 2 + 1 + 3 + 1
    key = np.sort(ours.vertices[np.sort(ours.triangles, axis=1)].reshape(-1, 9), axis=0)
    tf = np.sort(np.asarray(theirs.faces), axis=1)
    ref = np.sort(np.asarray(theirs.vertices)[tf].reshape(-1, 9), axis=0)
    np.testing.assert_array_equal(key, ref)


def _box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=[1.0, 2.0, 3.0])


def _export(mesh: trimesh.Trimesh, path: Path) -> None:
    """Write with trimesh; a .gltf is saved as path + its external buffer file."""
    if path.suffix != ".gltf":
        mesh.export(str(path))
        return
    files = mesh.export(file_type="gltf")
    assert isinstance(files, dict)
    for name, data in files.items():
        (path if name.endswith(".gltf") else path.parent / name).write_bytes(data)


@pytest.mark.parametrize("suffix", [".glb", ".off", ".stl", ".gltf"])
def test_load_trimesh_formats(tmp_path: Path, suffix: str) -> None:
    box = _box()
    path = tmp_path / f"box{suffix}"
    _export(box, path)
    mesh = load_mesh(path)
    assert mesh.num_triangles == 12
    np.testing.assert_allclose(mesh.bounds, [[-0.5, -1, -1.5], [0.5, 1, 1.5]])


# ----------------------------------------------------------------------------- rescale PLY


@pytest.mark.parametrize("fmt", ["le", "be"])
@pytest.mark.parametrize("vertex_first", [True, False])
@pytest.mark.parametrize("polygons", [TRIANGLES, MIXED], ids=["tris", "mixed"])
def test_rescale_binary_ply_is_byte_exact(tmp_path: Path, fmt: str, vertex_first: bool,
                                          polygons: list[list[int]]) -> None:
    src = tmp_path / "in" / "mesh.ply"
    src.parent.mkdir()
    v = _write_ply(src, fmt, polygons, vertex_first)
    before = src.read_bytes()
    written = write_scaled_mesh(src, tmp_path / "out", SCALE)
    assert src.read_bytes() == before  # input untouched
    dst = tmp_path / "out" / "mesh.ply"
    assert written == [dst, tmp_path / "out" / "tex.png"]
    assert (tmp_path / "out" / "tex.png").read_bytes() == TEXTURE_BYTES
    raw, new = before, dst.read_bytes()
    assert len(new) == len(raw)
    h = _header_len(raw)
    assert new[:h] == raw[:h]
    bo = "<" if fmt == "le" else ">"
    vdtype = np.dtype([(n, bo + t) for n, t in VERTEX_DTYPE])
    vbytes = len(v) * vdtype.itemsize
    face_bytes = len(raw) - h - vbytes
    vstart = h if vertex_first else h + face_bytes
    fstart = h + vbytes if vertex_first else h
    assert new[fstart:fstart + face_bytes] == raw[fstart:fstart + face_bytes]
    old_rows = np.frombuffer(raw, vdtype, count=len(v), offset=vstart)
    new_rows = np.frombuffer(new, vdtype, count=len(v), offset=vstart)
    np.testing.assert_array_equal(old_rows, v)  # the test's own layout computation is right
    for name, _ in VERTEX_DTYPE:
        if name in "xyz":
            assert new_rows[name].dtype == vdtype[name]
            np.testing.assert_array_equal(new_rows[name], (v[name] * SCALE).astype(np.float32))
        else:
            assert new_rows[name].tobytes() == old_rows[name].tobytes()


def test_rescale_ascii_ply_changes_only_xyz_tokens(tmp_path: Path) -> None:
    src = tmp_path / "in" / "mesh.ply"
    src.parent.mkdir()
    v = _write_ply(src, "ascii", MIXED, vertex_first=False)
    written = write_scaled_mesh(src, tmp_path / "out", SCALE)
    assert (tmp_path / "out" / "tex.png") in written
    raw, new = src.read_bytes(), written[0].read_bytes()
    h = _header_len(raw)
    assert new[:h] == raw[:h]
    old_lines, new_lines = raw[h:].split(b"\n"), new[h:].split(b"\n")
    assert len(old_lines) == len(new_lines)
    n_faces = len(MIXED)
    assert old_lines[:n_faces] == new_lines[:n_faces]  # faces come first here
    assert old_lines[n_faces + len(v):] == new_lines[n_faces + len(v):]
    for i, (a, b) in enumerate(zip(old_lines[n_faces:n_faces + len(v)],
                                   new_lines[n_faces:n_faces + len(v)], strict=True)):
        ta, tb = a.split(), b.split()
        assert ta[3:] == tb[3:]
        for k, axis in enumerate("xyz"):
            assert np.float32(tb[k].decode()) == np.float32(v[axis][i] * SCALE)
    back = load_mesh(written[0])
    np.testing.assert_array_equal(back.vertices[:, 0], (v["x"] * SCALE).astype(np.float32))


def test_rescale_ascii_ply_keeps_whitespace_and_double_precision(tmp_path: Path) -> None:
    text = (
        "ply\r\nformat ascii 1.0\r\nelement vertex 2\r\nproperty double x\r\n"
        "property double y\r\nproperty double z\r\nproperty uchar red\r\n"
        "element face 1\r\nproperty list uchar int vertex_indices\r\nend_header\r\n"
        "  0.1\t0.2   0.3 7\r\n\r\n1e-3 2 3 8\r\n3 0 1 1\r\n"
    )
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "d.ply").write_bytes(text.encode())
    out = write_scaled_mesh(tmp_path / "in" / "d.ply", tmp_path / "out", 3.0)
    expected = text.replace("  0.1\t0.2   0.3 7", f"  {0.1 * 3!r}\t{0.2 * 3!r}   {0.3 * 3!r} 7")
    expected = expected.replace("1e-3 2 3 8", f"{1e-3 * 3!r} 6.0 9.0 8")
    assert out[0].read_bytes() == expected.encode()


def test_rescale_ply_is_float64_exact_for_general_scale(tmp_path: Path) -> None:
    """float32 x scaled by a non-representable factor: float64 product rounded once."""
    src = tmp_path / "in" / "m.ply"
    src.parent.mkdir()
    v = _write_ply(src, "le")
    s = 0.0123456789
    out = write_scaled_mesh(src, tmp_path / "out", s)
    back = PlyData.read(str(out[0]))["vertex"].data
    np.testing.assert_array_equal(back["y"], (v["y"].astype(np.float64) * s).astype(np.float32))


# ----------------------------------------------------------------------------- rescale OBJ


@pytest.mark.parametrize("crlf", [False, True])
def test_rescale_obj_changes_only_v_lines_and_copies_textures(tmp_path: Path,
                                                             crlf: bool) -> None:
    src = _write_obj(tmp_path / "in", crlf)
    before = src.read_bytes()
    written = write_scaled_mesh(src, tmp_path / "out", SCALE)
    assert src.read_bytes() == before
    out = tmp_path / "out"
    assert set(written) == {out / "mesh.obj", out / "materials.mtl",
                            out / "textures" / "diffuse.png", out / "bump map.png",
                            out / "normals.png"}  # missing.png: warned, not copied
    for rel in ["materials.mtl", "textures/diffuse.png", "bump map.png", "normals.png"]:
        assert (out / rel).read_bytes() == (src.parent / rel).read_bytes()
    old_lines = before.split(b"\n")
    new_lines = (out / "mesh.obj").read_bytes().split(b"\n")
    assert len(old_lines) == len(new_lines)
    n_v = 0
    for a, b in zip(old_lines, new_lines, strict=True):
        if a.lstrip().startswith((b"v ", b"v\t")):
            ta, tb = a.split(), b.split()
            assert tb[0] == b"v" and ta[4:] == tb[4:]  # w or r g b kept verbatim
            assert [float(t) for t in tb[1:4]] == [float(t) * SCALE for t in ta[1:4]]
            assert a.endswith(b"\r") == b.endswith(b"\r")
            n_v += 1
        else:
            assert a == b
    assert n_v == 5
    np.testing.assert_array_equal(load_mesh(out / "mesh.obj").vertices,
                                  np.array(OBJ_VERTICES) * SCALE)


def test_rescale_obj_without_mtl(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    src = tmp_path / "in" / "plain.obj"
    src.write_text("v 1 2 3\nv 4 5 6\nv 7 8 9\nf 1 2 3\n")
    written = write_scaled_mesh(src, tmp_path / "out", 2.0)
    assert written == [tmp_path / "out" / "plain.obj"]
    assert written[0].read_text() == "v 2.0 4.0 6.0\nv 8.0 10.0 12.0\nv 14.0 16.0 18.0\nf 1 2 3\n"


# ----------------------------------------------------------------------------- rescale others


def _gltf_positions(path: Path) -> np.ndarray:
    return load_mesh(path).vertices


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_rescale_gltf_scales_position_buffer(tmp_path: Path, suffix: str) -> None:
    (tmp_path / "in").mkdir()
    box = _box()
    box.apply_translation([10.0, 0.0, 0.0])
    src = tmp_path / "in" / f"box{suffix}"
    _export(box, src)
    written = write_scaled_mesh(src, tmp_path / "out", SCALE)
    np.testing.assert_allclose(load_mesh(written[0]).vertices, load_mesh(src).vertices * SCALE)
    doc = _gltf_json(written[0])
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    np.testing.assert_allclose(acc["min"], [9.5 * SCALE, -1 * SCALE, -1.5 * SCALE])
    np.testing.assert_allclose(acc["max"], [10.5 * SCALE, 1 * SCALE, 1.5 * SCALE])
    _check_only_positions_changed(src, written[0], SCALE)
    if suffix == ".gltf":  # the external buffers were written beside it
        assert sorted(p.name for p in written[1:]) == ["gltf_buffer_0.bin", "gltf_buffer_1.bin"]


def _gltf_buffer_bytes(path: Path) -> list[bytes]:
    raw = path.read_bytes()
    if raw[:4] == b"glTF":
        json_size = struct.unpack_from("<I", raw, 12)[0]
        bin_size = struct.unpack_from("<I", raw, 20 + json_size)[0]
        return [raw[28 + json_size: 28 + json_size + bin_size]]
    return [(path.parent / b["uri"]).read_bytes() for b in json.loads(raw)["buffers"]]


def _check_only_positions_changed(src: Path, dst: Path, scale: float) -> None:
    """Every buffer byte outside POSITION accessors identical; positions x scale in float32."""
    doc = _gltf_json(src)
    old, new = _gltf_buffer_bytes(src), _gltf_buffer_bytes(dst)
    assert [len(b) for b in old] == [len(b) for b in new]
    changed = [np.frombuffer(a, np.uint8) != np.frombuffer(b, np.uint8)
               for a, b in zip(old, new, strict=True)]
    pos = doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    acc = doc["accessors"][pos]
    view = doc["bufferViews"][acc["bufferView"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    a = np.frombuffer(old[view["buffer"]], "<f4", acc["count"] * 3, start)
    b = np.frombuffer(new[view["buffer"]], "<f4", acc["count"] * 3, start)
    np.testing.assert_array_equal(b, (a.astype(np.float64) * scale).astype(np.float32))
    changed[view["buffer"]][start:start + 12 * acc["count"]] = False
    assert not any(c.any() for c in changed)


def _gltf_json(path: Path) -> dict:
    raw = path.read_bytes()
    if raw[:4] == b"glTF":
        size = struct.unpack_from("<I", raw, 12)[0]
        return json.loads(raw[20:20 + size])
    return json.loads(raw)


def test_rescale_binary_stl_is_byte_exact(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    src = tmp_path / "in" / "box.stl"
    _box().export(str(src))
    raw = bytearray(src.read_bytes())
    raw[:80] = b"solid-looking header of a binary STL".ljust(80, b" ")
    dtype = np.dtype([("n", "<f4", (3,)), ("v", "<f4", (9,)), ("a", "<u2")])
    rows = np.frombuffer(raw, dtype, offset=84).copy()
    rows["a"] = np.arange(len(rows)) * 1000 + 7  # attribute bytes must survive
    raw[84:] = rows.tobytes()
    src.write_bytes(bytes(raw))
    written = write_scaled_mesh(src, tmp_path / "out", SCALE)
    new = written[0].read_bytes()
    assert len(new) == len(raw) and new[:84] == raw[:84]
    out = np.frombuffer(new, dtype, offset=84)
    assert out["n"].tobytes() == rows["n"].tobytes()
    assert out["a"].tobytes() == rows["a"].tobytes()
    np.testing.assert_array_equal(out["v"], (rows["v"] * SCALE).astype(np.float32))
    np.testing.assert_allclose(load_mesh(written[0]).bounds, load_mesh(src).bounds * SCALE)


def test_rescale_ascii_stl_changes_only_vertex_lines(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    src = tmp_path / "in" / "tri.stl"
    text = ("solid tri\n  facet normal 0 0 1\n    outer loop\n      vertex 0 0 0\n"
            "      vertex 1.5 0 0\n      vertex 0 1 0.25\n    endloop\n  endfacet\nendsolid tri\n")
    src.write_text(text)
    written = write_scaled_mesh(src, tmp_path / "out", 2.0)
    assert written[0].read_text() == text.replace("vertex 0 0 0", "vertex 0.0 0.0 0.0").replace(
        "vertex 1.5 0 0", "vertex 3.0 0.0 0.0").replace("vertex 0 1 0.25", "vertex 0.0 2.0 0.5")


def test_rescale_off_changes_only_vertex_lines(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    src = tmp_path / "in" / "q.off"
    text = ("COFF\n# a comment\n\n5 2 0\n0 0 0 255 0 0 255\n1 0 0 0 255 0 255 # first\n"
            "\t1 1 0 0 0 255 255\n0 1 0 9 9 9 255\n0.5 0.5 2 1 1 1 255\n4 0 1 2 3\n3 0 1 4 8 8 8\n")
    src.write_text(text)
    written = write_scaled_mesh(src, tmp_path / "out", 2.0)
    expected = (text.replace("\n0 0 0 255", "\n0.0 0.0 0.0 255")
                .replace("1 0 0 0 255 0 255 #", "2.0 0.0 0.0 0 255 0 255 #")
                .replace("\t1 1 0 0 0", "\t2.0 2.0 0.0 0 0").replace("\n0 1 0 9", "\n0.0 2.0 0.0 9")
                .replace("0.5 0.5 2 1", "1.0 1.0 4.0 1"))
    assert written[0].read_text() == expected
    mesh = load_mesh(written[0])
    assert mesh.num_triangles == 3
    np.testing.assert_array_equal(mesh.vertices[4], [1.0, 1.0, 4.0])


# ----------------------------------------------------------------------------- errors


def _cut(path: Path, keep: int) -> Path:
    raw = path.read_bytes()
    path.write_bytes(raw[:keep])
    return path


BAD_CASES: dict[str, tuple[str, bytes]] = {
    "empty": ("e.ply", b""),
    "not ply": ("n.ply", b"solid nothing\nendsolid\n"),
    "no end_header": ("h.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n"),
    "bad header line": ("b.ply", b"ply\nformat ascii 1.0\nbogus line\nend_header\n"),
    "point cloud": ("p.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                    b"property float y\nproperty float z\nend_header\n1 2 3\n4 5 6\n"),
    "nan vertex": ("nan.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                   b"property float y\nproperty float z\nelement face 1\n"
                   b"property list uchar int vertex_indices\nend_header\n"
                   b"0 0 0\n1 nan 0\n0 1 0\n3 0 1 2\n"),
    "index out of range": ("r.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n"
                           b"property float x\nproperty float y\nproperty float z\n"
                           b"element face 1\nproperty list uchar int vertex_indices\n"
                           b"end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n"),
    "ascii too few rows": ("t.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n"
                           b"property float x\nproperty float y\nproperty float z\n"
                           b"element face 1\nproperty list uchar int vertex_indices\n"
                           b"end_header\n0 0 0\n1 0 0\n"),
    "ascii junk": ("j.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n"
                   b"property float x\nproperty float y\nproperty float z\n"
                   b"element face 1\nproperty list uchar int vertex_indices\n"
                   b"end_header\n0 0 0\n1 zero 0\n0 1 0\n3 0 1 2\n"),
    "ascii bad list length": ("l.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n"
                              b"property float x\nproperty float y\nproperty float z\n"
                              b"element face 1\nproperty list uchar int vertex_indices\n"
                              b"end_header\n0 0 0\n1 0 0\n0 1 0\n5 0 1 2\n"),
    "ascii fractional index": ("fi.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n"
                               b"property float x\nproperty float y\nproperty float z\n"
                               b"element face 1\nproperty list uchar int vertex_indices\n"
                               b"end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1.5 2\n"),
    "ascii short vertex row": ("sv.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n"
                               b"property float x\nproperty float y\nproperty float z\n"
                               b"element face 1\nproperty list uchar int vertex_indices\n"
                               b"end_header\n0 0 0\n1 0\n0 1 0\n3 0 1 2\n"),
    "no vertex element": ("nv.ply", b"ply\nformat ascii 1.0\nelement face 1\n"
                          b"property list uchar int vertex_indices\nend_header\n3 0 1 2\n"),
    "bad format": ("bf.ply", b"ply\nformat binary_middle_endian 1.0\nend_header\n"),
    "obj nan": ("nan.obj", b"v 0 0 0\nv 1 inf 0\nv 0 1 0\nf 1 2 3\n"),
    "obj out of range": ("r.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n"),
    "obj negative out of range": ("nr.obj", b"v 0 0 0\nv 1 0 0\nf -1 -2 -3\n"),
    "obj index zero": ("z.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n"),
    "obj bad v": ("bv.obj", b"v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n"),
    "obj bad f": ("bf.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 a 3\n"),
    "obj no faces": ("nf.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
    "obj binary junk": ("bj.obj", bytes(range(256)) * 4),
    "unknown extension": ("m.xyz", b"0 0 0\n"),
    "glb junk": ("g.glb", b"glTF\x02\x00\x00\x00garbage garbage garbage"),
    "gltf junk": ("g.gltf", b"{not json"),
    "off junk": ("o.off", b"OFF\n3 1 0\n0 0 0\n1 0\n"),
    "stl junk": ("s.stl", b"\x00" * 80 + struct.pack("<I", 5) + b"\x00" * 20),
}


RESCALE_BAD_CASES = ["empty", "not ply", "no end_header", "bad header line", "ascii too few rows",
                     "obj bad v", "obj binary junk", "unknown extension", "glb junk",
                     "gltf junk", "off junk", "stl junk", "no vertex element", "bad format",
                     "glb bad magic", "ascii short vertex row"]
BAD_CASES["glb bad magic"] = ("m.glb", b"GLTF" + bytes(40))


@pytest.mark.parametrize("case", RESCALE_BAD_CASES)
def test_rescale_input_errors(tmp_path: Path, case: str) -> None:
    name, data = BAD_CASES[case]
    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(InputError) as err:
        write_scaled_mesh(path, tmp_path / "out", SCALE)
    assert err.value.path == str(path)


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_load_errors(tmp_path: Path, case: str) -> None:
    name, data = BAD_CASES[case]
    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(InputError) as err:
        load_mesh(path)
    assert err.value.path == str(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="does not exist"):
        load_mesh(tmp_path / "none.ply")
    with pytest.raises(InputError, match="does not exist"):
        write_scaled_mesh(tmp_path / "none.obj", tmp_path / "out", 2.0)


@pytest.mark.parametrize("fmt", ["le", "be"])
@pytest.mark.parametrize("where", ["header", "vertices", "faces"])
@pytest.mark.parametrize("vertex_first", [True, False])
def test_truncated_binary_ply(tmp_path: Path, fmt: str, where: str, vertex_first: bool) -> None:
    path = tmp_path / "in" / "t.ply"
    path.parent.mkdir()
    _write_ply(path, fmt, MIXED, vertex_first)
    raw = path.read_bytes()
    h = _header_len(raw)
    vbytes = 12 * np.dtype(VERTEX_DTYPE).itemsize
    first_is_vertex = (where == "vertices") == vertex_first
    keep = {"header": h - 5}.get(where, h + (vbytes // 2 if first_is_vertex else 7))
    if where != "header" and not first_is_vertex:
        keep = h + (len(raw) - h - vbytes) // 2
    _cut(path, keep)
    with pytest.raises(InputError):
        load_mesh(path)
    if where != "faces" or not vertex_first:  # trailing faces are copied verbatim
        with pytest.raises(InputError):
            write_scaled_mesh(path, tmp_path / "out", SCALE)


def test_binary_ply_index_out_of_range(tmp_path: Path) -> None:
    path = tmp_path / "o.ply"
    _write_ply(path, "le", [[0, 1, 12]])
    with pytest.raises(InputError, match="out of range"):
        load_mesh(path)


def test_rescale_errors(tmp_path: Path) -> None:
    src = tmp_path / "m.ply"
    _write_ply(src, "le")
    with pytest.raises(InputError, match="differ"):
        write_scaled_mesh(src, tmp_path, SCALE)
    with pytest.raises(InputError, match="positive"):
        write_scaled_mesh(src, tmp_path / "out", -1.0)
    with pytest.raises(InputError, match="unknown mesh extension"):
        write_scaled_mesh(tmp_path / "m.3ds", tmp_path / "out", SCALE)
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        write_scaled_mesh(src, tmp_path / "file", SCALE)
    ints = tmp_path / "i.ply"
    ints.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty int x\n"
                     b"property int y\nproperty int z\nend_header\n1 2 3\n")
    with pytest.raises(InputError, match="integer"):
        write_scaled_mesh(ints, tmp_path / "out", SCALE)
    obj = tmp_path / "bad.obj"
    obj.write_bytes(b"v 1 2\nf 1 1 1\n")
    with pytest.raises(InputError, match="line 1"):
        write_scaled_mesh(obj, tmp_path / "out", SCALE)
    assert not (tmp_path / "out" / "bad.obj").exists()  # no partial output left behind
    assert not list((tmp_path / "out").glob("*.partial"))


# ----------------------------------------------------------------------------- code paths


def _single_list_ply(path: Path, sizes: list[int], truncate: int = 0) -> tuple[np.ndarray, list]:
    """Binary LE PLY, faces (one uchar list, mixed sizes) before vertices: the fast row loop."""
    rng = np.random.default_rng(5)
    xyz = rng.normal(size=(10, 3)).astype("<f4")
    polys = [list(rng.choice(10, n, replace=False)) for n in sizes]
    faces = b"".join(struct.pack(f"<B{len(p)}i", len(p), *p) for p in polys)
    header = (f"ply\r\nformat binary_little_endian 1.0\r\nobj_info made by hand\r\n"
              f"element face {len(polys)}\r\nproperty list uchar int vertex_indices\r\n"
              f"element vertex 10\r\nproperty float x\r\nproperty float y\r\nproperty float z\r\n"
              f"end_header\r\n").encode()
    data = header + faces + xyz.tobytes()
    path.write_bytes(data[: len(data) - truncate])
    return xyz, polys


def test_single_list_variable_faces_before_vertices(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    src = tmp_path / "in" / "s.ply"
    xyz, polys = _single_list_ply(src, [3, 4, 3, 5, 3, 3, 4])
    mesh = load_mesh(src)
    np.testing.assert_array_equal(mesh.vertices, xyz.astype(np.float64))
    np.testing.assert_array_equal(mesh.triangles, _fan(polys))
    out = write_scaled_mesh(src, tmp_path / "out", SCALE)[0].read_bytes()
    raw = src.read_bytes()
    assert out[: len(raw) - 120] == raw[: len(raw) - 120]
    np.testing.assert_array_equal(np.frombuffer(out[-120:], "<f4").reshape(10, 3),
                                  (xyz * SCALE).astype(np.float32))
    _single_list_ply(src, [3, 4, 3, 5, 3, 3, 4], truncate=120 + 5)  # cut inside the faces
    with pytest.raises(InputError, match="truncated"):
        load_mesh(src)
    with pytest.raises(InputError, match="truncated"):
        write_scaled_mesh(src, tmp_path / "out", SCALE)


def test_streaming_in_small_chunks_and_without_sendfile(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Multi-chunk PLY/OBJ rewriting gives the same bytes as one chunk (and no sendfile)."""
    from sfm_laserscale.io.meshes import common
    from sfm_laserscale.io.meshes import ply as ply_format

    ply = tmp_path / "in" / "mesh.ply"
    ply.parent.mkdir()
    _write_ply(ply, "be", MIXED, vertex_first=False)
    obj = _write_obj(tmp_path / "in")
    reference = [p.read_bytes() for p in (write_scaled_mesh(ply, tmp_path / "a", SCALE)[0],
                                          write_scaled_mesh(obj, tmp_path / "a", SCALE)[0])]

    def no_sendfile(*args: object) -> int:
        raise OSError("sendfile not supported")

    monkeypatch.setattr(ply_format, "_SCALE_CHUNK", 3 * 37)  # 3 vertex rows per chunk
    monkeypatch.setattr(common, "_COPY_CHUNK", 16)
    monkeypatch.setattr(common.os, "sendfile", no_sendfile)
    chunked = [p.read_bytes() for p in (write_scaled_mesh(ply, tmp_path / "b", SCALE)[0],
                                        write_scaled_mesh(obj, tmp_path / "b", SCALE)[0])]
    assert chunked == reference
    bad = tmp_path / "in" / "bad.obj"
    bad.write_bytes(b"# a long enough comment line\n" * 5 + b"v 1 2 3\nv 1 2 x\nf 1 2 3\n")
    with pytest.raises(InputError, match="line 7: bad vertex line"):
        write_scaled_mesh(bad, tmp_path / "b", SCALE)


def test_obj_fast_and_line_readers_agree(tmp_path: Path) -> None:
    """Well-formed OBJ (vectorised reader) vs the same file made to need the line reader."""
    rng = np.random.default_rng(11)
    verts = rng.normal(size=(7, 3)).tolist()
    faces = ["f 1/1/1 2/2/1 3/3/1", "f 3//2 4//2 5//2 6//2", "f 7 1 2", "f 2/1 4/2 6/3 7/4 5/5"]
    plain = "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in verts) + "\n".join(faces) + "\n"
    (tmp_path / "a.obj").write_text(plain)
    (tmp_path / "b.obj").write_text(plain.replace("f 7 1 2", "  f 7 1 -6"))  # indent, negative
    a, b = load_mesh(tmp_path / "a.obj"), load_mesh(tmp_path / "b.obj")
    np.testing.assert_array_equal(a.vertices, verts)
    np.testing.assert_array_equal(a.triangles, _fan([[0, 1, 2], [2, 3, 4, 5], [6, 0, 1],
                                                     [1, 3, 5, 6, 4]]))
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.triangles, b.triangles)


def test_gltf_node_transforms_scale_with_the_positions(tmp_path: Path) -> None:
    """A translated + rotated node: the rescaled scene is the original scene x scale."""
    scene = trimesh.Scene()
    transform = trimesh.transformations.rotation_matrix(0.7, [0, 0, 1])
    transform[:3, 3] = [5.0, -2.0, 1.0]
    scene.add_geometry(_box(), transform=transform)
    scene.add_geometry(trimesh.creation.icosphere(subdivisions=1), transform=np.eye(4))
    (tmp_path / "in").mkdir()
    src = tmp_path / "in" / "scene.glb"
    src.write_bytes(scene.export(file_type="glb"))
    written = write_scaled_mesh(src, tmp_path / "out", SCALE)
    before, after = load_mesh(src), load_mesh(written[0])
    assert after.num_triangles == before.num_triangles == 12 + 80
    np.testing.assert_allclose(after.vertices, before.vertices * SCALE, rtol=1e-6, atol=1e-6)


def test_side_files_outside_the_folder_are_not_copied(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    (tmp_path / "outside.png").write_bytes(TEXTURE_BYTES)
    src = tmp_path / "in" / "m.obj"
    src.write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "in" / "m.mtl").write_text("newmtl a\nmap_Kd ../outside.png\n")
    written = write_scaled_mesh(src, tmp_path / "in" / "out", SCALE)
    assert written == [tmp_path / "in" / "out" / "m.obj", tmp_path / "in" / "out" / "m.mtl"]
    assert not (tmp_path / "in" / "outside.png").exists()


def _pack_glb(doc: dict, binary: bytes) -> bytes:
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = (struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(binary), 0x004E4942) + binary)
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


def test_gltf_trs_node_translation(tmp_path: Path) -> None:
    scene = trimesh.Scene()
    scene.add_geometry(_box())
    src = tmp_path / "in" / "trs.glb"
    src.parent.mkdir()
    src.write_bytes(scene.export(file_type="glb"))
    doc, binary = _gltf_json(src), _gltf_buffer_bytes(src)[0]
    for node in doc["nodes"]:
        node.pop("matrix", None)
        if "mesh" in node:
            node.update(translation=[5.0, -2.0, 1.0], rotation=[0.0, 0.0, 0.3826834, 0.9238795],
                        scale=[2.0, 2.0, 2.0])
    src.write_bytes(_pack_glb(doc, binary))
    written = write_scaled_mesh(src, tmp_path / "out", SCALE)
    before, after = load_mesh(src), load_mesh(written[0])
    assert np.ptp(before.vertices[:, 2]) == pytest.approx(6.0)  # the node scale is applied
    np.testing.assert_allclose(after.vertices, before.vertices * SCALE, rtol=1e-6, atol=1e-6)
    node = next(n for n in _gltf_json(written[0])["nodes"] if "mesh" in n)
    assert node["translation"] == [5.0 * SCALE, -2.0 * SCALE, 1.0 * SCALE]
    assert node["scale"] == [2.0, 2.0, 2.0]


def test_gltf_data_uri_buffers_and_external_images(tmp_path: Path) -> None:
    import cv2
    from trimesh.exchange.gltf import export_gltf

    scene = trimesh.Scene()
    scene.add_geometry(_box())
    files = export_gltf(scene, embed_buffers=True)
    assert list(files) == ["model.gltf"]
    doc = json.loads(files["model.gltf"])
    assert doc["buffers"][0]["uri"].startswith("data:")
    doc["images"] = [{"uri": "textures/t%20x.png"}]  # URI-encoded space
    src = tmp_path / "in" / "m.gltf"
    (tmp_path / "in" / "textures").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "in" / "textures" / "t x.png"), np.zeros((4, 4, 3), np.uint8))
    src.write_text(json.dumps(doc))
    written = write_scaled_mesh(src, tmp_path / "out", SCALE)
    assert written == [tmp_path / "out" / "m.gltf", tmp_path / "out" / "textures" / "t x.png"]
    out_doc = _gltf_json(written[0])
    assert out_doc["buffers"][0]["uri"].startswith("data:")
    np.testing.assert_allclose(load_mesh(written[0]).vertices, load_mesh(src).vertices * SCALE)


def test_gltf_quantised_positions_are_refused(tmp_path: Path) -> None:
    src = tmp_path / "q.glb"
    src.write_bytes(_box().export(file_type="glb"))
    doc, binary = _gltf_json(src), _gltf_buffer_bytes(src)[0]
    pos = doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    doc["accessors"][pos]["componentType"] = 5123  # unsigned short (KHR_mesh_quantization)
    src.write_bytes(_pack_glb(doc, binary))
    with pytest.raises(InputError, match="quantised"):
        write_scaled_mesh(src, tmp_path / "out", SCALE)


_HEAD = b"ply\nformat ascii 1.0\n"
_XYZ = b"property float x\nproperty float y\nproperty float z\n"
_FACE = b"element face 1\nproperty list uchar int vertex_indices\n"
HEADER_ERRORS = {
    "bad element count": (_HEAD + b"element vertex many\nend_header\n", "bad PLY element"),
    "property first": (_HEAD + b"property float x\nend_header\n", "before any element"),
    "no format": (b"ply\nelement vertex 0\nend_header\n", "no format line"),
    "repeated property": (_HEAD + b"element vertex 1\nproperty float x\nproperty float x\n"
                          b"end_header\n", "repeats a property"),
    "float list length": (_HEAD + b"element face 1\nproperty list float int vertex_indices\n"
                          b"end_header\n", "bad PLY list property"),
    "unknown type": (_HEAD + b"element vertex 1\nproperty real x\nend_header\n",
                     "bad PLY property"),
    "no z": (_HEAD + b"element vertex 1\nproperty float x\nproperty float y\n" + _FACE
             + b"end_header\n", "no scalar property 'z'"),
    "no vertex_indices": (_HEAD + b"element vertex 3\n" + _XYZ
                          + b"element face 1\nproperty list uchar int corners\nend_header\n",
                          "no 'vertex_indices'"),
    "negative list length": (_HEAD + b"element vertex 3\n" + _XYZ + _FACE
                             + b"end_header\n0 0 0\n1 0 0\n0 1 0\n-1 0 1 2\n",
                             "bad list length"),
    "binary negative length": (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n" + _XYZ
                               + b"element face 1\nproperty list char int vertex_indices\n"
                               b"end_header\n" + bytes(12) + b"\xff", "negative list length"),
}


@pytest.mark.parametrize("case", sorted(HEADER_ERRORS))
def test_ply_structure_errors(tmp_path: Path, case: str) -> None:
    data, message = HEADER_ERRORS[case]
    path = tmp_path / "h.ply"
    path.write_bytes(data)
    with pytest.raises(InputError, match=message):
        load_mesh(path)


def test_faces_with_two_vertices_are_skipped(tmp_path: Path,
                                             caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "two.ply"
    path.write_bytes(_HEAD + b"element vertex 3\n" + _XYZ + b"element face 2\n"
                     b"property list uchar int vertex_indices\nend_header\n"
                     b"0 0 0\n1 0 0\n0 1 0\n2 0 1\n3 0 1 2\n")
    mesh = load_mesh(path)
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2]])
    assert "skipped 1 faces" in caplog.text


OTHER_RESCALE_ERRORS = {
    "off no counts": ("a.off", b"OFF\n# nothing\n", "no vertex count"),
    "off truncated": ("b.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n", "ends inside the vertex list"),
    "noff": ("c.off", b"nOFF\n4\n1 1 0\n", "unsupported nOFF"),
    "off bad vertex": ("d.off", b"OFF\n3 1 0\n0 0 0\n1 0\n0 1 0\n3 0 1 2\n", "line 4:"),
    "gltf json array": ("e.gltf", b"[1, 2]", "not an object"),
    "gltf missing buffer": ("f.gltf", json.dumps({"buffers": [{"uri": "no.bin"}]}).encode(),
                            "not found"),
    "glb truncated chunk": ("g.glb", b"glTF" + struct.pack("<IIII", 2, 40, 100, 0x4E4F534A)
                            + b"{}" + bytes(18), "truncated GLB chunk"),
    "gltf bad accessor": ("h.gltf", json.dumps({"meshes": [{"primitives": [
        {"attributes": {"POSITION": 3}}]}], "accessors": []}).encode(), "invalid glTF"),
}


@pytest.mark.parametrize("case", sorted(OTHER_RESCALE_ERRORS))
def test_other_rescale_errors(tmp_path: Path, case: str) -> None:
    name, data, message = OTHER_RESCALE_ERRORS[case]
    (tmp_path / name).write_bytes(data)
    with pytest.raises(InputError, match=message):
        write_scaled_mesh(tmp_path / name, tmp_path / "out", SCALE)
    assert not (tmp_path / "out" / name).exists()


def test_directory_is_not_a_mesh(tmp_path: Path) -> None:
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(InputError, match="not a file"):
        load_mesh(tmp_path / "d.ply")
