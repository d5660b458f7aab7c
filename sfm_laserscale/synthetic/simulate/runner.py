"""``simulate``: every trial of a mode, in this process or in spawned worker processes, collected
into estimate rows, PCM-joint groups added, statistics and tables built (no files written)."""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.lifecycle import process_pool
from sfm_laserscale.model import Camera
from sfm_laserscale.raycast import MeshRaycaster
from sfm_laserscale.rig import Rig
from sfm_laserscale.synthetic.simulate.areas import SimScene, load_scene
from sfm_laserscale.synthetic.simulate.configs import (
    LaserSetting,
    SimulationInputs,
    SimulationOptions,
    load_settings,
)
from sfm_laserscale.synthetic.simulate.samples import (
    Collected,
    GroupResult,
    GroupTask,
    add_groups,
    collect,
    group_tasks,
    joint_group,
)
from sfm_laserscale.synthetic.simulate.stats import grid_maps, overall, summarize
from sfm_laserscale.synthetic.simulate.tables import markdown_report
from sfm_laserscale.synthetic.simulate.trial import TrialContext, TrialRecord, run_trial
from sfm_laserscale.synthetic.simulate.views import ViewJob, grid_angles, make_jobs
from sfm_laserscale.version import __version__

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


_WORKER: TrialContext | None = None


def _init_worker(vertices: F64, triangles: NDArray[np.int64], camera: Camera,
                 settings: tuple[LaserSetting, ...], options: SimulationOptions) -> None:
    global _WORKER
    _WORKER = TrialContext(MeshRaycaster(vertices, triangles), camera, settings, options)


def _work(job: ViewJob) -> TrialRecord:
    if _WORKER is None:  # pragma: no cover - the pool's initializer always runs first
        raise RuntimeError("worker not initialised")
    return run_trial(_WORKER, job)


def _group_work(task: GroupTask) -> GroupResult:
    return joint_group(task)


Mapper = Callable[[Callable[[Any], Any], Sequence[Any]], Iterator[Any]]


