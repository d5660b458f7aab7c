"""How accurate a spot centre can be on the physical benchmark's photographs, with the scene
known exactly.

Usage::

    python scripts/bench_centre_floor.py [--per-condition 20] [--size 1920x1080]
        [--conditions red_clean,faint_far,...] [--seed 0] [--workers 2] [--markdown]

Every frame of ``sfm_laserscale.synthetic.underwater`` (the same generators as
``bench_detection_physical.py --sizes WxH``: seed, condition index, 0, image index) is also
captured without the lasers, with the same noise draws and without JPEG
(``render_frame(..., laser_free=True, laser_free_jpeg=False)``). The frame minus that capture,
decoded with the sRGB curve and its channels summed, is the lasers' light with the camera's
demosaicing, sharpening, colour processing and the frame's own JPEG 4:2:0, the light's shot
noise, and no scene: what a detector would have to work with if it knew the scene exactly.

Two estimators are started at the true centre and run on it: a Gaussian-windowed centroid
(window σ 1.5 σ_spot + 0.5 px, σ_spot the footprint's, the PSF's and any motion or defocus
blur's in quadrature, iterated to its fixed point) and a least-squares fit of a
pixel-integrated 2D Gaussian plus a constant. Their errors are a floor that a detector, which
must also tell the light from the scene, is not expected to beat; they are no proof of a bound
(a better model of the camera's processing could do better). Spots within 12 px of the border
are left out. No code of ``sfm_laserscale.detection`` is used.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.special import erf

from sfm_laserscale.synthetic.underwater import CONDITIONS, Frame, render_frame
from sfm_laserscale.synthetic.underwater.sensor import srgb_decode

F64 = NDArray[np.float64]
#: spots nearer the border than this (px) are left out
BORDER_PX = 12


@dataclass(frozen=True)
class Job:
    """One frame: condition, size (width, height), seed, image index."""

    condition: str
    size: tuple[int, int]
    seed: int
    index: int


def windowed_centroid(light: F64, xy: tuple[float, float], window_px: float) -> tuple[float, float]:
    """Fixed point of the Gaussian-windowed centroid of ``light`` (H, W; COLMAP pixel centres
    at +0.5) started at ``xy``."""
    gy, gx = np.mgrid[0:light.shape[0], 0:light.shape[1]].astype(np.float64) + 0.5
    w_light = np.clip(light, 0.0, None)
    x, y = xy
    for _ in range(200):
        w = np.exp(-0.5 * ((gx - x) ** 2 + (gy - y) ** 2) / window_px ** 2) * w_light
        total = float(w.sum())
        if total <= 0.0:
            return math.nan, math.nan
        nx, ny = float((w * gx).sum()) / total, float((w * gy).sum()) / total
        if math.hypot(nx - x, ny - y) < 1e-7:
            break
        x, y = x + 0.7 * (nx - x), y + 0.7 * (ny - y)
    return x, y


def gaussian_fit(light: F64, xy: tuple[float, float], sigma_px: float) -> tuple[float, float]:
    """Centre of a least-squares pixel-integrated 2D Gaussian plus a constant fitted to
    ``light`` (H, W), started at ``xy`` with width ``sigma_px``."""
    gy, gx = np.mgrid[0:light.shape[0], 0:light.shape[1]].astype(np.float64) + 0.5

    def residual(p: F64) -> F64:
        amp, cx, cy, sig, base = p
        k = 1.0 / (math.sqrt(2.0) * max(abs(sig), 1e-3))
        ix = 0.5 * (erf((gx + 0.5 - cx) * k) - erf((gx - 0.5 - cx) * k))
        iy = 0.5 * (erf((gy + 0.5 - cy) * k) - erf((gy - 0.5 - cy) * k))
        return np.asarray((amp * ix * iy + base - light).ravel())

    start = np.array([float(light.max()) * 2.0 * math.pi * sigma_px ** 2, xy[0], xy[1],
                      sigma_px, 0.0])
    fit = least_squares(residual, start)
    return float(fit.x[1]), float(fit.x[2])


def spot_errors(light: F64, truth: tuple[float, float], sigma_px: float
                ) -> tuple[float, float] | None:
    """(centroid error, fit error) px of one spot on the laser-only ``light`` (H, W), or None
    near the border."""
    height, width = light.shape
    x0, y0 = int(truth[0]), int(truth[1])
    reach = max(10, math.ceil(6.0 * sigma_px))
    margin = max(reach, BORDER_PX)
    if not (margin <= x0 < width - margin and margin <= y0 < height - margin):
        return None
    crop = light[y0 - reach:y0 + reach + 1, x0 - reach:x0 + reach + 1]
    local = (truth[0] - (x0 - reach), truth[1] - (y0 - reach))
    cx, cy = windowed_centroid(crop, local, 1.5 * sigma_px + 0.5)
    half = max(4, math.ceil(4.0 * sigma_px))
    inner = crop[reach - half:reach + half + 1, reach - half:reach + half + 1]
    fx, fy = gaussian_fit(inner, (local[0] - (reach - half), local[1] - (reach - half)), sigma_px)
    return (math.hypot(cx - local[0], cy - local[1]),
            math.hypot(fx + (reach - half) - local[0], fy + (reach - half) - local[1]))


def image_sigma_px(meta: dict[str, Any], footprint_sigma_px: float) -> float:
    """The spot's σ (px) in the image: its footprint's, the lens PSF's, a motion blur's
    (a segment of length L: L/√12) and a defocus disc's (radius R: R/2), in quadrature; at
    least 0.5 px."""
    var = (footprint_sigma_px ** 2 + float(meta.get("psf_sigma_px", 0.0)) ** 2
           + float(meta.get("motion_px", 0.0)) ** 2 / 12.0
           + (float(meta.get("defocus_radius_px", 0.0)) / 2.0) ** 2)
    return max(math.sqrt(var), 0.5)


def render_job(job: Job, laser_free_jpeg: bool = False) -> tuple[Frame, NDArray[np.uint8]]:
    """One job's frame (the benchmark's generator state: seed, condition index, 0, image
    index) and its capture without the lasers (same noise draws; JPEG'd like the frame only
    with ``laser_free_jpeg``)."""
    ci = list(CONDITIONS).index(job.condition)
    frame = render_frame(job.condition, job.size[0], job.size[1],
                         np.random.default_rng([job.seed, ci, 0, job.index]),
                         laser_free=True, laser_free_jpeg=laser_free_jpeg)
    if frame.image_laser_free_rgb is None:
        raise RuntimeError("the generator gave no laser-free capture")
    return frame, frame.image_laser_free_rgb


def run_job(job: Job) -> list[tuple[float, float]]:
    """Both estimators' errors (px) for every spot of one frame."""
    frame, dark = render_job(job)
    light = (srgb_decode(frame.image_rgb / 255.0) - srgb_decode(dark / 255.0)).sum(axis=2)
    out = []
    for name, truth in frame.truth.items():
        if truth is None:
            continue
        sigma = image_sigma_px(frame.meta, float(frame.meta["spots"][name]["sigma_major_px"]))
        errs = spot_errors(light, (float(truth[0]), float(truth[1])), sigma)
        if errs is not None:
            out.append(errs)
    return out


