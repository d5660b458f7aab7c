"""How runs end (issue #20): SIGTERM/SIGINT stop a real CLI run cleanly (exit 143/130, staging
folder removed, nothing half-written), a run killed with SIGKILL leaves a staging folder that
the next run removes by the staging lock's logic (also when the killed run was pid 1 of its
PID namespace, as in a container), and process-pool workers die with their run.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sfm_laserscale.io.outputs import check_output_dir, clean_stale_staging, staged_output_dir
from sfm_laserscale.io.run_lock import claim_if_abandoned, create_lock
from sfm_laserscale.lifecycle import Interrupted, process_pool, signals_as_exceptions

REPO = Path(__file__).resolve().parents[1]

#: ``apply`` through the real CLI, its mesh writer replaced by one that writes half a file
#: into the staging folder, says READY with the staging folder's path, and waits.
_BLOCKING_RUN = r"""
import os, sys, time
from pathlib import Path
import sfm_laserscale.commands.apply as apply_cmd
from sfm_laserscale.cli import main

def half_written(src, dst_dir, scale, **kw):
    (Path(dst_dir) / "mesh.ply").write_bytes(b"ply\n" + b"x" * 1000)  # half a mesh
    print("READY", os.getpid(), Path(dst_dir).parent, flush=True)
    time.sleep(120)

apply_cmd.write_scaled_mesh = half_written
main(["apply", "--scale", "2", "--mesh", sys.argv[1], "--out", sys.argv[2], *sys.argv[3:]])
"""


def _start_blocking_run(tmp_path: Path, out: Path, prefix: tuple[str, ...] = (),
                        extra: tuple[str, ...] = ()) -> subprocess.Popen[str]:
    mesh = tmp_path / "in.ply"
    mesh.write_bytes(b"not read: the writer is replaced")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen([*prefix, sys.executable, "-c", _BLOCKING_RUN, str(mesh), str(out),
                             *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _wait_ready(proc: subprocess.Popen[str]) -> str:
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.startswith("READY"), (line, proc.stderr.read() if proc.stderr else "")
    return line


def _staging(out: Path) -> list[Path]:
    return sorted(p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}."))


@pytest.mark.parametrize(("signum", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_stops_a_cli_run_cleanly(tmp_path: Path, signum: int, status: int) -> None:
    out = tmp_path / "out"
    proc = _start_blocking_run(tmp_path, out)
    _wait_ready(proc)
    assert any(p.name.startswith(".out.partial-") for p in _staging(out))  # mid-write
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == status, err
    assert signal.Signals(signum).name in err and "no output written" in err
    assert "Traceback" not in err
    assert not out.exists() and _staging(out) == []  # nothing half-written, no lock left


def test_signal_keeps_the_previous_output(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.json").write_text("previous")
    proc = _start_blocking_run(tmp_path, out, extra=("--overwrite",))
    _wait_ready(proc)
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=30)
    assert proc.returncode == 143
    assert (out / "report.json").read_text() == "previous" and _staging(out) == []


def _sigkilled_leftovers(tmp_path: Path, prefix: tuple[str, ...]) -> tuple[Path, list[Path]]:
    out = tmp_path / "out"
    proc = _start_blocking_run(tmp_path, out, prefix)
    _wait_ready(proc)
    # the run itself (not unshare): the child of `proc` when it runs in a namespace
    target = proc.pid if not prefix else _only_child(proc.pid)
    os.kill(target, signal.SIGKILL)
    proc.wait(timeout=30)
    left = _staging(out)
    assert {p.name.split("-")[0] for p in left} == {".out.partial", ".out.lock"}, left
    return out, left


def _only_child(pid: int) -> int:
    children: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        children += [int(c) for c in (task / "children").read_text().split()]
    assert len(children) == 1, children
    return children[0]


def test_sigkilled_run_leaves_a_folder_the_next_run_removes(tmp_path: Path) -> None:
    out, left = _sigkilled_leftovers(tmp_path, ())
    assert not out.exists()
    removed = clean_stale_staging(out)  # what the next run does first
    assert [p.name for p in removed] == [p.name for p in left if ".partial-" in p.name]
    assert _staging(out) == []


def _pid_namespaces_available() -> bool:
    unshare = shutil.which("unshare")
    if unshare is None:
        return False
    probe = subprocess.run([unshare, "--pid", "--fork", sys.executable, "-c",
                            "import os; print(os.getpid())"], capture_output=True, text=True)
    return probe.returncode == 0 and probe.stdout.strip() == "1"


@pytest.mark.skipif(not _pid_namespaces_available(),
                    reason="no PID namespaces here (unshare --pid needs root or user namespaces)")
def test_sigkilled_pid1_run_is_cleaned_without_pids(tmp_path: Path) -> None:
    """The container case: the killed run was pid 1 of its PID namespace and so is this test's
    parent's init; a pid check ("is pid 1 alive?") would keep its folder forever."""
    out, left = _sigkilled_leftovers(tmp_path, ("unshare", "--pid", "--fork"))
    partial = [p for p in left if ".partial-" in p.name]
    assert partial[0].name.startswith(".out.partial-1-")  # named after pid 1
    os.kill(1, 0)  # pid 1 is alive here too: only the lock can tell the run is gone
    check_output_dir(out, overwrite=False)  # the next run on the same --out
    assert _staging(out) == []


