"""``apply`` (rescale by a known scale) through the CLI and the library, and the transform files.

Inputs: the real COLMAP text model and OpenMVG sfm_data.json fixtures (read only, never
written), a binary copy of the COLMAP model, and small PLY/OBJ meshes made here.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import plyfile
import pytest
from click.testing import CliRunner, Result

from sfm_laserscale.cli import main
from sfm_laserscale.commands import apply as apply_command
from sfm_laserscale.commands.apply import ApplyInputs, ApplyOptions
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.colmap import read_colmap_model
from sfm_laserscale.io.colmap_write import write_colmap_model_binary
from sfm_laserscale.io.meshes.mesh import load_mesh
from sfm_laserscale.io.openmvg import read_openmvg_sfm_data
from sfm_laserscale.io.transforms import (
    metric_from_model_matrix,
    read_matrix_4x4,
    read_sim3,
    write_matrix_4x4,
    write_sim3,
)
from sfm_laserscale.model import SparseModel

FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures"
COLMAP_TXT = FIXTURES / "maupertuis_colmap" / "reconstruction"
OPENMVG_JSON = FIXTURES / "maupertuis_openmvg" / "sfm_data.json"
SCALE = 0.0371234567891234  # metres per model unit (not a round number on purpose)


def _run(args: Sequence[object]) -> Result:
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def _digest(path: Path) -> str:
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode() + f.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def colmap_bin(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The fixture's COLMAP model written as a binary model."""
    out = tmp_path_factory.mktemp("bin") / "sparse"
    write_colmap_model_binary(read_colmap_model(COLMAP_TXT), out)
    return out


def _ply(path: Path, n: int = 40, seed: int = 0) -> Path:
    """Binary PLY: float32 x y z, normals, uchar colours, a few triangles."""
    rng = np.random.default_rng(seed)
    vert = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"),
                              ("ny", "<f4"), ("nz", "<f4"), ("red", "u1"), ("green", "u1"),
                              ("blue", "u1")])
    for name in ("x", "y", "z", "nx", "ny", "nz"):
        vert[name] = rng.normal(size=n)
    for name in ("red", "green", "blue"):
        vert[name] = rng.integers(0, 255, n)
    faces = np.empty(n - 2, dtype=[("vertex_indices", "<i4", (3,))])
    faces["vertex_indices"] = np.column_stack([np.zeros(n - 2), np.arange(1, n - 1),
                                              np.arange(2, n)])
    plyfile.PlyData([plyfile.PlyElement.describe(vert, "vertex"),
                     plyfile.PlyElement.describe(faces, "face")], text=False).write(str(path))
    return path


def _centres(model: SparseModel) -> np.ndarray:
    return np.array([model.images[k].cam_from_world.center for k in sorted(model.images)])


def _check_scaled_model(src: SparseModel, dst: SparseModel, scale: float) -> None:
    """Points and camera centres x scale, rotations and intrinsics unchanged, ids kept."""
    assert np.array_equal(src.point3D_ids, dst.point3D_ids)
    np.testing.assert_allclose(dst.points_xyz, scale * src.points_xyz, rtol=1e-13, atol=0)
    np.testing.assert_allclose(_centres(dst), scale * _centres(src), rtol=1e-10, atol=1e-15)
    for k, im in src.images.items():
        np.testing.assert_allclose(dst.images[k].cam_from_world.R, im.cam_from_world.R,
                                   atol=1e-15)
        assert np.array_equal(dst.images[k].xy_px, im.xy_px)
    for k, cam in src.cameras.items():
        assert np.array_equal(dst.cameras[k].params, cam.params)


# --------------------------------------------------------------------------- CLI, COLMAP


