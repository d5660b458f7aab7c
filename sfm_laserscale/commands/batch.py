"""``batch``: ``scale`` on every model of a manifest, on Dask (docs/BATCH.md).

The manifest is read and checked whole before any work (exit status 2 naming the row and
column). Each model's outputs go to ``DIR/<name>/`` (exactly what ``scale --out`` writes, its
``run.log`` included; a failed model: its log there); ``DIR/summary.csv`` and
``DIR/summary.html`` list every model. A model whose inputs and options are unchanged since its
output was written is skipped unless ``overwrite``; a model killed mid-run left no output and
is redone. One failed model never stops the others.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from sfm_laserscale.batch.execute import run_jobs
from sfm_laserscale.batch.job import JobOutcome, ModelJob
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.manifest import read_manifest
from sfm_laserscale.provenance import progress_bar
from sfm_laserscale.report.batch_summary import write_summary
from sfm_laserscale.resources import available_cpus

__all__ = ["BatchInputs", "BatchOptions", "BatchResult", "run"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class BatchInputs:
    """The manifest (CSV)."""

    manifest: Path


@dataclass(frozen=True)
class BatchOptions:
    """How the models run."""

    jobs: int | None = None  # models at once (None: one per available core); 1: in-process
    scheduler: str | None = None  # an existing Dask cluster's address (tcp://host:8786)
    method: str = "all"  # for rows without a method
    seed: int = 0
    progress: bool = True
    guided_spots: bool = True  # scale's search for missed spots where the model puts them
    scene_reference: bool = True  # scale's second detection with the model images' render


@dataclass(frozen=True)
class BatchResult:
    """Every model's outcome, in the manifest's order."""

    outcomes: tuple[JobOutcome, ...]
    out_dir: Path
    all_scaled: bool
    summary: str


def _prepare(out_dir: Path) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("output path exists and is not a folder", out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder ({exc.strerror})", out_dir) \
            from None


def run(inputs: BatchInputs, out_dir: Path, options: BatchOptions = BatchOptions(),  # noqa: B008
        overwrite: bool = False) -> BatchResult:
    """Scale every model of the manifest into ``out_dir``; write the summary."""
    manifest = inputs.manifest.resolve()
    rows = read_manifest(manifest)
    jobs_n = options.jobs if options.jobs is not None else available_cpus()
    if jobs_n < 1:
        raise InputError(f"--jobs must be at least 1, got {jobs_n}")
    out_dir = out_dir.resolve()
    _prepare(out_dir)
    # a model killed mid-run left no report.json, only a staging folder that its next scale
    # run removes (io/outputs.py): it is redone
    jobs = [ModelJob(row=r, out_dir=out_dir / r.name, method=r.method or options.method,
                     seed=options.seed, overwrite=overwrite, guided_spots=options.guided_spots,
                     scene_reference=options.scene_reference)
            for r in rows]
    jobs_n = min(jobs_n, len(jobs))  # no idle worker processes
    where = options.scheduler or (f"{jobs_n} local worker processes" if jobs_n > 1
                                  else "this process")
    logger.info("batch: %d models from %s on %s", len(jobs), manifest, where)
    with progress_bar(options.progress, "models", total=len(jobs), unit="model") as bar:
        def done(o: JobOutcome) -> None:
            bar.update(1)
            logger.info("%s: %s%s", o.name, o.status, f" ({o.reason})" if o.reason else "")

        outcomes = run_jobs(jobs, jobs_n, options.scheduler, done)
    write_summary(out_dir, outcomes, manifest)
    counts = {s: sum(o.status == s for o in outcomes) for s in ("ok", "skipped", "no_scale",
                                                              "error")}
    scaled = sum(o.has_scale for o in outcomes)
    summary = (f"{scaled} of {len(outcomes)} models scaled ("
               + ", ".join(f"{n} {s}" for s, n in counts.items() if n)
               + f"); summary: {out_dir / 'summary.csv'}, {out_dir / 'summary.html'}")
    return BatchResult(tuple(outcomes), out_dir, scaled == len(outcomes), summary)