@contextmanager
def worker_pool(caster: MeshRaycaster, settings: tuple[LaserSetting, ...],
                options: SimulationOptions, n_jobs: int) -> Iterator[Mapper]:
    """An ordered ``map`` for trials and groups: in this process, or in ``options.workers``
    spawned processes (each builds its own ray caster once; they never outlive the run).
    Spawned processes import the caller's main module: a script calling this with
    workers > 1 needs the usual
    ``if __name__ == "__main__":`` guard (without it the pool never starts)."""
    global _WORKER
    if options.workers == 1 or n_jobs < 8 * options.workers:
        previous = _WORKER
        _WORKER = TrialContext(caster, options.camera, settings, options)
        try:
            yield lambda fn, items: map(fn, items)
        finally:
            _WORKER = previous
        return
    quiet = replace(options, progress=False)
    # workers die with this process and are killed when the run ends early (a signal, an
    # error): none is left computing trials nobody will read (sfm_laserscale.lifecycle)
    with process_pool(options.workers, initializer=_init_worker,
                      initargs=(caster.vertices, caster.triangles, options.camera,
                                settings, quiet)) as pool:
        def pmap(fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[Any]:
            chunk = max(1, min(16, len(items) // (8 * options.workers)))
            return pool.map(fn, items, chunksize=chunk)

        yield pmap


def _progress(items: Iterable[Any], total: int, desc: str, options: SimulationOptions
              ) -> Iterator[Any]:
    from tqdm import tqdm

    yield from tqdm(items, total=total, desc=desc, unit="view", leave=False,
                    disable=not options.progress or not sys.stderr.isatty())


def run_trials(pmap: Mapper, jobs: Sequence[ViewJob], options: SimulationOptions
               ) -> Iterator[TrialRecord]:
    """Every job's record, in job order."""
    yield from _progress(pmap(_work, jobs), len(jobs), f"simulate {options.mode}", options)


@dataclass(frozen=True)
class SimulationResult:
    """Everything a simulation produced (results.json's content, the tables, the rows)."""

    options: SimulationOptions
    settings: tuple[LaserSetting, ...]
    scene: SimScene
    collected: Collected
    results: dict[str, Any]
    table_md: str
    timings: dict[str, float]
    summary: str


def _jsonable(x: Any) -> Any:
    """Plain JSON values: arrays to lists, NaN/inf to None, dataclasses and tuples unpacked."""
    if hasattr(x, "__dataclass_fields__") and not isinstance(x, type):
        return {k: _jsonable(v) for k, v in asdict(x).items()}
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _rig_json(rig: Rig) -> dict[str, Any]:
    return {"name": rig.name,
            "lasers": [{"name": las.name, "origin_m": las.origin, "direction": las.direction}
                       for las in rig.lasers],
            "pairs": [{"lasers": list(p.lasers), "separation_m": p.separation}
                      for p in rig.pairs]}


def _maps_json(col: Collected, options: SimulationOptions) -> list[dict[str, Any]]:
    if options.mode != "grid":
        return []
    angles = grid_angles(options).tolist()
    return [{"config": c, "distance_m": d, "area": area, "method": m, "angles_deg": angles,
             "mean_error_percent": arr}
            for (c, d), areas in grid_maps(col, options).items()
            for area, maps in areas.items() for m, arr in maps.items()]


def build_results(scene: SimScene, settings: Sequence[LaserSetting], col: Collected,
                  options: SimulationOptions, timings: dict[str, float]) -> dict[str, Any]:
    """The content of results.json (plain JSON values)."""
    unit = {"grid": "per view", "random": "views in all", "noise-table": "per cell"}[options.mode]
    rot, centre = np.asarray(col.rotation_error_deg), np.asarray(col.centre_error_m)
    return _jsonable({
        "version": __version__, "mode": options.mode, "true_scale": options.true_scale,
        "units": "bias, std, rmse, predicted_sigma: % of the true scale; ratio = std / "
                 "predicted_sigma; z = (estimate − truth) / reported sigma; coverage95: "
                 "fraction of 95 % intervals holding the truth",
        "trials": options.resolved("trials"), "trials_unit": unit,
        "camera": options.camera, "group_size": options.group_size,
        "outlier_ratio": options.outlier_ratio, "n_points": options.n_points,
        "antithetic": options.antithetic, "seed": options.seed,
        "scene": {"source": scene.source, "areas": scene.areas},
        "configs": {s.config: _rig_json(s.rig) for s in settings},
        "registration": {"views": col.views, "failed": sum(col.failed.values()),
                         "reasons": dict(col.failed),
                         "rotation_error_deg_median": float(np.median(rot)) if len(rot) else None,
                         "centre_error_mm_median": float(np.median(centre)) * 1e3
                         if len(centre) else None},
        "settings": summarize(col, options), "overall": overall(col, options),
        "grid_maps": _maps_json(col, options), "timings_s": timings,
    })


def _summary_line(results: dict[str, Any], seconds: float) -> str:
    reg = results["registration"]
    parts = [f"simulate {results['mode']}: {reg['views']} views ({reg['failed']} not "
             f"registered) in {seconds:.0f} s"]
    for config, per in results["overall"].items():
        for m in ("fcm", "fcm_fused", "pcm", "pcm_joint"):
            v = per.get(m)
            if v and v.get("z_rms") is not None:
                parts.append(f"{config} {m}: RMS z {v['z_rms']:.2f}, 95 % coverage "
                             f"{v['coverage95']:.3f} (n {v['n']})")
    return "\n".join(parts)


def simulate(inputs: SimulationInputs, options: SimulationOptions,
             prepared: tuple[SimScene, MeshRaycaster] | None = None) -> SimulationResult:
    """Run the experiments of ``options.mode`` (no files written). ``prepared``: a scene from
    :func:`load_scene` / :func:`build_scene` with the same ``true_scale`` (else it is loaded)."""
    timings: dict[str, float] = {}
    t_all = t0 = time.perf_counter()
    scene, caster = prepared if prepared is not None else load_scene(inputs, options)
    settings = load_settings(inputs, options)
    timings["scene"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    jobs = make_jobs(scene, caster, options)
    timings["views"] = time.perf_counter() - t0
    with worker_pool(caster, settings, options, len(jobs)) as pmap:
        t0 = time.perf_counter()
        col = collect(run_trials(pmap, jobs, options), settings)
        timings["trials"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        tasks = group_tasks(col, settings, options)
        add_groups(col, pmap(_group_work, tasks))
        timings["pcm_joint"] = time.perf_counter() - t0
    timings["trial_cpu_ms_mean"] = 1e3 * float(np.mean(col.cpu_s)) if col.cpu_s else 0.0
    timings["total"] = time.perf_counter() - t_all
    timings["workers"] = float(options.workers)
    results = build_results(scene, settings, col, options, timings)
    logger.info("simulation done: %d views, %d estimates", col.views, len(col.table))
    return SimulationResult(options, settings, scene, col, results,
                            markdown_report(results, options), timings,
                            _summary_line(results, timings["total"]))
