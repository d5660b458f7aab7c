"""``batch`` ends like every run (issue #20): SIGTERM stops it with exit 143 and its local Dask
cluster's processes (nannies and workers) are gone; after SIGKILL, which gives the batch no
chance to close its cluster, they end too (each Dask process watches its parent)."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from tests.test_batch import cruise  # noqa: F401 - the module-scoped fixture

REPO = Path(__file__).resolve().parents[1]


def _long_manifest(root: Path, copies: int = 12) -> Path:
    """The cruise's 'roof_small' row repeated: a batch that runs long enough to be stopped."""
    with (root / "small.csv").open(newline="") as fh:
        header, row = list(csv.reader(fh))
    path = root / "long.csv"
    with path.open("w", newline="") as fh:
        csv.writer(fh).writerows([header, *([f"m{i}", *row[1:]] for i in range(copies))])
    return path


def _start_batch(manifest: Path, out: Path) -> tuple[subprocess.Popen[str], list[psutil.Process]]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "sfm_laserscale.cli", "batch", str(manifest), "--out", str(out),
         "--jobs", "2", "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=dict(os.environ, PYTHONPATH=str(REPO)))
    deadline = time.monotonic() + 120
    family: list[psutil.Process] = []
    while time.monotonic() < deadline and proc.poll() is None:
        family = psutil.Process(proc.pid).children(recursive=True)
        if len(family) >= 2:  # the cluster is up: let its workers take jobs
            time.sleep(3.0)
            family = psutil.Process(proc.pid).children(recursive=True)
            break
        time.sleep(0.2)
    assert proc.poll() is None and len(family) >= 2, proc.stderr.read() if proc.stderr else ""
    return proc, family


def _gone(family: list[psutil.Process], timeout: float = 30.0) -> list[int]:
    _, alive = psutil.wait_procs(family, timeout=timeout)
    return [p.pid for p in alive]


def test_batch_stopped_by_sigterm_leaves_no_dask_process(cruise: Path,  # noqa: F811
                                                         tmp_path: Path) -> None:
    proc, family = _start_batch(_long_manifest(cruise), tmp_path / "out")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=90)
    assert proc.returncode == 143, err
    assert _gone(family) == []


def test_sigkilled_batch_leaves_no_dask_process(cruise: Path, tmp_path: Path) -> None:  # noqa: F811
    proc, family = _start_batch(_long_manifest(cruise), tmp_path / "out")
    proc.kill()
    proc.wait(timeout=30)
    left = _gone(family, timeout=60)
    for pid in left:  # do not leave them to the rest of the suite
        with pytest.raises(psutil.NoSuchProcess):
            psutil.Process(pid).kill()
    assert left == []