def summary_rows(jobs: Sequence[Job], results: Sequence[list[tuple[float, float]]]
                 ) -> list[tuple[str, int, float, float, float, float]]:
    """Per condition: (condition, spots, centroid median, p95, fit median, p95) px."""
    rows = []
    for cond in dict.fromkeys(j.condition for j in jobs):
        errs = np.array([e for j, r in zip(jobs, results, strict=True) if j.condition == cond
                         for e in r]).reshape(-1, 2)
        if len(errs) == 0:
            continue
        med, p95 = np.median(errs, axis=0), np.percentile(errs, 95, axis=0)
        rows.append((cond, len(errs), float(med[0]), float(p95[0]), float(med[1]),
                     float(p95[1])))
    return rows


def parse_args(argv: Sequence[str] | None, description: str, records: bool = False
               ) -> argparse.Namespace:
    """The options of a benchmark over the physical generator's conditions (``records``: and
    ``--json``, where a script writes its per-spot records)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--per-condition", type=int, default=20)
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--conditions", default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--markdown", action="store_true")
    if records:
        ap.add_argument("--json", default=None, help="also write the per-spot records here")
    return ap.parse_args(argv)


def make_jobs(args: argparse.Namespace) -> list[Job]:
    """The frames :func:`parse_args`'s options ask for (every condition with lasers by
    default); ValueError names unknown conditions."""
    width, height = (int(v) for v in args.size.lower().split("x"))
    conds = (args.conditions.split(",") if args.conditions else
             [c for c in CONDITIONS if c != "no_lasers"])
    unknown = [c for c in conds if c not in CONDITIONS]
    if unknown:
        raise ValueError(f"unknown conditions: {', '.join(unknown)}")
    return [Job(c, (width, height), args.seed, i) for c in conds
            for i in range(args.per_condition)]


def run_all(argv: Sequence[str] | None, description: str, worker: Callable[[Job], Any],
            records: bool = False) -> tuple[argparse.Namespace, list[Job], list[Any]] | None:
    """The options (``records``: with ``--json``), the jobs and ``worker``'s result for each
    (in ``--workers`` processes); None, with the error printed, when the options name unknown
    conditions."""
    args = parse_args(argv, description, records)
    try:
        jobs = make_jobs(args)
    except ValueError as err:
        print(err, file=sys.stderr)
        return None
    with multiprocessing.Pool(max(1, args.workers)) as pool:
        return args, jobs, pool.map(worker, jobs, chunksize=1)


def main(argv: Sequence[str] | None = None) -> int:
    ran = run_all(argv, __doc__.split("\n\n")[0], run_job)
    if ran is None:
        return 2
    args, jobs, results = ran
    rows = summary_rows(jobs, results)
    if args.markdown:
        print("| condition | spots | centroid median / p95 px | Gaussian fit median / p95 px |")
        print("|---|---|---|---|")
    for cond, n, cm, cp, fm, fp in rows:
        if args.markdown:
            print(f"| {cond} | {n} | {cm:.3f} / {cp:.3f} | {fm:.3f} / {fp:.3f} |")
        else:
            print(f"{cond:18s} {n:4d} centroid {cm:.3f} / {cp:.3f}  fit {fm:.3f} / {fp:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
