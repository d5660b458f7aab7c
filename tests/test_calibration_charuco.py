"""`calibrate` with a ChArUco target: rendered boards of a known rig, partial views, CLI."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sfm_laserscale.calibration.target import (
    CalibrateOptions,
    CalibrateResult,
    calibrate_images,
    find_target,
)
from sfm_laserscale.cli import main
from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import load_rig, rig_from_dict
from sfm_laserscale.synthetic.calibration_images import (
    BoardSpec,
    board_pose,
    render_calibration_shot,
)

CAMERA = Camera(1, "PINHOLE", 1024, 768, np.array([900.0, 900.0, 512.0, 384.0]))
TRUE_RIG = rig_from_dict({"laser": [
    {"name": "A", "origin": [0.1, 0.02, 0], "direction": [0.01, -0.005, 1], "color": "red"},
    {"name": "B", "origin": [-0.1, 0.02, 0], "direction": [0.01, -0.005, 1], "color": "red"},
]})
BOARD = BoardSpec(cols=8, rows=6, square_m=0.06, kind="charuco", margin_squares=0.5)
OPTIONS = CalibrateOptions(board=(8, 6), square_m=0.06, target="charuco")
# the last two views show only part of the board (it runs off the image)
POSES = [(1.0, 10, -20, (0.0, 0.05)), (1.6, -15, 10, (0.02, 0.05)), (2.2, 20, 5, (0.0, 0.05)),
         (2.4, -5, -15, (0.03, 0.05)), (0.6, 5, 10, (0.1, 0.14)), (0.6, -10, 5, (-0.16, -0.12))]


@pytest.fixture(scope="module")
def shots() -> list:  # type: ignore[type-arg]
    return [render_calibration_shot(CAMERA, TRUE_RIG, board_pose(*p), BOARD) for p in POSES]


@pytest.fixture(scope="module")
def calibrated(shots: list) -> CalibrateResult:  # type: ignore[type-arg]
    return calibrate_images({f"c{i}.png": s.image for i, s in enumerate(shots)}, CAMERA, OPTIONS)


def test_partial_view_gives_corners_and_pose(shots: list) -> None:  # type: ignore[type-arg]
    full = find_target(shots[0].image, OPTIONS)
    part = find_target(shots[4].image, OPTIONS)
    assert full is not None and part is not None
    assert len(full[0]) == 35 and 6 <= len(part[0]) < 35  # 7 x 5 inner corners in all


def test_charuco_calibration_recovers_rig(calibrated: CalibrateResult) -> None:
    rig = calibrated.calibration.rig
    assert len(rig.lasers) == 2
    for las in rig.lasers:
        assert las.origin is not None and las.direction is not None
        o, d = las.origin, las.direction
        true = min(TRUE_RIG.lasers, key=lambda t: float(np.linalg.norm(np.asarray(t.origin) - o)))
        o_err = float(np.linalg.norm(o - np.asarray(true.origin)))
        ang = float(np.degrees(np.arccos(np.clip(d @ np.asarray(true.direction), -1, 1))))
        assert o_err < 0.002 and ang < 0.1
        print(f"\n{las.name}: origin err {1e3 * o_err:.3f} mm, direction err {ang:.4f} deg")
    assert len(rig.pairs) == 1 and rig.pairs[0].separation == pytest.approx(0.2, abs=0.002)
    # the partial views were used (each laser seen in every image)
    assert all(len(cl.spots) == len(POSES) for cl in calibrated.calibration.lasers)


def test_charuco_options_are_checked() -> None:
    with pytest.raises(InputError, match="dictionary"):
        CalibrateOptions(target="charuco", dictionary="DICT_NOPE")
    with pytest.raises(InputError, match="marker"):
        CalibrateOptions(target="charuco", square_m=0.05, marker_m=0.06)
    with pytest.raises(InputError, match="target"):
        CalibrateOptions(target="circles")


def test_chessboard_finder_does_not_see_charuco(shots: list) -> None:  # type: ignore[type-arg]
    # a wrong --board setting must fail loudly, not give a pose from the wrong geometry
    assert find_target(shots[0].image, CalibrateOptions(board=(9, 6), square_m=0.06)) is None



def test_cli_charuco(shots: list, tmp_path: Path) -> None:  # type: ignore[type-arg]
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i, shot in enumerate(shots):
        cv2.imwrite(str(folder / f"c{i}.png"), shot.image[:, :, ::-1])
    args = ["calibrate", str(folder), "--board", "charuco", "--squares", "8x6",
            "--square-size", "0.06", "--self-calibrate", "--out", str(tmp_path / "out")]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    rig = load_rig(tmp_path / "out" / "rig.toml")
    assert rig.names == ["L1", "L2"] and len(rig.pairs) == 1
    assert rig.pairs[0].separation == pytest.approx(0.2, abs=0.005)
    bad = CliRunner().invoke(main, [a for a in args if a not in ("--squares", "8x6")][:-2]
                             + ["--out", str(tmp_path / "o2")])
    assert bad.exit_code == 2 and "--squares" in bad.output
