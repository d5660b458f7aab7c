"""The scale job as a library call: truth on synthetic data, invariance to the model scale."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from sfm_laserscale.commands import scale as scale_command
from sfm_laserscale.commands.demo import scale_inputs_for
from sfm_laserscale.io.colmap_write import write_scaled_colmap_model
from sfm_laserscale.io.meshes.mesh import write_scaled_mesh
from sfm_laserscale.run_types import ScaleOptions


@pytest.fixture(scope="module")
def baseline(small_scale_run: Any) -> Any:
    """The session's real scale run of the small dataset (tests/conftest.py)."""
    return small_scale_run


def test_scale_matches_truth(baseline: Any, small_dataset: Any) -> None:
    assert baseline.success
    err = (baseline.scale.value - small_dataset.true_scale) / small_dataset.true_scale
    assert abs(err) < 0.01
    assert all(im.registration is not None and im.registration.success for im in baseline.images)


def test_rescaled_model_and_mesh_change_scale_by_inverse(baseline: Any, small_dataset: Any,
                                                         tmp_path: Path) -> None:
    k = 7.25
    model = tmp_path / "model"
    write_scaled_colmap_model(small_dataset.model_dir, model, k)
    write_scaled_mesh(small_dataset.mesh_path, tmp_path / "mesh", k)
    inputs = scale_inputs_for(small_dataset)
    from dataclasses import replace

    inputs = replace(inputs, model=model, mesh=tmp_path / "mesh" / small_dataset.mesh_path.name)
    res = scale_command.run(inputs, tmp_path / "run", ScaleOptions(progress=False))
    assert res.success
    # Not bit-exact: the pose refinement's stopping tolerances are not scale-free (seen 6e-6).
    assert res.scale.value == pytest.approx(baseline.scale.value / k, rel=1e-4)
    assert res.scale.std == pytest.approx(baseline.scale.std / k, rel=1e-2)


def test_report_json_matches_result(baseline: Any) -> None:
    report = json.loads((baseline.out_dir / "report.json").read_text())
    assert report["scale"]["value"] == pytest.approx(baseline.scale.value, rel=1e-15)
    assert report["scale"]["n_estimates"] == baseline.scale.n_estimates
    assert len(report["images"]) == len(baseline.images)


def test_scaled_model_is_metric(baseline: Any, small_dataset: Any) -> None:
    """Distances between camera centres of the rescaled model equal the true metric ones."""
    import numpy as np

    from sfm_laserscale.geometry import rotmat_from_qvec
    from sfm_laserscale.io.colmap import read_colmap_model

    scaled = read_colmap_model(baseline.out_dir / "scaled" / "model")
    truth = json.loads(small_dataset.truth_path.read_text())["reference_images"]
    true_c = {}
    for t in truth:
        R = rotmat_from_qvec(np.array(t["cam_from_world"]["rotation_wxyz"]))
        true_c[t["name"]] = -R.T @ np.array(t["cam_from_world"]["translation"])
    names = sorted(true_c)
    est_c = {im.name: im.cam_from_world.center for im in scaled.images.values()}
    d_true = [np.linalg.norm(true_c[a] - true_c[b]) for a in names for b in names if a < b]
    d_est = [np.linalg.norm(est_c[a] - est_c[b]) for a in names for b in names if a < b]
    ratio = np.median(np.array(d_est) / np.array(d_true))
    assert ratio == pytest.approx(1.0, abs=0.01)


def test_run_log_and_provenance(baseline: Any, small_dataset: Any) -> None:
    import hashlib

    log = (baseline.out_dir / "run.log").read_text()
    assert "registration:" in log and "run finished" in log
    prov = json.loads((baseline.out_dir / "report.json").read_text())["provenance"]
    by_path = {d["path"]: d for d in prov["inputs"]}
    mesh = by_path[str(small_dataset.mesh_path)]
    assert mesh["sha256"] == hashlib.sha256(small_dataset.mesh_path.read_bytes()).hexdigest()
    assert mesh["bytes"] == small_dataset.mesh_path.stat().st_size
    assert any(p.endswith(".png") for p in by_path)
    assert prov["options"]["method"] == "all" and "registration" in prov["options"]


def test_mesh_check_on_the_crop_is_the_whole_mesh_check(baseline: Any,
                                                        small_dataset: Any) -> None:
    """The report's mesh–model check, computed on the cropped mesh, equals the whole mesh's;
    a mesh that does not fit the model (shifted by 3 % of the extent) falls back to the whole
    mesh and is flagged; the crop keeps a small part of the mesh."""
    import dataclasses

    import numpy as np

    from sfm_laserscale.commands.scale import (
        crop_mesh,
        load_inputs,
        mesh_check_points,
        mesh_model_agreement,
    )
    from sfm_laserscale.io.meshes.mesh import TriangleMesh
    from sfm_laserscale.raycast import MeshRaycaster

    opts = ScaleOptions(progress=False)
    loaded = load_inputs(scale_inputs_for(small_dataset), opts)
    runs = baseline.images
    pts = mesh_check_points(runs, opts, loaded.model.extent)
    assert len(pts) >= 50  # the registered laser images' inliers near the spots
    crop = crop_mesh(runs, loaded, opts)
    assert crop.kept_fraction < 0.5
    assert loaded.mesh is not None
    whole = MeshRaycaster(loaded.mesh.vertices, loaded.mesh.triangles)
    extent = loaded.model.extent

    def never() -> TriangleMesh:
        raise AssertionError("the whole mesh is not needed for a mesh that fits")

    on_crop = mesh_model_agreement(pts, crop.raycaster(), extent, never)
    # equal up to Open3D's float32 distances (crop and mesh are centred differently)
    assert on_crop == pytest.approx(mesh_model_agreement(pts, whole, extent, never), rel=1e-3)
    assert on_crop == pytest.approx(baseline.report["checks"]["mesh_model_agreement"])
    assert 0 < on_crop < 0.005
    assert loaded.mesh is not None
    shift = np.array([0.0, 0.0, 0.03 * loaded.model.extent])
    moved_mesh = TriangleMesh(loaded.mesh.vertices + shift, loaded.mesh.triangles)
    bad = crop_mesh(runs, dataclasses.replace(loaded, mesh=moved_mesh), opts).raycaster()
    want = float(np.median(MeshRaycaster(moved_mesh.vertices, moved_mesh.triangles)
                           .distances(pts))) / loaded.model.extent
    got = mesh_model_agreement(pts, bad, extent, lambda: moved_mesh)
    assert got == pytest.approx(want, rel=1e-6)
    assert want > 0.02  # beyond the crop's exact radius: the whole mesh was used
