"""Laser spot detection benchmark on physically rendered underwater photographs.

Usage::

    python scripts/bench_detection_physical.py [--per-condition 20]
        [--sizes 1920x1080,4000x3000] [--conditions clipped_cores,green_water,...]
        [--seed 0 | --seed 2-5 | --seed 2,4] [--workers 2] [--out results.json] [--markdown]
        [--visibility] [--cache DIR] [--compare earlier.json]

Images come from the independent generator ``sfm_laserscale.synthetic.underwater`` (which
shares no code or parameter with the detector): per condition and size, ``--per-condition``
frames, each from its own ``numpy.random.Generator`` seeded with (seed, condition index, size
index, image index). Every frame is given to ``sfm_laserscale.detection.detect_spots`` with
its COLMAP camera (``commands.detect.parse_camera``) and its rig (``rig.rig_from_dict``: the true
beams plus a small calibration error) and default ``DetectionOptions()``.

Scoring: a true spot is FOUND when the detector assigns a spot to the right laser within
1.5 px of the truth; every other reported spot is FALSE (a spot of the right laser farther
than 1.5 px is both a miss and a false). Per condition x size: spots (true, visible), found
%, false % (false / reported), false per image, median / p95 / max error (px) of the found
spots, detection seconds per image, the misses (image index, laser, the detector's reason
from ``result.missing``) and the falses. Targets: found >= 99 %, false <= 0.5 %, median <=
0.15 px, p95 <= 0.5 px. Per size, how the stated σ holds the errors: of the found spots (all
and per wavelength), and of every reported spot of a laser in view (the found ones and those
reported beyond 1.5 px, which ``scale`` uses all the same), also per rule that took them
(``taken_by`` in the found and false records: the detector's ``Candidate.taken_by``). Each
miss records the detector's candidate at its truth (``at_truth``: the nearest within 1.5 px,
the test it failed), and a line per size counts the misses by it.

``--visibility`` also captures every frame without the lasers (same noise draws) and records,
for each missed spot, how much it changes the photograph (``visible_levels``: the largest
8-bit difference near the truth); a miss of >= 20 levels is a spot anyone sees.

``--seed`` takes one draw or several (``2-5``, ``2,4``): the summary pools them, and a pooled
line per draw follows. Rules are written on some draws and checked on others
(docs/DETECTION.md, "Held-out draws"). ``--cache DIR`` keeps every rendered frame in DIR (one
file per frame, under a folder named by a hash of the generator's source, so a changed
generator never reuses stale frames): a run that re-scores the same frames after a change to
the detector skips the rendering, about half of a run's time. After the run the folder is
pruned (:func:`prune_cache`): frames of an earlier generator go, then the least recently used
frames until it holds at most ``--cache-max-gb`` (40 GB by default, 0 for no limit; a draw of
340 frames at 1920 × 1080 takes about 2.3 GB, at 4000 × 3000 about 12 GB), the run's own frames
never. ``--compare earlier.json`` (an
``--out`` file of an earlier run of the same frames) prints, frame by frame, the spots found,
lost or moved and the false spots gained or dropped.

``--scene-reference SHIFT,BLUR,GAIN`` gives the detector a scene reference of every frame
(``detect_spots(..., scene_rgb=)``, docs/DETECTION.md "A scene reference"): the generator's
capture of the seafloor alone (``render_frame(..., scene_reference=True)``: no lasers, hot
spots or particles; its own noise) as a model image warped into the frame through the mesh
would show it (:func:`as_rendered`): shifted SHIFT px in a random direction (registration
and mesh error), blurred by a Gaussian of BLUR px (resampling, the texture's resolution) and
lit by a gain ramp of ±GAIN across the frame (lamps elsewhere). As in ``scale``, the
reference is then kept only where it fits the frame (``scene_fit.fit_reference``: cells whose
neighbourhood's residual texture is no smaller than the frame's, or shifted more than 1 px,
are dropped); ``--no-scene-fit`` gives it whole. ``--no-scene-scaling`` subtracts its texture
unscaled (``DetectionOptions.scene_gain_sigma_px=None``) instead of scaled to the frame's light.

``run_benchmark`` (and ``run_small``, a reduced set for tests) can be imported through
``tests/script_loader.py``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import json
import math
import multiprocessing
import os
import pickle
import re
import sys
import time
import tomllib
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

import sfm_laserscale.synthetic.underwater as underwater
from sfm_laserscale.synthetic.underwater import CONDITIONS, Frame, render_frame

MATCH_PX = 1.5
#: a spot that changes the photograph by this many 8-bit levels is plainly visible (the
#: scene's texture varies by 2-10 levels between neighbouring pixels)
VISIBLE_LEVELS = 20
TARGETS = {"found_pct": 99.0, "false_pct": 0.5, "median_px": 0.15, "p95_px": 0.5}
DEFAULT_SIZES = ((1920, 1080), (4000, 3000))


@dataclass(frozen=True)
class SceneReference:
    """How a scene reference rendered from the model differs from the seafloor it shows
    (:func:`as_rendered`): shift (px, random direction), Gaussian blur (px), gain ramp (±);
    ``fit``: kept only where it fits the frame (``scene_fit.fit_reference``, as ``scale``);
    ``scaled``: its texture scaled to the frame's light (``DetectionOptions.scene_gain_sigma_px``;
    ``gain`` is the ramp's, a property of the reference, not of the detector)."""

    shift_px: float = 0.5
    blur_px: float = 0.7
    gain: float = 0.1
    fit: bool = True
    scaled: bool = True


