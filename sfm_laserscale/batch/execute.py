"""The batch's jobs on Dask (``dask.distributed``): in this process (``jobs`` 1), on a local
cluster of ``jobs`` worker processes started here and closed with the batch, or on an existing
cluster (``scheduler`` address; its workers need the package and the paths). Each job's threads
are capped so that the jobs running at once on a host use at most its cores: the cores a worker
reports (``available_cpus`` run there) divided by the task slots of all workers on its host.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from sfm_laserscale.batch.job import JobOutcome, ModelJob, run_model_job
from sfm_laserscale.batch.threads import thread_env, threads_per_job
from sfm_laserscale.resources import available_cpus

logger = logging.getLogger(__name__)


def _in_worker(job: ModelJob, caps: dict[str, int]) -> JobOutcome:
    """The task: the job with the thread cap of the worker it landed on."""
    from distributed import get_worker

    return run_model_job(job, caps.get(get_worker().address, 1))


def _result(future: Any, job: ModelJob) -> JobOutcome:
    """The task's outcome; a worker lost meanwhile (killed, out of memory) is the model's error,
    not the batch's."""
    try:
        return future.result()  # type: ignore[no-any-return]
    except Exception as exc:
        logger.warning("%s: its worker failed: %s", job.row.name, exc)
        return JobOutcome(name=job.row.name, status="error",
                          reason=f"the Dask worker running it failed: {exc.__class__.__name__}: "
                                 f"{exc}")


def worker_thread_caps(client: Any) -> dict[str, int]:
    """Worker address -> threads per job: its host's cores over the host's task slots."""
    info = client.scheduler_info(n_workers=-1)["workers"]
    cores = client.run(available_cpus)
    slots: dict[str, int] = {}
    for w in info.values():
        slots[w["host"]] = slots.get(w["host"], 0) + int(w["nthreads"])
    return {addr: threads_per_job(int(cores.get(addr, 1)), slots[w["host"]])
            for addr, w in info.items()}


@contextmanager
def dask_client(jobs: int, scheduler: str | None) -> Iterator[Any]:
    """A Client of the existing cluster (``scheduler``), of a local cluster of ``jobs``
    processes (closed on exit: no worker outlives the batch), or None for in-process."""
    if scheduler is None and jobs <= 1:
        yield None
        return
    from distributed import Client, LocalCluster

    if scheduler is not None:
        with Client(scheduler, timeout="30s") as client:
            yield client
        return
    threads = threads_per_job(available_cpus(), jobs)
    with LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True,
                      dashboard_address=None, env=thread_env(threads),
                      memory_limit=0) as cluster, Client(cluster) as client:
        yield client


def run_jobs(jobs: Sequence[ModelJob], n_jobs: int, scheduler: str | None,
             done: Callable[[JobOutcome], None]) -> list[JobOutcome]:
    """Run every job; ``done`` is called as each finishes; outcomes in the jobs' order."""
    outcomes: dict[str, JobOutcome] = {}
    with dask_client(n_jobs, scheduler) as client:
        if client is None:
            threads = available_cpus()
            for job in jobs:
                outcomes[job.row.name] = run_model_job(job, threads)
                done(outcomes[job.row.name])
        else:
            from distributed import as_completed

            caps = worker_thread_caps(client)
            logger.info("Dask: %d worker(s), threads per job %s", len(caps), sorted(set(
                caps.values())))
            futures = {client.submit(_in_worker, job, caps, pure=False,
                                     key=f"sfm-laserscale-{job.row.name}-{uuid.uuid4().hex}"):
                       job for job in jobs}
            for future in as_completed(futures):
                outcome = _result(future, futures[future])
                outcomes[outcome.name] = outcome
                done(outcome)
    return [outcomes[job.row.name] for job in jobs]
