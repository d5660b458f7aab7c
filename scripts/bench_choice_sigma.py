"""What the σ term of the rule that took a spot does to `scale` (docs/DETECTION.md, "The rule
that took a spot").

Each survey of the independent generator (``synthetic/underwater/survey.py``: real SfM, the
true floor as the mesh, green beams at 960 × 540) is made once; ``scale`` then runs on it
twice, with the detector's σ terms for the floor search and the second look switched off
(``sigma_floor_choice`` and ``sigma_second_look_choice`` 0) and at their defaults. The same
SfM model serves both runs, so the difference is the term's alone (pycolmap's SfM is not
bit-reproducible between surveys made twice).

    python scripts/bench_choice_sigma.py --seeds 0-11 [--rig-error-scale 0]

Prints a Markdown row per survey (scale error ± σ, without and with the term) and the pooled
median |error|, RMS error, largest |error| and RMS error / σ.
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from bench_detection_physical import _seeds

from sfm_laserscale.detection import DetectionOptions
from sfm_laserscale.pipeline_folders import GivenInputs, resolve_scale_inputs
from sfm_laserscale.run_types import ScaleOptions
from sfm_laserscale.synthetic.underwater.survey import SurveyOptions, make_survey

#: the detector without the rule's σ term, then with it (the defaults)
VARIANTS = (DetectionOptions(sigma_floor_choice=0.0, sigma_second_look_choice=0.0),
            DetectionOptions())


def survey_errors(seed: int, rig_error_scale: float, work: Path) -> list[tuple[float, float]]:
    """(scale error %, σ %) of one survey, per variant of :data:`VARIANTS`."""
    from sfm_laserscale.commands.scale import run

    s = make_survey(work / f"survey_{seed}", SurveyOptions(
        width=960, height=540, seed=seed, rig_error_scale=rig_error_scale, progress=False))
    inputs = resolve_scale_inputs(GivenInputs(
        laser_images=(s.laser_images_dir,), rig=s.rig_path, model=s.model_dir, mesh=s.mesh_path,
        database=s.database_path))
    out = []
    for detection in VARIANTS:
        res = run(inputs, None, replace(ScaleOptions(progress=False), detection=detection))
        out.append((100 * (res.scale.value - s.true_scale) / s.true_scale,
                    100 * res.scale.std / s.true_scale))
    return out


def pooled_words(pairs: Sequence[tuple[float, float]]) -> str:
    """Median |error|, RMS error, largest |error| (%) and RMS error / σ of (error, σ) pairs."""
    errs = [e for e, _ in pairs]
    rms = math.sqrt(sum(e * e for e in errs) / len(errs))
    rms_z = math.sqrt(sum((e / s) ** 2 for e, s in pairs) / len(pairs))
    return (f"median |error| {statistics.median(abs(e) for e in errs):.3f} %, RMS {rms:.3f} %, "
            f"largest {max(abs(e) for e in errs):.3f} %, RMS error/σ {rms_z:.2f}")


def main(argv: Sequence[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=_seeds, default=list(range(12)))
    ap.add_argument("--rig-error-scale", type=float, default=0.0)
    args = ap.parse_args(argv)
    rows: list[list[tuple[float, float]]] = []
    print("| seed | without the term: error ± σ | with it |\n|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            rows.append(survey_errors(seed, args.rig_error_scale, Path(tmp)))
            print(f"| {seed} | " + " | ".join(f"{e:+.3f} % ± {s:.3f} %" for e, s in rows[-1])
                  + " |", flush=True)
    for k, name in enumerate(("without the term", "with it")):
        print(f"{name}: {pooled_words([r[k] for r in rows])}")
    closer = sum(abs(r[1][0]) < abs(r[0][0]) for r in rows)
    farther = sum(abs(r[1][0]) > abs(r[0][0]) for r in rows)
    print(f"with the term: {closer} surveys closer to the truth, {farther} farther")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