@dataclass(frozen=True)
class Job:
    """One image of the benchmark."""

    condition: str
    width: int
    height: int
    index: int
    seed: int
    condition_index: int
    size_index: int
    laser_free: bool = False  # also capture it without the lasers (visibility of misses)
    cache: str | None = None  # folder of rendered frames (:func:`cached_frame`)
    scene: SceneReference | None = None  # give the detector a scene reference (as_rendered)

    def rng(self) -> np.random.Generator:
        """The frame's own generator (reproducible, independent of the other frames)."""
        return np.random.default_rng([self.seed, self.condition_index, self.size_index,
                                      self.index])


def jobs_for(conditions: Sequence[str], sizes: Sequence[tuple[int, int]], per_condition: int,
             seed: int, laser_free: bool = False) -> list[Job]:
    """All images of a run of one draw (``seed``), condition-major."""
    names = list(CONDITIONS)
    return [Job(c, w, h, i, seed, names.index(c), si, laser_free)
            for c in conditions for si, (w, h) in enumerate(sizes) for i in range(per_condition)]


@functools.lru_cache(maxsize=1)
def generator_version() -> str:
    """A hash (12 hex digits) of the generator's source files: frames cached under another
    hash came from other code."""
    digest = hashlib.sha256()
    for path in sorted(Path(underwater.__file__).parent.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:12]


def cache_path(job: Job) -> Path:
    """Where ``job``'s rendered frame is kept under ``job.cache``."""
    if job.cache is None:
        raise ValueError("the job has no cache folder")
    name = (f"s{job.seed}_{job.condition}_{job.width}x{job.height}_z{job.size_index}"
            f"_{job.index:03d}{'_lf' if job.laser_free else ''}"
            f"{'_sc' if job.scene is not None else ''}.pkl")
    return Path(job.cache) / generator_version() / name


def cached_frame(job: Job) -> Frame:
    """``job``'s frame: rendered, or read back from ``job.cache`` where an earlier run kept it
    (pickle: the files are this benchmark's own, written below)."""
    path = None if job.cache is None else cache_path(job)
    if path is not None and path.exists():
        with path.open("rb") as f:
            cached: Frame = pickle.load(f)
        with contextlib.suppress(OSError):  # a read-only cache is read all the same
            os.utime(path)  # used now: the pruning keeps the recently used frames
        return cached
    frame = render_frame(job.condition, job.width, job.height, job.rng(), job.laser_free,
                         scene_reference=job.scene is not None)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(f".{multiprocessing.current_process().pid}.part")
        with partial.open("wb") as f:
            pickle.dump(frame, f, protocol=pickle.HIGHEST_PROTOCOL)
        partial.replace(path)  # whole files only, also when two runs share the folder
    return frame


def run_jobs(conditions: Sequence[str], sizes: Sequence[tuple[int, int]], per_condition: int,
             seeds: Sequence[int], laser_free: bool, cache: Path | None,
             scene: SceneReference | None = None) -> list[Job]:
    """All images of a run over the draws ``seeds``, each job carrying the cache folder and
    the scene reference's description."""
    return [replace(j, cache=None if cache is None else str(cache), scene=scene)
            for s in seeds for j in jobs_for(conditions, sizes, per_condition, s, laser_free)]


def as_rendered(scene_rgb: NDArray[np.uint8], how: SceneReference,
                rng: np.random.Generator) -> NDArray[np.float32]:
    """The seafloor's capture (H, W, 3 uint8) as a render from the model would give it:
    shifted ``how.shift_px`` in a direction drawn from ``rng`` (bilinear), blurred, and
    multiplied by a linear ramp from 1 - ``how.gain`` to 1 + ``how.gain`` across the frame
    in a drawn direction. Float 8-bit levels, as ``detect_spots(scene_rgb=)`` takes them."""
    height, width = scene_rgb.shape[:2]
    angle = rng.uniform(0.0, 2.0 * math.pi)
    shift = np.array([[1.0, 0.0, how.shift_px * math.cos(angle)],
                      [0.0, 1.0, how.shift_px * math.sin(angle)]], dtype=np.float32)
    out = cv2.warpAffine(scene_rgb.astype(np.float32), shift, (width, height),
                         flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    if how.blur_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), how.blur_px, borderType=cv2.BORDER_REFLECT)
    ramp_angle = rng.uniform(0.0, 2.0 * math.pi)
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    along = ((cols / width - 0.5) * math.cos(ramp_angle)
             + (rows / height - 0.5) * math.sin(ramp_angle))  # within ±sqrt(0.5)
    gain = 1.0 + how.gain * along / np.float32(math.sqrt(0.5))
    return (out * gain[..., None]).astype(np.float32)


