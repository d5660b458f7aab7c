#!/usr/bin/env python3
"""Benchmark: a batch of N synthetic models (the demo's survey generator, one seed per model:
real pycolmap SfM, 6 laser images each at 1024x768 by default) run with ``--jobs 1`` (in this
process) and ``--jobs 2`` (a local Dask cluster of 2 processes), as a user runs it: the
``sfm-laserscale batch`` command in a subprocess. Measures the wall time, the CPU time of the
batch and every process it started (user + system, from ``getrusage(RUSAGE_CHILDREN)``), the
CPU use (CPU time / wall time / cores) and checks every model against its true scale.

    .venv/bin/python scripts/bench_batch.py [--models 6] [--small] [--data DIR] [--jobs 1 2]

The data sets are made once in ``--data`` (reused when present).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sfm_laserscale.resources import available_cpus
from sfm_laserscale.synthetic.dataset import DemoDataOptions, make_demo_dataset

REPO = Path(__file__).resolve().parents[1]


def make_models(data: Path, n: int, small: bool) -> list[tuple[str, Path, float]]:
    """(name, data set folder, true scale) of n demo data sets (seeds 0..n-1)."""
    out = []
    for k in range(n):
        folder = data / f"model_{k:02d}"
        if not (folder / "truth.json").is_file():
            t0 = time.perf_counter()
            make_demo_dataset(folder, DemoDataOptions(small=small, seed=k, progress=False),
                              overwrite=True)
            print(f"made {folder} in {time.perf_counter() - t0:.0f} s", flush=True)
        truth = json.loads((folder / "truth.json").read_text())
        out.append((f"model_{k:02d}", folder, float(truth["true_scale"])))
    return out


def write_manifest(path: Path, models: list[tuple[str, Path, float]]) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["name", "laser_images", "rig", "model", "mesh", "database"])
        for name, folder, _ in models:
            w.writerow([name, folder / "laser_images", folder / "rig.toml", folder / "sparse" / "0",
                        folder / "mesh.ply", folder / "database.db"])


def run_batch(manifest: Path, out: Path, jobs: int) -> tuple[float, float, int]:
    """(wall s, CPU s of the batch's process tree, exit status)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run([str(Path(sys.executable).parent / "sfm-laserscale"), "batch",
                           str(manifest), "--out", str(out), "--jobs", str(jobs), "--quiet"],
                          capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode != 0:
        print(proc.stdout, proc.stderr, file=sys.stderr)
    return wall, cpu, proc.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--models", type=int, default=6)
    parser.add_argument("--small", action="store_true", help="the tests' small survey")
    parser.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "bench_batch")
    parser.add_argument("--jobs", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()

    models = make_models(args.data, args.models, args.small)
    manifest = args.data / "manifest.csv"
    write_manifest(manifest, models)
    cores = available_cpus()
    print(f"{len(models)} models, {cores} cores, load average {os.getloadavg()[0]:.2f}")
    for jobs in args.jobs:
        out = args.data / f"out_jobs{jobs}"
        wall, cpu, code = run_batch(manifest, out, jobs)
        with (out / "summary.csv").open() as fh:
            rows = list(csv.DictReader(fh))
        errors = [float(r["scale"]) / truth - 1 for r, (_, _, truth) in zip(rows, models,
                                                                            strict=True)
                  if r["scale"]]
        per_model = sorted(float(r["wall_s"]) for r in rows)
        print(f"--jobs {jobs}: exit {code}, wall {wall:.1f} s, CPU {cpu:.1f} s "
              f"({100 * cpu / wall / cores:.0f} % of {cores} cores), per model "
              f"{per_model[0]:.1f}-{per_model[-1]:.1f} s, {len(errors)}/{len(rows)} scaled, "
              f"max |error| {100 * max(abs(e) for e in errors):.3f} %", flush=True)


if __name__ == "__main__":
    main()
