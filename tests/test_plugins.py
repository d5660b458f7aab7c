"""The pipeline plugins: plugins/colmap (SfM -> mesh -> scale in one command) and plugins/openmvg
(our step on a real OpenMVG reconstruction, and the glue script's command sequence).

Truth for the COLMAP plugin: the plugin builds a FRESH reconstruction of the synthetic survey
(``small_dataset``), so its true scale is found here by aligning the fresh model's camera
centres to the true camera centres of truth.json (Umeyama): s_true = 1 / s_model_from_world.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from sfm_laserscale.cli import main as cli_main
from sfm_laserscale.geometry import rotmat_from_qvec, umeyama_sim3
from sfm_laserscale.io.openmvg import read_openmvg_sfm_data
from sfm_laserscale.model import Pose, SparseModel
from sfm_laserscale.raycast import MeshRaycaster, pixel_rays
from sfm_laserscale.rig import Laser, Rig, rig_to_toml

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO.parent / "shared" / "fixtures"
OPENMVG_DIR = FIXTURES / "maupertuis_openmvg"
COLMAP = shutil.which("colmap")


def _load(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses resolve annotations through sys.modules
    spec.loader.exec_module(module)
    return module


plugin = _load("colmap_laserscale", REPO / "plugins" / "colmap" / "colmap_laserscale.py")


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
    return ["--images", str(ds.images_dir), "--laser-images", str(ds.laser_images_dir),
            "--rig", str(ds.rig_path), "--out", str(out), "--backend", backend,
            "--pairs", str(ds.out_dir / "pairs.txt"), "--camera-model", ds.camera.model,
            "--camera-params", params, "--max-features", "2000", "--sift-first-octave", "0"]


def _check_plugin_run(out: Path, ds: Any, backend: str) -> float:
    """Outputs present, scale within 1 % of the fresh model's truth; returns the error."""
    report = json.loads((out / "scale" / "report.json").read_text())
    _, model = plugin.largest_model(out / "sfm" / "sparse")
    assert len(model.images) == 8, "every reference image registered"
    for rel in ("sfm/database.db", "sfm/mesh_coarse.ply", "scale/transform.sim3",
                "scale/transform_4x4.txt", "scale/scaled/mesh_coarse.ply",
                "scale/scaled/model/images.bin"):
        assert (out / rel).is_file(), rel
    truth = true_scale_of(model, ds.truth_path)
    err = report["scale"]["value"] / truth - 1
    print(f"\nCOLMAP plugin ({backend}): scale {report['scale']['value']:.6f}, truth {truth:.6f}, "
          f"error {100 * err:+.3f} %")
    assert abs(err) < 0.01, f"scale error {100 * err:+.3f} %"
    return err


