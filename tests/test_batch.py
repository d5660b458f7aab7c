"""``sfm-laserscale batch``: a manifest of models scaled on Dask. A broken row is reported and
the others scaled; a rerun skips the unchanged ones and redoes a changed or killed one; bad
manifests exit 2 naming the row and column before any work; ``--jobs 2`` (a local cluster
started by the batch) and ``--scheduler`` (a LocalCluster started here) run the same tasks with
each job's threads capped (2 jobs on 2 cores: 1 thread each, no SIFT worker process).

The models are the real OpenMVG fixture with laser spots and rigs made for imposed scales
(tests/test_plugins.py), so each model's right answer is known, and cheap to run.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
from click.testing import CliRunner

from sfm_laserscale.cli import main as cli_main
from sfm_laserscale.io.manifest import read_manifest
from sfm_laserscale.report.batch_summary import SUMMARY_COLUMNS
from tests.test_plugins import OPENMVG_DIR
from tests.test_workspaces import openmvg_project


@pytest.fixture(scope="module")
def cruise(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three models: 'roof' (an OpenMVG + OpenMVS project, scale 2.5), 'roof_small' (explicit
    model + mesh + spots, scale 1.5) and 'broken' (its mesh file is not a mesh)."""
    root = tmp_path_factory.mktemp("cruise")
    _, laser, rig, spots = openmvg_project(root / "roof", 2.5)
    small = root / "small"
    small.mkdir()
    from tests.test_plugins import _openmvg_case

    mesh2, _, rig2, spots2 = _openmvg_case(small, 1.5)
    (root / "broken.ply").write_text("ply\nthis is not a mesh\n")
    rows = [
        ["name", "laser_images", "rig", "spots", "model", "mesh", "openmvg_project", "method"],
        ["roof", f"roof/images/{laser.name}", "roof/rig.toml", "roof/spots.csv", "", "", "roof",
         "fcm"],
        ["roof_small", str(laser), str(rig2.relative_to(root)), str(spots2.relative_to(root)),
         str(OPENMVG_DIR / "sfm_data.json"), str(mesh2.relative_to(root)), "", "fcm"],
        ["broken", str(laser), "roof/rig.toml", "roof/spots.csv",
         str(OPENMVG_DIR / "sfm_data.json"), "broken.ply", "", ""],
    ]
    (root / "broken2.ply").write_bytes(b"")
    manifests = {"manifest.csv": [rows[0], rows[1], rows[3]],  # roof, broken
                 "small.csv": [rows[0], rows[2]],  # roof_small
                 "broken.csv": [rows[0], rows[3], [*rows[3][:5], "broken2.ply", "", ""]]}
    manifests["broken.csv"][2][0] = "broken2"
    for name, content in manifests.items():
        with (root / name).open("w", newline="") as fh:
            csv.writer(fh).writerows(content)
    return root


def _summary(out: Path) -> dict[str, dict[str, str]]:
    with (out / "summary.csv").open() as fh:
        reader = csv.DictReader(fh)
        assert tuple(reader.fieldnames or ()) == SUMMARY_COLUMNS
        return {r["name"]: r for r in reader}


