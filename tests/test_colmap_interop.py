"""Interoperability with COLMAP: our transform files as COLMAP reads them, and models written
by Debian's COLMAP 3.8 read, rescaled and checked again by COLMAP 3.8's own tools.

The tests marked ``colmap_cli`` need the ``colmap`` executable (Debian: ``apt-get install
colmap``; ``make install`` does it when it can) and skip with the reason when it is absent.
COLMAP 3.8's tools can exit 0 after failing, so every check reads what they printed or wrote.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from sfm_laserscale.commands import apply as apply_command
from sfm_laserscale.commands.apply import ApplyInputs, ApplyOptions
from sfm_laserscale.io.colmap import read_colmap_model
from sfm_laserscale.io.transforms import read_sim3
from sfm_laserscale.model import SparseModel

FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures"
COLMAP_TXT = FIXTURES / "maupertuis_colmap" / "reconstruction"
SCALE = 0.0427318  # metres per model unit
COLMAP = shutil.which("colmap")
needs_colmap = pytest.mark.skipif(
    COLMAP is None, reason="colmap CLI not installed (Debian: apt-get install colmap)")


def _colmap(*args: str | Path) -> str:
    """Run a COLMAP command; its stdout+stderr (fails the test on a non-zero exit)."""
    assert COLMAP is not None
    proc = subprocess.run([COLMAP, *map(str, args)], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "QT_QPA_PLATFORM": "offscreen"})
    assert proc.returncode == 0, f"colmap {args[0]} exit {proc.returncode}: {proc.stderr[-2000:]}"
    return proc.stdout + proc.stderr


def analyzer_stats(model_dir: Path) -> dict[str, float]:
    """``colmap model_analyzer`` output as numbers: {"Points": 1039.0, ...}."""
    out = _colmap("model_analyzer", "--path", model_dir)
    stats = {m.group(1): float(m.group(2))
             for m in re.finditer(r"^([A-Za-z ]+):\s*([-+0-9.eE]+)(?:px)?\s*$", out, re.M)}
    assert {"Cameras", "Registered images", "Points", "Mean reprojection error"} <= set(stats), out
    return stats


def _centres(model: SparseModel) -> np.ndarray:
    return np.array([model.images[k].cam_from_world.center for k in sorted(model.images)])


def _assert_same_model(a: SparseModel, b: SparseModel, rtol: float = 1e-12) -> None:
    ia, ib = a.point_index, b.point_index
    ids = sorted(ia)
    assert ids == sorted(ib)
    np.testing.assert_allclose(np.array([b.points_xyz[ib[i]] for i in ids]),
                               np.array([a.points_xyz[ia[i]] for i in ids]), rtol=rtol)
    np.testing.assert_allclose(_centres(b), _centres(a), rtol=1e-9, atol=1e-12)
    for k in a.images:
        np.testing.assert_allclose(b.images[k].cam_from_world.R, a.images[k].cam_from_world.R,
                                   atol=1e-12)
        np.testing.assert_array_equal(b.images[k].point3D_ids, a.images[k].point3D_ids)


@pytest.fixture(scope="module")
def pycolmap_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The fixture model written by pycolmap 4.x (binary, with rigs.bin/frames.bin)."""
    out = tmp_path_factory.mktemp("pycolmap") / "sparse"
    out.mkdir()
    pycolmap.Reconstruction(COLMAP_TXT).write(out)
    return out


# --------------------------------------------------------------------------- pycolmap (always)


def test_sim3_file_is_the_similarity_pycolmap_applies(tmp_path: Path,
                                                      pycolmap_model: Path) -> None:
    """transform.sim3 read as COLMAP's Sim3d (scale, qw qx qy qz, t) and applied by pycolmap
    gives exactly our rescaled model."""
    res = apply_command.run(ApplyInputs(model=pycolmap_model), tmp_path / "out",
                            ApplyOptions(SCALE))
    s, q_wxyz, t = read_sim3(res.out_dir / "transform.sim3")
    sim3 = pycolmap.Sim3d(s, pycolmap.Rotation3d(np.r_[q_wxyz[1:], q_wxyz[0]]), t)
    rec = pycolmap.Reconstruction(pycolmap_model)
    rec.transform(sim3)
    theirs = tmp_path / "pycolmap_transformed"
    theirs.mkdir()
    rec.write(theirs)
    _assert_same_model(read_colmap_model(theirs), read_colmap_model(res.out_dir / "scaled" /
                                                                    "model"))


# --------------------------------------------------------------------------- COLMAP 3.8 CLI


