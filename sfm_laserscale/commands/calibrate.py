"""``calibrate``: the laser rig from images of a chessboard or ChArUco target at several
distances (:mod:`sfm_laserscale.calibration`). Writes, atomically (a staged folder replaces
``DIR`` only when everything is written)::

    DIR/rig.toml                  the calibrated rig (docs/RIG.md)
    DIR/calibration_report.json   camera, lasers, pairs, per-image residuals
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from sfm_laserscale.calibration.target import CalibrateOptions, CalibrateResult, calibrate_images
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.images import camera_for_size, expand_image_paths, read_rgb
from sfm_laserscale.io.models import load_model
from sfm_laserscale.io.outputs import check_output_dir, staged_output_dir
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import rig_to_toml

__all__ = ["CalibrateInputs", "CalibrateOptions", "CalibrateResult", "run"]


@dataclass(frozen=True)
class CalibrateInputs:
    """Target images (files/folders) and where the intrinsics come from."""

    images: tuple[Path, ...]
    model: Path | None = None  # COLMAP folder / OpenMVG sfm_data.json; None = self-calibrate


def _camera_from_model(model_path: Path, width: int, height: int) -> Camera:
    cam = camera_for_size(load_model(model_path), width, height)
    if cam is None:
        raise InputError(f"no camera of the model is {width}x{height} px (the target images' "
                         "size); use --self-calibrate", model_path)
    return cam


def run(inputs: CalibrateInputs, out: Path | None, options: CalibrateOptions,
        overwrite: bool = False) -> CalibrateResult:
    """Read the target images, calibrate, write rig.toml and calibration_report.json (``out``
    None: nothing written, the Python API)."""
    if out is not None:
        check_output_dir(out, overwrite)
    if not inputs.images:
        raise InputError("no target images given")
    files = expand_image_paths(list(inputs.images))
    images = {f.name: read_rgb(f) for f in files}
    if len(images) != len(files):
        raise InputError("several target images share a file name")
    sizes = {im.shape[:2] for im in images.values()}
    if len(sizes) != 1:
        raise InputError(f"target images have different sizes: {sorted(sizes)}")
    h, w = next(iter(sizes))
    camera = None if inputs.model is None else _camera_from_model(inputs.model, w, h)
    result = calibrate_images(images, camera, options)
    if out is None:
        return result
    with staged_output_dir(out, overwrite) as tmp:
        (tmp / "rig.toml").write_text(rig_to_toml(result.calibration.rig), encoding="utf-8")
        (tmp / "calibration_report.json").write_text(json.dumps(result.report, indent=2),
                                                     encoding="utf-8")
    return result
