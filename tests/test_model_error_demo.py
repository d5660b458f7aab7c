"""Scenes whose SfM model has its own focal-length error (real SfM of rendered images, run with a
wrong focal length held fixed; the mesh carried into that model): the headline's interval holds
the truth, the error budget names the model's intrinsics, and a large focal error is warned
about by name with the focal-corrected scale offered beside the headline."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from sfm_laserscale.commands import scale as scale_command
from sfm_laserscale.commands.demo import scale_inputs_for
from sfm_laserscale.run_types import ScaleOptions
from sfm_laserscale.synthetic.dataset import DemoDataOptions, make_demo_dataset


def _run(tmp: Path, focal_error: float) -> tuple[Any, float]:
    data = make_demo_dataset(tmp / "data", DemoDataOptions(
        small=True, seed=0, progress=False, rig="diverging", sfm_focal_error=focal_error))
    res = scale_command.run(scale_inputs_for(data), tmp / "out", ScaleOptions(progress=False))
    return res, data.true_scale


@pytest.fixture(scope="module")
def focal_015(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, float]:
    return _run(tmp_path_factory.mktemp("focal_015"), 0.0015)


@pytest.fixture(scope="module")
def focal_2(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, float]:
    return _run(tmp_path_factory.mktemp("focal_2"), 0.02)


def test_focal_off_015_pct_interval_holds_the_truth(focal_015: tuple[Any, float]) -> None:
    """SfM focal +0.15 %, beams diverging 3° (FCM moves ~0.8 × the focal error): |error| within
    2σ, the intrinsics term a large share of the budget (measured 2026-11-27: error +0.09 %
    against the mesh's scale, σ 0.15 %, of which intrinsics 44 % and spots 56 %; before the
    spots' σ held the 2 × 2 sampling of colour, σ 0.13 % and intrinsics 62 %: the demo's PNG
    renders keep colour at full resolution, so that term overstates their spots' σ)."""
    res, truth = focal_015
    s = res.report["scale"]
    assert s["method"] == "fcm"
    err = s["value"] - truth
    assert abs(err) <= 2 * s["std"]
    assert s["ci95"][0] <= truth <= s["ci95"][1]
    assert s["budget_shares"]["intrinsics"] > 0.3
    intr = res.report["model_error"]["intrinsics"]["cameras"][0]
    assert intr["from_covariance"] and intr["focal_sigma_pct"] >= 0.1  # at least the floor
    assert "model_checks" in res.report and res.report["model_checks"]["focal"]["sources"]


def test_focal_off_2_pct_is_warned_by_name(focal_2: tuple[Any, float]) -> None:
    """The small scene (6 laser images) reads a 2 % focal error at 5σ: a warning by name, the
    headline widened. (At 1 % it reads 0.87 ± 0.37 %, 2.4σ: a note, "possibly".)"""
    res, truth = focal_2
    r = res.report
    warn = [w for w in r["warnings"] if w["code"] == "focal_error"]
    assert warn and warn[0]["level"] == "warning" and "focal length" in warn[0]["message"]
    f = r["model_checks"]["focal"]
    assert f["significant"] and f["focal_error_pct"] == pytest.approx(2.0, abs=3 * f["sigma_pct"])
    s = r["scale"]
    assert abs(s["value"] - truth) <= 3 * s["std"]  # widened by the focal error the data show
    assert f["headline_widened"]
    fc = r["methods"]["focal_corrected"]
    assert abs(fc["value"] - truth) <= 3 * fc["std"]
    assert s["method"] == "fcm"  # the headline is never replaced
    html = (res.out_dir / "report.html").read_text(encoding="utf-8")
    assert "Focal-length error" in html and 'id="budget-table"' in html