def prune_cache(cache: Path, max_bytes: int, keep: Iterable[Path]) -> tuple[int, int]:
    """(files removed, bytes freed) from the frame cache ``cache``: every frame of another
    generator (never read again, :func:`generator_version`), then the least recently used of
    this generator's until the folder holds at most ``max_bytes`` (0: no limit); the frames in
    ``keep`` (the run's own) stay whatever the limit."""
    current = cache / generator_version()
    stats = {p: p.stat() for p in cache.glob("*/*.pkl") if p.is_file()}
    stale = [p for p in stats if p.parent != current]
    kept = {p.resolve() for p in keep}
    fresh = sorted((p for p in stats if p.parent == current), key=lambda p: stats[p].st_mtime)
    total = sum(stats[p].st_size for p in fresh)
    doomed = list(stale)
    for p in fresh:
        if max_bytes <= 0 or total <= max_bytes:
            break
        if p.resolve() not in kept:
            doomed.append(p)
            total -= stats[p].st_size
    for p in doomed:
        p.unlink()
    freed = sum(stats[p].st_size for p in doomed)
    for folder in {p.parent for p in stale}:
        if not any(folder.iterdir()):
            folder.rmdir()
    return len(doomed), freed


def score_frame(frame: Frame, result: Any) -> dict[str, Any]:
    """Found / missed / false spots of one detection result against the frame's truth."""
    by_laser: dict[str, list[Any]] = {}
    for spot in result.spots:
        by_laser.setdefault(spot.laser, []).append(spot)
    found: list[dict[str, Any]] = []
    misses: list[dict[str, Any]] = []
    falses: list[dict[str, Any]] = []
    truths = {k: v for k, v in frame.truth.items() if v is not None}
    for laser, spots in by_laser.items():
        truth = truths.get(laser)
        for spot in spots:
            err = math.hypot(spot.x - truth[0], spot.y - truth[1]) if truth else math.inf
            if truth is not None and err <= MATCH_PX and not any(
                    f["laser"] == laser for f in found):
                found.append({"laser": laser, "error_px": err, "dx": spot.x - truth[0],
                              "dy": spot.y - truth[1], "score": spot.score,
                              "sigma_px": spot.sigma_px, "taken_by": taken_by(result, spot)})
                continue
            near = min((math.hypot(spot.x - t[0], spot.y - t[1]) for t in truths.values()),
                       default=math.inf)
            false = {"laser": laser, "x": spot.x, "y": spot.y, "score": spot.score,
                     "nearest_truth_px": near,
                     "why": "laser off / no spot" if truth is None
                     else f"{err:.2f} px from its truth"}
            if truth is not None:  # its own laser's spot, off: for _reported_sigma_words
                false |= {"dx": spot.x - truth[0], "dy": spot.y - truth[1],
                          "sigma_px": spot.sigma_px, "taken_by": taken_by(result, spot)}
            falses.append(false)
    for laser, truth in truths.items():
        if any(f["laser"] == laser for f in found):
            continue
        reported = by_laser.get(laser)
        if reported:
            dist = min(math.hypot(s.x - truth[0], s.y - truth[1]) for s in reported)
            reason = f"reported {dist:.1f} px away"
        else:
            reason = str(result.missing.get(laser, "not reported"))
        visible = frame.meta.get("spots", {}).get(laser, {}).get("visible_levels")
        misses.append({"laser": laser, "reason": reason, "visible_levels": visible,
                       "at_truth": candidate_at(result, truth)})
    return {"truths": len(truths), "reported": len(result.spots), "found": found,
            "misses": misses, "falses": falses}


def taken_by(result: Any, spot: Any) -> str:
    """The rule that took a reported spot (its candidate's ``taken_by``), "" when none says."""
    return next((c.taken_by for c in getattr(result, "candidates", ())
                 if getattr(c, "laser", None) == spot.laser and getattr(c, "taken_by", "")), "")


def candidate_at(result: Any, truth: tuple[float, float]) -> dict[str, Any] | None:
    """The detector's candidate nearest a missed spot's truth, within MATCH_PX (None when
    there is none): how far, which response it came from, the test it failed (its reason's
    gist, :func:`candidate_test`), its score and its response in clutter levels."""
    near = [(math.hypot(c.x - truth[0], c.y - truth[1]), c)
            for c in getattr(result, "candidates", ())]
    if not near:
        return None
    dist, cand = min(near, key=lambda dc: dc[0])
    if dist > MATCH_PX:
        return None
    ratio = float(cand.clutter_ratio)
    return {"distance_px": dist, "source": cand.source, "test": candidate_test(cand.reason),
            "score": cand.score, "clutter_ratio": ratio if math.isfinite(ratio) else None}