@pytest.mark.skipif(not _pid_namespaces_available(),
                    reason="no PID namespaces here (unshare --pid needs root or user namespaces)")
def test_sigterm_reaches_the_run_as_pid1(tmp_path: Path) -> None:
    """As pid 1 (a container without tini or --init) a process gets no default signal action;
    the run's own handler still stops it cleanly."""
    out = tmp_path / "out"
    proc = _start_blocking_run(tmp_path, out, ("unshare", "--pid", "--fork"))
    _wait_ready(proc)
    os.kill(_only_child(proc.pid), signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 143, err
    assert not out.exists() and _staging(out) == []


def test_live_runs_folder_is_kept(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with staged_output_dir(out, overwrite=False) as tmp:
        (tmp / "a.txt").write_text("x")
        assert clean_stale_staging(out) == []  # our own lock is held
        assert tmp.is_dir()
    assert (out / "a.txt").read_text() == "x" and _staging(out) == []


def test_lock_claimed_only_after_its_owner_is_gone(tmp_path: Path) -> None:
    token, lock = create_lock(tmp_path, ".x.lock-")
    assert lock.path.name == f".x.lock-{token}" and lock.held
    # another open file description cannot take it while we hold it
    assert claim_if_abandoned(lock.path) is None
    lock.release(unlink=False)  # as when the process dies: the file stays, the lock goes
    claimed = claim_if_abandoned(lock.path)
    assert claimed is not None and claimed.held
    claimed.release()
    assert not lock.path.exists()
    missing = claim_if_abandoned(tmp_path / ".x.lock-gone")
    assert missing is not None and not missing.held  # no file: nobody owns it


def test_signals_as_exceptions_raises_and_restores() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted) as info, signals_as_exceptions():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler runs first
    assert info.value.exit_status == 143 and info.value.signal_name == "SIGTERM"
    assert signal.getsignal(signal.SIGTERM) is before


# ---------------------------------------------------------------------------- workers

def _sleep_task(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


def _wait_gone(pids: list[int], timeout: float = 20.0) -> list[int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and any(_alive(p) for p in pids):
        time.sleep(0.1)
    return [p for p in pids if _alive(p)]


def test_pool_workers_killed_when_the_run_is_interrupted() -> None:
    """An exception (here a signal's) ends the block: queued tasks are cancelled and the busy
    workers killed, not waited for."""
    t0 = time.monotonic()
    with pytest.raises(Interrupted), signals_as_exceptions(), process_pool(2) as pool:
        pids = list(pool.map(_sleep_task, [0.0] * 4))
        futures = [pool.submit(_sleep_task, 60.0) for _ in range(6)]
        time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)
    assert time.monotonic() - t0 < 30
    assert _wait_gone(sorted(set(pids))) == []
    # the executor's manager thread fails the killed workers' futures (BrokenProcessPool) a
    # moment after they die: every future ends, cancelled or failed, without waiting for a task
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and not all(f.cancelled() or f.done() for f in futures):
        time.sleep(0.05)
    assert all(f.cancelled() or f.done() for f in futures)
    assert all(f.cancelled() or f.exception() is not None for f in futures)


_POOL_PARENT = r"""
import os, sys, time
from sfm_laserscale.lifecycle import process_pool

def task(seconds):
    time.sleep(seconds)
    return os.getpid()

if __name__ == "__main__":
    with process_pool(2) as pool:
        pids = sorted(set(pool.map(task, [0.3] * 4)))
        futures = [pool.submit(task, 120.0) for _ in range(2)]
        print("PIDS", *pids, flush=True)
        time.sleep(120)
"""


def test_pool_workers_die_with_a_sigkilled_parent(tmp_path: Path) -> None:
    """SIGKILL gives the parent no chance to clean up: the kernel ends the workers
    (PR_SET_PDEATHSIG)."""
    script = tmp_path / "parent.py"
    script.write_text(_POOL_PARENT)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.startswith("PIDS"), line
    pids = [int(p) for p in line.split()[1:]]
    assert pids and all(_alive(p) for p in pids)
    proc.kill()
    proc.wait(timeout=30)
    assert _wait_gone(pids) == []


def _children(pid: int) -> list[int]:
    found: list[int] = []
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            found += [int(c) for c in (task / "children").read_text().split()]
    except (FileNotFoundError, ProcessLookupError):
        pass
    return found


def _small_seafloor(path: Path, n: int = 40) -> Path:
    """A gently waved 40 × 40 m floor (metric, facing +z) as a PLY file."""
    import open3d as o3d

    u, v = np.meshgrid(np.linspace(-20, 20, n), np.linspace(-20, 20, n))
    verts = np.column_stack([u.ravel(), v.ravel(), (0.2 * np.sin(u / 3) * np.cos(v / 4)).ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(),
                  idx[1:, :-1].ravel())
    tris = np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts),
                                     o3d.utility.Vector3iVector(tris))
    assert o3d.io.write_triangle_mesh(str(path), mesh)
    return path


def test_simulate_stopped_by_sigterm_leaves_no_worker(tmp_path: Path) -> None:
    """The issue's case: `simulate` with two workers, ended with SIGTERM, left them running at
    full CPU. Now it exits 143 and its workers are gone."""
    out = tmp_path / "sim"
    mesh = _small_seafloor(tmp_path / "floor.ply")  # the demo's seafloor takes 20 s to build
    proc = subprocess.Popen(
        [sys.executable, "-m", "sfm_laserscale.cli", "simulate", "--out", str(out), "--mode",
         "random", "--trials", "5000", "--config", "A", "--distance", "2", "--workers", "2",
         "--mesh", str(mesh), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, env=dict(os.environ, PYTHONPATH=str(REPO)))
    deadline = time.monotonic() + 120
    workers: list[int] = []
    while time.monotonic() < deadline and proc.poll() is None:
        workers = _children(proc.pid)
        if len(workers) >= 2 and all(_alive(w) for w in workers):
            time.sleep(1.0)  # the workers are busy with trials
            break
        time.sleep(0.2)
    assert proc.poll() is None and len(workers) >= 2, proc.stderr.read() if proc.stderr else ""
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert _wait_gone(workers) == []
    assert not out.exists() and _staging(out) == []