@pytest.fixture(scope="module")
def colmap38_models(tmp_path_factory: pytest.TempPathFactory,
                    pycolmap_model: Path) -> dict[str, Path]:
    """The pycolmap model converted by the colmap CLI to its own binary and text formats."""
    if COLMAP is None:
        pytest.skip("colmap CLI not installed (Debian: apt-get install colmap)")
    root = tmp_path_factory.mktemp("colmap38")
    out = {}
    for kind in ("BIN", "TXT"):
        out[kind] = root / kind
        out[kind].mkdir()
        _colmap("model_converter", "--input_path", pycolmap_model, "--output_path", out[kind],
                "--output_type", kind)
    assert (out["BIN"] / "images.bin").is_file() and (out["TXT"] / "images.txt").is_file()
    return out


@needs_colmap
@pytest.mark.parametrize("kind", ["BIN", "TXT"])
def test_colmap38_model_rescaled_passes_model_analyzer(tmp_path: Path, kind: str,
                                                       colmap38_models: dict[str, Path]) -> None:
    src = colmap38_models[kind]
    _assert_same_model(read_colmap_model(src), read_colmap_model(COLMAP_TXT))  # our reader
    res = apply_command.run(ApplyInputs(model=src), tmp_path / "out", ApplyOptions(SCALE))
    scaled = res.out_dir / "scaled" / "model"
    before, after = analyzer_stats(src), analyzer_stats(scaled)
    assert after["Registered images"] == before["Registered images"] == 4
    assert after["Points"] == before["Points"] == 1039
    assert after["Observations"] == before["Observations"]
    assert after["Mean track length"] == pytest.approx(before["Mean track length"], rel=1e-6)
    # reprojection errors do not depend on the scale: a wrong rescale would change them
    assert after["Mean reprojection error"] == pytest.approx(before["Mean reprojection error"],
                                                             rel=1e-4)
    assert 0 < after["Mean reprojection error"] < 2


@needs_colmap
def test_colmap38_reads_our_rescaled_binary_exactly(tmp_path: Path,
                                                    colmap38_models: dict[str, Path]) -> None:
    res = apply_command.run(ApplyInputs(model=colmap38_models["BIN"]), tmp_path / "out",
                      ApplyOptions(SCALE))
    txt = tmp_path / "as_text"
    txt.mkdir()
    _colmap("model_converter", "--input_path", res.out_dir / "scaled" / "model",
            "--output_path", txt, "--output_type", "TXT")
    ours = read_colmap_model(res.out_dir / "scaled" / "model")
    _assert_same_model(read_colmap_model(txt), ours, rtol=1e-15)
    np.testing.assert_allclose(ours.points_xyz,
                               SCALE * read_colmap_model(colmap38_models["BIN"]).points_xyz,
                               rtol=1e-15)


@needs_colmap
def test_colmap38_model_transformer_reads_transform_4x4(tmp_path: Path,
                                                        colmap38_models: dict[str, Path]) -> None:
    """COLMAP 3.8's model_transformer reads a 4x4 matrix: transform_4x4.txt gives our model."""
    res = apply_command.run(ApplyInputs(model=colmap38_models["TXT"]), tmp_path / "out",
                      ApplyOptions(SCALE))
    theirs = tmp_path / "transformed"
    theirs.mkdir()
    _colmap("model_transformer", "--input_path", colmap38_models["TXT"], "--output_path", theirs,
            "--transform_path", res.out_dir / "transform_4x4.txt")
    _assert_same_model(read_colmap_model(theirs), read_colmap_model(res.out_dir / "scaled" /
                                                                    "model"))


@needs_colmap
def test_colmap38_cannot_read_the_sim3_file(tmp_path: Path,
                                            colmap38_models: dict[str, Path]) -> None:
    """Why transform_4x4.txt is the file for COLMAP 3.8: given the 8-number Sim3d file, its
    model_transformer exits 0 and writes a wrong (NaN) model."""
    if "COLMAP 3.8" not in _colmap("help"):
        pytest.skip("only COLMAP 3.8 reads a 4x4 matrix here")
    res = apply_command.run(ApplyInputs(model=colmap38_models["TXT"]), tmp_path / "out",
                      ApplyOptions(SCALE))
    theirs = tmp_path / "transformed"
    theirs.mkdir()
    _colmap("model_transformer", "--input_path", colmap38_models["TXT"], "--output_path", theirs,
            "--transform_path", res.out_dir / "transform.sim3")
    rec = pycolmap.Reconstruction(theirs)
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    ours = read_colmap_model(res.out_dir / "scaled" / "model").points_xyz
    assert not np.isfinite(xyz).all() or not np.allclose(np.sort(xyz, 0), np.sort(ours, 0))
