"""Benchmark of the model-guided spot search (docs/DETECTION.md, "Where the model puts a spot").

Two measurements, both on data from the independent generator (synthetic/underwater):

``frames``: single photographs of bench_detection_physical's conditions. ``detect_spots`` runs
as in that benchmark; each laser it leaves without a spot is then searched with
``detect_near`` around its true spot moved by a seeded Gaussian error (``--noise-px`` per axis:
what the prediction from the model, the scale and the rig is off by). The false-spot rate of a
search at a wrong place is measured too: every laser is searched at a random point of its
band at least 12 px from its true spot.

``surveys``: whole surveys (survey.py: SfM, mesh, truth). ``scale`` runs on each with and
without the guided search; spots are scored against the truth (found within 1.5 px).

    python scripts/bench_guided.py frames --per-condition 8 --seed 0
    python scripts/bench_guided.py surveys --seeds 0-5 --rig-error-scale 0 [--size 1920x1080]
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import tempfile
import time
import tomllib
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from bench_detection_physical import MATCH_PX, Job, jobs_for

from sfm_laserscale.synthetic.underwater.conditions import CONDITIONS, render_frame

RANDOM_POINT_MIN_PX = 12.0


def _band_point(region: Any, name: str, truth: Any, width: int, height: int,
                rng: np.random.Generator) -> tuple[float, float] | None:
    """A random point of a laser's band polyline at least RANDOM_POINT_MIN_PX from its truth."""
    line = region.polylines.get(name)
    if line is None or len(line) < 2:
        return None
    for _ in range(50):
        k, a = int(rng.integers(0, len(line) - 1)), float(rng.uniform())
        p = (1 - a) * line[k] + a * line[k + 1]
        inside = 5 < p[0] < width - 5 and 5 < p[1] < height - 5
        if inside and (truth is None or math.dist(p, truth) > RANDOM_POINT_MIN_PX):
            return float(p[0]), float(p[1])
    return None


def frame_job(args: tuple[Job, float]) -> dict[str, Any]:
    """One photograph: spots alone, spots added by the guided search, random-point searches."""
    from sfm_laserscale.commands.detect import parse_camera
    from sfm_laserscale.detection import DetectionOptions, detect_spots
    from sfm_laserscale.detection.beams import search_region
    from sfm_laserscale.detection.guided import detect_near
    from sfm_laserscale.rig import rig_from_dict

    job, noise = args
    frame = render_frame(job.condition, job.width, job.height, job.rng())
    camera = parse_camera(frame.camera_spec)
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    alone = detect_spots(frame.image_rgb, camera, rig, DetectionOptions())
    truths = {k: v for k, v in frame.truth.items() if v is not None}
    rng = np.random.default_rng([job.seed, job.condition_index, job.size_index, job.index, 77])

    def hit(spot: Any) -> bool:
        t = truths.get(spot.laser)
        return t is not None and math.dist((spot.x, spot.y), t) <= MATCH_PX

    found = sum(hit(s) for s in alone.spots)
    have = {s.laser for s in alone.spots}
    pred = {n: (t[0] + rng.normal(0, noise), t[1] + rng.normal(0, noise))
            for n, t in truths.items() if n not in have}
    guided = detect_near(frame.image_rgb, camera, rig, pred)
    region = search_region(camera, rig, DetectionOptions())
    points = {n: p for las in rig.lasers
              if (p := _band_point(region, (n := las.name), truths.get(n), camera.width,
                                   camera.height, rng)) is not None}
    random = detect_near(frame.image_rgb, camera, rig, points)
    return {"condition": job.condition, "size": f"{job.width}x{job.height}",
            "truths": len(truths), "found": found, "false": len(alone.spots) - found,
            "guided_found": sum(hit(s) for s in guided.spots),
            "guided_false": sum(not hit(s) for s in guided.spots),
            "guided_errors": [math.dist((s.x, s.y), truths[s.laser]) for s in guided.spots
                              if hit(s)],
            "random_searched": len(points), "random_spots": len(random.spots)}


