"""Threads per job so that jobs × threads ≤ the cores a host may use: each job's SIFT worker
processes, OpenCV's, FAISS's and every OpenMP/BLAS pool (threadpoolctl) are capped inside the
job; the environment variables are set for worker processes started by a local cluster.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
              "NUMEXPR_NUM_THREADS")


def threads_per_job(cores: int, slots: int) -> int:
    """Threads each of ``slots`` concurrent jobs may use on ``cores`` cores (at least 1)."""
    return max(1, cores // max(1, slots))


def thread_env(threads: int) -> dict[str, str]:
    """Environment of a worker process whose jobs may use ``threads`` threads."""
    return {k: str(threads) for k in THREAD_ENV}


@contextmanager
def capped_threads(threads: int) -> Iterator[None]:
    """Cap OpenCV, FAISS and the OpenMP/BLAS pools of this process at ``threads`` while the
    block runs (restored after it)."""
    import cv2
    import faiss
    from threadpoolctl import threadpool_limits

    cv_before, faiss_before = cv2.getNumThreads(), faiss.omp_get_max_threads()
    cv2.setNumThreads(threads)
    faiss.omp_set_num_threads(threads)
    try:
        with threadpool_limits(limits=threads):
            yield
    finally:
        cv2.setNumThreads(cv_before)
        faiss.omp_set_num_threads(faiss_before)
