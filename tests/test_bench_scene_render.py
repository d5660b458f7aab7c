"""The survey benchmark of scene references in ``scale``: its lines, per survey and pooled."""

from __future__ import annotations

from types import ModuleType

import pytest
from script_loader import load_script


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_script("bench_scene_render")


def test_lines(bench: ModuleType) -> None:
    runs = [bench.SurveyRun(0, "alone", (0.3, 0.5, 0.7), 1, 4, 0.2, 0.5),
            bench.SurveyRun(1, "alone", (0.1,) * 4, 0, 4, -0.4, 0.5),
            bench.SurveyRun(0, "with references", (0.2, 0.3, 0.4, 0.5), 0, 4, 0.1, 0.5,
                            0.95, 1.0, 0.2, 0.4, 3.25)]
    assert bench.run_line(runs[0]) == (
        "seed 0 alone: 3 of 4 spots within 1.5 px (1 farther), scale error +0.200 % "
        "(σ 0.500 %)")
    assert bench.run_line(runs[2]).endswith(
        "; reference coverage 0.95, kept 1.00, shift 0.20 px, ratio 0.40; 3.2 s")
    alone, scene = bench.pooled_lines(runs)
    assert alone == ("alone: 7 of 8 spots within 1.5 px (1 farther), mean error 0.271 px, "
                     "median 0.100 px; scale error RMS 0.316 %, max |error| 0.400 %, "
                     "max |error|/σ 0.80")
    assert scene.startswith("with references: 4 of 4 spots within 1.5 px (0 farther)")