@pytest.mark.parametrize("fmt", ["text", "binary"])
def test_apply_colmap_model_and_mesh(tmp_path: Path, colmap_bin: Path, fmt: str) -> None:
    model_dir = COLMAP_TXT if fmt == "text" else colmap_bin
    mesh = _ply(tmp_path / "dense mesh.ply")
    before = _digest(model_dir), _digest(mesh)
    out = tmp_path / "out"
    res = _run(["apply", "--scale", repr(SCALE), "--model", model_dir, "--mesh", mesh,
                "--out", out])
    assert res.exit_code == 0, res.output
    assert f"colmap-{fmt}" in res.stdout
    suffix = ".txt" if fmt == "text" else ".bin"
    assert sorted(p.name for p in (out / "scaled" / "model").iterdir()) == sorted(
        p.name for p in model_dir.iterdir())
    assert all(p.suffix == suffix for p in (out / "scaled" / "model").iterdir())
    # the cameras file does not depend on the scale: copied byte for byte
    cams = f"cameras{suffix}"
    assert (out / "scaled" / "model" / cams).read_bytes() == (model_dir / cams).read_bytes()
    _check_scaled_model(read_colmap_model(model_dir), read_colmap_model(out / "scaled" / "model"),
                        SCALE)
    _check_scaled_mesh(mesh, out / "scaled" / mesh.name, SCALE)
    _check_transforms(out, SCALE)
    assert (_digest(model_dir), _digest(mesh)) == before  # inputs untouched
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no debris


def _check_scaled_mesh(src: Path, dst: Path, scale: float) -> None:
    a, b = plyfile.PlyData.read(str(src)), plyfile.PlyData.read(str(dst))
    va, vb = a["vertex"].data, b["vertex"].data
    assert va.dtype == vb.dtype
    for name in va.dtype.names:
        if name in "xyz":
            np.testing.assert_allclose(vb[name], (va[name].astype(np.float64) * scale)
                                       .astype(np.float32), rtol=1e-6)
        else:
            assert np.array_equal(va[name], vb[name]), name
    assert np.array_equal(a["face"].data["vertex_indices"].tolist(),
                          b["face"].data["vertex_indices"].tolist())


def _check_transforms(out: Path, scale: float) -> None:
    s, q, t = read_sim3(out / "transform.sim3")
    assert s == scale and q.tolist() == [1, 0, 0, 0] and t.tolist() == [0, 0, 0]
    np.testing.assert_array_equal(read_matrix_4x4(out / "transform_4x4.txt"),
                                  metric_from_model_matrix(scale))


def test_apply_mesh_only_obj(tmp_path: Path) -> None:
    obj = tmp_path / "m.obj"
    obj.write_text("# test\nv 1 2 3\nv 4 5 6\nv -7 8.5 9\nvn 0 0 1\nf 1//1 2//1 3//1\n")
    res = _run(["apply", "--scale", "2.5", "--mesh", obj, "--out", tmp_path / "o"])
    assert res.exit_code == 0, res.output
    assert not (tmp_path / "o" / "scaled" / "model").exists()
    text = (tmp_path / "o" / "scaled" / "m.obj").read_text()
    assert "vn 0 0 1\n" in text and "f 1//1 2//1 3//1\n" in text
    np.testing.assert_allclose(load_mesh(tmp_path / "o" / "scaled" / "m.obj").vertices,
                               2.5 * np.array([[1, 2, 3], [4, 5, 6], [-7, 8.5, 9]]))
    _check_transforms(tmp_path / "o", 2.5)


# --------------------------------------------------------------------------- OpenMVG


def test_apply_openmvg_model_only(tmp_path: Path) -> None:
    before = _digest(OPENMVG_JSON)
    out = tmp_path / "out"
    res = _run(["apply", "--scale", repr(SCALE), "--model", OPENMVG_JSON, "--out", out])
    assert res.exit_code == 0, res.output
    dst = out / "scaled" / "model" / "sfm_data.json"
    assert [p.name for p in (out / "scaled").iterdir()] == ["model"]
    regions = OPENMVG_JSON.parent / "matches"  # keypoints: not copied beside the output
    _check_scaled_model(read_openmvg_sfm_data(OPENMVG_JSON),
                        read_openmvg_sfm_data(dst, regions_dir=regions), SCALE)
    # every byte outside the scaled numbers is kept: the texts differ only in numbers
    strip = re.compile(r"-?\d+(\.\d+)?([eE][-+]?\d+)?")
    assert strip.sub("#", OPENMVG_JSON.read_text()) == strip.sub("#", dst.read_text())
    assert _digest(OPENMVG_JSON) == before


