"""The mismatch table of docs/SIMULATE.md: surveys whose data carry errors the estimator is not
told about (``synthetic/simulate/mismatch.py``), coverage and std/σ of the headline per setting,
and how often the model checks flag them.

    .venv/bin/python scripts/bench_mismatch.py --out /tmp/mismatch [--surveys 200] [--views 8]
        [--settings "none" "σ_l understated 2×" ...] [--workers 2] [--seed 0]

Writes OUT/results.json (every setting's statistics) and OUT/table.md, and prints the table.
Settings run in ``--workers`` spawned processes (each builds its own scene and survey).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from sfm_laserscale.synthetic.simulate.mismatch import (
    MismatchOptions,
    mismatch_table,
    run_mismatch,
)
from sfm_laserscale.synthetic.simulate.mismatch_data import SETTINGS


def _one(args: tuple[str, int, int, int]) -> dict[str, Any]:
    name, surveys, views, seed = args
    res = run_mismatch(MismatchOptions(settings=(name,), surveys=surveys, views=views,
                                       seed=seed, progress=False))
    return {"meta": {k: v for k, v in res.items() if k != "settings"},
            "setting": res["settings"][0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--surveys", type=int, default=200)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--settings", nargs="+", default=[s.name for s in SETTINGS])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    jobs = [(name, a.surveys, a.views, a.seed) for name in a.settings]
    if a.workers > 1:
        with ProcessPoolExecutor(a.workers, mp_context=multiprocessing.get_context("spawn")) as ex:
            parts = list(ex.map(_one, jobs))
    else:
        parts = [_one(j) for j in jobs]
    results = dict(parts[0]["meta"])
    results["settings"] = [p["setting"] for p in parts]
    results["seconds"] = time.perf_counter() - t0
    table = mismatch_table(results)
    (a.out / "results.json").write_text(json.dumps(results, indent=1), encoding="utf-8")
    (a.out / "table.md").write_text(table, encoding="utf-8")
    print(table)
    for s in results["settings"]:
        print(s["name"], {k: round(v, 3) for k, v in s.get("flag_rates", {}).items()},
              f"corrected coverage {s.get('corrected_coverage95')}",
              f"{s.get('seconds', 0):.0f} s")
    print(f"total {results['seconds']:.0f} s")


if __name__ == "__main__":
    main()
