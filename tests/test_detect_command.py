"""The ``detect`` command: outputs, round trip into ``scale --spots``, exit codes, and a small
version of scripts/bench_detection.py."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from script_loader import load_script

from sfm_laserscale.cli import main
from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, DetectionResult, detect_spots
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.spots_csv import read_spots_csv
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import rig_from_dict, rig_to_toml
from sfm_laserscale.synthetic.spots import paint_spot, to_uint8

CAM = Camera(1, "PINHOLE", 640, 480, np.array([560.0, 560.0, 320.0, 240.0]))
CAM_TEXT = "PINHOLE 640 480 560 560 320 240"
BEAMS = {"L1": ([0.15, 0.0, 0.0], [0.02, 0.01, 1.0]), "L2": ([-0.15, 0.0, 0.0], [0.0, -0.02, 1.0])}


def _rig_file(tmp: Path) -> Path:
    rig = rig_from_dict({"laser": [{"name": n, "origin": o, "direction": d, "color": "red"}
                                   for n, (o, d) in BEAMS.items()]})
    path = tmp / "rig.toml"
    path.write_text(rig_to_toml(rig), encoding="utf-8")
    return path


def _images(tmp: Path, n: int, spots: bool = True) -> dict[str, dict[str, np.ndarray]]:
    """n PNG images with one spot per beam (ranges 1.5-4 m); returns the true centres."""
    rng = np.random.default_rng(0)
    truth: dict[str, dict[str, np.ndarray]] = {}
    for k in range(n):
        img = np.full((CAM.height, CAM.width, 3), (0.1, 0.32, 0.36), np.float32)
        img *= rng.uniform(0.8, 1.2, (1, CAM.width, 1)).astype(np.float32)
        t = {}
        for name, (o, d) in BEAMS.items():
            d_u = np.array(d) / np.linalg.norm(d)
            xy = CAM.project(np.array(o) + rng.uniform(1.5, 4.0) * d_u)[0]
            if spots:
                paint_spot(img, (float(xy[0]), float(xy[1])), "red", sigma_px=1.8, peak=3.0)
            t[name] = xy
        img += rng.normal(0, 0.01, img.shape).astype(np.float32)
        name = f"img{k:02d}.png"
        cv2.imwrite(str(tmp / name), to_uint8(img, gamma=2.2)[:, :, ::-1])
        truth[name] = t
    return truth


def test_detect_writes_spots_csv_json_overlays_and_round_trips(tmp_path: Path) -> None:
    truth = _images(tmp_path, 3)
    rig = _rig_file(tmp_path)
    out = tmp_path / "out"
    args = ["detect", *[str(tmp_path / n) for n in truth], "--rig", str(rig),
            "--camera", CAM_TEXT, "--out", str(out)]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "6 spots in 3 of 3 images" in res.output
    spots = read_spots_csv(out / "spots.csv", list(truth), ["L1", "L2"])
    assert set(spots) == set(truth)
    for name, lst in spots.items():
        for s in lst:
            assert math.hypot(s.x - truth[name][s.laser][0], s.y - truth[name][s.laser][1]) < 0.3
            assert s.source == "detected" and 0 < s.score <= 1
    record = json.loads((out / "detections.json").read_text())
    assert [im["name"] for im in record["images"]] == list(truth)
    assert all(im["missing"] == {} and im["num_candidates"] >= 2 for im in record["images"])
    # two clean spots per image, each taken on its own evidence (the rule that took it)
    assert [s["taken_by"] for im in record["images"] for s in im["spots"]] == [
        "own evidence"] * 6
    assert record["learned_beam_lines"] is None  # every laser calibrated
    for name in truth:
        overlay = cv2.imread(str(out / "overlays" / (Path(name).stem + ".jpg")))
        assert overlay is not None and overlay.shape[1] >= 1200
    # hand edit: move one spot, delete another; scale --spots reads it back as given
    lines = (out / "spots.csv").read_text().splitlines()
    first = lines[1].split(",")
    first[2], first[6] = "100.25", "manual"
    edited = tmp_path / "edited.csv"
    edited.write_text("\n".join([lines[0], ",".join(first), *lines[3:]]) + "\n")
    back = read_spots_csv(edited, list(truth), ["L1", "L2"])
    assert back[first[0]][0].x == 100.25 and back[first[0]][0].source == "manual"
    assert sum(len(v) for v in back.values()) == 5
    # an existing output folder is refused without --overwrite
    again = CliRunner().invoke(main, args)
    assert again.exit_code == 2 and "not empty" in again.output
    assert CliRunner().invoke(main, [*args, "--overwrite"]).exit_code == 0


def test_no_spot_anywhere_exits_1_and_reports_reasons(tmp_path: Path) -> None:
    truth = _images(tmp_path, 2, spots=False)
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["detect", str(tmp_path), "--rig", str(_rig_file(tmp_path)),
                                    "--camera", CAM_TEXT, "--out", str(out)])
    assert res.exit_code == 1, res.output
    record = json.loads((out / "detections.json").read_text())
    assert len(record["images"]) == len(truth)
    assert all(set(im["missing"]) == {"L1", "L2"} for im in record["images"])


@pytest.mark.parametrize("extra, message", [
    (["--camera", "PINHOLE 640 480 560"], "needs"),
    (["--camera", "NOPE 640 480 1 2 3"], "MODEL W H"),
    (["--camera", "PINHOLE 800 600 560 560 400 300"], "does not match"),
    ([], "exactly one of --model"),
])
def test_bad_input_exits_2(tmp_path: Path, extra: list[str], message: str) -> None:
    _images(tmp_path, 1)
    res = CliRunner().invoke(main, ["detect", str(tmp_path / "img00.png"), "--rig",
                                    str(_rig_file(tmp_path)), "--out", str(tmp_path / "o"),
                                    *extra])
    assert res.exit_code == 2, res.output
    assert message in res.output
    assert not (tmp_path / "o").exists()


def test_missing_image_exits_2(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["detect", str(tmp_path / "nope.jpg"), "--rig",
                                    str(_rig_file(tmp_path)), "--camera", CAM_TEXT,
                                    "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "not found" in res.output


def test_parse_camera() -> None:
    cam = parse_camera("SIMPLE_RADIAL 1920 1080 1500 960 540 -0.1")
    assert (cam.model, cam.width, cam.height) == ("SIMPLE_RADIAL", 1920, 1080)
    np.testing.assert_allclose(cam.params, [1500, 960, 540, -0.1])
    with pytest.raises(InputError):
        parse_camera("PINHOLE 0 1080 1 1 1 1")


def _bench() -> ModuleType:
    return load_script("bench_detection")


def test_small_benchmark_meets_targets() -> None:
    """A few images of eight conditions (the full run: docs/DETECTION.md)."""
    bench = _bench()
    wanted = ("clean red", "motion blur", "distractors", "missing", "camera in beam plane",
              "very faint", "overlapping halos", "faint spots on textured seafloor")
    conds = tuple(c for c in bench.CONDITIONS if any(w in c.name for w in wanted))
    assert len(conds) == len(wanted)
    rows = bench.run_benchmark(3, seed=7, conditions=conds)
    for cond in conds:
        r = rows[cond.name]
        # per condition loosely (12 spots each; seed 7 loses 2 distractor-condition spots lying
        # on the edge of a saturated red organism, see docs/DETECTION.md), pooled strictly
        assert r["detection_rate"] >= 0.8 and r["false_rate"] == 0.0, (cond.name, r)
        assert r["rms_px"] < (0.5 if cond.blurred else 0.2), (cond.name, r)
    # pooled over the seven flat-water conditions (the seafloor one, per condition only: seed 7
    # loses 1 of its 12 spots, a white-clipped core on a bright pale pebble rejected as white)
    flat = [r for name, r in rows.items() if "seafloor" not in name]
    expected = sum(r["expected"] for r in flat)
    found = sum(r["detection_rate"] * r["expected"] for r in flat)
    assert found / expected >= 0.97, found / expected


def _valid(result: DetectionResult) -> int:
    """Candidates that would be spots: scoring at least the detector's min_score."""
    return sum(c.score >= DetectionOptions().min_score for c in result.candidates)