def _batch(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(cli_main, ["batch", *args, "--quiet"])
    return res.exit_code, res.output


def test_batch_scales_the_others_reports_the_broken_one_and_skips_on_rerun(
        cruise: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    code, output = _batch(str(cruise / "manifest.csv"), "--out", str(out), "--jobs", "1")
    assert code == 1, output  # one model has no scale
    rows = _summary(out)
    assert list(rows) == ["roof", "broken"]
    r = rows["roof"]
    assert r["status"] == "ok" and float(r["scale"]) == pytest.approx(2.5, rel=2e-3)
    assert float(r["ci95_low"]) < float(r["scale"]) < float(r["ci95_high"])
    assert float(r["inverse"]) == pytest.approx(1 / float(r["scale"]))
    assert r["method"] == "fcm" and r["images_used"] == "1" and r["estimates"] == "4"
    assert float(r["std"]) > 0 and float(r["wall_s"]) > 0 and r["reason"] == ""
    assert (out / "roof" / "report.json").is_file() and (out / "roof" / "run.log").is_file()
    assert rows["broken"]["status"] == "error" and "broken.ply" in rows["broken"]["reason"]
    assert rows["broken"]["scale"] == ""
    assert "broken.ply" in (out / "broken" / "run.log").read_text()
    html = (out / "summary.html").read_text()
    assert 'href="roof/report.html"' in html and "1 error" in html and html.count("<svg") == 1
    report = json.loads((out / "roof" / "report.json").read_text())
    assert report["inputs"]["openmvg_project"] == str(cruise / "roof")

    stamp = (out / "roof" / "report.json").stat().st_mtime_ns
    code, output = _batch(str(cruise / "manifest.csv"), "--out", str(out), "--jobs", "1")
    assert code == 1, output
    rows2 = _summary(out)
    assert rows2["roof"]["status"] == "skipped" and "unchanged" in rows2["roof"]["reason"]
    assert rows2["roof"]["scale"] == rows["roof"]["scale"]  # the kept output's numbers
    assert rows2["broken"]["status"] == "error"  # a failed model is tried again
    assert (out / "roof" / "report.json").stat().st_mtime_ns == stamp

    # a model killed mid-run left no output, only its staging folder (a dead process's): it is
    # redone and the staging folder removed
    shutil.rmtree(out / "roof")
    stale = out / ".roof.partial-999999999-abc"
    (stale / "overlays").mkdir(parents=True)
    code, _ = _batch(str(cruise / "manifest.csv"), "--out", str(out), "--jobs", "1")
    assert _summary(out)["roof"]["status"] == "ok" and not stale.exists()

    # --no-guided-spots and --no-scene-reference change the options that decide the numbers:
    # redone, without the search and without the second detection
    for flag, key in (("--no-guided-spots", "guided"), ("--no-scene-reference", "scene")):
        code, _ = _batch(str(cruise / "manifest.csv"), "--out", str(out), "--jobs", "1", flag)
        assert _summary(out)["roof"]["status"] == "ok"
        ran = json.loads((out / "roof" / "report.json").read_text())["provenance"]["options"]
        assert ran[key]["enabled"] is False
        assert ran["scene" if key == "guided" else "guided"]["enabled"] is True
    shutil.rmtree(out / "roof")
    code, _ = _batch(str(cruise / "manifest.csv"), "--out", str(out), "--jobs", "1")

    # what a rerun compares: any input file's bytes, and the options that change numbers
    from sfm_laserscale.batch.job import ModelJob, _given, scale_options
    from sfm_laserscale.batch.rerun import previous_report, unchanged_reason
    from sfm_laserscale.pipeline_folders import resolve_scale_inputs

    row = read_manifest(cruise / "manifest.csv")[0]
    job = ModelJob(row=row, out_dir=out / "roof", method="fcm", seed=0, overwrite=False)
    inputs, options = resolve_scale_inputs(_given(row)), scale_options(job, 2)
    previous = previous_report(out / "roof")
    assert previous is not None and unchanged_reason(previous, inputs, options) is None
    assert unchanged_reason(previous, inputs, scale_options(job, 1)) is None  # threads: same
    assert unchanged_reason(previous, inputs, replace(options, seed=1)) == "options changed"
    rig = cruise / "roof" / "rig.toml"
    text = rig.read_text()
    try:
        rig.write_text(text.replace("imposed", "imposeD"))  # same size, other bytes
        assert unchanged_reason(previous, inputs, options) == f"input file changed ({rig})"
    finally:
        rig.write_text(text)


def test_batch_exit_0_when_every_model_is_scaled_on_an_existing_dask_cluster(
        cruise: Path, tmp_path: Path) -> None:
    """--scheduler: the tasks run on a LocalCluster started here (2 processes of 1 thread on
    this host): each job capped at cores / 2 threads, so no SIFT worker process on 2 cores."""
    from distributed import Client, LocalCluster

    from sfm_laserscale.batch.execute import worker_thread_caps
    from sfm_laserscale.resources import available_cpus

    out = tmp_path / "out"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        with Client(cluster) as client:
            caps = worker_thread_caps(client)
        code, output = _batch(str(cruise / "small.csv"), "--out", str(out), "--scheduler",
                              cluster.scheduler_address)
    threads = max(1, available_cpus() // 2)
    assert len(caps) == 2 and set(caps.values()) == {threads}
    assert code == 0, output
    assert "1 of 1 models scaled" in output
    row = _summary(out)["roof_small"]
    assert row["status"] == "ok" and float(row["scale"]) == pytest.approx(1.5, rel=2e-3)
    options = json.loads((out / "roof_small" / "report.json").read_text())["provenance"]
    assert options["options"]["sift_workers"]["workers"] == threads - 1
    assert options["options"]["sift"]["num_threads"] == threads


def test_batch_jobs_2_runs_on_a_local_cluster_and_reports_every_failure(
        cruise: Path, tmp_path: Path) -> None:
    """--jobs 2: a local cluster of 2 processes started and closed by the batch; two broken
    models, each reported with its own reason (no worker outlives the batch)."""
    from multiprocessing import resource_tracker

    import psutil

    # the interpreter's one resource tracker lives as long as this process: started by the
    # cluster when no test before this one in the process did, it is no worker of the batch
    resource_tracker.ensure_running()
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    code, output = _batch(str(cruise / "broken.csv"), "--out", str(tmp_path / "out"),
                          "--jobs", "2")
    assert code == 1, output
    rows = _summary(tmp_path / "out")
    assert rows["broken"]["status"] == rows["broken2"]["status"] == "error"
    assert "broken.ply" in rows["broken"]["reason"] and "broken2.ply" in rows["broken2"]["reason"]
    assert "0 of 2 models scaled (2 error)" in output
    left = {p.pid for p in psutil.Process().children(recursive=True)} - before
    assert not left, f"worker processes left behind: {left}"


def _manifest(tmp: Path, header: str, *rows: str) -> Path:
    (tmp / "rig.toml").write_text("")
    (tmp / "mesh.ply").write_text("x")
    (tmp / "laser").mkdir(exist_ok=True)
    path = tmp / "m.csv"
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


OK_ROW = f"a,laser,rig.toml,{OPENMVG_DIR / 'sfm_data.json'},mesh.ply"


@pytest.mark.parametrize(("header", "rows", "expect"), [
    ("name,laser_images,model,mesh", [], "line 1 (header), column 'rig': missing column"),
    ("name,laser_images,rig,model,mesh,colour", [OK_ROW + ",red"],
     "line 1 (header), column 'colour': unknown column"),
    ("name,laser_images,rig,model,mesh", [OK_ROW, OK_ROW.replace("a,", "b,", 1), OK_ROW],
     "line 4 (row 3), column 'name': duplicate name 'a' (first on line 2)"),
    ("name,laser_images,rig,model,mesh", [OK_ROW.replace("mesh.ply", "missing.ply")],
     "line 2 (row 1), column 'mesh': file not found"),
    ("name,laser_images,rig,model,mesh", [OK_ROW.replace("rig.toml", "nope.toml")],
     "line 2 (row 1), column 'rig': file not found"),
    ("name,laser_images,rig,model,mesh", [OK_ROW.replace(",laser,", ",,")],
     "line 2 (row 1), column 'laser_images': empty (required)"),
    ("name,laser_images,rig,model,mesh", [OK_ROW.replace(",laser,", ",laser;gone.jpg,")],
     "line 2 (row 1), column 'laser_images': file or folder not found"),
    ("name,laser_images,rig,model,mesh,method", [OK_ROW + ",best"],
     "line 2 (row 1), column 'method': 'best' is not one of fcm, pcm, all"),
    ("name,laser_images,rig,model,mesh,colmap_workspace", [OK_ROW + ",laser"],
     "line 2 (row 1), column 'colmap_workspace': give one model, not model and "
     "colmap_workspace"),
    ("name,laser_images,rig,model,mesh", ["a,laser,rig.toml,,"],
     "line 2 (row 1), column 'model': no model"),
    ("name,laser_images,rig,model,mesh", [OK_ROW.replace("mesh.ply", "")],
     "line 2 (row 1), column 'mesh': empty: a model needs its mesh"),
    ("name,laser_images,rig,model,mesh", [OK_ROW.replace("a,", "../up,", 1)],
     "line 2 (row 1), column 'name': '../up' cannot name an output folder"),
    ("name,laser_images,rig,model,mesh", [], "has no row"),
])
def test_bad_manifests_exit_2_naming_row_and_column(tmp_path: Path, header: str,
                                                    rows: list[str], expect: str) -> None:
    manifest = _manifest(tmp_path, header, *rows)
    code, output = _batch(str(manifest), "--out", str(tmp_path / "out"))
    assert code == 2, output
    line = output.strip().splitlines()[-1]
    assert line.startswith(f"sfm-laserscale: error: {manifest}: ") and expect in line, line
    assert not (tmp_path / "out").exists(), "no work before the manifest is checked"


def test_unreadable_manifest_exits_2(tmp_path: Path) -> None:
    code, output = _batch(str(tmp_path / "nope.csv"), "--out", str(tmp_path / "out"))
    assert code == 2 and "manifest not found" in output
    bad = tmp_path / "bad.csv"
    bad.write_bytes(b"\xff\xfe\x00name")
    code, output = _batch(str(bad), "--out", str(tmp_path / "out"))
    assert code == 2 and "cannot read the manifest" in output


def test_manifest_paths_are_relative_to_its_folder(tmp_path: Path) -> None:
    sub = tmp_path / "cruise"
    sub.mkdir()
    manifest = _manifest(sub, "name,laser_images,rig,model,mesh,method",
                         "a,laser;rig.toml,rig.toml," + str(OPENMVG_DIR / "sfm_data.json")
                         + ",mesh.ply,pcm")
    cwd = os.getcwd()
    try:
        os.chdir(tmp_path)
        (row,) = read_manifest(Path("cruise/m.csv"))
    finally:
        os.chdir(cwd)
    assert row.laser_images == (Path("cruise/laser"), Path("cruise/rig.toml"))
    assert row.mesh == Path("cruise/mesh.ply") and row.method == "pcm" and row.line == 2
    assert manifest.is_file()
