"""The pipeline commands: ``colmap`` (SfM -> mesh -> scale in one command; plugins/colmap runs
it) and ``openmvg`` (OpenMVG + OpenMVS -> scale -> TransformScene; plugins/openmvg runs it): our
step on a real OpenMVG reconstruction, the command sequence, tool failures (exit 4, the step
named) and the hold-out of laser images by name and content.

Truth for the COLMAP plugin: the plugin builds a FRESH reconstruction of the synthetic survey
(``small_dataset``), so its true scale is found here by aligning the fresh model's camera
centres to the true camera centres of truth.json (Umeyama): s_true = 1 / s_model_from_world.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from sfm_laserscale.cli import main as cli_main
from sfm_laserscale.geometry import rotmat_from_qvec, umeyama_sim3
from sfm_laserscale.io.colmap import read_colmap_model
from sfm_laserscale.io.meshes.new_ply import write_new_ply
from sfm_laserscale.io.openmvg import read_openmvg_sfm_data
from sfm_laserscale.io.workspace import choose_sparse_model
from sfm_laserscale.meshing import CoarseMeshOptions, coarse_mesh, delaunay_25d
from sfm_laserscale.model import Pose, SparseModel
from sfm_laserscale.pipelines.hold_out import select_sfm_images
from sfm_laserscale.raycast import MeshRaycaster, pixel_rays
from sfm_laserscale.rig import Laser, Rig, rig_to_toml

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO.parent / "shared" / "fixtures"
OPENMVG_DIR = FIXTURES / "maupertuis_openmvg"
COLMAP = shutil.which("colmap")
PLUGIN = REPO / "plugins" / "colmap" / "colmap_laserscale.py"


def largest_model(sparse: Path) -> tuple[Path, SparseModel]:
    folder, _, _ = choose_sparse_model(sparse)
    assert folder is not None
    return folder, read_colmap_model(folder)


def true_scale_of(model: SparseModel, truth_path: Path) -> float:
    """Metres per model unit of a fresh model: its cameras aligned to the true poses."""
    truth = json.loads(truth_path.read_text())
    world = {}
    for ref in truth["reference_images"]:
        q, t = ref["cam_from_world"]["rotation_wxyz"], ref["cam_from_world"]["translation"]
        world[ref["name"]] = Pose(rotmat_from_qvec(np.array(q)), np.array(t)).center
    images = list(model.images.values())
    s, _, _ = umeyama_sim3(np.array([world[im.name] for im in images]),
                           np.array([im.cam_from_world.center for im in images]))
    return 1.0 / s


def _plugin_args(ds: Any, out: Path, backend: str) -> list[str]:
    params = ",".join(f"{p:.12g}" for p in ds.camera.params)
    return ["colmap", "--quiet", "--images", str(ds.images_dir), "--laser-images",
            str(ds.laser_images_dir), "--rig", str(ds.rig_path), "--out", str(out),
            "--backend", backend,
            "--pairs", str(ds.out_dir / "pairs.txt"), "--camera-model", ds.camera.model,
            "--camera-params", params, "--max-features", "2000", "--sift-first-octave", "0"]


def _check_plugin_run(out: Path, ds: Any, backend: str) -> float:
    """Outputs present, scale within 1 % of the fresh model's truth; returns the error."""
    report = json.loads((out / "scale" / "report.json").read_text())
    _, model = largest_model(out / "sfm" / "sparse")
    assert len(model.images) == 8, "every reference image registered"
    for rel in ("sfm/database.db", "sfm/mesh_coarse.ply", "sfm/mesh_coarse.ply.json",
                "scale/transform.sim3",
                "scale/transform_4x4.txt", "scale/scaled/mesh_coarse.ply",
                "scale/scaled/model/images.bin"):
        assert (out / rel).is_file(), rel
    truth = true_scale_of(model, ds.truth_path)
    err = report["scale"]["value"] / truth - 1
    print(f"\nCOLMAP plugin ({backend}): scale {report['scale']['value']:.6f}, truth {truth:.6f}, "
          f"error {100 * err:+.3f} %")
    assert abs(err) < 0.01, f"scale error {100 * err:+.3f} %"
    return err


