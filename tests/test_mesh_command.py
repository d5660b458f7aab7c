"""``sfm-laserscale mesh``: a coarse surface of a sparse model, written as PLY with what it
interpolates beside it; the surface passes through the model's points (known answer: the
synthetic survey's true metric mesh, brought into the model's frame, is the seafloor the sparse
points sample)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from click.testing import CliRunner

from sfm_laserscale.cli import main as cli_main
from sfm_laserscale.io.colmap import read_colmap_model
from sfm_laserscale.io.meshes.mesh import load_mesh
from sfm_laserscale.raycast import MeshRaycaster


def test_mesh_command_writes_a_surface_through_the_sparse_points(small_dataset: Any,
                                                                 tmp_path: Path) -> None:
    out = tmp_path / "coarse.ply"
    res = CliRunner().invoke(cli_main, ["mesh", "--model", str(small_dataset.model_dir),
                                        "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    assert "interpolating" in res.output
    mesh = load_mesh(out)
    info = json.loads((tmp_path / "coarse.ply.json").read_text())
    assert info["triangles"] == mesh.num_triangles and info["method"] == "delaunay25d"
    assert 0 < info["points_used"] <= info["points_total"]
    assert "sparse 3D points only" in info["interpolates"]
    assert b"interpolates" in out.read_bytes()[:1000]  # the PLY header says it too
    model = read_colmap_model(small_dataset.model_dir)
    # the model's points lie on it (it passes through them) ...
    d_model = MeshRaycaster(mesh.vertices, mesh.triangles).distances(model.points_xyz)
    assert float(np.median(d_model)) < 1e-6 * model.extent
    # ... and it follows the true seafloor (the data set's dense mesh, in the model frame)
    # within a small share of the scene's extent where the two overlap
    true = load_mesh(small_dataset.mesh_path)
    near = MeshRaycaster(true.vertices, true.triangles).distances(mesh.vertices)
    assert float(np.median(near)) < 0.005 * model.extent


def test_mesh_command_refuses_an_existing_file_and_a_bad_model(small_dataset: Any,
                                                               tmp_path: Path) -> None:
    out = tmp_path / "m.ply"
    out.write_text("keep me")
    res = CliRunner().invoke(cli_main, ["mesh", "--model", str(small_dataset.model_dir),
                                        "--out", str(out)])
    assert res.exit_code == 2 and "--overwrite" in res.output
    assert out.read_text() == "keep me"
    res = CliRunner().invoke(cli_main, ["mesh", "--model", str(tmp_path / "nope"),
                                        "--out", str(tmp_path / "n.ply")])
    assert res.exit_code == 2 and "model not found" in res.output
    res = CliRunner().invoke(cli_main, ["mesh", "--model", str(small_dataset.model_dir),
                                        "--out", str(tmp_path / "n.obj")])
    assert res.exit_code == 2 and ".ply" in res.output