def test_colmap_plugin_pycolmap_backend(small_dataset: Any, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    code = plugin.main(_plugin_args(small_dataset, tmp_path / "run", "pycolmap"))
    stdout = capsys.readouterr().out
    assert code == 0, stdout
    assert "SfM (pycolmap): 8/8 images" in stdout and "coarse mesh_coarse.ply" in stdout
    _check_plugin_run(tmp_path / "run", small_dataset, "pycolmap")


@pytest.mark.skipif(COLMAP is None, reason="colmap CLI not installed (apt-get install colmap)")
def test_colmap_plugin_colmap_cli_backend(small_dataset: Any, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    code = plugin.main(_plugin_args(small_dataset, tmp_path / "run", "colmap"))
    stdout = capsys.readouterr().out
    assert code == 0, stdout
    assert "SfM (colmap): 8/8 images" in stdout
    log = (tmp_path / "run" / "sfm" / "colmap.log").read_text()
    for step in ("feature_extractor", "matches_importer", "mapper", "use_gpu 0"):
        assert step in log
    _check_plugin_run(tmp_path / "run", small_dataset, "colmap")


def test_plugin_holds_out_laser_images_found_among_source_images(small_dataset: Any,
                                                                 tmp_path: Path) -> None:
    mixed = tmp_path / "mixed"
    shutil.copytree(small_dataset.images_dir, mixed)
    laser = sorted(small_dataset.laser_images_dir.iterdir())[0]
    shutil.copy(laser, mixed / laser.name)
    names = plugin.source_image_names(mixed, (mixed / laser.name,))
    assert laser.name not in names and len(names) == 8
    assert laser.name in plugin.source_image_names(mixed, (small_dataset.laser_images_dir,))


@pytest.mark.parametrize("case", ["few images", "out not empty", "no colmap", "bad params"])
def test_plugin_bad_input_exits_2(small_dataset: Any, tmp_path: Path, case: str,
                                  capsys: pytest.CaptureFixture[str]) -> None:
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
    assert plugin.main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("colmap_laserscale: error:") and len(err.strip().splitlines()) == 1
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
    tri = plugin.delaunay_25d(xyz, np.array([0.0, 0.0, 1.0]),
                              plugin.CoarseMeshOptions().max_edge_factor)
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
    v, f = plugin.coarse_mesh(model, plugin.CoarseMeshOptions(method=method,
                                                              min_track_length=2))
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
    v, f = plugin.coarse_mesh(model, plugin.CoarseMeshOptions(min_track_length=2))
    mesh = plugin.write_ply(tmp / "scene_dense_mesh_refine_texture.ply", v, f)
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


# --------------------------------------------------------------------------- glue script


GLUE = REPO / "plugins" / "openmvg" / "openmvg_openmvs_laserscale.sh"
TOOLS = ["openMVG_main_SfMInit_ImageListing", "openMVG_main_ComputeFeatures",
         "openMVG_main_PairGenerator", "openMVG_main_ComputeMatches",
         "openMVG_main_GeometricFilter", "openMVG_main_SfM", "openMVG_main_ConvertSfM_DataFormat",
         "openMVG_main_openMVG2openMVS", "DensifyPointCloud", "ReconstructMesh", "RefineMesh",
         "TextureMesh", "sfm-laserscale", "TransformScene"]


def test_openmvg_glue_script_runs_the_documented_sequence(tmp_path: Path) -> None:
    """Every tool replaced by a stub that logs its arguments: the order, the hold-out of the
    laser images and the hand-over of transform_4x4.txt to TransformScene."""
    stubs = tmp_path / "bin"
    stubs.mkdir()
    log = tmp_path / "calls.log"
    for tool in TOOLS:
        (stubs / tool).write_text(f'#!/bin/sh\necho "{tool} $*" >> "{log}"\n')
        (stubs / tool).chmod(0o755)
    images, laser = tmp_path / "images", tmp_path / "laser"
    images.mkdir()
    laser.mkdir()
    for name in ("a.jpg", "b.jpg", "c.jpg", "l1.jpg"):
        (images / name).write_bytes(b"x")
    (laser / "l1.jpg").write_bytes(b"x")
    (tmp_path / "rig.toml").write_text("")
    env = {**os.environ, "PATH": f"{stubs}:{os.environ['PATH']}", "FOCAL_PX": "1200"}
    proc = subprocess.run(["bash", str(GLUE), str(images), str(laser), str(tmp_path / "rig.toml"),
                           str(tmp_path / "out")], env=env, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    calls = log.read_text().splitlines()
    assert [c.split()[0] for c in calls] == TOOLS
    sfm_images = tmp_path / "out" / "images_sfm"
    assert sorted(p.name for p in sfm_images.iterdir()) == ["a.jpg", "b.jpg", "c.jpg"]
    assert f"-i {sfm_images}" in calls[0] and "-f 1200" in calls[0]
    scale = next(c for c in calls if c.startswith("sfm-laserscale"))
    assert "--model" in scale and "sfm_data.json" in scale
    assert "scene_dense_mesh_refine_texture.ply" in scale and f"--laser-images {laser}" in scale
    transform = calls[-1]
    assert "--transform-file" in transform and "transform_4x4.txt" in transform
    assert "scene_dense_mesh_refine_texture.mvs" in transform


def test_openmvg_glue_script_refuses_missing_intrinsics(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("FOCAL_PX", "CAMERA_DB",
                                                            "INTRINSICS_K")}
    for d in ("images", "laser"):
        (tmp_path / d).mkdir()
    proc = subprocess.run(["bash", str(GLUE), str(tmp_path / "images"), str(tmp_path / "laser"),
                           str(tmp_path / "rig.toml"), str(tmp_path / "out")], env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "FOCAL_PX" in proc.stderr