def candidate_test(reason: str) -> str:
    """A candidate's reason up to its first detail, laser names as L#: "no stronger than the
    scene's own blobs (response 1.2 × …)" -> "no stronger than the scene's own blobs"."""
    head = re.split(r" \(|:", reason, maxsplit=1)[0]
    return re.sub(r"\bL\d+\b", "L#", head).strip()


def run_job(job: Job) -> dict[str, Any]:
    """Render, detect and score one image."""
    from sfm_laserscale.commands.detect import parse_camera
    from sfm_laserscale.detection import DetectionOptions, detect_spots
    from sfm_laserscale.rig import rig_from_dict
    from sfm_laserscale.scene_fit import fit_reference

    t0 = time.perf_counter()
    frame = cached_frame(job)
    t1 = time.perf_counter()
    camera = parse_camera(frame.camera_spec)
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    scene_rgb = None
    if job.scene is not None and frame.image_scene_rgb is not None:
        scene_rng = np.random.default_rng([job.seed, job.condition_index, job.size_index,
                                           job.index, 7])
        scene_rgb = as_rendered(frame.image_scene_rgb, job.scene, scene_rng)
    fit = None
    if scene_rgb is not None and job.scene is not None and job.scene.fit:
        fit = fit_reference(frame.image_rgb, scene_rgb)
        scene_rgb = fit.rgb
    options = DetectionOptions()
    if job.scene is not None and not job.scene.scaled:
        options = replace(options, scene_gain_sigma_px=None)
    result = detect_spots(frame.image_rgb, camera, rig, options, scene_rgb=scene_rgb)
    t2 = time.perf_counter()
    rec = score_frame(frame, result)
    rec.update({"seed": job.seed, "condition": job.condition,
                "size": f"{job.width}x{job.height}", "index": job.index,
                "render_s": t1 - t0, "detect_s": t2 - t1,
                "water": frame.meta["water"], "wavelength_nm": frame.meta["wavelength_nm"],
                "scene_fit": None if fit is None else {
                    "kept_share": fit.kept_share, "ratio_median": fit.ratio_median,
                    "shift_median_px": fit.shift_median_px},
                "spot_meta": {k: {m: v for m, v in d.items()
                                  if m in ("peak_over_white", "range_m", "incidence_deg",
                                           "sigma_major_px", "oracle_shift_px",
                                           "geometric_shift_px", "visible_levels")}
                              for k, d in frame.meta["spots"].items()}})
    return rec


