"""One model of a batch, as a Dask task: resolve its inputs, keep its previous output when
nothing changed, else run ``scale`` into ``DIR/<name>/`` with its threads capped. Whatever
happens comes back as a :class:`JobOutcome` (a failure is a reason, never an exception): one
failed model never stops the others.
"""

from __future__ import annotations

import logging
import time
import traceback
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from sfm_laserscale.batch.rerun import previous_report, unchanged_reason
from sfm_laserscale.batch.threads import capped_threads
from sfm_laserscale.errors import InputError, ToolFailedError
from sfm_laserscale.guided_spots import GuidedSpotOptions
from sfm_laserscale.io.manifest import ManifestRow
from sfm_laserscale.pipeline_folders import GivenInputs, resolve_scale_inputs
from sfm_laserscale.provenance import captured_log
from sfm_laserscale.registration.options import SiftOptions
from sfm_laserscale.registration.sift_workers import SiftWorkerOptions
from sfm_laserscale.run_types import ScaleOptions
from sfm_laserscale.scene_reference import SceneStageOptions

logger = logging.getLogger(__name__)

STATUSES = ("ok", "no_scale", "error", "skipped")


@dataclass(frozen=True)
class ModelJob:
    """Everything a worker needs for one model (picklable)."""

    row: ManifestRow
    out_dir: Path  # DIR/<name>
    method: str  # the row's, else the batch's
    seed: int
    overwrite: bool  # redo even when nothing changed
    guided_spots: bool = True  # scale's search for missed spots where the model puts them
    scene_reference: bool = True  # scale's second detection with the model images' render


@dataclass(frozen=True)
class JobOutcome:
    """One row of summary.csv (docs/BATCH.md)."""

    name: str
    status: str  # ok | no_scale | error | skipped
    scale: float | None = None
    std: float | None = None
    ci95_low: float | None = None
    ci95_high: float | None = None
    inverse: float | None = None
    method: str | None = None
    images_used: int | None = None
    estimates: int | None = None
    wall_s: float = 0.0
    reason: str | None = None
    report: str | None = None  # <name>/report.html when written
    has_scale: bool = False


def scale_options(job: ModelJob, threads: int) -> ScaleOptions:
    """``scale``'s options for one job: no progress bars, ``threads - 1`` SIFT workers beside
    the job's process, pycolmap's SIFT on ``threads`` threads."""
    return ScaleOptions(method=job.method, seed=job.seed, progress=False,
                        sift=SiftOptions(num_threads=threads),
                        sift_workers=SiftWorkerOptions(workers=threads - 1),
                        guided=GuidedSpotOptions(enabled=job.guided_spots),
                        scene=SceneStageOptions(enabled=job.scene_reference))


def outcome_from_report(name: str, status: str, report: dict[str, Any], wall_s: float,
                        reason: str | None = None) -> JobOutcome:
    """The summary row of a written report.json."""
    s = report.get("scale") or {}
    ci = s.get("ci95") or [None, None]
    has = s.get("value") is not None
    why = reason if reason is not None else (None if has else s.get("reason"))
    return JobOutcome(name=name, status=status, scale=s.get("value"), std=s.get("std"),
                      ci95_low=ci[0], ci95_high=ci[1], inverse=s.get("inverse"),
                      method=s.get("method"), images_used=len(s.get("images_used") or []),
                      estimates=s.get("n_estimates"), wall_s=round(wall_s, 3), reason=why,
                      report=f"{name}/report.html", has_scale=has)


def _given(row: ManifestRow) -> GivenInputs:
    return GivenInputs(laser_images=row.laser_images, rig=row.rig, model=row.model,
                       mesh=row.mesh, images=row.images, database=row.database,
                       features=row.features, spots=row.spots,
                       colmap_workspace=row.colmap_workspace, openmvg_project=row.openmvg_project)


def _write_failure_log(out_dir: Path, lines: list[str], error: str) -> None:
    """The failed job's log: DIR/<name>/run.log, or run.failed.log beside a previous complete
    output (kept)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    name = "run.failed.log" if (out_dir / "report.json").exists() else "run.log"
    (out_dir / name).write_text("\n".join([*lines, error]) + "\n", encoding="utf-8")


def _scale(job: ModelJob, threads: int, t0: float) -> JobOutcome:
    from sfm_laserscale.commands import scale as scale_command

    inputs = resolve_scale_inputs(_given(job.row))
    options = scale_options(job, threads)
    previous = previous_report(job.out_dir)
    if previous is not None and not job.overwrite:
        changed = unchanged_reason(previous, inputs, options)
        if changed is None:
            return outcome_from_report(job.row.name, "skipped", previous,
                                       time.perf_counter() - t0,
                                       "inputs and options unchanged: kept")
        logger.info("%s: redone (%s)", job.row.name, changed)
    with capped_threads(threads):
        result = scale_command.run(inputs, job.out_dir, options, overwrite=True)
    return outcome_from_report(job.row.name, "ok" if result.success else "no_scale",
                               result.report, time.perf_counter() - t0)


def run_model_job(job: ModelJob, threads: int = 1) -> JobOutcome:
    """Run one model (in a Dask worker or in-process); never raises for the model's own
    failures: bad input, a tool failure or a bug become an ``error`` with its reason."""
    t0 = time.perf_counter()
    with captured_log() as lines:
        try:
            return _scale(job, threads, t0)
        except (InputError, ToolFailedError) as exc:
            reason = str(exc)
            detail = f"ERROR {reason}"
        except Exception as exc:  # a bug in one model must not stop the batch
            reason = f"internal error: {exc.__class__.__name__}: {exc}"
            detail = f"ERROR {reason}\n{traceback.format_exc()}"
    logger.warning("%s: %s", job.row.name, reason)
    _write_failure_log(job.out_dir, lines, detail)
    return replace(JobOutcome(name=job.row.name, status="error", reason=reason),
                   wall_s=round(time.perf_counter() - t0, 3))
