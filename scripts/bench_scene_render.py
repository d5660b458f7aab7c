"""``scale`` with and without scene references on surveys of the independent generator: the
spots it takes and the scale it gives (docs/DETECTION.md, "A scene reference in scale").

Each survey (``synthetic/underwater/survey.py``: real SfM, the true floor as the mesh, green
beams in green water with pale clutter, 960 × 540 by default) is made once, with the true rig in
rig.toml (``rig_error_scale=0``: the layout's calibration error would move the scale by 0.6 %
RMS and hide the photographs' part, tests/test_underwater_survey.py); ``scale`` runs on it three
times with the model's images given: ``--no-scene-reference``, with references (the default),
both with the guided search (as a user runs it), and with the true spots (``--spots``: what is
left is registration and the model's error). Per survey and pooled:

- the references: coverage, the share the fit kept, the fit's shift and residual ratio
  (medians over the laser images; ``scene_fit.fit_reference``);
- the spots ``scale`` took, against ``true_spots.csv``: within 1.5 px, their mean and median
  error, and those farther (wrong);
- the scale's error against the truth (%), and its stated σ (%);
- the scene stage's wall time.

    python scripts/bench_scene_render.py --seeds 0-5 [--size 960x540]
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from bench_detection_physical import MATCH_PX, _seeds, _sizes

from sfm_laserscale.io.spots_csv import read_spots_csv
from sfm_laserscale.pipeline_folders import GivenInputs, resolve_scale_inputs
from sfm_laserscale.rig import load_rig
from sfm_laserscale.run_types import ScaleOptions
from sfm_laserscale.scene_reference import SceneStageOptions
from sfm_laserscale.synthetic.underwater.survey import SurveyOptions, make_survey

VARIANTS = ("alone", "with references", "true spots")


@dataclass(frozen=True)
class SurveyRun:
    """One survey, one variant: the spots' errors (px, every spot matched to its laser's
    truth), the spots farther than MATCH_PX, the truths, the scale's error and σ (%), and the
    used references' medians (NaN without)."""

    seed: int
    variant: str
    errors_px: tuple[float, ...]
    wrong: int
    truths: int
    scale_error_pct: float
    sigma_pct: float
    coverage: float = math.nan
    kept_share: float = math.nan
    shift_px: float = math.nan
    ratio: float = math.nan
    scene_s: float = 0.0  # the scene stage's wall time, all laser images


def survey_runs(seed: int, size: tuple[int, int], work: Path) -> list[SurveyRun]:
    """Make survey ``seed`` and run ``scale`` on it alone and with scene references."""
    from sfm_laserscale.commands.scale import run

    survey = make_survey(work / f"survey_{seed}", SurveyOptions(
        width=size[0], height=size[1], seed=seed, progress=False, rig_error_scale=0.0))
    given = GivenInputs(
        laser_images=(survey.laser_images_dir,), rig=survey.rig_path, model=survey.model_dir,
        mesh=survey.mesh_path, database=survey.database_path, images=survey.images_dir)
    rig = load_rig(survey.rig_path)
    truths = read_spots_csv(survey.spots_path, None, rig.names)
    out = []
    for variant in VARIANTS:
        spots = survey.spots_path if variant == "true spots" else None
        inputs = resolve_scale_inputs(replace(given, spots=spots))
        options = ScaleOptions(progress=False, scene=SceneStageOptions(
            enabled=variant == "with references"))
        result = run(inputs, None, options)
        errors = []
        for image in result.images:
            truth = {s.laser: (s.x, s.y) for s in truths.get(image.name, [])}
            errors += [math.dist((s.x, s.y), truth[s.laser]) for s in image.spots
                       if s.laser in truth]
        value, sigma = result.scale.value, result.scale.std
        used = [r.scene for r in result.images if r.scene is not None and r.scene.used]
        out.append(SurveyRun(
            seed, variant, tuple(e for e in errors if e <= MATCH_PX),
            sum(e > MATCH_PX for e in errors), sum(len(v) for v in truths.values()),
            100 * (value - survey.true_scale) / survey.true_scale, 100 * sigma / value,
            scene_s=float(result.report["timings_s"].get("scene", 0.0)), **_medians(used)))
    return out


def _medians(used: Sequence[object]) -> dict[str, float]:
    if not used:
        return {}
    keys = {"coverage": "coverage", "kept_share": "kept_share", "shift_px": "shift_median_px",
            "ratio": "residual_ratio_median"}
    return {k: float(np.nanmedian([getattr(u, a) for u in used])) for k, a in keys.items()}


def run_line(r: SurveyRun) -> str:
    """One survey's variant in a line."""
    ref = ("" if math.isnan(r.coverage) else
           f"; reference coverage {r.coverage:.2f}, kept {r.kept_share:.2f}, shift "
           f"{r.shift_px:.2f} px, ratio {r.ratio:.2f}; {r.scene_s:.1f} s")
    return (f"seed {r.seed} {r.variant}: {len(r.errors_px)} of {r.truths} spots within "
            f"{MATCH_PX} px ({r.wrong} farther), scale error {r.scale_error_pct:+.3f} % "
            f"(σ {r.sigma_pct:.3f} %){ref}")


def pooled_lines(runs: Sequence[SurveyRun]) -> list[str]:
    """Per variant, pooled over the surveys."""
    lines = []
    for variant in VARIANTS:
        mine = [r for r in runs if r.variant == variant]
        if not mine:
            continue
        errs = [e for r in mine for e in r.errors_px]
        scale = [r.scale_error_pct for r in mine]
        z = [r.scale_error_pct / r.sigma_pct for r in mine]
        lines.append(
            f"{variant}: {len(errs)} of {sum(r.truths for r in mine)} spots within {MATCH_PX} "
            f"px ({sum(r.wrong for r in mine)} farther), mean error {np.mean(errs):.3f} px, "
            f"median {np.median(errs):.3f} px; scale error RMS "
            f"{math.sqrt(statistics.fmean(s * s for s in scale)):.3f} %, max |error| "
            f"{max(abs(s) for s in scale):.3f} %, max |error|/σ {max(abs(v) for v in z):.2f}")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=_seeds, default=list(range(6)))
    ap.add_argument("--size", type=_sizes, default=[(960, 540)])
    args = ap.parse_args(argv)
    runs: list[SurveyRun] = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            new = survey_runs(seed, args.size[0], Path(tmp))
            for r in new:
                print(run_line(r), flush=True)
            runs.extend(new)
    print("\n".join(pooled_lines(runs)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