def frames(conditions: Sequence[str], size: tuple[int, int], per_condition: int, seed: int,
           noise: float, workers: int) -> str:
    """The frames measurement as a Markdown table."""
    jobs = [(j, noise) for j in jobs_for(conditions, [size], per_condition, seed)]
    with mp.Pool(workers) as pool:
        recs = pool.map(frame_job, jobs, chunksize=1)
    rows: dict[str, dict[str, Any]] = defaultdict(lambda: defaultdict(float))
    for r in recs:
        for key in ("", r["condition"]):
            g = rows[key or "all"]
            for k in ("truths", "found", "false", "guided_found", "guided_false",
                      "random_searched", "random_spots"):
                g[k] += r[k]
            g["errors"] = [*g.get("errors", []), *r["guided_errors"]]  # type: ignore[misc]
    lines = ["| condition | spots | found alone % | + guided % | guided false | guided median "
             "px | random band points | spots there |", "|---|---|---|---|---|---|---|---|"]
    for name in [*conditions, "all"]:
        g = rows[name]
        n = max(g["truths"], 1)
        med = f"{np.median(g['errors']):.3f}" if g.get("errors") else "-"
        lines.append(f"| {name} | {int(g['truths'])} | {100 * g['found'] / n:.1f} | "
                     f"{100 * (g['found'] + g['guided_found']) / n:.1f} | "
                     f"{int(g['guided_false'])} | {med} | {int(g['random_searched'])} | "
                     f"{int(g['random_spots'])} |")
    return "\n".join(lines)


def _score(report: dict[str, Any], truth: dict[str, Any]) -> dict[str, int]:
    true_xy = {(im["name"], s["laser"]): (s["x"], s["y"])
               for im in truth["laser_images"] for s in im["spots"] if s.get("x") is not None}
    out = {"truths": len(true_xy)}
    for im in report["images"]:
        for s in im["spots"]:
            t = true_xy.get((im["name"], s["laser"]))
            ok = t is not None and math.dist(t, (s["x"], s["y"])) <= MATCH_PX
            key = f"{s['source']}_{'found' if ok else 'false'}"
            out[key] = out.get(key, 0) + 1
    out["images_without_spots"] = sum(not im["spots"] for im in report["images"])
    return out


class PredictionRecorder:
    """Records every prediction ``scale``'s guided search makes (commands.scale.predict_spots
    wrapped for the measurement), keyed by the image's pose translation."""

    def __init__(self) -> None:
        import sfm_laserscale.commands.scale as scale_cmd

        self.rows: list[tuple[Any, dict[str, tuple[float, float]]]] = []
        self._module = scale_cmd
        self._orig = scale_cmd.predict_spots

        def wrapped(*args: Any, **kw: Any) -> Any:
            pred, why = self._orig(*args, **kw)
            if "offsets" in kw or len(args) > 6:  # the search's own predictions (with offsets)
                self.rows.append((args[1].t.copy(), dict(pred)))
            return pred, why

        scale_cmd.predict_spots = wrapped  # type: ignore[assignment]

    def errors(self, images: Any, true_xy: dict[tuple[str, str], tuple[float, float]]
               ) -> list[float]:
        """Distance (px) of every recorded prediction with a true spot from that spot."""
        names = {im.name: im.registration.cam_from_world.t for im in images
                 if im.registration is not None and im.registration.cam_from_world is not None}
        out = []
        for t, pred in self.rows:
            name = next((n for n, tt in names.items() if np.allclose(tt, t)), "")
            out += [math.dist(xy, true_xy[(name, las)]) for las, xy in pred.items()
                    if (name, las) in true_xy]
        return out

    def close(self) -> None:
        self._module.predict_spots = self._orig  # type: ignore[assignment]


