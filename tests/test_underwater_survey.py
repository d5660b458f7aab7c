"""`scale` end to end on photographs the method's authors did not make (issue #16, item 5).

The survey (synthetic/underwater/survey.py) is rendered by the independent generator: green
532 nm beams with clipped white cores, green-cyan coastal water, pale clutter on the floor,
Bayer sensor, camera processing and JPEG 4:2:0; SfM is pycolmap's. `scale` runs on it through
the command line with automatic spot detection (no --spots).

The survey is built with the true rig in rig.toml (``rig_error_scale=0``; the file still
carries the layout's sigmas): the layout's calibration error (1 mm per origin axis, 0.05° per
direction axis) moves the scale a perfect run would find by 0.63 % RMS over seeds (more than
0.3 % for 20 of 30 seeds; truth.json's ``rig_file_fcm_bias_pct_mean`` gives it per data set),
which would hide what this test is about: the photographs.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner, Result

from sfm_laserscale.cli import main
from sfm_laserscale.synthetic.underwater.survey import Survey, SurveyOptions, make_survey

SURVEY_PY = (Path(__file__).resolve().parents[1] / "sfm_laserscale" / "synthetic"
             / "underwater" / "survey.py")
#: the stages under test: the survey must not use them to make its data
FORBIDDEN = ("sfm_laserscale.detection", "sfm_laserscale.registration", "sfm_laserscale.raycast",
             "sfm_laserscale.methods", "sfm_laserscale.pipeline", "sfm_laserscale.fusion",
             "sfm_laserscale.uncertainty", "sfm_laserscale.synthetic.spots",
             "sfm_laserscale.synthetic.render", "sfm_laserscale.synthetic.scene")


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Survey:
    """12 reference and 4 laser images at 960 x 540, seed 1, the true rig in rig.toml. Seed 1's
    spots are all whitened clipped cores or lost among pale clutter: the detector alone leaves
    three lasers of one laser image without a spot (two of the four images had none before its
    brightness's blobs were found on a ridge-free response), so the guided search has work to
    do."""
    out = tmp_path_factory.mktemp("underwater_survey") / "data"
    return make_survey(out, SurveyOptions(seed=1, rig_error_scale=0.0))


def _run(survey: Survey, out: Path, *extra: str) -> tuple[Result, Path]:
    """`sfm-laserscale scale` on the survey, as a user would type it."""
    args = ["scale", "--model", str(survey.model_dir), "--mesh", str(survey.mesh_path),
            "--rig", str(survey.rig_path), "--database", str(survey.database_path),
            "--out", str(out), "--quiet", "--laser-images", str(survey.laser_images_dir), *extra]
    return CliRunner().invoke(main, args, catch_exceptions=False), out


@pytest.fixture(scope="module")
def scale_run(survey: Survey, tmp_path_factory: pytest.TempPathFactory) -> tuple[Result, Path]:
    """`scale` with its defaults (automatic spots: the detector, then the guided search)."""
    return _run(survey, tmp_path_factory.mktemp("underwater_survey_scale") / "run")


@pytest.fixture(scope="module")
def alone_run(survey: Survey, tmp_path_factory: pytest.TempPathFactory) -> tuple[Result, Path]:
    """`scale --no-guided-spots`: the detector alone."""
    return _run(survey, tmp_path_factory.mktemp("underwater_survey_alone") / "run",
                "--no-guided-spots")


def _report(run: tuple[Result, Path]) -> dict[str, Any]:
    result, out = run
    assert result.exit_code == 0, result.stderr
    return dict(json.loads((out / "report.json").read_text()))


def _spot_summary(report: dict[str, Any], truth: dict[str, Any]) -> str:
    """Per laser image: registration, each detected spot's distance to its truth, and the
    reason of every missing spot (what a failure needs to show)."""
    true_spots = {im["name"]: {s["laser"]: s for s in im["spots"]}
                  for im in truth["laser_images"]}
    lines = []
    for im in report["images"]:
        found = []
        for s in im["spots"]:
            t = true_spots[im["name"]].get(s["laser"], {})
            off = (math.hypot(s["x"] - t["x"], s["y"] - t["y"]) if t.get("x") is not None
                   else math.nan)
            found.append(f"{s['laser']} {off:.2f} px")
        lines.append(f"{im['name']}: registered={im['registered']} ({im['reason']}); found "
                     f"[{', '.join(found)}]; missing {im.get('missing_spots')}")
    return "\n".join(lines)


def test_survey_uses_none_of_the_stages_under_test() -> None:
    from tests.test_underwater_generator import imported_modules

    for mod in imported_modules(SURVEY_PY):
        assert not mod.startswith(FORBIDDEN), f"survey.py imports {mod}"


def test_sfm_registers_every_reference_image(survey: Survey) -> None:
    assert survey.sfm.n_registered == survey.sfm.n_images == 12
    truth = json.loads(survey.truth_path.read_text())
    assert truth["alignment_rms_m"] < 0.02
    assert truth["camera"].startswith("OPENCV 960 540 ")


def test_photographs_are_jpeg_green_water_with_pale_clutter(survey: Survey) -> None:
    truth = json.loads(survey.truth_path.read_text())
    assert truth["water"] == "green_coastal" and truth["wavelength_nm"] == 532.0
    files = sorted(survey.images_dir.glob("*.jpg")) + sorted(survey.laser_images_dir.glob("*.jpg"))
    assert len(files) == 16
    assert all(f.read_bytes()[:2] == b"\xff\xd8" for f in files)
    assert min(im["pale_patches_drawn"] for im in truth["reference_images"]) >= 100
    import cv2

    rgb = cv2.imread(str(files[0]))[:, :, ::-1]
    med = np.median(rgb.reshape(-1, 3), axis=0)
    assert med[1] > med[2] > med[0]  # green-cyan
    peaks = [s["peak_over_white"] for im in truth["laser_images"] for s in im["spots"]]
    assert len(peaks) == 16 and min(peaks) >= 3.0  # every core clips


def test_scale_end_to_end_on_the_survey(survey: Survey, scale_run: tuple[Result, Path]) -> None:
    report = _report(scale_run)
    truth = json.loads(survey.truth_path.read_text())
    summary = _spot_summary(report, truth)
    value = report["scale"]["value"]
    err = (value - survey.true_scale) / survey.true_scale
    assert abs(err) < 0.003, f"scale {value} vs true {survey.true_scale}: {err:+.3%}\n{summary}"
    names = sorted(p.name for p in survey.laser_images_dir.glob("*.jpg"))
    assert sorted(im["name"] for im in report["images"]) == names
    for im in report["images"]:
        assert im["spots"], f"no spot detected in {im['name']}\n{summary}"


def test_spots_the_detector_missed_are_found_where_the_model_puts_them(
        survey: Survey, scale_run: tuple[Result, Path], alone_run: tuple[Result, Path]
) -> None:
    truth = json.loads(survey.truth_path.read_text())
    true_xy = {(im["name"], s["laser"]): (s["x"], s["y"])
               for im in truth["laser_images"] for s in im["spots"] if s.get("x") is not None}
    alone, guided = _report(alone_run), _report(scale_run)
    summary = _spot_summary(guided, truth)

    def spots(report: dict[str, Any], source: str) -> list[float]:
        return [math.dist((s["x"], s["y"]), true_xy[(im["name"], s["laser"])])
                for im in report["images"] for s in im["spots"] if s["source"] == source]

    assert spots(alone, "guided") == []
    assert sum(4 - len(im["spots"]) for im in alone["images"]) >= 3  # what the search is for
    found = spots(guided, "guided")
    assert len(found) >= 2 and max(found) < 1.0, summary
    assert sum(not im["spots"] for im in guided["images"]) == 0, summary
    assert len(spots(guided, "detected")) == len(spots(alone, "detected"))
    assert "guided" in guided["timings_s"] and "guided" not in alone["timings_s"]
    rows = (scale_run[1] / "spots.csv").read_text().splitlines()
    assert sum(r.endswith(",guided") for r in rows) == len(found)


@pytest.fixture(scope="module")
def scene_run(survey: Survey, tmp_path_factory: pytest.TempPathFactory) -> tuple[Result, Path]:
    """`scale` given the model's images: each laser image searched again against its scene
    reference (saved), the guided search off to see the detector's own spots."""
    return _run(survey, tmp_path_factory.mktemp("underwater_survey_scene") / "run",
                "--images", str(survey.images_dir), "--save-scene-references",
                "--no-guided-spots")


def _within(report: dict[str, Any], truth: dict[str, Any], px: float) -> list[float]:
    true_xy = {(im["name"], s["laser"]): (s["x"], s["y"])
               for im in truth["laser_images"] for s in im["spots"] if s.get("x") is not None}
    errors = [math.dist((s["x"], s["y"]), true_xy[(im["name"], s["laser"])])
              for im in report["images"] for s in im["spots"]
              if (im["name"], s["laser"]) in true_xy]
    return [e for e in errors if e <= px]


def test_without_model_images_no_scene_reference_and_the_report_says_why(
        scale_run: tuple[Result, Path]) -> None:
    for im in _report(scale_run)["images"]:
        assert im["scene_reference"]["used"] is False
        assert "give --images" in im["scene_reference"]["reason"]
    assert not (scale_run[1] / "scene_references").exists()


def test_scene_references_find_the_spots_the_photographs_alone_miss(
        survey: Survey, scene_run: tuple[Result, Path], alone_run: tuple[Result, Path]) -> None:
    truth = json.loads(survey.truth_path.read_text())
    report, alone = _report(scene_run), _report(alone_run)
    summary = _spot_summary(report, truth)
    model_images = {p.name for p in survey.images_dir.glob("*.jpg")}
    for im in report["images"]:
        use = im["scene_reference"]
        assert use["used"] and use["reason"] is None, summary
        assert len(use["views"]) == 3 and set(use["views"]) <= model_images
        assert use["coverage"] > 0.7 and use["kept_share"] > 0.5 and use["shift_median_px"] < 1
        assert use["spots_alone"] == len(next(a for a in alone["images"]
                                              if a["name"] == im["name"])["spots"])
        saved = scene_run[1] / use["file"]
        assert saved.is_file() and use["file"] == f"scene_references/{Path(im['name']).stem}.png"
    found, before = _within(report, truth, 1.5), _within(alone, truth, 1.5)
    assert len(found) > len(before), summary
    assert len(found) >= 15, summary
    err = (report["scale"]["value"] - survey.true_scale) / survey.true_scale
    assert abs(err) < 0.003, f"{err:+.3%}\n{summary}"
    assert "scene" in report["timings_s"] and "scene" not in alone["timings_s"]


def test_detect_reads_the_saved_references(survey: Survey, scene_run: tuple[Result, Path],
                                           tmp_path: Path) -> None:
    report = _report(scene_run)
    out = tmp_path / "detect"
    args = ["detect", *(str(p) for p in sorted(survey.laser_images_dir.glob("*.jpg"))),
            "--rig", str(survey.rig_path), "--model", str(survey.model_dir),
            "--scene", str(scene_run[1] / "scene_references"), "--out", str(out), "--quiet"]
    result = CliRunner().invoke(main, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    detections = json.loads((out / "detections.json").read_text())
    by_name = {im["name"]: im for im in report["images"]}
    for im in detections["images"]:
        assert im["scene_reference"].endswith(f"{Path(im['name']).stem}.png")
        # the saved reference holds 1/257 of a level: the same spots, within 0.01 px
        want = {s["laser"]: (s["x"], s["y"]) for s in by_name[im["name"]]["spots"]}
        got = {s["laser"]: (s["x"], s["y"]) for s in im["spots"]}
        assert got.keys() == want.keys()
        assert all(math.dist(got[k], want[k]) < 0.01 for k in got)


def test_no_scene_reference_searches_the_photographs_alone(
        survey: Survey, alone_run: tuple[Result, Path], tmp_path: Path) -> None:
    off = _report(_run(survey, tmp_path / "run", "--images", str(survey.images_dir),
                       "--no-guided-spots", "--no-scene-reference"))
    alone = _report(alone_run)
    assert all(im["scene_reference"] is None for im in off["images"])
    assert [im["spots"] for im in off["images"]] == [im["spots"] for im in alone["images"]]
    assert "scene" not in off["timings_s"]