def test_colmap_command_pycolmap_backend(small_dataset: Any, tmp_path: Path) -> None:
    res = CliRunner().invoke(cli_main, _plugin_args(small_dataset, tmp_path / "run", "pycolmap"))
    assert res.exit_code == 0, res.output
    assert "SfM (pycolmap): 8/8 images" in res.output and "coarse mesh_coarse.ply" in res.output
    _check_plugin_run(tmp_path / "run", small_dataset, "pycolmap")
    report = json.loads((tmp_path / "run" / "scale" / "report.json").read_text())
    assert report["inputs"]["colmap_workspace"] == str(tmp_path / "run" / "sfm")
    assert report["held_out"]["content_compared_in"] == str(small_dataset.images_dir)


@pytest.mark.skipif(COLMAP is None, reason="colmap CLI not installed (apt-get install colmap)")
def test_colmap_command_with_the_colmap_cli_backend(small_dataset: Any, tmp_path: Path) -> None:
    """COLMAP 3.8's own command line does the SfM (each step's threads from --workers)."""
    args = [*_plugin_args(small_dataset, tmp_path / "run", "colmap"), "--workers", "1"]
    res = CliRunner().invoke(cli_main, args)
    assert res.exit_code == 0, res.output
    assert "SfM (colmap): 8/8 images" in res.output
    log = (tmp_path / "run" / "sfm" / "colmap.log").read_text()
    for step in ("feature_extractor", "matches_importer", "mapper", "use_gpu 0",
                 "--SiftExtraction.num_threads 2"):
        assert step in log
    _check_plugin_run(tmp_path / "run", small_dataset, "colmap")


