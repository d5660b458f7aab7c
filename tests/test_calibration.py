"""Rig calibration: closed-form maths, rendered targets of a known rig, refusals, CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sfm_laserscale.calibration.fit import (
    CalibrationOptions,
    Plane,
    SpotPoint,
    calibrate_rig,
    fit_line,
    ray_plane_points,
)
from sfm_laserscale.calibration.target import CalibrateOptions, CalibrateResult, calibrate_images
from sfm_laserscale.calibration.target import self_calibrate as self_cal
from sfm_laserscale.cli import main
from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import Rig, load_rig, rig_from_dict
from sfm_laserscale.synthetic.calibration_images import (
    BoardSpec,
    board_pose,
    render_calibration_shot,
)

CAMERA = Camera(1, "PINHOLE", 1280, 960, np.array([1100.0, 1100.0, 640.0, 480.0]))
TRUE_RIG = rig_from_dict({"laser": [
    {"name": "A", "origin": [0.1, 0.02, 0], "direction": [0.01, -0.005, 1], "color": "red"},
    {"name": "B", "origin": [-0.1, 0.02, 0], "direction": [0.01, -0.005, 1], "color": "red"},
    {"name": "C", "origin": [0.0, 0.2, 0], "direction": [0.02, -0.01, 1], "color": "red"},
]})
BOARD = BoardSpec(square_m=0.06)
POSES = [(1.0, 10, -20, (0.0, 0.1)), (1.5, -15, 10, (0.03, 0.08)), (2.0, 20, 5, (0.0, 0.1)),
         (2.5, -5, -25, (0.05, 0.1)), (3.0, 25, 15, (0.05, 0.08)), (3.5, -20, -10, (0.05, 0.1)),
         (4.0, 5, 20, (0.06, 0.1))]


@pytest.fixture(scope="module")
def images() -> dict[str, np.ndarray]:
    return {f"t{i}.png": render_calibration_shot(CAMERA, TRUE_RIG, board_pose(*p), BOARD).image
            for i, p in enumerate(POSES)}


@pytest.fixture(scope="module")
def calibrated(images: dict[str, np.ndarray]) -> CalibrateResult:
    return calibrate_images(images, CAMERA, CalibrateOptions(square_m=0.06))


def _match(rig: Rig) -> dict[str, str]:
    """Calibrated name -> true name by nearest origin."""
    out = {}
    true = {t.name: np.asarray(t.origin) for t in TRUE_RIG.lasers}
    for las in rig.lasers:
        o = np.asarray(las.origin)
        out[las.name] = min(true, key=lambda n: float(np.linalg.norm(true[n] - o)))
    return out


def test_fit_line_recovers_exact_line() -> None:
    d = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0])
    pts = np.array([0.2, 0.1, 0.0]) + np.array([1.0, 2.0, 3.5])[:, None] * d
    fit = fit_line(pts)
    np.testing.assert_allclose(fit.origin, [0.2, 0.1, 0.0], atol=1e-12)
    np.testing.assert_allclose(fit.direction, d, atol=1e-12)
    assert fit.sigma_origin_m < 1e-9 and np.max(fit.residuals_m) < 1e-12


def test_fit_line_sigmas_match_scatter() -> None:
    rng = np.random.default_rng(0)
    d = np.array([0.0, 0.0, 1.0])
    errs, sig = [], []
    for _ in range(300):
        pts = np.array([0.1, 0.0, 0.0]) + np.linspace(1, 4, 8)[:, None] * d
        pts[:, :2] += rng.normal(0, 1e-3, (8, 2))
        fit = fit_line(pts)
        errs.append(fit.origin[0] - 0.1)
        sig.append(fit.sigma_origin_m)
    assert float(np.std(errs)) == pytest.approx(float(np.mean(sig)), rel=0.25)


def test_ray_plane_points() -> None:
    plane = Plane(normal=np.array([0.0, 0.0, 1.0]), d=2.0)
    np.testing.assert_allclose(ray_plane_points(np.array([[0.5, -0.25, 1.0]]), plane),
                               [[1.0, -0.5, 2.0]])


def test_rendered_rig_recovered(calibrated: CalibrateResult) -> None:
    rig = calibrated.calibration.rig
    assert len(rig.lasers) == 3
    match = _match(rig)
    assert sorted(match.values()) == ["A", "B", "C"]
    for las in rig.lasers:
        true = TRUE_RIG.laser(match[las.name])
        assert las.origin is not None and las.direction is not None
        assert true.origin is not None and true.direction is not None
        assert float(np.linalg.norm(las.origin - true.origin)) < 2e-3
        angle = math.degrees(math.acos(min(1.0, float(las.direction @ true.direction))))
        assert angle < 0.1
        assert 0 < las.sigma_origin < 2e-3 and 0 < las.sigma_direction < math.radians(0.1)


def test_pair_found_with_separation(calibrated: CalibrateResult) -> None:
    rig = calibrated.calibration.rig
    match = _match(rig)
    assert len(rig.pairs) == 1
    pair = rig.pairs[0]
    assert sorted(match[n] for n in pair.lasers) == ["A", "B"]
    assert pair.separation == pytest.approx(0.2 * math.cos(math.atan(0.01)), abs=2e-3)


def test_report_residuals(calibrated: CalibrateResult) -> None:
    report = calibrated.report
    assert len(report["images"]) == len(POSES)
    res = [s["residual_mm"] for im in report["images"] for s in im["spots"].values()]
    assert len(res) == 3 * len(POSES) and max(res) < 1.0
    json.dumps(report)


def test_self_calibration(calibrated: CalibrateResult) -> None:
    corners = [o.corners_px for o in calibrated.observations if o.corners_px is not None]
    cam = self_cal(corners, (1280, 960), CalibrateOptions(square_m=0.06))
    assert cam.model == "OPENCV"
    np.testing.assert_allclose(cam.params[:4], [1100, 1100, 640, 480], atol=3.0)


def _spots(rng: np.random.Generator, distances: list[float], n_lasers: int = 2
           ) -> list[SpotPoint]:
    out = []
    for i, z in enumerate(distances):
        for las in TRUE_RIG.lasers[:n_lasers]:
            assert las.origin is not None and las.direction is not None
            p = las.origin + (z / las.direction[2]) * las.direction + rng.normal(0, 2e-4, 3)
            out.append(SpotPoint(i, np.zeros(2), p, "red"))
    return out


def test_maths_level_recovery_and_refusals() -> None:
    rng = np.random.default_rng(1)
    ok = calibrate_rig(_spots(rng, [1.0, 2.0, 3.0]), ["L1", "L2"])
    assert len(ok.rig.pairs) == 1
    with pytest.raises(InputError, match="too little range"):
        calibrate_rig(_spots(rng, [2.0, 2.2, 2.4]), ["L1", "L2"])
    with pytest.raises(InputError, match="fewer than 3 spots"):
        calibrate_rig(_spots(rng, [1.0, 3.0]), ["L1", "L2"])
    spots = _spots(rng, [1.0, 2.0, 3.0, 4.0])
    spots = [s for s in spots if not (s.image >= 2 and s.xyz_m[0] < 0.0)]  # B seen twice only
    with pytest.raises(InputError, match="fewer than 3 spots"):
        calibrate_rig(spots, ["L1", "L2"], options=CalibrationOptions())


def test_refuses_when_target_missing(images: dict[str, np.ndarray]) -> None:
    blank = np.full_like(images["t0.png"], 60)
    few = {"t0.png": images["t0.png"], "b1.png": blank}
    with pytest.raises(InputError, match="found in only 1 image"):
        calibrate_images(few, CAMERA, CalibrateOptions(square_m=0.06))


def test_cli_writes_rig(tmp_path: Path, images: dict[str, np.ndarray]) -> None:
    folder = tmp_path / "imgs"
    folder.mkdir()
    for name in list(images)[::3]:  # 3 images: 1, 2.5, 4 m
        cv2.imwrite(str(folder / name), images[name][:, :, ::-1])
    out = tmp_path / "out"
    runner = CliRunner()
    args = ["calibrate", str(folder), "--board", "9x6", "--square-size", "0.06",
            "--self-calibrate", "--names", "L,M,R", "--out", str(out)]
    res = runner.invoke(main, args)
    assert res.exit_code == 0, res.output
    rig = load_rig(out / "rig.toml")
    assert rig.names == ["L", "M", "R"] and len(rig.pairs) == 1
    assert json.loads((out / "calibration_report.json").read_text())["lasers"]
    bad = runner.invoke(main, [*args[:-2], "--names", "L,M,R,X", "--out", str(tmp_path / "o2")])
    assert bad.exit_code == 2 and "fewer than 3 spots" in bad.output