def test_apply_then_inverse_restores_the_model(tmp_path: Path, colmap_bin: Path) -> None:
    a = apply_command.run(ApplyInputs(model=colmap_bin), tmp_path / "a", ApplyOptions(SCALE))
    b = apply_command.run(ApplyInputs(model=a.out_dir / "scaled" / "model"), tmp_path / "b",
                    ApplyOptions(1.0 / SCALE))
    back, orig = read_colmap_model(b.out_dir / "scaled" / "model"), read_colmap_model(colmap_bin)
    np.testing.assert_allclose(back.points_xyz, orig.points_xyz, rtol=1e-14)
    np.testing.assert_allclose(_centres(back), _centres(orig), rtol=1e-12)
    assert a.model_format == "colmap-binary" and a.mesh_files == ()
    assert all(p.is_file() and p.is_relative_to(a.out_dir) for p in a.model_files)
    assert [p.name for p in a.transform_files] == ["transform.sim3", "transform_4x4.txt"]


# --------------------------------------------------------------------------- bad input


def _bad_model(tmp_path: Path, colmap_bin: Path) -> Path:
    bad = tmp_path / "bad_model"
    bad.mkdir()
    for f in colmap_bin.iterdir():
        data = f.read_bytes()
        (bad / f.name).write_bytes(data[: len(data) // 2] if f.name == "images.bin" else data)
    return bad


@pytest.mark.parametrize("case, message", [
    ("neither", "nothing to rescale"),
    ("zero scale", "positive finite"),
    ("negative scale", "positive finite"),
    ("nan scale", "positive finite"),
    ("inf scale", "positive finite"),
    ("missing model", "model not found"),
    ("missing mesh", "mesh not found"),
    ("truncated model", "truncated or corrupt"),
    ("not a model", "no COLMAP model here"),
    ("bad mesh", "bad.ply"),
    ("out is a file", "not a folder"),
])
def test_apply_bad_input_exits_2_and_writes_nothing(tmp_path: Path, colmap_bin: Path,
                                                     case: str, message: str) -> None:
    mesh = _ply(tmp_path / "m.ply")
    bad_mesh = tmp_path / "bad.ply"
    bad_mesh.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nend")
    out = tmp_path / "out"
    args: dict[str, object] = {"--scale": "0.5", "--model": colmap_bin, "--mesh": mesh,
                               "--out": out}
    change: dict[str, dict[str, object]] = {
        "neither": {"--model": None, "--mesh": None},
        "zero scale": {"--scale": "0"}, "negative scale": {"--scale": "-1"},
        "nan scale": {"--scale": "nan"}, "inf scale": {"--scale": "inf"},
        "missing model": {"--model": tmp_path / "nope"},
        "missing mesh": {"--mesh": tmp_path / "nope.ply"},
        "truncated model": {"--model": _bad_model(tmp_path, colmap_bin)},
        "not a model": {"--model": tmp_path},
        "bad mesh": {"--mesh": bad_mesh},
    }
    args.update(change.get(case, {}))
    if case == "out is a file":
        out.write_text("x")
    argv = ["apply"] + [str(x) for k, v in args.items() if v is not None for x in (k, v)]
    res = _run(argv)
    assert res.exit_code == 2, res.output
    assert message in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert out.is_file() if case == "out is a file" else not out.exists()
    assert not [p for p in tmp_path.iterdir() if ".partial" in p.name]


def test_apply_refuses_non_empty_out_unless_overwrite(tmp_path: Path) -> None:
    mesh = _ply(tmp_path / "m.ply")
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("old run")
    res = _run(["apply", "--scale", "2", "--mesh", mesh, "--out", out])
    assert res.exit_code == 2 and "--overwrite" in res.stderr
    assert (out / "keep.txt").read_text() == "old run"
    res = _run(["apply", "--scale", "2", "--mesh", mesh, "--out", out, "--overwrite"])
    assert res.exit_code == 0, res.output
    assert not (out / "keep.txt").exists() and (out / "scaled" / "m.ply").is_file()


def test_apply_failure_keeps_previous_output(tmp_path: Path, colmap_bin: Path) -> None:
    """A run that fails half-way (the mesh after the model) leaves the old output as it was."""
    out = tmp_path / "out"
    apply_command.run(ApplyInputs(mesh=_ply(tmp_path / "m.ply")), out, ApplyOptions(2.0))
    before = _digest(out)
    bad = tmp_path / "bad.obj"
    bad.write_text("v 1 2\nf 1 2 3\n")
    with pytest.raises(InputError):
        apply_command.run(ApplyInputs(model=colmap_bin, mesh=bad), out, ApplyOptions(3.0),
                    overwrite=True)
    assert _digest(out) == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]


def test_apply_rejects_non_numeric_scale_with_usage_error(tmp_path: Path) -> None:
    res = _run(["apply", "--scale", "abc", "--mesh", _ply(tmp_path / "m.ply"), "--out",
                tmp_path / "o"])
    assert res.exit_code == 2 and "abc" in res.stderr


# --------------------------------------------------------------------------- transform files


def _c_strtod_prefix(text: str) -> float | None:
    """What C's strtod reads at the start of ``text`` (None when no number)."""
    m = re.match(r"\s*([-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?|[-+]?(inf|nan))", text, re.I)
    return float(m.group(1)) if m else None


def openmvs_old_parser(text: str) -> list[float]:
    """TransformScene before OpenMVS v2.3.0: getline, then strtod of the line's start."""
    values = (_c_strtod_prefix(line) for line in text.splitlines())
    return [v for v in values if v is not None]


def openmvs_new_parser(text: str) -> list[float]:
    """TransformScene since July 2023: ``file >> token``, ``std::stod`` (skip failures)."""
    values = (_c_strtod_prefix(tok) for tok in text.split())
    return [v for v in values if v is not None]


def openmvs_accepts(values: list[float]) -> np.ndarray | None:
    """TransformScene's check and its Matrix3x4 (row-major), None for 'invalid transform'."""
    if len(values) != 12 and (len(values) != 16 or values[12:] != [0, 0, 0, 1]):
        return None
    return np.array(values[:12]).reshape(3, 4)


def colmap38_parser(text: str) -> np.ndarray:
    """COLMAP 3.8 SimilarityTransform3::FromFile: 16 numbers by operator>>, row-major."""
    return np.array([float(t) for t in text.split()[:16]]).reshape(4, 4)


@pytest.mark.parametrize("scale", [1.0, SCALE, 1234.5678, 1e-7])
def test_matrix_file_is_read_right_by_every_openmvs_and_colmap38(tmp_path: Path,
                                                                  scale: float) -> None:
    path = tmp_path / "transform_4x4.txt"
    write_matrix_4x4(path, scale)
    text = path.read_text()
    expect = metric_from_model_matrix(scale)
    for parser in (openmvs_old_parser, openmvs_new_parser):
        got = openmvs_accepts(parser(text))
        assert got is not None, parser.__name__
        np.testing.assert_array_equal(got, expect[:3])
    np.testing.assert_array_equal(colmap38_parser(text), expect)
    np.testing.assert_array_equal(read_matrix_4x4(path), expect)
    assert len(text.splitlines()) == 16


def test_four_numbers_per_row_would_break_old_openmvs() -> None:
    """Why one number per line: the old parser sees only 4 values in a 4-row file."""
    rows = "\n".join(" ".join(repr(float(x)) for x in r) for r in metric_from_model_matrix(0.5))
    assert len(openmvs_old_parser(rows)) == 4
    assert openmvs_accepts(openmvs_old_parser(rows)) is None
    assert openmvs_accepts(openmvs_new_parser(rows)) is not None


def test_sim3_file_round_trips_exactly(tmp_path: Path) -> None:
    for scale in (SCALE, 1 / 3, 2.0**-30, 7.0):
        write_sim3(tmp_path / "t.sim3", scale)
        s, q, t = read_sim3(tmp_path / "t.sim3")
        assert s == scale and math.isclose(float(np.linalg.norm(q)), 1.0)
        assert (tmp_path / "t.sim3").read_text().count("\n") == 1
        assert len((tmp_path / "t.sim3").read_text().split()) == 8