def survey_one(seed: int, rig_error_scale: float, work: Path,
               prediction_errors: list[float], size: tuple[int, int] = (960, 540)) -> str:
    """One survey's Markdown row: spots and scale error without and with the guided search
    (the guided run's prediction errors are appended to ``prediction_errors``)."""
    import json

    from sfm_laserscale.commands.scale import run
    from sfm_laserscale.guided_spots import GuidedSpotOptions
    from sfm_laserscale.pipeline_folders import GivenInputs, resolve_scale_inputs
    from sfm_laserscale.run_types import ScaleOptions
    from sfm_laserscale.synthetic.underwater.survey import SurveyOptions, make_survey

    s = make_survey(work / f"survey_{seed}", SurveyOptions(
        width=size[0], height=size[1], seed=seed, rig_error_scale=rig_error_scale,
        progress=False))
    truth = json.loads(s.truth_path.read_text())
    inputs = resolve_scale_inputs(GivenInputs(
        laser_images=(s.laser_images_dir,), rig=s.rig_path, model=s.model_dir, mesh=s.mesh_path,
        database=s.database_path))
    true_xy = {(im["name"], sp["laser"]): (sp["x"], sp["y"])
               for im in truth["laser_images"] for sp in im["spots"] if sp.get("x") is not None}
    cells = [str(seed)]
    for enabled in (False, True):
        opts = replace(ScaleOptions(progress=False), guided=GuidedSpotOptions(enabled=enabled))
        recorder = PredictionRecorder()
        try:
            res = run(inputs, None, opts)
        finally:
            recorder.close()
        prediction_errors += recorder.errors(res.images, true_xy)
        sc = _score(res.report, truth)
        err = 100 * (res.scale.value - s.true_scale) / s.true_scale
        sigma = 100 * res.scale.std / s.true_scale
        found = sc.get("detected_found", 0) + sc.get("guided_found", 0)
        cells += [f"{found} ({sc.get('guided_found', 0)} guided)" if enabled else str(found),
                  str(sc.get("detected_false", 0) + sc.get("guided_false", 0)),
                  str(sc["images_without_spots"]), f"{err:+.3f} % ± {sigma:.3f} %"]
    return "| " + " | ".join(cells) + " |"


def _seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(v) for v in text.split(",")]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    fr = sub.add_parser("frames")
    fr.add_argument("--per-condition", type=int, default=8)
    fr.add_argument("--size", default="1920x1080")
    fr.add_argument("--seed", type=int, default=0)
    fr.add_argument("--noise-px", type=float, default=0.7)
    fr.add_argument("--workers", type=int, default=2)
    sv = sub.add_parser("surveys")
    sv.add_argument("--seeds", type=_seeds, default=list(range(6)))
    sv.add_argument("--rig-error-scale", type=float, default=0.0)
    sv.add_argument("--size", default="960x540", help="the survey's images, WxH")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    if a.what == "frames":
        w, h = (int(v) for v in a.size.split("x"))
        print(frames(list(CONDITIONS), (w, h), a.per_condition, a.seed, a.noise_px, a.workers))
    else:
        print("| seed | found alone (of 16) | false | images without a spot | scale error ± σ | "
              "found, guided search on | false | images without a spot | scale error ± σ |")
        print("|---|---|---|---|---|---|---|---|---|")
        errors: list[float] = []
        with tempfile.TemporaryDirectory() as tmp:
            for seed in a.seeds:
                size = tuple(int(v) for v in a.size.split("x"))
                print(survey_one(seed, a.rig_error_scale, Path(tmp), errors,
                                 (size[0], size[1])), flush=True)
        if errors:
            print(f"\nPredictions of the lasers searched, against their true spots: "
                  f"{len(errors)}, median {np.median(errors):.2f} px, p90 "
                  f"{np.percentile(errors, 90):.2f} px, max {max(errors):.2f} px")
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
