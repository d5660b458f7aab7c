"""The Python API (issue #20): docs/API.md's worked example runs as shown, block by block;
``scale`` without ``out`` writes nothing anywhere; in-memory inputs give the numbers of the
files; every public name the doc lists exists."""

from __future__ import annotations

import re
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

import sfm_laserscale
from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.calibration_images import (
    BoardSpec,
    board_pose,
    render_calibration_shot,
)

REPO = Path(__file__).resolve().parents[1]
API_MD = REPO / "docs" / "API.md"


def example_blocks() -> list[str]:
    """The ```python blocks of docs/API.md's worked example, in order."""
    text = API_MD.read_text(encoding="utf-8")
    section = text.split("## Worked example", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, re.S)


def _targets(folder: Path) -> None:
    """Three chessboard photographs with three laser spots (as tests/test_calibration.py)."""
    camera = Camera(1, "PINHOLE", 1280, 960, np.array([1100.0, 1100.0, 640.0, 480.0]))
    rig = rig_from_dict({"laser": [
        {"name": "A", "origin": [0.1, 0.02, 0], "direction": [0.01, -0.005, 1]},
        {"name": "B", "origin": [-0.1, 0.02, 0], "direction": [0.01, -0.005, 1]},
        {"name": "C", "origin": [0.0, 0.2, 0], "direction": [0.02, -0.01, 1]}]})
    folder.mkdir()
    for i, pose in enumerate([(1.0, 10, -20, (0.0, 0.1)), (2.5, -5, -25, (0.05, 0.1)),
                              (4.0, 5, 20, (0.06, 0.1))]):
        shot = render_calibration_shot(camera, rig, board_pose(*pose), BoardSpec(square_m=0.06),
                                       ss=1)  # no supersampling: 9x faster, still found
        cv2.imwrite(str(folder / f"t{i}.png"), shot.image[:, :, ::-1])


def _listing(*roots: Path) -> set[str]:
    return {str(p) for r in roots for p in r.rglob("*")}


@pytest.fixture()
def workplace(tmp_path: Path, small_dataset: Any, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A folder as the doc describes it, and empty temporary and cache folders to watch."""
    work = tmp_path / "work"
    (work / "demo_out").mkdir(parents=True)
    (work / "demo_out" / "data").symlink_to(small_dataset.model_dir.parents[1])
    _targets(work / "targets")
    for name in ("tmp", "cache", "home"):
        (tmp_path / name).mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(work)
    return tmp_path


def test_the_worked_example_runs_as_shown(workplace: Path, small_dataset: Any) -> None:
    blocks = example_blocks()
    assert len(blocks) == 5
    namespace: dict[str, Any] = {"__name__": "api_example"}
    watched = [workplace / "work", workplace / "tmp", workplace / "cache", workplace / "home"]
    before = _listing(*watched)
    exec(compile(blocks[0], "docs/API.md[1]", "exec"), namespace)  # noqa: S102
    assert _listing(*watched) == before  # scale without out= wrote nothing, anywhere
    result = namespace["result"]
    err = abs(result.scale.value - small_dataset.true_scale) / small_dataset.true_scale
    assert err < 0.01
    assert namespace["report"]["schema_version"] == sfm_laserscale.SCHEMA_VERSION
    assert len(namespace["areas"]) == len(result.footprints) > len(result.images)
    for k, block in enumerate(blocks[1:], start=2):
        exec(compile(block, f"docs/API.md[{k}]", "exec"), namespace)  # noqa: S102
    written = namespace["written"]
    assert written.report["inputs"]["model"].startswith("<in memory")
    provenance_paths = [p["path"] for p in written.report["provenance"]["inputs"]]
    assert not any(p.startswith("<in memory") for p in provenance_paths)
    # the metric model: translations and points times the scale
    rec, metric = namespace["reconstruction"], namespace["metric_model"]
    s = result.scale.value
    pid = next(iter(rec.points3D))
    np.testing.assert_allclose(metric.points3D[pid].xyz, s * rec.points3D[pid].xyz, rtol=1e-12)
    scaled_file = namespace["scaled_model"]
    np.testing.assert_allclose(scaled_file.points3D[pid].xyz, s * rec.points3D[pid].xyz,
                               rtol=1e-9)
    np.testing.assert_allclose(np.asarray(namespace["metric_mesh"].vertices),
                               s * np.asarray(namespace["mesh"].vertices), rtol=1e-12)
    assert Path("metric/transform.sim3").is_file()
    assert any(namespace["found"].spots.values())
    assert sorted(las.name for las in namespace["rig"].lasers) == ["L", "M", "R"]


def test_every_public_name_listed_exists() -> None:
    text = API_MD.read_text(encoding="utf-8")
    listed = re.findall(r"^\| `([A-Za-z_]+)", text.split("## Every public name", 1)[1], re.M)
    assert set(listed) == set(sfm_laserscale.__all__)
    for name in listed:
        assert getattr(sfm_laserscale, name) is not None
    with pytest.raises(AttributeError):
        _ = sfm_laserscale.no_such_name  # type: ignore[attr-defined]


def test_api_refuses_bad_input(small_dataset: Any, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="method"):
        sfm_laserscale.scale(small_dataset.model_dir, small_dataset.mesh_path,
                             small_dataset.laser_images_dir, small_dataset.rig_path,
                             method="best")
    with pytest.raises(InputError, match="pycolmap.Reconstruction"):
        sfm_laserscale.scale(object(), small_dataset.mesh_path, small_dataset.laser_images_dir,
                             small_dataset.rig_path, database=small_dataset.database_path)
    with pytest.raises(InputError, match="nothing to rescale"):
        sfm_laserscale.apply(2.0)
    with pytest.raises(InputError, match="positive"):
        sfm_laserscale.apply(-1.0, mesh=small_dataset.mesh_path)
    with pytest.raises(InputError, match="exactly one"):
        sfm_laserscale.calibrate(tmp_path, 0.06)
    metric = sfm_laserscale.apply(0.5, model=small_dataset.model_dir)
    assert metric.files is None and metric.mesh is None
    assert not any(tmp_path.iterdir())