def _percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def summarise(records: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (condition, size), in the order first seen."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for rec in records:
        groups.setdefault((rec["condition"], rec["size"]), []).append(rec)
    rows = []
    for (cond, size), recs in groups.items():
        recs.sort(key=lambda r: (r.get("seed", 0), r["index"]))
        errs = [f["error_px"] for r in recs for f in r["found"]]
        spots = sum(r["truths"] for r in recs)
        reported = sum(r["reported"] for r in recs)
        n_false = sum(len(r["falses"]) for r in recs)
        misses = [{"seed": r.get("seed", 0), "image": r["index"], **m}
                  for r in recs for m in r["misses"]]
        reasons = Counter(_reason_kind(m["reason"]) for m in misses)
        rows.append({
            "condition": cond, "size": size, "images": len(recs), "spots": spots,
            "found": len(errs), "found_pct": 100.0 * len(errs) / spots if spots else None,
            "reported": reported, "false": n_false,
            "false_pct": 100.0 * n_false / reported if reported else 0.0,
            "false_per_image": n_false / len(recs),
            "median_px": _percentile(errs, 50), "p95_px": _percentile(errs, 95),
            "max_px": max(errs) if errs else None,
            "within_2sigma_pct": _within(recs, 1.96), "within_3sigma_pct": _within(recs, 3.0),
            "detect_s_per_image": float(np.mean([r["detect_s"] for r in recs])),
            "render_s_per_image": float(np.mean([r["render_s"] for r in recs])),
            "miss_reasons": reasons.most_common(),
            "misses_visible": _visible_misses(misses),
            "misses": misses,
            "falses": [{"seed": r.get("seed", 0), "image": r["index"], **f}
                       for r in recs for f in r["falses"]],
        })
    return rows


def _visible_misses(misses: list[dict[str, Any]]) -> int | None:
    """How many misses change the photograph by VISIBLE_LEVELS or more at the spot (None
    without misses, or when the run had no laser-free captures)."""
    levels = [m.get("visible_levels") for m in misses]
    if not levels or any(v is None for v in levels):
        return None
    return sum(1 for v in levels if v is not None and v >= VISIBLE_LEVELS)


def visibility_line(rows: Sequence[dict[str, Any]]) -> str | None:
    """The pooled visibility of the misses, in words (None without laser-free captures)."""
    counted = [r for r in rows if r.get("misses_visible") is not None]
    if not counted:
        return None
    n = sum(len(r["misses"]) for r in counted)
    seen = sum(r["misses_visible"] for r in counted)
    return (f"{seen} of {n} missed spots change the photograph by ≥ {VISIBLE_LEVELS} levels "
            "(8-bit, any channel) at the spot against its laser-free capture")


def _within(recs: list[dict[str, Any]], k: float) -> float | None:
    """Share (%) of the found spots' per-axis errors within k of their stated sigma."""
    z = _z_and_errors(recs)[0]
    return 100.0 * float(np.mean(z <= k)) if z.size else None


def _per_axis_z(spots: Sequence[dict[str, Any]]) -> NDArray[np.float64]:
    """Per-axis |error| / stated σ of spot records carrying ``dx``, ``dy`` and ``sigma_px``."""
    return np.array([abs(f[k]) / f["sigma_px"] for f in spots for k in ("dx", "dy")],
                    dtype=np.float64)


def _coverage_words(z: NDArray[np.float64]) -> str:
    """The shares of per-axis errors within 1.96σ and 3σ, and the worst, in words."""
    return (f"within 1.96σ {100 * float(np.mean(z <= 1.96)):.1f} %, within 3σ "
            f"{100 * float(np.mean(z <= 3.0)):.1f} %, worst {float(z.max()):.1f}σ")


def _found_with_sigma(recs: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The found spots' records that state a σ."""
    return [f for r in recs for f in r["found"] if f.get("sigma_px")]


def _reported_with_sigma(recs: Sequence[dict[str, Any]]
                         ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(every reported spot of a laser in view, those of them reported beyond MATCH_PX): the
    found spots and a laser's own false spots, whose records carry ``sigma_px``."""
    off = [f for r in recs for f in r["falses"] if f.get("sigma_px")]
    return _found_with_sigma(recs) + off, off


def _z_and_errors(recs: Sequence[dict[str, Any]]
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64], list[float]]:
    """The found spots' per-axis |error| / σ, per-axis signed errors (px) and stated σ (px)."""
    found = _found_with_sigma(recs)
    errs = np.array([f[k] for f in found for k in ("dx", "dy")], dtype=np.float64)
    return _per_axis_z(found), errs, [f["sigma_px"] for f in found]


def _sigma_words(recs: Sequence[dict[str, Any]]) -> str:
    """How the found spots' stated σ holds their errors, in words."""
    z, errs, sigmas = _z_and_errors(recs)
    if not sigmas:
        return "no spot found"
    robust = 1.4826 * float(np.median(np.abs(errs - np.median(errs))))
    return (f"{len(sigmas)} spots, per-axis error {robust:.3f} px (robust σ), stated σ "
            f"{float(np.median(sigmas)):.3f} px (median), {_coverage_words(z)}")


def _reported_sigma_words(recs: Sequence[dict[str, Any]]) -> str:
    """How the stated σ holds the errors of every reported spot of a laser in view, in words:
    the found spots and a laser's own spots reported beyond MATCH_PX of their truth (their
    false records carry ``sigma_px``). ``scale`` uses a spot whichever it is, so the found
    spots alone (:func:`_sigma_words`) leave out the ones whose σ matters most."""
    spots, off = _reported_with_sigma(recs)
    if not spots:
        return "no spot reported"
    n = len(spots)
    return (f"{n} spot{'' if n == 1 else 's'} ({len(off)} beyond {MATCH_PX:g} px), "
            f"{_coverage_words(_per_axis_z(spots))}")


def _rule_sigma_words(recs: Sequence[dict[str, Any]]) -> list[str]:
    """Per rule that took them (``taken_by``): how the stated σ holds the errors of the
    reported spots of a laser in view, found and off, in words."""
    spots, off = _reported_with_sigma(recs)
    rules = sorted({f.get("taken_by", "") for f in spots if f.get("taken_by")})
    lines = []
    for rule in rules:
        mine = [f for f in spots if f.get("taken_by") == rule]
        n_off = sum(1 for f in off if f.get("taken_by") == rule)
        n, sigma = len(mine), float(np.median([f["sigma_px"] for f in mine]))
        lines.append(f"{rule}: {n} spot{'' if n == 1 else 's'} ({n_off} beyond {MATCH_PX:g} "
                     f"px), stated σ {sigma:.3f} px (median), "
                     f"{_coverage_words(_per_axis_z(mine))}")
    return lines


def pooled_lines(records: Sequence[dict[str, Any]]) -> list[str]:
    """Per image size: the pooled counts and errors (and each draw's, when the records hold
    several), and the stated σ against the errors for all found spots, for every reported spot
    of a laser in view (and per rule that took them), and for the found spots per laser
    wavelength."""
    lines = []
    for size in dict.fromkeys(r["size"] for r in records):
        recs = [r for r in records if r["size"] == size]
        lines.append(f"{size} pooled: {_counts_words(recs)}")
        seeds = sorted({r.get("seed", 0) for r in recs})
        if len(seeds) > 1:
            lines.extend(f"{size} seed {s}: "
                         f"{_counts_words([r for r in recs if r.get('seed', 0) == s])}"
                         for s in seeds)
        lines.append(f"{size} σ, all: {_sigma_words(recs)}")
        lines.append(f"{size} σ, every reported spot of a laser in view: "
                     f"{_reported_sigma_words(recs)}")
        lines.extend(f"{size} σ, taken by {words}" for words in _rule_sigma_words(recs))
        for nm in sorted({r["wavelength_nm"] for r in recs if r.get("wavelength_nm")}):
            lines.append(f"{size} σ, {nm:g} nm: "
                         f"{_sigma_words([r for r in recs if r.get('wavelength_nm') == nm])}")
        at_truth = _at_truth_words(recs)
        if at_truth:
            lines.append(f"{size} misses, the candidate at the truth: {at_truth}")
    return lines


def _at_truth_words(recs: Sequence[dict[str, Any]]) -> str | None:
    """The misses counted by the detector's candidate at their truth (:func:`candidate_at`):
    none within MATCH_PX, or the test it failed; None when no miss records it (older runs)."""
    misses = [m for r in recs for m in r.get("misses", ()) if "at_truth" in m]
    if not misses:
        return None
    kinds = Counter(m["at_truth"]["test"] if m["at_truth"] else f"none within {MATCH_PX:g} px"
                    for m in misses)
    return f"{len(misses)} misses: " + "; ".join(f"{k} {n}" for k, n in kinds.most_common())


def _counts_words(recs: Sequence[dict[str, Any]]) -> str:
    """Spots found, false spots and the found spots' median and p95 error, in words."""
    errs = [f["error_px"] for r in recs for f in r["found"]]
    spots = sum(r["truths"] for r in recs)
    reported = sum(r["reported"] for r in recs)
    n_false = sum(len(r["falses"]) for r in recs)
    return (f"{len(errs)} of {spots} spots found "
            f"({_fmt(100.0 * len(errs) / spots if spots else None, 1)} %), {n_false} false of "
            f"{reported} reported ({_fmt(100.0 * n_false / reported if reported else None, 1)}"
            f" %); median {_fmt(_percentile(errs, 50), 3)} px, p95 "
            f"{_fmt(_percentile(errs, 95), 3)} px")


def _reason_kind(reason: str) -> str:
    """The gist of a miss reason, numbers replaced by #, to count kinds of reasons: for the
    detector's "no X spot accepted within N px of its beam: (x, y) why; (x, y) why; ..." the
    first candidate's "why"."""
    first = reason.split(";")[0]
    if ": (" in first and ")" in first.split(": (", 1)[1]:
        first = first.split(": (", 1)[1].split(")", 1)[1]
    return re.sub(r"-?\d+(\.\d+)?", "#", first).strip(" :")[:100]


def run_benchmark(conditions: Sequence[str] | None = None,
                  sizes: Sequence[tuple[int, int]] = DEFAULT_SIZES, per_condition: int = 20,
                  seed: int | Sequence[int] = 0, workers: int = 2, laser_free: bool = False,
                  cache: Path | None = None, cache_max_gb: float | None = None,
                  scene: SceneReference | None = None
                  ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(per-image records, per condition x size summary rows, pooled over the draws ``seed``);
    ``laser_free``: also capture every frame without the lasers, to tell how visible each
    missed spot was; ``cache``: keep the rendered frames there, or read them back
    (:func:`cached_frame`), and after the run prune it to ``cache_max_gb`` (None: leave it as
    it is; 0: drop only other generators' frames) keeping the run's own (:func:`prune_cache`);
    ``scene``: give the detector a scene reference of every frame, as described there."""
    names = list(conditions) if conditions else list(CONDITIONS)
    unknown = [c for c in names if c not in CONDITIONS]
    if unknown:
        raise ValueError(f"unknown condition(s) {unknown}; known: {list(CONDITIONS)}")
    seeds = [seed] if isinstance(seed, int) else list(seed)
    jobs = run_jobs(names, sizes, per_condition, seeds, laser_free, cache, scene)
    if workers > 1 and len(jobs) > 1:
        pool = multiprocessing.get_context("fork").Pool(workers)
        try:
            records = list(pool.imap_unordered(run_job, jobs))
        finally:  # close + join, not terminate: SIGTERM makes pycolmap's handler dump stacks
            pool.close()
            pool.join()
    else:
        records = [run_job(j) for j in jobs]
    order = {frame_key(j.seed, j.condition, f"{j.width}x{j.height}", j.index): k
             for k, j in enumerate(jobs)}
    records.sort(key=lambda r: order[record_key(r)])
    if cache is not None and cache_max_gb is not None:
        _prune_after_run(cache, cache_max_gb, [cache_path(j) for j in jobs])
    return records, summarise(records)


def frame_key(seed: int, condition: str, size: str, index: int) -> str:
    """One frame's name in a run: draw, condition, size, image."""
    return f"seed {seed} {condition} {size} #{index}"


def record_key(rec: dict[str, Any]) -> str:
    """:func:`frame_key` of a per-image record (records without a draw: seed 0)."""
    return frame_key(rec.get("seed", 0), rec["condition"], rec["size"], rec["index"])


def compare_records(old: Sequence[dict[str, Any]], new: Sequence[dict[str, Any]],
                    moved_px: float = 0.01) -> list[str]:
    """Frame by frame, what ``new`` finds that ``old`` did not (per-image records of the same
    frames): spots gained, lost, moved by more than ``moved_px``, false spots gained or
    dropped; the last line counts them. Frames in only one run are left out and counted."""
    before = {record_key(r): r for r in old}
    after = {record_key(r): r for r in new}
    lines, gained, lost, false_delta = [], 0, 0, 0
    for key in (k for k in after if k in before):
        a = {f["laser"]: f["error_px"] for f in before[key]["found"]}
        b = {f["laser"]: f["error_px"] for f in after[key]["found"]}
        words = [f"{n} lost ({a[n]:.2f} px)" if n not in b else
                 f"{n} found ({b[n]:.2f} px)" if n not in a else f"{n} {a[n]:.2f} → {b[n]:.2f} px"
                 for n in sorted(set(a) | set(b))
                 if n not in a or n not in b or abs(a[n] - b[n]) > moved_px]
        gained += len(set(b) - set(a))
        lost += len(set(a) - set(b))
        fa, fb = len(before[key]["falses"]), len(after[key]["falses"])
        false_delta += fb - fa
        if fa != fb:
            words.append(f"false {fa} → {fb}")
        if words:
            lines.append(f"{key}: " + "; ".join(words))
    unmatched = len(set(before) ^ set(after))
    lines.append(f"{len(lines)} frames differ: {gained} spots found, {lost} lost, false spots "
                 f"{false_delta:+d}" + (f" ({unmatched} frames in one run only)"
                                        if unmatched else ""))
    return lines


def run_small(conditions: Sequence[str] = ("clipped_cores", "no_lasers"),
              size: tuple[int, int] = (640, 480), per_condition: int = 1,
              seed: int = 0, laser_free: bool = False,
              scene: SceneReference | None = None) -> list[dict[str, Any]]:
    """A reduced benchmark (small images, one process) for tests: summary rows."""
    return run_benchmark(conditions, (size,), per_condition, seed, 1, laser_free,
                         scene=scene)[1]


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def markdown_table(rows: Sequence[dict[str, Any]]) -> str:
    """The summary as a Markdown table (targets in the header)."""
    head = (f"| condition | size | images | spots | found % (≥ {TARGETS['found_pct']:g}) | "
            f"false % (≤ {TARGETS['false_pct']:g}) | false/img | median px "
            f"(≤ {TARGETS['median_px']:g}) | p95 px (≤ {TARGETS['p95_px']:g}) | max px | "
            "within 2σ / 3σ % | det s/img | render s/img | most common miss reason |")
    lines = [head, "|" + "---|" * 14]
    for r in rows:
        reason = f"{r['miss_reasons'][0][1]}× {r['miss_reasons'][0][0]}" if r["miss_reasons"] \
            else ""
        lines.append(
            f"| {r['condition']} | {r['size']} | {r['images']} | {r['spots']} | "
            f"{_fmt(r['found_pct'], 1)} | {_fmt(r['false_pct'], 1)} | "
            f"{_fmt(r['false_per_image'])} | {_fmt(r['median_px'], 3)} | "
            f"{_fmt(r['p95_px'], 3)} | {_fmt(r['max_px'], 2)} | "
            f"{_fmt(r.get('within_2sigma_pct'), 0)} / {_fmt(r.get('within_3sigma_pct'), 0)} | "
            f"{_fmt(r['detect_s_per_image'])} | {_fmt(r['render_s_per_image'])} | "
            f"{reason.replace('|', '/')} |")
    return "\n".join(lines)


def _sizes(text: str) -> list[tuple[int, int]]:
    out = []
    for part in text.split(","):
        w, h = part.lower().split("x")
        out.append((int(w), int(h)))
    return out


def _seeds(text: str) -> list[int]:
    """``0``, ``2-5`` or ``2,4,6`` as a list of draws."""
    seeds: list[int] = []
    for part in text.split(","):
        first, dash, last = part.partition("-")
        try:
            lo = int(first)
            hi = int(last) if dash else lo
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a draw or range of draws: {part!r}") from None
        if hi < lo:
            raise argparse.ArgumentTypeError(f"empty range of draws: {part!r}")
        seeds.extend(range(lo, hi + 1))
    return seeds


def _scene_reference(text: str) -> SceneReference:
    """``SHIFT,BLUR,GAIN`` (px, px, ±) as a :class:`SceneReference`."""
    try:
        shift, blur, gain = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"not SHIFT,BLUR,GAIN (three numbers): {text!r}") from None
    if min(shift, blur, gain) < 0:
        raise argparse.ArgumentTypeError(f"SHIFT, BLUR and GAIN must be >= 0: {text!r}")
    return SceneReference(shift, blur, gain)


def main(argv: Sequence[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-condition", type=int, default=20)
    ap.add_argument("--sizes", type=_sizes, default=list(DEFAULT_SIZES),
                    help="comma list of WxH (default 1920x1080,4000x3000)")
    ap.add_argument("--conditions", default="",
                    help=f"comma list (default all): {','.join(CONDITIONS)}")
    ap.add_argument("--seed", type=_seeds, default=[0],
                    help="the draw, or several pooled: 2-5 or 2,4,6 (default 0)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="write results JSON here")
    ap.add_argument("--markdown", action="store_true", help="print a Markdown table")
    ap.add_argument("--visibility", action="store_true",
                    help="also capture every frame without the lasers (same noise) and count "
                         "the missed spots that are visible (slower: one more capture)")
    ap.add_argument("--cache", type=Path, default=None,
                    help="keep rendered frames in this folder and read them back on later runs")
    ap.add_argument("--cache-max-gb", type=float, default=40.0,
                    help="after the run, prune the cache to this size, least recently used "
                         "frames first, the run's own kept (default 40; 0: no limit)")
    ap.add_argument("--scene-reference", type=_scene_reference, default=None,
                    metavar="SHIFT,BLUR,GAIN",
                    help="give the detector a scene reference of every frame, shifted SHIFT px, "
                         "blurred BLUR px, lit by a ramp of ±GAIN (e.g. 0.5,0.7,0.1)")
    ap.add_argument("--no-scene-fit", action="store_true",
                    help="give the scene reference whole, without dropping the cells that do "
                         "not fit the frame (scale drops them: scene_fit.fit_reference)")
    ap.add_argument("--no-scene-scaling", action="store_true",
                    help="subtract the scene reference's texture unscaled, not scaled to the "
                         "frame's light (DetectionOptions.scene_gain_sigma_px=None)")
    ap.add_argument("--compare", type=Path, default=None,
                    help="an earlier run's --out file: print what changed, frame by frame")
    args = ap.parse_args(argv)
    conditions = [c for c in args.conditions.split(",") if c] or list(CONDITIONS)
    unknown = [c for c in conditions if c not in CONDITIONS]
    if unknown:
        ap.error(f"unknown condition(s) {', '.join(unknown)}; known: {', '.join(CONDITIONS)}")
    reference = (None if args.scene_reference is None else
                 replace(args.scene_reference, fit=not args.no_scene_fit,
                         scaled=not args.no_scene_scaling))
    t0 = time.perf_counter()
    records, rows = run_benchmark(conditions, args.sizes, args.per_condition, args.seed,
                                  args.workers, args.visibility, args.cache, args.cache_max_gb,
                                  reference)
    elapsed = time.perf_counter() - t0
    if args.out is not None:
        scene = None if reference is None else asdict(reference)
        args.out.write_text(json.dumps({"targets": TARGETS, "match_px": MATCH_PX,
                                        "seeds": args.seed, "scene_reference": scene,
                                        "summary": rows,
                                        "images": records}, indent=1, default=str))
    if args.markdown:
        print(markdown_table(rows))
    else:
        for r in rows:
            print(f"{r['condition']:16s} {r['size']:>9s}  found {_fmt(r['found_pct'], 1):>5s} %"
                  f"  false {_fmt(r['false_pct'], 1):>5s} % ({_fmt(r['false_per_image'])}/img)"
                  f"  median {_fmt(r['median_px'], 3)}  p95 {_fmt(r['p95_px'], 3)}"
                  f"  max {_fmt(r['max_px'])} px  det {_fmt(r['detect_s_per_image'])} s")
            for kind, n in r["miss_reasons"][:3]:
                print(f"{'':28s}{n:3d}x {kind}")
    if (line := visibility_line(rows)) is not None:
        print(line)
    print("\n".join(pooled_lines(records)))
    if args.compare is not None:
        earlier = json.loads(args.compare.read_text())["images"]
        print(f"against {args.compare}:")
        print("\n".join(compare_records(earlier, records)))
    print(f"{len(records)} images in {elapsed:.0f} s", file=sys.stderr)
    return 0


def _prune_after_run(cache: Path, max_gb: float, own: list[Path]) -> None:
    """Prune the frame cache after a run, keeping its ``own`` frames (:func:`prune_cache`), and
    say what it freed."""
    removed, freed = prune_cache(cache, int(max_gb * 1e9), own)
    if removed:
        print(f"cache: {removed} frame(s) removed ({freed / 1e9:.1f} GB freed)", file=sys.stderr)


if __name__ == "__main__":
    raise SystemExit(main())