def test_the_colmap_plugin_script_runs_the_colmap_command(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """plugins/colmap/colmap_laserscale.py hands its arguments to ``sfm-laserscale colmap`` and
    returns its exit status (here 2: the source images folder does not exist)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("colmap_laserscale", PLUGIN)
    assert spec is not None and spec.loader is not None
    plugin = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(plugin)
    (tmp_path / "rig.toml").write_text("")
    code = plugin.main(["--images", str(tmp_path / "nope"), "--laser-images", str(tmp_path),
                        "--rig", str(tmp_path / "rig.toml"), "--out", str(tmp_path / "out")])
    assert code == 2
    err = capsys.readouterr().err
    assert "sfm-laserscale: error:" in err and "source images folder not found" in err


def test_laser_images_are_held_out_by_name_and_by_content(small_dataset: Any,
                                                          tmp_path: Path) -> None:
    mixed = tmp_path / "mixed"
    shutil.copytree(small_dataset.images_dir, mixed)
    lasers = sorted(small_dataset.laser_images_dir.iterdir())
    shutil.copy(lasers[0], mixed / lasers[0].name)  # same name
    shutil.copy(lasers[1], mixed / "renamed.png")  # same content, another name
    sel = select_sfm_images(mixed, (small_dataset.laser_images_dir,))
    assert len(sel.names) == 8 and lasers[0].name not in sel.names
    assert "renamed.png" not in sel.names
    held = dict(sel.held_out)
    assert "same file name" in held[lasers[0].name] and "same content" in held["renamed.png"]
    assert "held out 2 laser image(s)" in sel.summary()


def test_a_failed_sfm_step_exits_4_and_names_it(tmp_path: Path) -> None:
    """Real pycolmap SfM on three images of unrelated noise: no image pair can start a model;
    exit status 4 and the step named, and no scale attempted."""
    rng = np.random.default_rng(0)
    images, laser = tmp_path / "images", tmp_path / "laser"
    images.mkdir()
    laser.mkdir()
    import cv2

    for k in range(3):
        cv2.imwrite(str(images / f"noise_{k}.png"),
                    rng.integers(0, 255, (240, 320), dtype=np.uint8))
    cv2.imwrite(str(laser / "laser.png"), rng.integers(0, 255, (240, 320), dtype=np.uint8))
    (tmp_path / "rig.toml").write_text("")
    res = CliRunner().invoke(cli_main, [
        "colmap", "--images", str(images), "--laser-images", str(laser), "--rig",
        str(tmp_path / "rig.toml"), "--out", str(tmp_path / "out"), "--backend", "pycolmap",
        "--max-features", "500", "--quiet"])
    assert res.exit_code == 4, res.output
    line = res.output.strip().splitlines()[-1]
    assert line.startswith("sfm-laserscale: tool failed: step ") and "failed" in line
    assert any(step in line for step in ("match_exhaustive", "incremental_mapping", "mapper"))
    assert not (tmp_path / "out" / "scale").exists()


@pytest.mark.parametrize("case", ["few images", "out not empty", "no colmap", "bad params"])
def test_colmap_command_bad_input_exits_2(small_dataset: Any, tmp_path: Path, case: str) -> None:
    args = _plugin_args(small_dataset, tmp_path / "out", "pycolmap")
    if case == "few images":
        few = tmp_path / "few"
        few.mkdir()
        for f in sorted(small_dataset.images_dir.iterdir())[:2]:
            shutil.copy(f, few / f.name)
        args[args.index("--images") + 1] = str(few)
    elif case == "out not empty":
        (tmp_path / "out").mkdir()
        (tmp_path / "out" / "x").write_text("x")
    elif case == "no colmap":
        args += ["--backend", "colmap", "--colmap", "no-such-colmap-binary"]
    else:
        args[args.index("--camera-params") + 1] = "1,2,x"
    res = CliRunner().invoke(cli_main, args)
    assert res.exit_code == 2, res.output
    err = res.output.strip().splitlines()
    assert err[-1].startswith("sfm-laserscale: error:") and len(err) == 1
    assert not (tmp_path / "out" / "sfm").exists()


def test_delaunay_25d_interpolates_a_height_field() -> None:
    """Sparse samples of a smooth height field: the 2.5D mesh stays within the interpolation
    error, and a triangle over a gap (edge > factor x median) is dropped."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1, 1, (600, 2))
    xy = xy[np.linalg.norm(xy - [0.5, 0.5], axis=1) > 0.3]  # a hole in the samples

    def height(p: np.ndarray) -> np.ndarray:
        return 0.1 * np.sin(2 * p[:, 0]) * np.cos(3 * p[:, 1])

    xyz = np.column_stack([xy, height(xy)])
    tri = delaunay_25d(xyz, np.array([0.0, 0.0, 1.0]), CoarseMeshOptions().max_edge_factor)
    caster = MeshRaycaster(xyz, tri)
    probe = rng.uniform(-0.8, 0.8, (300, 2))
    probe = probe[np.linalg.norm(probe - [0.5, 0.5], axis=1) > 0.45]
    res = caster.cast(np.column_stack([probe, np.full(len(probe), 5.0)]),
                      np.tile([0.0, 0.0, -1.0], (len(probe), 1)))
    assert res.hit.mean() > 0.95
    assert np.abs(res.xyz[res.hit, 2] - height(probe[res.hit])).max() < 0.01
    centre = caster.cast(np.array([[0.5, 0.5, 5.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert not centre.hit[0], "the hole must stay open"


@pytest.mark.parametrize("method", ["delaunay25d", "poisson"])
def test_coarse_mesh_of_the_openmvg_fixture_fits_its_points(method: str) -> None:
    model = read_openmvg_sfm_data(OPENMVG_DIR / "sfm_data.json")
    mesh = coarse_mesh(model, CoarseMeshOptions(method=method, min_track_length=2))
    v, f = mesh.vertices, mesh.triangles
    caster = MeshRaycaster(v, f)
    d = caster.distances(model.points_xyz) / model.extent
    assert len(f) > 100 and float(np.median(d)) < 0.01


# --------------------------------------------------------------------------- OpenMVG


def _spread_hits(image: Any, cam: Any, caster: MeshRaycaster) -> np.ndarray:
    """Four pixels where triangle centres of the mesh are seen unoccluded (rays hit that very
    triangle, away from edges), near the corners of the middle half of those pixels' box."""
    centres = caster.vertices[caster.triangles].mean(axis=1)
    x_cam = image.cam_from_world.transform(centres)
    front = x_cam[:, 2] > 0
    xy = cam.project(x_cam[front])
    ids = np.flatnonzero(front)
    res = caster.cast(*pixel_rays(cam, image.cam_from_world.inverse(), xy))
    ok = (res.primitive_id == ids) & (xy[:, 0] > 0) & (xy[:, 1] > 0) & (xy[:, 0] < cam.width) \
        & (xy[:, 1] < cam.height)
    xy = xy[ok]
    lo, hi = np.percentile(xy, [25, 75], axis=0)
    corners = [[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]]
    return np.array([xy[np.argmin(np.linalg.norm(xy - c, axis=1))] for c in corners])


def _openmvg_case(tmp: Path, s_true: float) -> tuple[Path, Path, Path, Path]:
    """Mesh (from the model's points), a laser image, a rig and spots with a known scale.

    MaupertuisTest_04.jpg serves as the laser image. Four of its pixels are cast into the mesh
    through the image's model pose; each beam of the rig is defined to pass through its
    origin (metres, near the lens) and the metric point s_true x X_cam of its hit, so FCM
    must return s_true.
    """
    model = read_openmvg_sfm_data(OPENMVG_DIR / "sfm_data.json")
    coarse = coarse_mesh(model, CoarseMeshOptions(min_track_length=2))
    v, f = coarse.vertices, coarse.triangles
    mesh = write_new_ply(tmp / "scene_dense_mesh_refine_texture.ply", v, f)
    image = model.image_by_name("MaupertuisTest_04.jpg")
    assert image is not None
    cam = model.cameras[image.camera_id]
    xy = _spread_hits(image, cam, MeshRaycaster(v, f))
    res = MeshRaycaster(v, f).cast(*pixel_rays(cam, image.cam_from_world.inverse(), xy))
    x_cam = image.cam_from_world.transform(res.xyz) * s_true  # metres
    origins = np.array([[-0.12, -0.12, 0], [0.12, -0.12, 0], [0.12, 0.12, 0], [-0.12, 0.12, 0]])
    lasers = tuple(Laser(name=f"L{k + 1}", origin=o, direction=(x - o) / np.linalg.norm(x - o),
                         color="red") for k, (o, x) in enumerate(zip(origins, x_cam, strict=True)))
    rig = tmp / "rig.toml"
    rig.write_text(rig_to_toml(Rig(name="imposed", lasers=lasers)))
    spots = tmp / "spots.csv"
    with spots.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["image", "laser", "x", "y"])
        for k, (x, y) in enumerate(xy):
            w.writerow([image.name, f"L{k + 1}", repr(float(x)), repr(float(y))])
    return mesh, OPENMVG_DIR / "images" / image.name, rig, spots


def test_openmvg_scale_step_on_real_reconstruction(tmp_path: Path) -> None:
    """The README's `sfm-laserscale scale --model sfm_data.json --mesh ...` step on the real
    OpenMVG fixture (regions found in matches/ beside it) with an imposed scale."""
    s_true = 2.5  # the camera is then ~3 m from the roof
    mesh, laser, rig, spots = _openmvg_case(tmp_path, s_true)
    out = tmp_path / "scaled_run"
    res = CliRunner().invoke(cli_main, [
        "scale", "--model", str(OPENMVG_DIR / "sfm_data.json"), "--mesh", str(mesh),
        "--laser-images", str(laser), "--rig", str(rig), "--spots", str(spots),
        "--method", "fcm", "--out", str(out), "--quiet"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    report = json.loads((out / "report.json").read_text())
    assert report["images"][0]["registered"] and report["images"][0]["num_inliers"] > 100
    assert report["scale"]["n_estimates"] == 4
    assert report["scale"]["value"] == pytest.approx(s_true, rel=2e-3)
    assert (out / "scaled" / "model" / "sfm_data.json").is_file()
    assert (out / "scaled" / mesh.name).is_file()
    m = [float(x) for x in (out / "transform_4x4.txt").read_text().split()]
    assert m[0] == m[5] == m[10] == report["scale"]["value"] and m[12:] == [0, 0, 0, 1]


# --------------------------------------------------------------------------- openmvg command


GLUE = REPO / "plugins" / "openmvg" / "openmvg_openmvs_laserscale.sh"
TOOLS = ["openMVG_main_SfMInit_ImageListing", "openMVG_main_ComputeFeatures",
         "openMVG_main_PairGenerator", "openMVG_main_ComputeMatches",
         "openMVG_main_GeometricFilter", "openMVG_main_SfM", "openMVG_main_ConvertSfM_DataFormat",
         "openMVG_main_openMVG2openMVS", "DensifyPointCloud", "ReconstructMesh", "RefineMesh",
         "TextureMesh", "TransformScene"]

# The documented interfaces (option names of each program's command-line parser, read from the
# sources: OpenMVG v2.1 src/software/SfM/main_*.cpp and export/main_openMVG2openMVS.cpp,
# OpenMVS v2.3.0 apps/*/*.cpp boost::program_options; OpenMVS's first positional argument is
# --input-file). No OpenMVG/OpenMVS package exists for Debian or PyPI, so the commands are
# checked against these, and run against stubs below.
DOCUMENTED = {
    "openMVG_main_SfMInit_ImageListing": {"-i", "-d", "-o", "-f", "-k", "-c", "-g", "-P", "-W",
                                          "-m"},
    "openMVG_main_ComputeFeatures": {"-i", "-o", "-m", "-u", "-f", "-p", "-n"},
    "openMVG_main_PairGenerator": {"-i", "-o", "-m", "-c"},
    "openMVG_main_ComputeMatches": {"-i", "-o", "-p", "-r", "-n", "-f", "-c", "-P"},
    "openMVG_main_GeometricFilter": {"-i", "-o", "-m", "-p", "-s", "-g", "-f", "-r", "-I", "-c"},
    "openMVG_main_SfM": {"-i", "-m", "-M", "-o", "-s", "-f", "-e", "-P", "-t", "-r", "-c", "-S",
                         "-G", "-g"},
    "openMVG_main_ConvertSfM_DataFormat": {"-i", "-o", "-V", "-I", "-E", "-S", "-O", "-C"},
    "openMVG_main_openMVG2openMVS": {"-i", "-o", "-d", "-n"},
    "DensifyPointCloud": {"-w", "--working-folder", "--max-threads", "-i", "-p", "-o",
                          "--resolution-level", "--number-views", "--fusion-mode",
                          "--dense-config-file"},
    "ReconstructMesh": {"-w", "--working-folder", "--max-threads", "-i", "-p",
                        "--pointcloud-file", "-o", "-d", "--decimate", "--mesh-file"},
    "RefineMesh": {"-w", "--working-folder", "--max-threads", "-i", "-m", "--mesh-file", "-o",
                   "--scales", "--gradient-step", "--resolution-level"},
    "TextureMesh": {"-w", "--working-folder", "--max-threads", "-i", "-m", "--mesh-file", "-o",
                    "--decimate", "--export-type"},
    "TransformScene": {"-w", "--working-folder", "--max-threads", "-i", "--input-file", "-p",
                       "-m", "-o", "-a", "-t", "--transform-file", "--export-type"},
}


def test_openmvg_openmvs_commands_use_only_documented_options(tmp_path: Path) -> None:
    from sfm_laserscale.pipelines.openmvg_steps import (
        OpenMvgOptions,
        reconstruction_steps,
        transform_step,
    )

    steps = [*reconstruction_steps(tmp_path, OpenMvgOptions(focal_px=1200.0, threads=2)),
             transform_step(tmp_path, tmp_path / "scale" / "transform_4x4.txt", 2)]
    assert [p.step.program for p in steps] == TOOLS
    for planned in steps:
        args = list(planned.step.args)
        options = [a for a in args if a.startswith("-") and not a.lstrip("-").isdigit()]
        unknown = set(options) - DOCUMENTED[planned.step.program]
        assert not unknown, (planned.step.program, unknown)
        if planned.step.program in ("DensifyPointCloud", "ReconstructMesh", "RefineMesh",
                                    "TextureMesh"):
            assert args[0].endswith(".mvs") and "-w" in args  # the input scene, positional
    by = {p.step.program: list(p.step.args) for p in steps}
    assert by["openMVG_main_SfM"][:2] == ["-s", "INCREMENTAL"]
    assert by["ReconstructMesh"][:3] == ["scene_dense.mvs", "-p", "scene_dense.ply"]
    assert by["TextureMesh"][1:5] == ["-m", "scene_dense_mesh_refine.ply", "-o",
                                      "scene_dense_mesh_refine_texture.mvs"]
    assert by["TransformScene"][3] == str((tmp_path / "scale" / "transform_4x4.txt").resolve())


STUB = r"""#!{python}
import json, os, shutil, sys
from pathlib import Path
tool = Path(sys.argv[0]).name
args = sys.argv[1:]
with open(os.environ["STUB_LOG"], "a") as fh:
    fh.write(json.dumps([tool, *args]) + "\n")
if tool == os.environ.get("STUB_FAIL"):
    sys.exit(1)
def opt(flag):
    return Path(args[args.index(flag) + 1])
fx = Path(os.environ["STUB_FIXTURE"])
w = opt("-w") if "-w" in args else None
if tool == "openMVG_main_SfMInit_ImageListing":
    shutil.copy(fx / "sfm_data.json", opt("-o") / "sfm_data.json")
elif tool == "openMVG_main_ComputeFeatures":
    shutil.copytree(fx / "matches", opt("-o"), dirs_exist_ok=True)
elif tool == "openMVG_main_SfM":
    opt("-o").mkdir(parents=True, exist_ok=True)
    shutil.copy(fx / "sfm_data.json", opt("-o") / "sfm_data.bin")
elif tool == "openMVG_main_ConvertSfM_DataFormat":
    shutil.copy(fx / "sfm_data.json", opt("-o"))
elif tool == "TextureMesh":
    shutil.copy(os.environ["STUB_MESH"], w / "scene_dense_mesh_refine_texture.ply")
elif tool in ("DensifyPointCloud", "ReconstructMesh", "RefineMesh", "TransformScene"):
    made = {{"DensifyPointCloud": ["scene_dense.mvs", "scene_dense.ply"],
             "ReconstructMesh": ["scene_dense_mesh.ply"],
             "RefineMesh": ["scene_dense_mesh_refine.ply"],
             "TransformScene": ["scene_metric.mvs"]}}[tool]
    if tool != os.environ.get("STUB_SILENT"):
        for name in made:
            (w / name).write_bytes(b"stub")
elif "-o" in args:
    opt("-o").parent.mkdir(parents=True, exist_ok=True)
    opt("-o").write_bytes(b"stub")
"""


def _stub_tools(tmp: Path, mesh: Path) -> tuple[Path, dict[str, str]]:
    """Every OpenMVG/OpenMVS program as one logging stub (they cannot be installed here): it
    writes what the real tool would, from the real OpenMVG fixture (its reconstruction and
    regions) and a mesh made from its points, so ``scale`` runs for real after them."""
    import sys

    stubs = tmp / "bin"
    stubs.mkdir()
    (stubs / "stub.py").write_text(STUB.format(python=sys.executable))
    (stubs / "stub.py").chmod(0o755)
    for tool in TOOLS:
        (stubs / tool).symlink_to(stubs / "stub.py")
    env = {"STUB_LOG": str(tmp / "calls.log"), "STUB_FIXTURE": str(OPENMVG_DIR),
           "STUB_MESH": str(mesh)}
    return stubs, env


def _openmvg_command_case(tmp: Path) -> tuple[list[str], dict[str, str]]:
    mesh, laser, rig, spots = _openmvg_case(tmp, 2.5)
    laser_dir = tmp / "laser"
    laser_dir.mkdir()
    shutil.copy(laser, laser_dir / "laser_0001.jpg")  # a model image's bytes, another name
    spots.write_text(spots.read_text().replace(laser.name, "laser_0001.jpg"))
    stubs, env = _stub_tools(tmp, mesh)
    args = ["openmvg", "--images", str(OPENMVG_DIR / "images"), "--laser-images",
            str(laser_dir), "--rig", str(rig), "--spots", str(spots), "--method", "fcm",
            "--focal-px", "1200", "--openmvg-bin", str(stubs), "--openmvs-bin", str(stubs),
            "--workers", "0", "--out", str(tmp / "out"), "--quiet"]
    return args, env


def _calls(tmp: Path) -> list[list[str]]:
    return [json.loads(line) for line in (tmp / "calls.log").read_text().splitlines()]


def test_openmvg_command_runs_the_sequence_then_scale_then_transform_scene(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    args, env = _openmvg_command_case(tmp_path)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    res = CliRunner().invoke(cli_main, args)
    assert res.exit_code == 0, res.output
    calls = _calls(tmp_path)
    assert [c[0] for c in calls] == TOOLS
    out = tmp_path / "out"
    linked = sorted(p.name for p in (out / "images_sfm").iterdir())
    assert linked == ["MaupertuisTest_01.jpg", "MaupertuisTest_02.jpg", "MaupertuisTest_03.jpg"]
    assert calls[0][1:3] == ["-i", str(out / "images_sfm")] and "1200" in calls[0]
    assert all(c[c.index("--max-threads") + 1] == "1" for c in calls if "--max-threads" in c)
    report = json.loads((out / "scale" / "report.json").read_text())
    assert report["scale"]["value"] == pytest.approx(2.5, rel=2e-3)
    assert report["inputs"]["mesh"] == str(out / "mvs" / "scene_dense_mesh_refine_texture.ply")
    assert report["inputs"]["model"] == str(out / "reconstruction_sequential" / "sfm_data.json")
    transform = calls[-1]
    assert transform[transform.index("--transform-file") + 1] == str(
        out / "scale" / "transform_4x4.txt")
    assert "metric OpenMVS scene" in res.output and "1 laser image(s) held out" in res.output


@pytest.mark.parametrize("how", ["exit status", "no output"])
def test_a_failed_openmvs_step_exits_4_and_names_it(tmp_path: Path, how: str,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    args, env = _openmvg_command_case(tmp_path)
    env["STUB_FAIL" if how == "exit status" else "STUB_SILENT"] = "ReconstructMesh"
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    res = CliRunner().invoke(cli_main, args)
    assert res.exit_code == 4, res.output
    line = res.output.strip().splitlines()[-1]
    assert line.startswith("sfm-laserscale: tool failed: step 'ReconstructMesh' failed: ")
    assert ("exited with status 1" if how == "exit status" else "wrote no") in line
    assert str(tmp_path / "out" / "tools.log") in line
    assert [c[0] for c in _calls(tmp_path)][-1] == "ReconstructMesh"  # nothing after it
    assert not (tmp_path / "out" / "scale").exists()


def test_openmvg_command_refuses_missing_tools_before_any_work(tmp_path: Path) -> None:
    (tmp_path / "rig.toml").write_text("")
    res = CliRunner().invoke(cli_main, [
        "openmvg", "--images", str(OPENMVG_DIR / "images"), "--laser-images",
        str(OPENMVG_DIR / "images" / "MaupertuisTest_04.jpg"), "--rig",
        str(tmp_path / "rig.toml"), "--focal-px", "1200", "--openmvg-bin", str(tmp_path),
        "--out", str(tmp_path / "out")])
    assert res.exit_code == 2, res.output
    assert "openMVG_main_SfMInit_ImageListing not found" in res.output
    assert not (tmp_path / "out").exists()


def test_openmvg_glue_script_runs_the_openmvg_command(tmp_path: Path) -> None:
    """plugins/openmvg's script hands its arguments and environment to ``sfm-laserscale
    openmvg`` (a stub here that logs them)."""
    stub = tmp_path / "sfm-laserscale"
    log = tmp_path / "args.log"
    stub.write_text(f'#!/bin/sh\necho "$@" > "{log}"\n')
    stub.chmod(0o755)
    env = {**os.environ, "SFM_LASERSCALE": str(stub), "FOCAL_PX": "1200",
           "OPENMVS_BIN": "/opt/openmvs", "SCALE_ARGS": "--method fcm"}
    proc = subprocess.run(["bash", str(GLUE), "imgs", "laser", "rig.toml", "out"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert log.read_text().split() == [
        "openmvg", "--images", "imgs", "--laser-images", "laser", "--rig", "rig.toml", "--out",
        "out", "--overwrite", "--focal-px", "1200", "--openmvs-bin", "/opt/openmvs", "--method",
        "fcm"]


def test_openmvg_glue_script_refuses_missing_intrinsics(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("FOCAL_PX", "CAMERA_DB",
                                                            "INTRINSICS_K")}
    for d in ("images", "laser"):
        (tmp_path / d).mkdir()
    proc = subprocess.run(["bash", str(GLUE), str(tmp_path / "images"), str(tmp_path / "laser"),
                           str(tmp_path / "rig.toml"), str(tmp_path / "out")], env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "FOCAL_PX" in proc.stderr
