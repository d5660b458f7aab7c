"""Time and summarise the `simulate` experiments (docs/SIMULATE.md numbers).

    .venv/bin/python scripts/bench_simulate.py --out /tmp/bench_sim [--runs sweep grid ...]
        [--workers 2]

Runs (each into OUT/<run>, overwritten):
    sweep       one 289-view sweep: configuration C, smooth area, 3 m, one draw per view
    grid        the default grid: A B C × smooth/rough × 2/3/4 m, one draw per view
    antithetic  the same grid with antithetic pairs (per-view bias maps)
    noise       the noise table: B C × σ_f {0.5, 1} × σ_l {0.25, 0.5} × 2/3/4 m, 500 draws
    random      10,000 random surface points and view angles (distances 2/3/4 m in turn)
    random_antithetic  3,000 random views as antithetic pairs (the systematic PCM error)
    noise_b33   the noise table (σ_f 0.5, σ_l 0.25) for configuration B with its two pairs
                0.33 m apart (opposite beams 16.5 cm from the camera) instead of 0.1 m: the
                separation the paper's PCM numbers imply (written to OUT/rig_b33.toml)

Prints, per run, the wall time, the mean CPU time of one trial, the number of views, and the
pooled calibration (RMS z, 95 % coverage) of the main methods; writes OUT/bench.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from sfm_laserscale.commands import simulate as simulate_command
from sfm_laserscale.resources import available_cpus
from sfm_laserscale.rig import rig_to_toml
from sfm_laserscale.synthetic.simulate.configs import (
    SimulationInputs,
    SimulationOptions,
    config_rig,
)

RUNS: dict[str, SimulationOptions] = {
    "sweep": SimulationOptions(mode="grid", configs=("C",), distances_m=(3.0,),
                               areas=("smooth",)),
    "grid": SimulationOptions(mode="grid"),
    "antithetic": SimulationOptions(mode="grid", antithetic=True),
    "noise": SimulationOptions(mode="noise-table"),
    "random": SimulationOptions(mode="random"),
    "random_antithetic": SimulationOptions(mode="random", trials=3000, antithetic=True),
    "noise_b33": SimulationOptions(mode="noise-table", sigma_f_px=(0.5,), sigma_l_px=(0.25,)),
}


def rig_b33(out: Path) -> Path:
    """Configuration B with each pair's beams 0.33 m apart (x = ±0.165 m), as a rig file."""
    base = config_rig("B")
    lasers = [replace(las, origin=np.array([3.3 * o[0], o[1], 0.0]))
              for las in base.lasers if (o := las.origin) is not None]
    rig = replace(base, name="B with 0.33 m pairs", lasers=tuple(lasers),
                  pairs=tuple(replace(p, separation=0.33) for p in base.pairs))
    path = out / "rig_b33.toml"
    path.write_text(rig_to_toml(rig), encoding="utf-8")
    return path


def _cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def bench(name: str, out: Path, workers: int) -> dict[str, Any]:
    """Run one experiment; its timings and pooled calibration."""
    options = replace(RUNS[name], workers=workers, progress=False)
    inputs = SimulationInputs(rig=rig_b33(out) if name == "noise_b33" else None)
    t0, cpu0 = time.perf_counter(), time.process_time() + _cpu_children()
    result = simulate_command.run(inputs, out / name, options, overwrite=True)
    wall = time.perf_counter() - t0
    cpu = time.process_time() + _cpu_children() - cpu0
    return {"wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "workers": workers,
            "load_avg_1min": round(os.getloadavg()[0], 2),
            "views": result.results["registration"]["views"],
            "timings_s": {k: round(v, 2) for k, v in result.timings.items()},
            "overall": result.results["overall"]}


def main() -> None:
    """Command line: which runs, output folder, workers."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--runs", nargs="+", choices=list(RUNS), default=list(RUNS))
    ap.add_argument("--workers", type=int, default=min(2, available_cpus()))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    report = {}
    for name in args.runs:
        report[name] = res = bench(name, args.out, args.workers)
        print(f"{name}: {res['views']} views, wall {res['wall_s']} s (trials "
              f"{res['timings_s']['trials']} s, {res['timings_s']['trial_cpu_ms_mean']} ms CPU "
              f"per trial, figures {res['timings_s'].get('figures', 0)} s), load "
              f"{res['load_avg_1min']}", flush=True)
        for config, per in res["overall"].items():
            print("   ", config, {m: (round(v["z_rms"], 3), round(v["coverage95"], 3))
                                for m, v in per.items() if v.get("z_rms") is not None})
        (args.out / "bench.json").write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
