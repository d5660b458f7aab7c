"""How a run ends: termination signals as an exception, and worker processes that never
outlive their run.

Signals (:func:`signals_as_exceptions`, installed by the CLI): SIGTERM (``docker stop``, a
batch scheduler) and SIGINT (Ctrl-C) raise :class:`Interrupted` in the main thread, so every
``finally`` and context manager runs: the staging folder is removed, worker processes are
stopped, and the CLI exits with 128 + the signal number (143, 130). Python's default for
SIGTERM is to die on the spot, skipping all of that. A second signal during the cleanup ends
the process at once (``os._exit``); what it leaves is removed by the next run (the staging
lock, :mod:`sfm_laserscale.io.outputs`). As pid 1 of a container a process gets no default
signal action at all, so without these handlers ``docker stop`` waits 10 s and kills it;
``docker run --init`` (tini) or the image's tini entry point forwards the signals.

Workers (:func:`process_pool`, :func:`die_with_parent`): a worker asks the kernel to SIGKILL
it when its parent dies (Linux ``PR_SET_PDEATHSIG``), so a run killed with SIGKILL leaves no
worker busy on results nobody will read; when the run ends with an exception (an
:class:`Interrupted` included) its pool is shut down without waiting for the queued tasks and
its workers are killed. Workers ignore SIGINT: Ctrl-C reaches the whole process group, and the
parent alone decides how the run ends.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from types import FrameType
from typing import Any

logger = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1  # linux/prctl.h
HANDLED_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class Interrupted(BaseException):  # noqa: N818 - like KeyboardInterrupt, not an error
    """The run was asked to stop by a signal; not an ``Exception`` (no handler swallows it)."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"interrupted by {signal.Signals(signum).name}")
        self.signum = int(signum)

    @property
    def exit_status(self) -> int:
        """128 + the signal number, as a shell reports a process ended by it (143, 130)."""
        return 128 + self.signum

    @property
    def signal_name(self) -> str:
        """SIGTERM, SIGINT, ..."""
        return signal.Signals(self.signum).name


def _raise_interrupted(signum: int, frame: FrameType | None) -> None:
    for s in HANDLED_SIGNALS:  # a second signal during the cleanup ends the process at once
        signal.signal(s, _exit_now)
    raise Interrupted(signum)


def _exit_now(signum: int, frame: FrameType | None) -> None:
    os._exit(128 + signum)


@contextlib.contextmanager
def signals_as_exceptions() -> Iterator[None]:
    """SIGTERM and SIGINT raise :class:`Interrupted` in the main thread during the block (the
    previous handlers come back after it). Outside the main thread: does nothing."""
    try:
        previous = {s: signal.signal(s, _raise_interrupted) for s in HANDLED_SIGNALS}
    except ValueError:  # not the main thread: signals cannot be handled here
        yield
        return
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def die_with_parent(parent_pid: int) -> None:
    """Linux: the kernel SIGKILLs this process when the thread that started it ends; if
    ``parent_pid`` is already gone, exit now. Elsewhere a no-op. The parent's id is compared,
    not "parent is pid 1": in a container the run itself may be pid 1."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        return
    if os.getppid() != parent_pid:  # the parent died before prctl: nobody reads our results
        os._exit(0)


def _start_worker(parent_pid: int, initializer: Callable[..., None] | None,
                  initargs: tuple[Any, ...]) -> None:
    """First thing a pool worker runs: die with the parent, leave SIGINT to it, then the
    caller's initializer."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    die_with_parent(parent_pid)
    if initializer is not None:
        initializer(*initargs)


def kill_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel the queued tasks and kill the pool's workers now (no waiting for their tasks)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())  # no public handle
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.kill()
    for proc in procs:
        proc.join(timeout=5.0)


@contextlib.contextmanager
def process_pool(workers: int, initializer: Callable[..., None] | None = None,
                 initargs: tuple[Any, ...] = ()) -> Iterator[ProcessPoolExecutor]:
    """A spawn-context process pool whose workers die with this process (SIGKILL included)
    and are killed, their queued tasks cancelled, when the block ends with an exception
    (:class:`Interrupted` included); a normal end waits for them as usual."""
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_start_worker,
                               initargs=(os.getpid(), initializer, initargs))
    try:
        yield pool
    except BaseException:
        kill_pool(pool)
        raise
    pool.shutdown(wait=True)
