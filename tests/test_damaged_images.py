"""A damaged laser image (a truncated JPEG) is named as damaged in the report's reason and on
the terminal, not reported as "only 0 matches" after libjpeg's warning (issue #20)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sfm_laserscale.cli import main
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.images import damage, read_rgb


def _jpeg(src: Path, dst: Path, keep: float = 1.0) -> Path:
    """``src`` re-encoded as JPEG at ``dst``, its bytes cut to the first ``keep`` share."""
    ok, buf = cv2.imencode(".jpg", cv2.imread(str(src)), [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    data = buf.tobytes()
    dst.write_bytes(data[: int(len(data) * keep)])
    return dst


def test_truncated_jpeg_is_damaged_whole_one_is_not(small_dataset: Any, tmp_path: Path) -> None:
    src = sorted(small_dataset.laser_images_dir.glob("*.png"))[0]
    whole = _jpeg(src, tmp_path / "whole.jpg")
    cut = _jpeg(src, tmp_path / "cut.jpg", keep=0.6)
    assert damage(whole) is None and damage(src) is None
    why = damage(cut)
    assert why is not None and why.startswith("damaged image") and "truncated" in why
    # OpenCV alone decodes the cut file (its lower part grey): the check is what tells
    assert cv2.imread(str(cut)) is not None
    with pytest.raises(InputError, match="damaged image"):
        read_rgb(cut)
    assert read_rgb(cut, check=False).shape == read_rgb(whole).shape
    assert np.array_equal(read_rgb(whole), read_rgb(whole, check=False))


def test_scale_names_the_damaged_laser_image(small_dataset: Any, tmp_path: Path) -> None:
    good = sorted(small_dataset.laser_images_dir.glob("*.png"))[:2]
    cut = _jpeg(good[0], tmp_path / "damaged_copy.jpg", keep=0.5)
    out = tmp_path / "o"
    args = ["scale", "--model", str(small_dataset.model_dir), "--mesh",
            str(small_dataset.mesh_path), "--rig", str(small_dataset.rig_path), "--database",
            str(small_dataset.database_path), "--out", str(out), "--method", "pcm",
            "--workers", "0", "--laser-images", *map(str, good), str(cut)]
    result = CliRunner().invoke(main, args, catch_exceptions=False)
    assert result.exit_code == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    images = {im["name"]: im for im in report["images"]}
    reason = images["damaged_copy.jpg"]["reason"]
    assert reason.startswith("damaged image") and "truncated" in reason
    assert "matches" not in reason
    assert all(images[p.name]["reason"] is None for p in good)
    warning = [ln for ln in result.stderr.splitlines() if "damaged_copy.jpg" in ln]
    assert warning and "damaged image" in warning[0]


def test_detect_names_the_damaged_image(small_dataset: Any, tmp_path: Path) -> None:
    good = sorted(small_dataset.laser_images_dir.glob("*.png"))[0]
    cut = _jpeg(good, tmp_path / "cut.jpg", keep=0.5)
    out = tmp_path / "d"
    result = CliRunner().invoke(main, ["detect", str(good), str(cut), "--rig",
                                       str(small_dataset.rig_path), "--model",
                                       str(small_dataset.model_dir), "--out", str(out)],
                                catch_exceptions=False)
    assert result.exit_code == 0, result.stderr
    record = {im["name"]: im for im in json.loads((out / "detections.json").read_text())["images"]}
    assert record["cut.jpg"]["readable"] is False
    assert "truncated" in record["cut.jpg"]["reason"]
    assert record[good.name]["spots"]
    assert "cut.jpg" in result.stderr and "damaged image" in result.stderr
