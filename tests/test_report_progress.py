"""Running it: progress bars (on a terminal only, off with --quiet), the mesh writers' progress,
and pycolmap's own (glog) messages captured for run.log."""

from __future__ import annotations

import fcntl
import io
import os
import pty
import re
import select
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import plyfile
import pycolmap
import pytest

from sfm_laserscale.io.meshes.mesh import write_scaled_mesh
from sfm_laserscale.provenance import (
    captured_colmap_log,
    progress_bar,
    progress_enabled,
    run_log_text,
)

REPO = Path(__file__).resolve().parents[1]


class FakeTerminal(io.StringIO):
    """A stderr that says it is a terminal (what a user's shell gives)."""

    def isatty(self) -> bool:
        return True


def _tqdm_text(raw: str) -> str:
    """tqdm's carriage-return redraws as lines."""
    return raw.replace("\r", "\n")


# --------------------------------------------------------------------------- progress rule


def test_progress_only_on_a_terminal_and_not_quiet(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert not progress_enabled(True)  # redirected to a file or pipe
    term = FakeTerminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert progress_enabled(True)
    assert not progress_enabled(False)  # --quiet
    bar = progress_bar(False, "x", total=3)
    bar.update(3)
    bar.close()
    assert term.getvalue() == ""
    with progress_bar(True, "shown", total=3) as bar:
        bar.update(3)
    assert "shown:" in term.getvalue()


# --------------------------------------------------------------------------- mesh writers


def _ply(path: Path, n: int, text: bool) -> None:
    rng = np.random.default_rng(0)
    v = np.zeros(n, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1")])
    for a in "xyz":
        v[a] = rng.normal(size=n)
    f = np.zeros(n - 2, dtype=[("vertex_indices", "i4", (3,))])
    f["vertex_indices"] = np.stack([np.zeros(n - 2), np.arange(1, n - 1), np.arange(2, n)], 1)
    els = [plyfile.PlyElement.describe(v, "vertex"), plyfile.PlyElement.describe(f, "face")]
    plyfile.PlyData(els, text=text).write(str(path))


@pytest.mark.parametrize("kind", ["ply-binary", "ply-ascii", "obj", "off"])
def test_mesh_writer_progress_adds_up_to_the_file(tmp_path: Path, kind: str) -> None:
    """The callbacks of one write sum to the source's size (a bar with total = size ends full)."""
    src = tmp_path / "in" / ("mesh." + kind.split("-")[0])
    src.parent.mkdir()
    if kind.startswith("ply"):
        _ply(src, 20000 if kind == "ply-binary" else 2000, text=kind == "ply-ascii")
    elif kind == "obj":
        src.write_text("".join(f"v {i} {i * 0.5} 1.0\n" for i in range(5000)) + "f 1 2 3\n")
    else:
        src.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    calls: list[int] = []
    write_scaled_mesh(src, tmp_path / "out", 2.0, progress=calls.append)
    assert sum(calls) == src.stat().st_size
    assert all(c >= 0 for c in calls)
    if kind == "ply-binary":
        assert len(calls) >= 3  # header, vertex rows, the rest: reported as it streams


def test_forced_on_bar_reports_the_mesh_writing(
    small_dataset: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The writer's scaled-mesh bar, on a (fake) terminal, counts the mesh to 100 %."""
    import sfm_laserscale.report.writer as writer
    from sfm_laserscale.commands.demo import scale_inputs_for
    from sfm_laserscale.report.writer import _write_scaled

    bars: list[Any] = []

    def keep(*args: Any, **kw: Any) -> Any:
        bars.append(progress_bar(*args, **kw))
        return bars[-1]

    monkeypatch.setattr(writer, "progress_bar", keep)
    term = FakeTerminal()
    monkeypatch.setattr(sys, "stderr", term)
    inputs = scale_inputs_for(small_dataset)
    loaded = SimpleNamespace(model=SimpleNamespace(source_format="colmap-binary"))
    _write_scaled(tmp_path, inputs, loaded, 0.5, True)  # type: ignore[arg-type]
    size = inputs.mesh.stat().st_size
    (bar,) = bars
    assert bar.total == size and bar.n == size  # counted to the end (closed bars say disable)
    assert re.search(r"^scaled mesh: +0%\|", _tqdm_text(term.getvalue()), re.M), term.getvalue()
    assert (tmp_path / "scaled" / inputs.mesh.name).stat().st_size == size
    # --quiet: nothing
    quiet = FakeTerminal()
    monkeypatch.setattr(sys, "stderr", quiet)
    (tmp_path / "q").mkdir()
    _write_scaled(tmp_path / "q", inputs, loaded, 0.5, False)  # type: ignore[arg-type]
    assert quiet.getvalue() == ""


def _run_in_terminal(args: list[str], timeout: float = 240.0) -> tuple[int, str]:
    """Run ``python ARGS`` with stdin/stdout/stderr on a pseudo-terminal; (exit status, output)."""
    main, child = pty.openpty()
    # a fresh pseudo-terminal is 0 columns wide (tqdm then draws nothing): give it a size
    fcntl.ioctl(child, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    env = dict(os.environ, COLUMNS="120", TERM="xterm")
    proc = subprocess.Popen(
        [sys.executable, *args],
        stdin=child,
        stdout=child,
        stderr=child,
        cwd=REPO,
        env=env,
        close_fds=True,
    )
    os.close(child)
    out = bytearray()
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        ready, _, _ = select.select([main], [], [], 0.5)
        if ready:
            try:
                chunk = os.read(main, 65536)
            except OSError:  # the child closed the terminal
                break
            if not chunk:
                break
            out += chunk
        elif proc.poll() is not None:
            break
    os.close(main)
    code = proc.wait(timeout=30)
    return code, out.decode("utf-8", "replace")


def test_pipeline_bar_on_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    """The per-laser-image bar (detection, SIFT, matching, registration) draws on a terminal."""
    def _progress(items: list[int], enabled: bool, desc: str) -> Any:
        return progress_bar(enabled, desc, iterable=items, unit="img")  # as scale.run does

    term = FakeTerminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert list(_progress([1, 2, 3], True, "laser images")) == [1, 2, 3]
    assert re.search(r"^laser images: +0%\|", _tqdm_text(term.getvalue()), re.M)
    quiet = FakeTerminal()
    monkeypatch.setattr(sys, "stderr", quiet)
    assert list(_progress([1, 2, 3], False, "laser images")) == [1, 2, 3]
    assert quiet.getvalue() == ""


def test_quiet_in_a_terminal_shows_no_progress(small_dataset: Any, tmp_path: Path) -> None:
    """On a real (pseudo-)terminal, where a bar does show, ``scale --quiet`` prints only its
    summary line."""
    code, out = _run_in_terminal(
        ["-c", "import tqdm, time\nfor _ in tqdm.tqdm(range(2)): time.sleep(0.15)"]
    )
    assert code == 0 and "%|" in out  # the terminal shows bars
    one = sorted(small_dataset.laser_images_dir.glob("*.png"))[0]
    base = [
        "-m",
        "sfm_laserscale.cli",
        "scale",
        "--model",
        str(small_dataset.model_dir),
        "--mesh",
        str(small_dataset.mesh_path),
        "--laser-images",
        str(one),
        "--rig",
        str(small_dataset.rig_path),
        "--database",
        str(small_dataset.database_path),
    ]
    code, out = _run_in_terminal([*base, "--out", str(tmp_path / "quiet"), "--quiet"])
    assert code == 0, out
    assert "%|" not in out and "it/s" not in out and "img/s" not in out, out
    assert out.strip().startswith("scale = ")  # only the summary line


# --------------------------------------------------------------------------- pycolmap's log


def _glog_flags() -> dict[str, Any]:
    lg = pycolmap.logging
    return {
        k: getattr(lg, k)
        for k in ("logtostderr", "alsologtostderr", "minloglevel", "stderrthreshold")
    }


@pytest.mark.parametrize("verbose", [False, True])
def test_colmap_log_captured_and_terminal_unchanged(
    verbose: bool, capfd: pytest.CaptureFixture[str]
) -> None:
    """Every glog level is captured (flushed before the block ends, files removed after); the
    terminal shows what the CLI's --verbose setting shows, and the settings come back."""
    from sfm_laserscale.registration.pose import configure_colmap_logging

    before = _glog_flags()
    try:
        configure_colmap_logging(verbose)
        configured = _glog_flags()
        capfd.readouterr()
        with captured_colmap_log() as log:
            pycolmap.logging.info("laserscale-test info")
            pycolmap.logging.warning("laserscale-test warning")
            mid = log.lines()  # flushed while the run goes on (run.log is written inside)
            pycolmap.logging.info("laserscale-test late")
            folder = log.folder
            assert folder.is_dir()
        assert not folder.exists()
        assert _glog_flags() == configured
        err = capfd.readouterr().err
    finally:
        for key, value in before.items():
            setattr(pycolmap.logging, key, value)
    assert [m.split("] ", 1)[1] for m in mid] == ["laserscale-test info", "laserscale-test warning"]
    assert [m[0] for m in mid] == ["I", "W"]
    assert log.stop()[-1].endswith("] laserscale-test late")
    assert ("laserscale-test info" in err) is verbose
    text = run_log_text(["a record"], log.stop())
    assert text.splitlines()[0] == "a record"
    assert text.splitlines()[1].startswith("---- pycolmap's own log (glog, 3 lines")
    assert text.splitlines()[2].startswith("pycolmap: I")


def test_run_log_without_pycolmap_lines() -> None:
    assert run_log_text(["x", "y"], []) == "x\ny\n"


def test_stale_glog_folders_of_dead_runs_are_removed(tmp_path: Path) -> None:
    """A killed run leaves its temporary glog folder; the next run removes it: a folder whose
    lock (``<folder>.lock``) can be taken or is missing (no pid compared: pid 1 in a container
    is always alive)."""
    from sfm_laserscale.io.run_lock import create_lock
    from sfm_laserscale.provenance import _GLOG_DIR_PREFIX, _remove_stale_glog_dirs

    token, dead_lock = create_lock(tmp_path, _GLOG_DIR_PREFIX, ".lock")
    dead_lock.release(unlink=False)  # its process died: the file stays, the lock is gone
    live_token, live_lock = create_lock(tmp_path, _GLOG_DIR_PREFIX, ".lock")
    names = {
        "dead": f"{_GLOG_DIR_PREFIX}{token}",
        "old version": f"{_GLOG_DIR_PREFIX}1_x1",  # no lock file: an older version's, or gone
        "live": f"{_GLOG_DIR_PREFIX}{live_token}",
        "other": "unrelated_123_x4",
    }
    for name in names.values():
        (tmp_path / name).mkdir()
        (tmp_path / name / "pycolmap-1.log").write_text("I... msg\n")
    _remove_stale_glog_dirs(tmp_path)
    left = sorted(p.name for p in tmp_path.iterdir() if p.is_dir())
    assert left == sorted(names[k] for k in ("live", "other"))
    assert live_lock.path.exists() and not dead_lock.path.exists()
    live_lock.release()
