"""What the scene under a spot costs each signal the detector centres it on, on the physical
benchmark's photographs.

Usage::

    python scripts/bench_texture_cost.py [--per-condition 20] [--size 1920x1080]
        [--conditions green_water,red_clean,...] [--seed 0] [--workers 2] [--markdown]

Every frame is rendered as in ``bench_centre_floor.py`` (the generators of
``bench_detection_physical.py --sizes WxH``), with its laser-free capture: the same noise
draws, without JPEG. The detector runs on the frame with its default options. Every spot it
reports within MATCH_PX of its truth is refined again from the detector's centre, at its
candidate's half-maximum radius, with ``refine.refine_centroid`` on each signal the detector
can centre it on (``refine.spot_patch``): the light freed of the texture's colour, and luma
for a luma-dominant laser:

- *with the scene*: the signal as the detector sees it;
- *without the scene*: the same signal minus the same signal of the laser-free capture, read
  with the same colour weights (the texture colour of the frame's ring), so what is left is
  the lasers' light through that signal.

Per condition and signal, the medians and p95 of the two errors tell how much of a signal's
error is the scene under the spot (texture, clutter, the lamps' shading) and how much is the
rest (noise, demosaicing, 4:2:0 chroma, the camera's processing, the window). The detector's
own error on the same spots is given beside them. Numbers: docs/DETECTION.md.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from bench_centre_floor import Job, render_job, run_all
from numpy.typing import NDArray

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, detect_spots
from sfm_laserscale.detection.inputs import group_rgb
from sfm_laserscale.detection.options import Candidate
from sfm_laserscale.detection.refine import (
    SpotGuess,
    luma_dominant,
    refine_centroid,
    spot_patch,
)
from sfm_laserscale.detection.response import Planes, crop_channels, make_planes
from sfm_laserscale.detection.shape import expected_support_px
from sfm_laserscale.rig import Rig, rig_from_dict
from sfm_laserscale.synthetic.underwater import Frame

#: a reported spot this close to its truth (px) is measured (the benchmark's match distance)
MATCH_PX = 1.5
#: half-size (px) of the crop a spot is measured in
CROP_PX = 40
SIGNALS = ("light", "luma")


@dataclass(frozen=True)
class SpotCost:
    """One spot's errors (px): the detector's, and per signal (with, without the scene)."""

    detector_px: float
    signals: dict[str, tuple[float, float]]


def _planes(image_rgb: NDArray[np.uint8], roi: tuple[int, int, int, int], color: str,
            laser_rgb: tuple[float, float, float], options: DetectionOptions) -> Planes:
    """The detection planes of one laser colour on a crop."""
    return make_planes(crop_channels(image_rgb, roi, options.input_gamma), color, options,
                       float(CROP_PX) / 4.0, laser_rgb)


def signal_errors(planes: Planes, dark: Planes, guess: SpotGuess,
                  corner: tuple[int, int], truth: tuple[float, float], signal: str
                  ) -> tuple[float, float] | None:
    """(error with the scene, error without it) px of one spot's centroid on one signal, or
    None when the signal cannot be read there."""
    seen = spot_patch(planes, guess, guess.patch_support, signal=signal)
    if seen is None:
        return None
    scene = spot_patch(dark, guess, guess.patch_support, signal=signal, texture=seen.texture)
    if scene is None:
        return None
    light = replace(seen, signal=seen.signal - scene.signal)
    window = max(1.0, guess.radius_px)
    local = (truth[0] - corner[0], truth[1] - corner[1])
    errs = []
    for patch in (seen, light):
        x, y, _ = refine_centroid(patch, guess.x, guess.y, window)
        errs.append(math.hypot(x - local[0], y - local[1]) if math.isfinite(x) else math.inf)
    return errs[0], errs[1]


def spot_cost(frame: Frame, dark_rgb: NDArray[np.uint8], rig: Rig, cand: Candidate,
              xy: tuple[float, float], options: DetectionOptions) -> SpotCost | None:
    """The detector's error and each signal's errors for one reported spot (``dark_rgb``:
    the frame's capture without the lasers), or None near the border."""
    truth = frame.truth.get(cand.laser or "")
    if truth is None:
        return None
    height, width = frame.image_rgb.shape[:2]
    col, row = int(xy[0]), int(xy[1])
    if not (CROP_PX <= col < width - CROP_PX and CROP_PX <= row < height - CROP_PX):
        return None
    corner = (col - CROP_PX, row - CROP_PX)
    roi = (corner[0], corner[1], col + CROP_PX + 1, row + CROP_PX + 1)
    laser_rgb = group_rgb(rig, cand.color)
    planes = _planes(frame.image_rgb, roi, cand.color, laser_rgb, options)
    dark = _planes(dark_rgb, roi, cand.color, laser_rgb, options)
    bright = bool(planes.clipped_laser[CROP_PX - 2:CROP_PX + 3, CROP_PX - 2:CROP_PX + 3].any())
    guess = SpotGuess(xy[0] - corner[0], xy[1] - corner[1], cand.radius_px,
                      expected_support_px(cand.radius_px), bright)
    signals = SIGNALS if luma_dominant(np.asarray(laser_rgb)) else SIGNALS[:1]
    out = {s: e for s in signals
           if (e := signal_errors(planes, dark, guess, corner, truth, s)) is not None}
    return SpotCost(math.dist(xy, truth), out)


def run_job(job: Job) -> list[SpotCost]:
    """The costs of every spot the detector found in one frame."""
    frame, dark_rgb = render_job(job)
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    options = DetectionOptions()
    result = detect_spots(frame.image_rgb, parse_camera(frame.camera_spec), rig, options)
    chosen = {c.laser: c for c in result.candidates if c.laser}
    costs = []
    for spot in result.spots:
        truth, cand = frame.truth.get(spot.laser), chosen.get(spot.laser)
        if truth is None or cand is None or math.dist((spot.x, spot.y), truth) > MATCH_PX:
            continue
        cost = spot_cost(frame, dark_rgb, rig, cand, (spot.x, spot.y), options)
        if cost is not None:
            costs.append(cost)
    return costs


def _stats(values: list[float]) -> str:
    if not values:
        return "-"
    return f"{np.median(values):.3f} / {np.percentile(values, 95):.3f}"


def summary_rows(jobs: Sequence[Job], results: Sequence[list[SpotCost]]) -> list[list[str]]:
    """Per condition: condition, spots, detector's median / p95, then per signal (with the
    scene, without it) median / p95, px."""
    rows = []
    for cond in dict.fromkeys(j.condition for j in jobs):
        costs = [c for j, r in zip(jobs, results, strict=True) if j.condition == cond for c in r]
        row = [cond, str(len(costs)), _stats([c.detector_px for c in costs])]
        for s in SIGNALS:
            for k in (0, 1):
                row.append(_stats([c.signals[s][k] for c in costs if s in c.signals]))
        rows.append(row)
    return rows


HEADER = ("condition", "spots", "detector", "light, with the scene", "light, without",
          "luma, with the scene", "luma, without")


def main(argv: Sequence[str] | None = None) -> int:
    ran = run_all(argv, __doc__.split("\n\n")[0], run_job)
    if ran is None:
        return 2
    args, jobs, results = ran
    rows = summary_rows(jobs, results)
    if args.markdown:
        print("| " + " | ".join(HEADER) + " |")
        print("|" + "---|" * len(HEADER))
    for row in rows:
        print("| " + " | ".join(row) + " |" if args.markdown else "  ".join(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
