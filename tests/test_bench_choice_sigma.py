"""scripts/bench_choice_sigma.py: the variants it compares and its pooled figures."""

from __future__ import annotations

from script_loader import load_script

from sfm_laserscale.detection import DetectionOptions


def test_variants_are_the_term_off_then_the_defaults() -> None:
    bench = load_script("bench_choice_sigma")
    off, on = bench.VARIANTS
    assert (off.sigma_floor_choice, off.sigma_second_look_choice) == (0.0, 0.0)
    assert on == DetectionOptions()
    assert on.sigma_floor_choice > 0 and on.sigma_second_look_choice > 0
    assert bench._seeds("0-3") == [0, 1, 2, 3] and bench._seeds("2,5") == [2, 5]


def test_pooled_words() -> None:
    bench = load_script("bench_choice_sigma")
    # errors 0.1, -0.3, 0.2 % with σ 0.5 %: RMS sqrt(0.14 / 3), error/σ RMS sqrt(0.56 / 3)
    words = bench.pooled_words([(0.1, 0.5), (-0.3, 0.5), (0.2, 0.5)])
    assert words == ("median |error| 0.200 %, RMS 0.216 %, largest 0.300 %, "
                     "RMS error/σ 0.43")