def test_no_false_spots_on_laser_free_textured_seafloor() -> None:
    """Laser-free images of the benchmark's seafloor (the demo texture: pebbles, brown patches,
    red organisms; lit through water), 4 random calibrated red rigs per image, 3 images: at
    most half a false spot per image (measured: 6 in 12; 0 with the clutter gate at 5×, which
    lost most small spots in green water: docs/DETECTION.md). Searching the whole image (an
    uncalibrated pair), the clutter gate keeps fewer would-be spots than without it (so this
    test can fail)."""
    bench = _bench()
    cond = next(c for c in bench.CONDITIONS if not c.lasers_on)
    pair = rig_from_dict({"laser": [{"name": "U1", "color": "red"}, {"name": "U2", "color": "red"}],
                          "pair": [{"lasers": ["U1", "U2"], "separation": 0.2}]})
    rng = np.random.default_rng(11)
    valid = valid_without = false = 0
    for _ in range(3):
        img, truth = bench.make_image(cond, bench.calibrated_rig(rng, "red"), rng)
        assert truth == {}
        for _ in range(4):
            false += len(detect_spots(img, bench.CAMERA, bench.calibrated_rig(rng, "red")).spots)
        valid += _valid(detect_spots(img, bench.CAMERA, pair))  # whole image searched
        valid_without += _valid(detect_spots(img, bench.CAMERA, pair,
                                             DetectionOptions(min_clutter_ratio=0.0)))
    # red organisms lying in a red laser's band are laser-coloured compact blobs of the size of
    # a spot: only the clutter gate tells them apart (docs/DETECTION.md: its trade-off)
    assert false <= 6, false
    assert valid < valid_without, (valid, valid_without)
