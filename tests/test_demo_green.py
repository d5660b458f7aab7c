"""`demo --laser-color green` (issue #16, item 5): green beams with clipped white cores in
green-cyan water over a floor with pale clutter, end to end through the command line."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sfm_laserscale.cli import main
from sfm_laserscale.commands.demo import DemoOptions
from sfm_laserscale.errors import InputError
from sfm_laserscale.synthetic.dataset import (
    GREEN_WATER_ATTENUATION,
    GREEN_WATER_PALE_PATCHES_PER_M2,
    DemoDataOptions,
    resolve_options,
)


def test_green_beams_imply_green_water_unless_told() -> None:
    assert DemoOptions().resolved_water == "clear"
    assert DemoOptions(laser_color="green").resolved_water == "green"
    assert DemoOptions(laser_color="green", water="clear").resolved_water == "clear"
    assert DemoOptions(laser_color="red", water="green").resolved_water == "green"


def test_water_presets() -> None:
    clear = resolve_options(DemoDataOptions(small=True))
    assert clear.render == DemoDataOptions().render
    assert clear.scene.pale_patches_per_m2 == 0.0
    green = resolve_options(DemoDataOptions(small=True, water="green"))
    assert green.render.attenuation_per_m == GREEN_WATER_ATTENUATION
    assert green.scene.pale_patches_per_m2 == GREEN_WATER_PALE_PATCHES_PER_M2
    assert green.image_size == clear.image_size  # the small preset still applies
    with pytest.raises(InputError):
        resolve_options(DemoDataOptions(laser_color="violet"))
    with pytest.raises(InputError):
        resolve_options(DemoDataOptions(water="brown"))


def test_demo_green_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    result = CliRunner().invoke(main, ["demo", "--small", "--laser-color", "green", "--out",
                                       str(out), "--quiet"], catch_exceptions=False)
    assert result.exit_code == 0, result.stderr
    assert "true scale" in result.stdout
    truth = json.loads((out / "data" / "truth.json").read_text())
    report = json.loads((out / "scale" / "report.json").read_text())
    err = (report["scale"]["value"] - truth["true_scale"]) / truth["true_scale"]
    assert abs(err) < 0.003, f"scale error {err:+.3%}"
    rig = tomllib.loads((out / "data" / "rig.toml").read_text())
    assert {las["color"] for las in rig["laser"]} == {"green"}
    for im in report["images"]:  # automatic spots (no --spots) in every laser image
        assert im["registered"] and im["spots"], (im["name"], im.get("missing_spots"))
    ref = cv2.imread(str(out / "data" / "images" / "ref_000.png"))[:, :, ::-1]
    med = np.median(ref.reshape(-1, 3), axis=0)
    assert med[1] > med[2] > med[0]  # green-cyan water
