"""``simulate``: the paper's synthetic experiments (:mod:`sfm_laserscale.synthetic.simulate`)
through the code of ``scale``. Writes, atomically (a staged folder replaces ``DIR`` only when
everything is written)::

    DIR/results.json     statistics per setting and method, registration summary, timings
    DIR/table.md         the paper-like table and the calibration of the reported sigma
    DIR/trials.csv.gz    every estimate, one row each
    DIR/*.png            figures (errors, heatmaps, PCM vs depth difference, calibration)

docs/SIMULATE.md describes the experiments.
"""

from __future__ import annotations

import csv
import gzip
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.outputs import check_output_dir, staged_output_dir
from sfm_laserscale.synthetic.simulate.configs import SimulationInputs, SimulationOptions
from sfm_laserscale.synthetic.simulate.mismatch import (
    MismatchOptions,
    mismatch_table,
    run_mismatch,
)
from sfm_laserscale.synthetic.simulate.runner import SimulationResult, _jsonable, simulate
from sfm_laserscale.synthetic.simulate.samples import Collected

__all__ = ["MismatchOptions", "SimulationInputs", "SimulationOptions", "SimulationResult", "run",
           "run_mismatch_command"]


def _trial_rows(col: Collected) -> Iterator[list[Any]]:
    t = col.table
    a = t.arrays()
    for i in range(len(t)):
        key = t.keys[int(a["key"][i])]
        yield [key.config, key.area, f"{key.distance_m:g}", f"{key.sigma_f_px:g}",
               f"{key.sigma_l_px:g}", t.vocab[int(a["method"][i])], t.vocab[int(a["sub"][i])],
               int(a["view"][i]), int(a["round"][i]), int(a["sign"][i]), int(a["edge"][i]),
               *(f"{float(a[c][i]):.10g}" for c in ("pitch", "roll", "value", "sigma", "lo",
                                                   "hi", "depth"))]


def write_trials_csv(path: Path, col: Collected) -> None:
    """Every estimate, one row each (gzip-compressed CSV)."""
    with gzip.open(path, "wt", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["config", "area", "distance_m", "sigma_f_px", "sigma_l_px", "method",
                    "laser", "view", "round", "sign", "edge", "pitch_deg", "roll_deg", "scale",
                    "sigma", "ci95_lo", "ci95_hi", "depth_difference_m"])
        w.writerows(_trial_rows(col))


def require_matplotlib() -> None:
    """InputError (exit 2) with the install line when matplotlib, an optional dependency that
    only ``simulate``'s figures use, is missing; checked before any trial runs."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise InputError("simulate draws its figures with matplotlib, which is not installed: "
                         "pip install 'sfm-laserscale[simulate]' (or pip install matplotlib)"
                         ) from None


def write_simulation(out_dir: Path, result: SimulationResult, overwrite: bool) -> None:
    """results.json, table.md, trials.csv.gz and the figures, staged then moved into place."""
    require_matplotlib()
    from sfm_laserscale.report.simulate_plots import simulation_figures

    with staged_output_dir(out_dir, overwrite) as tmp:
        t0 = time.perf_counter()
        for name, png in simulation_figures(result).items():
            (tmp / name).write_bytes(png)
        result.timings["figures"] = time.perf_counter() - t0
        write_trials_csv(tmp / "trials.csv.gz", result.collected)
        (tmp / "table.md").write_text(result.table_md, encoding="utf-8")
        result.results["timings_s"] = _jsonable(result.timings)
        (tmp / "results.json").write_text(json.dumps(result.results, indent=1,
                                                     allow_nan=False), encoding="utf-8")


def run(inputs: SimulationInputs, out_dir: Path,
        options: SimulationOptions = SimulationOptions(),  # noqa: B008
        overwrite: bool = False) -> SimulationResult:
    """The ``simulate`` command: run the experiments and write every output into ``out_dir``."""
    require_matplotlib()
    check_output_dir(out_dir, overwrite)
    result = simulate(inputs, options)
    write_simulation(out_dir, result, overwrite)
    return result


def run_mismatch_command(out_dir: Path, options: MismatchOptions, overwrite: bool = False
                         ) -> dict[str, Any]:
    """``simulate --mode mismatch``: the mismatch settings' surveys (docs/SIMULATE.md); writes
    results.json and table.md into ``out_dir``; returns results.json's content with a
    ``summary`` line."""
    check_output_dir(out_dir, overwrite)
    results = run_mismatch(options)
    table = mismatch_table(results)
    with staged_output_dir(out_dir, overwrite) as tmp:
        (tmp / "results.json").write_text(json.dumps(_jsonable(results), indent=1,
                                                     allow_nan=False), encoding="utf-8")
        (tmp / "table.md").write_text(table, encoding="utf-8")
    met = sum(1 for s in results["settings"] if s.get("n") and (
        0.90 <= s["coverage95"] <= 0.97 if s["covered"] else s["flagged_any"] >= 0.8))
    results["summary"] = (f"simulate mismatch: {len(results['settings'])} settings x "
                          f"{options.surveys} surveys of {options.views} views in "
                          f"{results['seconds']:.0f} s; targets met in {met}")
    return results
