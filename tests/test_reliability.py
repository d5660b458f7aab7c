"""Nothing lost, nothing corrupted (issue #7): runs killed with SIGKILL leave no ``--out`` or a
complete one, stale staging folders are cleaned, inputs are never modified, and the same
inputs and seed give the same report numbers.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from sfm_laserscale.cli import main
from sfm_laserscale.io import outputs
from sfm_laserscale.io.colmap import read_colmap_model
from sfm_laserscale.io.meshes.mesh import load_mesh
from sfm_laserscale.io.outputs import check_output_dir, clean_stale_staging, staged_output_dir

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO.parent / "shared" / "fixtures"
RUN_TIMEOUT_S = 120.0

#: The outputs of ``scale`` (docs/OUTPUTS.md) on the synthetic data set (COLMAP binary model,
#: PLY mesh).
SCALE_OUTPUTS = ("report.json", "report.html", "estimates.csv", "spots.csv", "transform.sim3",
                 "transform_4x4.txt", "run.log", "scaled/model/cameras.bin",
                 "scaled/model/images.bin", "scaled/model/points3D.bin", "scaled/mesh.ply")


# ---------------------------------------------------------------------------- helpers

def tree_digest(*roots: Path) -> dict[str, tuple[str, int]]:
    """Relative path -> (sha256, mtime_ns) of every file under the roots (files or folders)."""
    out: dict[str, tuple[str, int]] = {}
    for root in roots:
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        for f in files:
            out[str(f)] = (hashlib.sha256(f.read_bytes()).hexdigest(), f.stat().st_mtime_ns)
    return out


def assert_complete_scale_output(out: Path, image_names: list[str], mesh_vertices: int) -> None:
    """Every output (docs/OUTPUTS.md) is there and readable: a complete, uncorrupted ``--out``."""
    missing = [rel for rel in SCALE_OUTPUTS if not (out / rel).is_file()]
    assert not missing, f"{out} lacks {missing}"
    report = json.loads((out / "report.json").read_text())
    s = report["scale"]
    assert np.isfinite(s["value"]) and s["value"] > 0
    assert s["inverse"] == pytest.approx(1 / s["value"])
    assert [im["name"] for im in report["images"]] == image_names
    assert sorted(p.name for p in (out / "overlays").glob("*.jpg")) == sorted(
        Path(n).stem + ".jpg" for n in image_names)
    sim3 = [float(v) for v in (out / "transform.sim3").read_text().split()]
    assert sim3[0] == pytest.approx(s["value"])
    assert len(read_colmap_model(out / "scaled" / "model").images) > 0
    assert len(load_mesh(out / "scaled" / "mesh.ply").vertices) == mesh_vertices
    assert "</html>" in (out / "report.html").read_text()


def report_numbers(report: dict[str, Any]) -> dict[str, Any]:
    """report.json without what may differ between two identical runs (timings, provenance
    command line / environment)."""
    return {k: v for k, v in report.items() if k not in ("timings_s", "provenance")}


def leftovers(out: Path) -> list[Path]:
    """Staging or set-aside folders beside ``out``."""
    return sorted(out.parent.glob(f".{out.name}.partial-*")) + sorted(
        out.parent.glob(f".{out.name}.old-*"))


def dead_pid() -> int:
    """The id of a process that has exited (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


# ---------------------------------------------------------------------------- atomic move

def _write_tree(folder: Path, tag: str) -> None:
    (folder / "sub").mkdir(parents=True, exist_ok=True)
    (folder / "report.json").write_text(json.dumps({"tag": tag}))
    (folder / "sub" / "data.bin").write_bytes(tag.encode() * 1000)


def _tag(folder: Path) -> str:
    return str(json.loads((folder / "report.json").read_text())["tag"])


def test_rename_exchange_supported_here(tmp_path: Path) -> None:
    """The atomic swap works on this file system (else the two-rename fallback is used)."""
    a, b = tmp_path / "a", tmp_path / "b"
    _write_tree(a, "A")
    _write_tree(b, "B")
    assert outputs._exchange(a, b)
    assert _tag(a) == "B" and _tag(b) == "A"


@pytest.mark.parametrize("exchange", [True, False], ids=["exchange", "two-renames"])
def test_overwrite_keeps_old_until_new_complete(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                exchange: bool) -> None:
    if not exchange:
        monkeypatch.setattr(outputs, "_exchange", lambda a, b: False)
    out = tmp_path / "out"
    _write_tree(out, "old")
    with staged_output_dir(out, overwrite=True) as tmp:
        assert tmp.parent == out.parent and tmp.name.startswith(f".out.partial-{os.getpid()}-")
        _write_tree(tmp, "new")
        assert _tag(out) == "old"  # untouched while the new one is written
    assert _tag(out) == "new" and (out / "sub" / "data.bin").read_bytes() == b"new" * 1000
    assert leftovers(out) == []


def test_failed_run_keeps_old_output_and_leaves_nothing(tmp_path: Path) -> None:
    out = tmp_path / "out"
    _write_tree(out, "old")
    with pytest.raises(RuntimeError), staged_output_dir(out, overwrite=True) as tmp:
        _write_tree(tmp, "half")
        raise RuntimeError("stage failed")
    assert _tag(out) == "old" and leftovers(out) == []


def test_out_filled_during_run_is_not_swapped_away(tmp_path: Path) -> None:
    """No --overwrite: a folder that became non-empty meanwhile is refused at the end too."""
    from sfm_laserscale.errors import InputError

    out = tmp_path / "out"
    with pytest.raises(InputError, match="not empty"), staged_output_dir(out, False) as tmp:
        _write_tree(tmp, "new")
        _write_tree(out, "someone else's")
    assert _tag(out) == "someone else's" and leftovers(out) == []


def test_stale_folders_of_dead_runs_are_removed(tmp_path: Path) -> None:
    """Whose a folder is, the staging lock tells (no process ids): a folder whose lock can be
    taken, or that has no lock file (an older version's), is a dead run's."""
    from sfm_laserscale.io.run_lock import create_lock

    out = tmp_path / "out"
    _write_tree(out, "current")
    token, abandoned = create_lock(tmp_path, ".out.lock-")
    abandoned.release(unlink=False)  # its owner died: the file stays, the lock is gone
    stale = [tmp_path / f".out.partial-{token}", tmp_path / f".out.old-{token}",
             tmp_path / f".out.partial-{dead_pid()}-abc"]  # no lock file at all
    live_token, live_lock = create_lock(tmp_path, ".out.lock-")  # a live run's
    live = tmp_path / f".out.partial-{live_token}"
    other = tmp_path / ".outer.partial-1-abc"  # another --out's folder
    for d in [*stale, live, other]:
        _write_tree(d, "x")
    removed = clean_stale_staging(out)
    assert sorted(removed) == sorted(stale)
    assert not (tmp_path / f".out.lock-{token}").exists()
    assert live.is_dir() and live_lock.path.exists() and other.is_dir()
    assert _tag(out) == "current"
    live_lock.release()


def test_old_output_restored_when_a_run_died_between_renames(tmp_path: Path) -> None:
    out = tmp_path / "out"
    old = tmp_path / f".out.old-{dead_pid()}"
    _write_tree(old, "old")
    check_output_dir(out, overwrite=True)
    assert _tag(out) == "old" and leftovers(out) == []


_KILL_IN_MOVE = r"""
import os, signal, sys
from pathlib import Path
from sfm_laserscale.io import outputs
out, mode = Path(sys.argv[1]), sys.argv[2]
def die(*a, **k):
    os.kill(os.getpid(), signal.SIGKILL)
if mode == "two-renames":
    outputs._exchange = lambda a, b: False
    real = os.replace
    def replace(a, b):
        real(a, b)
        die()
    outputs.os.replace = replace  # killed right after moving the old output aside
else:
    outputs.shutil.rmtree = die  # killed right after the swap, before removing the old one
with outputs.staged_output_dir(out, True) as tmp:
    (tmp / "report.json").write_text('{"tag": "new"}')
"""


@pytest.mark.parametrize("mode", ["exchange", "two-renames"])
def test_kill_inside_the_final_move(tmp_path: Path, mode: str) -> None:
    """SIGKILL at the worst instant of the move: a complete output survives, and the next run
    tidies up (restores the old one if the new one was not in place)."""
    out = tmp_path / "out"
    _write_tree(out, "old")
    proc = subprocess.run([sys.executable, "-c", _KILL_IN_MOVE, str(out), mode],
                          timeout=60, capture_output=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    if mode == "exchange":
        assert _tag(out) == "new"
        assert len(leftovers(out)) == 1  # the old output, in the dead run's staging folder
    else:
        assert not out.exists()  # the documented window of the fallback: old one set aside
        left = {p.name.split("-")[0]: p for p in leftovers(out)}
        assert sorted(left) == [".out.old", ".out.partial"]  # + the new one, not yet moved
        assert _tag(left[".out.old"]) == "old"
    check_output_dir(out, overwrite=True)
    assert _tag(out) == ("new" if mode == "exchange" else "old")
    assert leftovers(out) == []


# ---------------------------------------------------------------------------- killed scale runs

@dataclass
class KillCampaign:
    """Subprocess ``scale`` runs on one --out: a good one, killed ones, a final good one."""

    out: Path
    image_names: list[str]
    mesh_vertices: int
    inputs_before: dict[str, tuple[str, int]]
    inputs_after: dict[str, tuple[str, int]] = field(default_factory=dict)
    first_report: dict[str, Any] = field(default_factory=dict)
    last_report: dict[str, Any] = field(default_factory=dict)
    kills: list[dict[str, Any]] = field(default_factory=list)
    fresh_kill: dict[str, Any] = field(default_factory=dict)
    leftovers_before_final: list[Path] = field(default_factory=list)
    leftovers_after_final: list[Path] = field(default_factory=list)


#: kill when a log line holding this appears (spread over load, register and write), or
#: after a seeded random delay (seconds).
KILL_TRIGGERS: tuple[str | float, ...] = (
    "registration:", "wrote model rescaled", "run finished")
N_RANDOM_KILLS = 1


def _scale_cmd(ds: Any, laser: Path, spots: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "sfm_laserscale.cli", "scale", "--model", str(ds.model_dir),
            "--mesh", str(ds.mesh_path), "--rig", str(ds.rig_path), "--database",
            str(ds.database_path), "--spots", str(spots), "--seed", "3", "--out", str(out),
            "--overwrite", "-v", "--laser-images", str(laser)]


def _run_and_kill(cmd: list[str], trigger: str | float) -> dict[str, Any]:
    """Start ``cmd``; SIGKILL it at the trigger. Returns what happened."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                            cwd=REPO)
    assert proc.stderr is not None
    killed = False
    try:
        if isinstance(trigger, float):
            try:
                proc.communicate(timeout=trigger)
            except subprocess.TimeoutExpired:
                proc.kill()
                killed = True
        else:
            for raw in proc.stderr:
                if trigger in raw.decode("utf-8", "replace"):
                    proc.kill()
                    killed = True
                    break
                if time.monotonic() - t0 > RUN_TIMEOUT_S:
                    break
        proc.wait(timeout=RUN_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    return {"trigger": trigger, "killed": killed, "returncode": proc.returncode,
            "seconds": round(time.monotonic() - t0, 2)}


def _spots_of(ds: Any, laser: Path, folder: Path) -> Path:
    """The true spots of one laser image as a --spots CSV (an input like the others)."""
    rows = ds.spots_path.read_text().splitlines()
    spots = folder / "spots.csv"
    spots.write_text("\n".join([rows[0]] + [r for r in rows[1:] if r.startswith(laser.name)]))
    return spots


def _good_run(cmd: list[str], out: Path) -> dict[str, Any]:
    proc = subprocess.run(cmd, capture_output=True, timeout=RUN_TIMEOUT_S, cwd=REPO)
    assert proc.returncode == 0, proc.stderr.decode()[-2000:]
    return dict(json.loads((out / "report.json").read_text()))


@pytest.fixture(scope="module")
def campaign(small_dataset: Any, tmp_path_factory: pytest.TempPathFactory) -> KillCampaign:
    ds = small_dataset
    work = tmp_path_factory.mktemp("kill")
    laser = sorted(ds.laser_images_dir.glob("*.png"))[0]
    spots = _spots_of(ds, laser, work)
    inputs = [ds.model_dir, ds.mesh_path, ds.rig_path, ds.database_path, ds.laser_images_dir,
              ds.images_dir, spots]
    out = work / "out"
    camp = KillCampaign(out=out, image_names=[laser.name],
                        mesh_vertices=len(load_mesh(ds.mesh_path).vertices),
                        inputs_before=tree_digest(*inputs))
    cmd = _scale_cmd(ds, laser, spots, out)
    camp.fresh_kill = _run_and_kill(cmd, "wrote model rescaled")  # no --out yet
    camp.fresh_kill["out_exists"] = out.exists()
    camp.fresh_kill["staging_left"] = [p.name for p in leftovers(out)]
    camp.first_report = _good_run(cmd, out)
    (out / "OLD_MARKER").write_text("previous complete output")
    rng = np.random.default_rng(7)
    # random delays first; a kill while writing last, so that it leaves a staging folder for
    # the final run to clean (each run removes the staging folders of dead runs)
    triggers: list[str | float] = [float(d) for d in rng.uniform(1.0, 4.0, N_RANDOM_KILLS)]
    triggers += [t for t in KILL_TRIGGERS if t != KILL_TRIGGERS[1]] + [KILL_TRIGGERS[1]]
    for trigger in triggers:
        marker_before = (out / "OLD_MARKER").exists()
        kill = _run_and_kill(cmd, trigger)
        kill["out_exists"] = out.exists()
        kill["old_kept"] = (out / "OLD_MARKER").exists()
        kill["staging_left"] = [p.name for p in leftovers(out)]
        if out.exists():
            assert_complete_scale_output(out, camp.image_names, camp.mesh_vertices)
        kill["marker_before"] = marker_before
        camp.kills.append(kill)
    camp.leftovers_before_final = leftovers(out)
    camp.last_report = _good_run(cmd, out)
    camp.leftovers_after_final = leftovers(out)
    camp.inputs_after = tree_digest(*inputs)
    return camp


def test_killed_runs_leave_the_old_or_a_new_complete_output(campaign: KillCampaign) -> None:
    """With --overwrite on a complete --out, a SIGKILL at any point leaves a complete --out
    (the old one until the new one is complete, checked in the fixture), never none."""
    assert all(k["out_exists"] for k in campaign.kills), campaign.kills
    # the campaign really killed runs, some of them while the outputs were being written
    assert sum(k["killed"] for k in campaign.kills) >= len(KILL_TRIGGERS)
    write_kills = [k for k in campaign.kills if k["trigger"] == KILL_TRIGGERS[1]]
    assert all(k["killed"] and k["staging_left"] for k in write_kills), write_kills
    assert all(k["old_kept"] or not k["marker_before"] or not k["killed"] for k in write_kills)


def test_next_run_removes_staging_left_by_killed_runs(campaign: KillCampaign) -> None:
    assert campaign.leftovers_before_final, "no kill left a staging folder: the test is void"
    assert campaign.leftovers_after_final == []
    assert_complete_scale_output(campaign.out, campaign.image_names, campaign.mesh_vertices)
    assert not (campaign.out / "OLD_MARKER").exists()


def test_scale_runs_do_not_modify_inputs(campaign: KillCampaign) -> None:
    """Checksums and mtimes of the model, database, mesh, rig, spots and images, before the
    first and after the last of the (good and killed) runs; no file added beside them."""
    assert campaign.inputs_after == campaign.inputs_before


def test_same_inputs_and_seed_give_identical_report_numbers(campaign: KillCampaign) -> None:
    """Two runs in separate processes, same inputs and seed: the report is the same apart
    from timings and provenance (which names the same inputs with the same checksums)."""
    a, b = campaign.first_report, campaign.last_report
    assert report_numbers(a) == report_numbers(b)
    assert a["provenance"]["inputs"] == b["provenance"]["inputs"]
    assert a["scale"]["value"] == b["scale"]["value"]  # bit-identical, not approximately


def test_kill_in_fresh_out_leaves_no_out(campaign: KillCampaign) -> None:
    """No previous --out: a run killed while writing its outputs leaves no --out at all, only
    its staging folder (removed by the next run, see above)."""
    kill = campaign.fresh_kill
    assert kill["killed"] and not kill["out_exists"] and kill["staging_left"], kill


# ---------------------------------------------------------------------------- other commands

def test_detect_apply_calibrate_do_not_modify_inputs(small_dataset: Any, tmp_path: Path) -> None:
    import cv2
    from test_calibration import BOARD, CAMERA, POSES, TRUE_RIG  # calibrate's own test scene

    from sfm_laserscale.synthetic.calibration_images import board_pose, render_calibration_shot

    poses = [POSES[0], POSES[3], POSES[6]]
    ds = small_dataset
    calib = tmp_path / "calib"
    calib.mkdir()
    for i, pose in enumerate(poses):
        shot = render_calibration_shot(CAMERA, TRUE_RIG, board_pose(*pose), BOARD)
        cv2.imwrite(str(calib / f"t{i}.png"), shot.image[:, :, ::-1])
    colmap_fx = FIXTURES / "maupertuis_colmap"
    openmvg_fx = FIXTURES / "maupertuis_openmvg"
    roots = [ds.out_dir, calib, colmap_fx, openmvg_fx]
    before = tree_digest(*roots)
    runs = {
        "detect": ["detect", str(ds.laser_images_dir), "--rig", str(ds.rig_path), "--model",
                   str(ds.model_dir)],
        "apply": ["apply", "--scale", "0.5", "--model", str(ds.model_dir), "--mesh",
                  str(ds.mesh_path)],
        "apply_colmap_text": ["apply", "--scale", "2", "--model",
                              str(colmap_fx / "reconstruction")],
        "apply_openmvg": ["apply", "--scale", "2", "--model", str(openmvg_fx / "sfm_data.json")],
        "calibrate": ["calibrate", str(calib), "--square-size", "0.06", "--self-calibrate",
                      "--names", "L,M,R"],
    }
    for name, args in runs.items():
        res = CliRunner().invoke(main, [*args, "--quiet", "--out", str(tmp_path / name)])
        assert res.exit_code == 0, (name, res.output)
    assert tree_digest(*roots) == before


def test_bad_inputs_doc_names_real_tests() -> None:
    """docs/BAD_INPUTS.md: 30+ cases, and every test it names exists."""
    import re

    doc = (REPO / "docs" / "BAD_INPUTS.md").read_text(encoding="utf-8")
    rows = [r for r in doc.splitlines() if re.match(r"^\| \d+ \|", r)]
    assert len(rows) >= 30
    named = re.findall(r"(tests/test_\w+\.py)::(test_\w+)", doc)
    assert len({r.split("|")[1] for r in rows}) == len(rows)
    for rel, name in named:
        source = (REPO / rel).read_text(encoding="utf-8")
        assert re.search(rf"^def {name}\(", source, re.M), f"{rel}::{name} not found"
    assert all("tests/" in r for r in rows)
