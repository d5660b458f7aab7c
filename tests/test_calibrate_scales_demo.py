"""A rig calibrated by `calibrate` from rendered target images scales the demo scene as well as
the true rig does (issue 5; small demo data set, same laser images, same pipeline)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sfm_laserscale.calibration.target import CalibrateOptions, CalibrateResult, calibrate_images
from sfm_laserscale.commands import scale as scale_command
from sfm_laserscale.commands.demo import scale_inputs_for
from sfm_laserscale.io.images import camera_for_size
from sfm_laserscale.io.models import load_model
from sfm_laserscale.rig import Laser, Pair, Rig, rig_to_toml
from sfm_laserscale.run_types import ScaleOptions
from sfm_laserscale.synthetic.calibration_images import (
    BoardSpec,
    board_pose,
    render_calibration_shot,
)

BOARD = BoardSpec(cols=9, rows=6, square_m=0.06)
# distance (m), tilt x, tilt y (degrees), board centre offset (m): the board sits where the
# demo rig's four spots are (around the optical axis), 1-3 m away
POSES = [(1.0, 10, -20, (0.0, 0.0)), (1.4, -15, 10, (0.01, 0.0)), (1.8, 20, 5, (0.0, 0.01)),
         (2.2, -5, -25, (0.02, 0.0)), (2.6, 25, 15, (0.0, 0.02)), (3.0, -20, -10, (0.02, 0.02))]


@pytest.fixture(scope="module")
def calibration(small_dataset: Any) -> CalibrateResult:
    cam = small_dataset.camera
    model_cam = camera_for_size(load_model(small_dataset.model_dir), cam.width, cam.height)
    assert model_cam is not None
    rng = np.random.default_rng(5)
    shots = {f"t{i}.png": render_calibration_shot(model_cam, small_dataset.rig, board_pose(*p),
                                                  BOARD, rng=rng, noise=0.004).image
             for i, p in enumerate(POSES)}
    return calibrate_images(shots, model_cam, CalibrateOptions(square_m=BOARD.square_m))


def _renamed(calibrated: Rig, true: Rig) -> Rig:
    """The calibrated rig with each laser named after the true laser with the nearest origin."""
    names = {}
    for las in calibrated.lasers:
        assert las.origin is not None
        names[las.name] = min(true.lasers, key=lambda t: float(
            np.linalg.norm(np.asarray(t.origin) - las.origin))).name
    assert sorted(names.values()) == sorted(true.names)
    lasers = tuple(replace(las, name=names[las.name]) for las in calibrated.lasers)
    pairs = tuple(Pair(lasers=(names[p.lasers[0]], names[p.lasers[1]]), separation=p.separation)
                  for p in calibrated.pairs)
    return Rig(name=calibrated.name, lasers=lasers, pairs=pairs)


def _errors(rig: Rig, true: Rig) -> tuple[float, float]:
    """Largest origin error (m) and direction error (degrees) over the lasers."""
    o_err, d_err = 0.0, 0.0
    for las in rig.lasers:
        t: Laser = true.laser(las.name)
        assert las.origin is not None and las.direction is not None
        o_err = max(o_err, float(np.linalg.norm(las.origin - np.asarray(t.origin))))
        cosang = float(np.clip(las.direction @ np.asarray(t.direction), -1, 1))
        d_err = max(d_err, float(np.degrees(np.arccos(cosang))))
    return o_err, d_err


def test_calibrated_rig_scales_demo_like_true_rig(
    calibration: CalibrateResult, small_dataset: Any, tmp_path: Path
) -> None:
    true = small_dataset.rig
    rig = _renamed(calibration.calibration.rig, true)
    o_err, d_err = _errors(rig, true)
    assert o_err < 0.002 and d_err < 0.1, (o_err, d_err)
    rig_path = tmp_path / "calibrated_rig.toml"
    rig_path.write_text(rig_to_toml(rig), encoding="utf-8")
    inputs = scale_inputs_for(small_dataset)
    opts = ScaleOptions(progress=False, overlays=False, method="fcm")
    res_true = scale_command.run(inputs, tmp_path / "true", opts)
    res_cal = scale_command.run(replace(inputs, rig=rig_path), tmp_path / "cal", opts)
    s_true = small_dataset.true_scale
    assert res_true.success and res_cal.success
    for res in (res_true, res_cal):
        # within 3 sigma of the truth (the fused sigma includes the rig's stated uncertainty)
        assert abs(res.scale.value - s_true) < 3.0 * res.scale.std, (res.scale, s_true)
    rel = (res_cal.scale.value - res_true.scale.value) / res_true.scale.value
    assert abs(rel) < 0.005, rel
    print(f"\norigin err {1e3 * o_err:.2f} mm, direction err {d_err:.4f} deg; "
          f"true rig {res_true.scale.value / s_true - 1:+.4%} ± {res_true.scale.std / s_true:.4%}"
          f"; calibrated rig {res_cal.scale.value / s_true - 1:+.4%} "
          f"± {res_cal.scale.std / s_true:.4%}")
