"""``scale --colmap-workspace`` / ``--openmvg-project``: the inputs found in a pipeline's own folder
(the model with the most registered images, the dense mesh of that very model, the most refined
OpenMVS mesh), explicit paths overriding them, messages naming where it looked, the folders left
byte-identical, and the held-out check (a laser image that is a model image, by name or by
content) with ``--reuse-model-poses``.

The COLMAP workspace is laid out as ``colmap automatic_reconstructor`` leaves it, from the small
synthetic survey (real pycolmap SfM): its true scale is known. The OpenMVG project is the real
OpenMVG fixture with an OpenMVS-named mesh and an imposed scale (tests/test_plugins.py).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from sfm_laserscale.cli import main as cli_main
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.colmap import model_without_images, read_colmap_model
from sfm_laserscale.io.colmap_write import write_colmap_model_binary
from sfm_laserscale.io.workspace import (
    find_colmap_workspace,
    find_openmvg_project,
    registered_image_count,
)
from sfm_laserscale.pipeline_folders import GivenInputs, resolve_scale_inputs
from tests.test_plugins import OPENMVG_DIR, _openmvg_case


def tree_digest(root: Path) -> dict[str, str]:
    """Relative path -> SHA-256 of every file under ``root`` (and the set of paths)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def colmap_workspace(ds: Any, root: Path) -> Path:
    """``automatic_reconstructor``'s layout: database.db, images/, sparse/0 (a partial model of
    3 images, in the same frame), sparse/1 (the full model), dense/1/meshed-poisson.ply (the
    full model's mesh) and dense/0/meshed-poisson.ply (the partial model's: a decoy, 1 far
    triangle that no laser ray would hit)."""
    root.mkdir()
    shutil.copy(ds.database_path, root / "database.db")
    shutil.copytree(ds.images_dir, root / "images")
    full = read_colmap_model(ds.model_dir)
    names = sorted(im.name for im in full.images.values())
    write_colmap_model_binary(model_without_images(full, names[3:]), root / "sparse" / "0")
    shutil.copytree(ds.model_dir, root / "sparse" / "1")
    (root / "dense" / "1").mkdir(parents=True)
    shutil.copy(ds.mesh_path, root / "dense" / "1" / "meshed-poisson.ply")
    (root / "dense" / "0").mkdir()
    (root / "dense" / "0" / "meshed-poisson.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "1000 1000 1000\n1001 1000 1000\n1000 1001 1000\n3 0 1 2\n")
    return root


def test_colmap_workspace_finder_picks_the_largest_model_and_its_own_dense_mesh(
        small_dataset: Any, tmp_path: Path) -> None:
    ws = colmap_workspace(small_dataset, tmp_path / "ws")
    assert registered_image_count(ws / "sparse" / "0") == 3
    assert registered_image_count(ws / "sparse" / "1") == 8
    found = find_colmap_workspace(ws)
    assert found.model == ws / "sparse" / "1"
    assert found.mesh == ws / "dense" / "1" / "meshed-poisson.ply"
    assert found.database == ws / "database.db" and found.images == ws / "images"
    assert any("8 registered images" in c and "0: 3" in c for c in found.choices)
    # without the poisson mesh the delaunay one of the same model; never another model's
    (ws / "dense" / "1" / "meshed-poisson.ply").rename(ws / "dense" / "1" / "meshed-delaunay.ply")
    assert find_colmap_workspace(ws).mesh == ws / "dense" / "1" / "meshed-delaunay.ply"
    (ws / "dense" / "1" / "meshed-delaunay.ply").unlink()
    assert find_colmap_workspace(ws).mesh is None


def test_colmap_workspace_scales_with_one_command_and_is_left_byte_identical(
        small_dataset: Any, small_scale_run: Any, tmp_path: Path) -> None:
    ws = colmap_workspace(small_dataset, tmp_path / "ws")
    before = tree_digest(ws)
    out = tmp_path / "out"
    res = CliRunner().invoke(cli_main, [
        "scale", "--colmap-workspace", str(ws), "--laser-images",
        str(small_dataset.laser_images_dir), "--rig", str(small_dataset.rig_path), "--out",
        str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    assert tree_digest(ws) == before, "the workspace must be left byte-identical"
    report = json.loads((out / "report.json").read_text())
    inputs = report["inputs"]
    assert inputs["model"] == str(ws / "sparse" / "1")
    assert inputs["mesh"] == str(ws / "dense" / "1" / "meshed-poisson.ply")
    assert inputs["database"] == str(ws / "database.db") and inputs["images"] is None
    assert inputs["colmap_workspace"] == str(ws)
    assert any(c.startswith("model: ") and "8 registered images" in c for c in inputs["found"])
    log = (out / "run.log").read_text()
    assert "found in the pipeline folder: model: " in log and "meshed-poisson.ply" in log
    used = {d["path"] for d in report["provenance"]["inputs"]}
    assert str(ws / "database.db") in used and str(ws / "dense/1/meshed-poisson.ply") in used
    # the same inputs as the explicit run of the same data: the same numbers
    assert report["scale"]["value"] == small_scale_run.report["scale"]["value"]
    assert report["held_out"]["in_model"] == []
    err = report["scale"]["value"] / small_dataset.true_scale - 1
    assert abs(err) < 0.01


def test_explicit_paths_override_the_workspace(small_dataset: Any, tmp_path: Path) -> None:
    ws = colmap_workspace(small_dataset, tmp_path / "ws")
    given = GivenInputs(laser_images=(small_dataset.laser_images_dir,), rig=small_dataset.rig_path,
                        colmap_workspace=ws, model=ws / "sparse" / "0",
                        mesh=small_dataset.mesh_path, images=ws / "images")
    inputs = resolve_scale_inputs(given)
    assert inputs.model == ws / "sparse" / "0" and inputs.mesh == small_dataset.mesh_path
    assert inputs.images == ws / "images" and inputs.database is None  # given: no database
    assert any("overrides the colmap-workspace" in c for c in inputs.found)


@pytest.mark.parametrize("case", ["no mesh", "no model", "not a folder", "both folders",
                                  "nothing"])
def test_missing_inputs_say_where_they_were_looked_for(small_dataset: Any, tmp_path: Path,
                                                       case: str) -> None:
    ws = colmap_workspace(small_dataset, tmp_path / "ws")
    args = ["scale", "--laser-images", str(small_dataset.laser_images_dir), "--rig",
            str(small_dataset.rig_path), "--out", str(tmp_path / "out")]
    expect: tuple[str, ...]
    if case == "no mesh":
        shutil.rmtree(ws / "dense")
        args += ["--colmap-workspace", str(ws)]
        expect = (str(ws / "dense" / "1" / "meshed-poisson.ply"), "meshed-delaunay.ply",
                  f"sfm-laserscale mesh --model {ws / 'sparse' / '1'}")
    elif case == "no model":
        shutil.rmtree(ws / "sparse")
        args += ["--colmap-workspace", str(ws)]
        expect = ("no COLMAP model found", str(ws / "sparse"))
    elif case == "not a folder":
        args += ["--openmvg-project", str(tmp_path / "missing")]
        expect = ("OpenMVG project not found",)
    elif case == "both folders":
        args += ["--colmap-workspace", str(ws), "--openmvg-project", str(ws)]
        expect = ("not both",)
    else:
        expect = ("--colmap-workspace DIR", "--openmvg-project DIR")
    res = CliRunner().invoke(cli_main, args)
    assert res.exit_code == 2, res.output
    line = res.output.strip().splitlines()[-1]
    assert line.startswith("sfm-laserscale: error:")
    for text in expect:
        assert text in line, (text, line)
    assert not (tmp_path / "out").exists()


def openmvg_project(root: Path, s_true: float) -> tuple[Path, Path, Path, Path]:
    """An OpenMVG + OpenMVS project as the pipelines leave it: reconstruction_sequential/
    sfm_data.json, matches/ (regions and the listing's own sfm_data.json, without poses),
    images/, mvs/scene_dense_mesh_refine_texture.ply (the real surface), and less refined
    meshes as decoys (scene_dense_mesh.ply: one far triangle; the .mvs scenes)."""
    root.mkdir()
    (root / "reconstruction_sequential").mkdir()
    shutil.copy(OPENMVG_DIR / "sfm_data.json", root / "reconstruction_sequential")
    shutil.copytree(OPENMVG_DIR / "matches", root / "matches")
    listing = json.loads((OPENMVG_DIR / "sfm_data.json").read_text())
    listing["extrinsics"], listing["structure"] = [], []
    (root / "matches" / "sfm_data.json").write_text(json.dumps(listing))
    shutil.copytree(OPENMVG_DIR / "images", root / "images")
    (root / "mvs").mkdir()
    mesh, laser, rig, spots = _openmvg_case(root / "mvs", s_true)
    (root / "mvs" / "scene_dense_mesh.ply").write_bytes(
        (root / "mvs" / mesh.name).read_bytes()[:0] + b"not a mesh")
    for stem in ("scene", "scene_dense", "scene_dense_mesh_refine_texture"):
        (root / "mvs" / f"{stem}.mvs").write_bytes(b"MVSI")
    (root / "mvs" / "rig.toml").rename(root / "rig.toml")
    (root / "mvs" / "spots.csv").rename(root / "spots.csv")
    return mesh, laser, root / "rig.toml", root / "spots.csv"


def test_openmvg_project_finder(tmp_path: Path) -> None:
    proj = tmp_path / "proj"
    openmvg_project(proj, 2.5)
    found = find_openmvg_project(proj)
    assert found.model == proj / "reconstruction_sequential" / "sfm_data.json"
    assert found.mesh == proj / "mvs" / "scene_dense_mesh_refine_texture.ply"
    assert found.features == proj / "matches" and found.images == proj / "images"
    (found.mesh).rename(proj / "scene_dense_mesh_refine.obj")
    assert find_openmvg_project(proj).mesh == proj / "scene_dense_mesh_refine.obj"
    (proj / "reconstruction_sequential" / "sfm_data.json").rename(
        proj / "reconstruction_sequential" / "sfm_data.bin")
    assert find_openmvg_project(proj).model == proj / "reconstruction_sequential" / "sfm_data.bin"


def test_openmvg_project_scales_with_one_command_and_is_left_byte_identical(
        tmp_path: Path) -> None:
    """The laser image is a copy of model image 04 under another name: the held-out check finds
    it by content and warns; the scale is the imposed one."""
    s_true = 2.5
    proj = tmp_path / "proj"
    _, laser, rig, spots = openmvg_project(proj, s_true)
    laser_dir = tmp_path / "laser"
    laser_dir.mkdir()
    shutil.copy(laser, laser_dir / "laser_0001.jpg")
    spots.write_text(spots.read_text().replace(laser.name, "laser_0001.jpg"))
    before = tree_digest(proj)
    out = tmp_path / "out"
    res = CliRunner().invoke(cli_main, [
        "scale", "--openmvg-project", str(proj), "--laser-images", str(laser_dir), "--rig",
        str(rig), "--spots", str(spots), "--method", "fcm", "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    assert tree_digest(proj) == before, "the project must be left byte-identical"
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["model"] == str(proj / "reconstruction_sequential" / "sfm_data.json")
    assert report["inputs"]["mesh"] == str(proj / "mvs" / "scene_dense_mesh_refine_texture.ply")
    assert report["inputs"]["features"] == str(proj / "matches")
    assert report["scale"]["value"] == pytest.approx(s_true, rel=2e-3)
    assert report["held_out"]["in_model"] == [
        {"image": "laser_0001.jpg", "model_image": "MaupertuisTest_04.jpg", "by": "content"}]
    warn = [w for w in report["warnings"] if w["code"] == "laser_image_in_model"]
    assert len(warn) == 1 and warn[0]["level"] == "warning"
    assert "pose comes from SfM" in warn[0]["message"]
    assert "laser_image_in_model" in (out / "report.html").read_text() or \
        "not held out of SfM" in (out / "report.html").read_text()


def test_reuse_model_poses_takes_the_model_pose(tmp_path: Path) -> None:
    """Same name as a model image and --reuse-model-poses: the reported pose is the model's own
    (not a registration), the scale the imposed one, and the report says so in a note."""
    s_true = 2.5
    proj = tmp_path / "proj"
    _, laser, rig, spots = openmvg_project(proj, s_true)
    out = tmp_path / "out"
    res = CliRunner().invoke(cli_main, [
        "scale", "--openmvg-project", str(proj), "--laser-images", str(laser), "--rig", str(rig),
        "--spots", str(spots), "--method", "fcm", "--reuse-model-poses", "--out", str(out),
        "--quiet"])
    assert res.exit_code == 0, res.output
    report = json.loads((out / "report.json").read_text())
    from sfm_laserscale.geometry import qvec_from_rotmat
    from sfm_laserscale.io.openmvg import read_openmvg_sfm_data

    model = read_openmvg_sfm_data(OPENMVG_DIR / "sfm_data.json")
    image = model.image_by_name(laser.name)
    assert image is not None
    pose = report["images"][0]["cam_from_world"]
    q = qvec_from_rotmat(image.cam_from_world.R)
    assert np.allclose(pose["translation"], image.cam_from_world.t, atol=1e-12)
    assert np.allclose(np.abs(pose["rotation_wxyz"]), np.abs(q), atol=1e-12)
    assert report["images"][0]["num_matches"] == report["images"][0]["num_inliers"] > 100
    assert report["scale"]["value"] == pytest.approx(s_true, rel=1e-6)
    assert report["held_out"]["reuse_model_poses"] is True
    assert report["held_out"]["in_model"][0]["by"] == "name"
    note = [w for w in report["warnings"] if w["code"] == "laser_image_in_model"]
    assert note and note[0]["level"] == "note"


def test_openmvg_bin_sfm_data_is_found_and_refused_with_a_conversion_hint(
        tmp_path: Path) -> None:
    from sfm_laserscale.io.models import load_model

    proj = tmp_path / "proj"
    (proj / "reconstruction_global").mkdir(parents=True)
    (proj / "reconstruction_global" / "sfm_data.bin").write_bytes(b"\x01")
    found = find_openmvg_project(proj)
    assert found.model == proj / "reconstruction_global" / "sfm_data.bin"
    with pytest.raises(InputError, match="ConvertSfM_DataFormat"):
        load_model(found.model)
