"""SIFT of the laser images in worker processes: planning, identical features, a worker that
dies or fails, and the pipeline with and without workers (same numbers)."""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sfm_laserscale.cli import main
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.images import read_rgb
from sfm_laserscale.model import ImageFeatures, ObservationFeatures
from sfm_laserscale.provenance import glog_lines, merged_glog
from sfm_laserscale.registration.options import SiftOptions
from sfm_laserscale.registration.sift import extract_sift
from sfm_laserscale.registration.sift_workers import SiftPool, SiftWorkerOptions, plan_workers

GB = 2**30


def _laser_paths(ds: Any) -> list[Path]:
    return sorted(ds.laser_images_dir.glob("*.png"))


def _same(a: ImageFeatures, b: ImageFeatures) -> bool:
    return bool(np.array_equal(a.xy_px, b.xy_px) and np.array_equal(a.descriptors, b.descriptors))


@pytest.mark.parametrize(
    ("n_images", "pixels", "cpus", "avail", "workers", "expected"),
    [
        (6, 640 * 480, 2, 16 * GB, None, 1),  # one free core
        (6, 640 * 480, 8, 16 * GB, None, 5),  # fewer workers than images
        (1, 640 * 480, 8, 16 * GB, None, 0),  # one image: this process alone
        (20, 640 * 480, 8, 16 * GB, None, 7),  # this process keeps a core
        (6, 640 * 480, 1, 16 * GB, None, 0),  # one core: none
        (20, 4000 * 3000, 16, 8 * GB, None, 1),  # 0.3 GB + 3.6 GB each, half of 8 GB: one
        (20, 4000 * 3000, 16, 3 * GB, None, 0),  # not even one fits
        (20, 640 * 480, 8, None, None, 7),  # memory unknown: cores decide
        (6, 640 * 480, 1, 16 * GB, 3, 3),  # asked for: taken as given
        (2, 640 * 480, 8, 16 * GB, 5, 2),  # ... but no more than images
        (6, 640 * 480, 8, 16 * GB, 0, 0),
        (0, 0, 8, 16 * GB, None, 0),
    ],
)
def test_plan_workers(n_images: int, pixels: int, cpus: int, avail: int | None,
                      workers: int | None, expected: int) -> None:
    options = SiftWorkerOptions(workers=workers)
    assert plan_workers(n_images, pixels, cpus, avail, options) == expected


def test_worker_options_reject_bad_values() -> None:
    with pytest.raises(InputError, match=">= 0"):
        SiftWorkerOptions(workers=-1)
    with pytest.raises(InputError, match="memory_share"):
        SiftWorkerOptions(memory_share=0.0)


def test_pool_features_are_bit_identical_and_shared(small_dataset: Any) -> None:
    """Two workers and this process share the images; every image's features are those of
    ``extract_sift`` here, whoever extracted them."""
    paths = _laser_paths(small_dataset)
    options = SiftOptions()
    local = [extract_sift(read_rgb(p), options) for p in paths]
    with SiftPool(paths, options, workers=2) as pool:
        time.sleep(3.0)  # the workers start and take images from the back
        got = [pool.features(p, read_rgb(p)) for p in paths]
        assert pool.workers == 2
        assert pool.images_in_workers >= 1 and pool.seconds_in_workers > 0
    assert all(_same(a, b) for a, b in zip(local, got, strict=True))
    # the workers' pycolmap (glog) lines are kept for run.log: one extractor per image
    made = [ln for ln in pool.glog_lines if "Creating SIFT CPU feature extractor" in ln]
    assert len(made) == pool.images_in_workers


def test_pool_killed_worker_gives_its_image_back(small_dataset: Any,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    """A worker killed while extracting: this process extracts that image, with a warning."""
    paths = _laser_paths(small_dataset)
    options = SiftOptions()
    with SiftPool(paths, options, workers=1) as pool:
        w = pool._workers[0]
        deadline = time.monotonic() + 30
        while w.current is None and time.monotonic() < deadline:
            time.sleep(0.005)
        lost = w.current
        assert lost is not None, "the worker never took an image"
        with caplog.at_level(logging.WARNING, logger="sfm_laserscale.registration.sift_workers"):
            w.proc.kill()
            got = [pool.features(p, read_rgb(p)) for p in paths]
        assert not w.alive
    assert "SIFT worker" in caplog.text and "extracted in this process" in caplog.text
    assert all(_same(extract_sift(read_rgb(p), options), g) for p, g in zip(paths, got,
                                                                           strict=True))


def test_pool_raises_the_workers_error_for_its_image(tmp_path: Path, small_dataset: Any) -> None:
    """An image the worker cannot read: its InputError is raised when that image is asked for."""
    good = _laser_paths(small_dataset)[0]
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not a png at all")
    with SiftPool([good, bad], SiftOptions(), workers=1) as pool:
        deadline = time.monotonic() + 30
        while pool.images_in_workers == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pool.images_in_workers >= 1  # the worker takes the last image first: the bad one
        with pytest.raises(InputError, match="not a readable image"):
            pool.features(bad, None)
        assert _same(pool.features(good, read_rgb(good)), extract_sift(read_rgb(good),
                                                                        SiftOptions()))
    with pytest.raises(ValueError, match="not one of the pool's images"):
        pool.features(tmp_path / "other.png", None)


def test_pool_image_asked_for_twice_is_extracted_again(small_dataset: Any) -> None:
    """A second request for an image returns the same features (extracted here) instead of
    waiting for a worker result that was already handed out."""
    paths = _laser_paths(small_dataset)
    with SiftPool(paths, SiftOptions(), workers=1) as pool:
        last = paths[-1]
        deadline = time.monotonic() + 30
        while pool.images_in_workers == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        first = pool.features(last, read_rgb(last))  # the worker's
        again = pool.features(last, read_rgb(last))  # this process's
    assert _same(first, again)


def test_pool_without_a_startable_worker_extracts_here(small_dataset: Any, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch,
                                                       caplog: pytest.LogCaptureFixture) -> None:
    """No interpreter to start: a warning, no worker, every image extracted here."""
    paths = _laser_paths(small_dataset)[:2]
    monkeypatch.setattr("sys.executable", str(tmp_path / "no-such-python"))
    with (caplog.at_level(logging.WARNING, logger="sfm_laserscale.registration.sift_workers"),
          SiftPool(paths, SiftOptions(), workers=1) as pool):
        got = [pool.features(p, read_rgb(p)) for p in paths]
        assert pool.workers == 0 and pool.images_in_workers == 0
    assert "no SIFT worker process" in caplog.text
    assert all(_same(extract_sift(read_rgb(p), SiftOptions()), g) for p, g in zip(paths, got,
                                                                                   strict=True))


def test_worker_imports_this_package_from_another_folder(small_dataset: Any, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """The worker finds the package the caller imported, whatever the working folder."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("PYTHONPATH", raising=False)
    path = _laser_paths(small_dataset)[-1]
    with SiftPool([path], SiftOptions(), workers=1) as pool:
        deadline = time.monotonic() + 30
        while pool.images_in_workers == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pool.images_in_workers == 1
        assert _same(pool.features(path, None), extract_sift(read_rgb(path), SiftOptions()))


_ORPHAN_SCRIPT = """
import sys, time
from pathlib import Path
from sfm_laserscale.registration.options import SiftOptions
from sfm_laserscale.registration.sift_workers import SiftPool
pool = SiftPool([Path(p) for p in sys.argv[1:]], SiftOptions(), workers=1)
while pool._workers[0].current is None:
    time.sleep(0.005)
print(pool._workers[0].proc.pid, flush=True)
time.sleep(60)
"""


@pytest.mark.skipif(sys.platform != "linux", reason="PR_SET_PDEATHSIG is Linux's")
def test_worker_dies_with_a_killed_run(small_dataset: Any, tmp_path: Path) -> None:
    """SIGKILL of the process that started a worker, mid-image: the worker goes at once, not
    after the image (a 4000 x 3000 image: ~12 s of SIFT)."""
    small = read_rgb(_laser_paths(small_dataset)[0])
    big = np.tile(small, (7, 7, 1))[:3000, :4000]
    paths = []
    for i in range(2):
        paths.append(str(tmp_path / f"big{i}.png"))
        cv2.imwrite(paths[-1], big[:, :, ::-1])
    proc = subprocess.Popen([sys.executable, "-c", _ORPHAN_SCRIPT, *paths],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        worker = int(proc.stdout.readline())
        proc.kill()
        proc.wait()
        deadline = time.monotonic() + 3.0
        while _alive(worker) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not _alive(worker), f"worker {worker} outlived the run"
    finally:
        if proc.poll() is None:
            proc.kill()


def _alive(pid: int) -> bool:
    """The process exists and is not a zombie waiting to be reaped."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _numbers(report: dict[str, Any]) -> dict[str, Any]:
    return {"scale": report["scale"], "methods": report["methods"], "images": report["images"]}


def test_scale_with_and_without_workers_gives_the_same_report(small_dataset: Any,
                                                              tmp_path: Path) -> None:
    """``scale --workers 0`` and ``--workers 2`` (CliRunner): the same numbers; the report
    says how the SIFT time was shared."""
    from sfm_laserscale.commands.demo import scale_inputs_for

    inputs = scale_inputs_for(small_dataset)
    reports = {}
    for n in (0, 2):
        out = tmp_path / f"out{n}"
        args = ["scale", "-q", "--workers", str(n), "--model", str(inputs.model), "--mesh",
                str(inputs.mesh), "--rig", str(inputs.rig), "--database", str(inputs.database),
                "--out", str(out)]
        for p in inputs.laser_images:
            args += ["--laser-images", str(p)]
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 0, res.output
        reports[n] = json.loads((out / "report.json").read_text())
    assert _numbers(reports[0]) == _numbers(reports[2])
    assert "sift_in_workers" not in reports[0]["timings_s"]
    assert reports[2]["timings_s"]["sift_in_workers"] > 0
    assert "worker process(es)" in (tmp_path / "out2" / "run.log").read_text()
    res = CliRunner().invoke(main, ["scale", "--workers", "-1", "--model", "x", "--mesh", "x",
                                    "--rig", "x", "--out", "x", "--laser-images", "x"])
    assert res.exit_code == 2 and "--workers" in res.output


def test_merged_glog_orders_processes_by_time() -> None:
    here = ["I20261125 10:00:00.000001 1 a.cc:1] first", "  continued",
            "W20261125 10:00:02.000000 1 a.cc:2] third"]
    worker = ["I20261125 10:00:01.500000 9 sift.cc:764] second",
              "I20261125 10:00:03.000000 9 sift.cc:764] fourth"]
    assert merged_glog(here, worker) == [here[0], here[1], worker[0], here[2], worker[1]]
    assert glog_lines("Traceback (most recent call last):\n" + worker[0] + "\nboom\n") == [
        worker[0]]


def test_model_images_reextracted_with_workers_are_the_same(
        small_dataset: Any, caplog: pytest.LogCaptureFixture) -> None:
    """``--images`` (no database): the model images' SIFT shared with two workers ties the
    same keypoints to the same observations as extracting it all here."""
    from sfm_laserscale.io.models import load_model
    from sfm_laserscale.registration.features import load_model_features
    from sfm_laserscale.registration.options import TieOptions

    model = load_model(small_dataset.model_dir)
    args = (model, small_dataset.model_dir, None, small_dataset.images_dir, None, TieOptions())
    here = load_model_features(*args)
    with caplog.at_level(logging.INFO, logger="sfm_laserscale.registration.sift_workers"):
        shared = load_model_features(*args, SiftWorkerOptions(workers=2))
    assert f"SIFT of {len(here)} model images shared with 2 worker" in caplog.text
    assert list(shared) == list(here)
    for name, feats in here.items():
        other = shared[name]
        assert isinstance(feats, ObservationFeatures) and isinstance(other, ObservationFeatures)
        np.testing.assert_array_equal(other.observation_idx, feats.observation_idx)
        np.testing.assert_array_equal(other.descriptors, feats.descriptors)


def test_model_image_of_the_wrong_size_is_named_before_any_extraction(
        small_dataset: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import sfm_laserscale.registration.features as features
    import sfm_laserscale.registration.ties as ties
    from sfm_laserscale.io.models import load_model
    from sfm_laserscale.registration.options import TieOptions

    images = tmp_path / "images"
    shutil.copytree(small_dataset.images_dir, images)
    model = load_model(small_dataset.model_dir)
    victim = images / sorted(im.name for im in model.images.values())[-1]
    full = cv2.imread(str(victim))
    cv2.imwrite(str(victim), cv2.resize(full, (full.shape[1] // 2, full.shape[0] // 2)))

    def forbidden(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("nothing is extracted before every size is checked")

    monkeypatch.setattr(features, "start_pool", forbidden)
    monkeypatch.setattr(ties, "extract_sift", forbidden)
    with pytest.raises(InputError, match=r"image is 320×240 px but its camera is 640×480"):
        features.load_model_features(model, small_dataset.model_dir, None, images, None,
                                     TieOptions(), SiftWorkerOptions(workers=1))
