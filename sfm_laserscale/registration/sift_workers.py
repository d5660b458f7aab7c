"""SIFT of the laser images in worker processes, ahead of the registration (issue #7).

pycolmap's CPU SIFT runs one image on one core and holds the GIL, so threads cannot share
it. Worker processes (``python -m sfm_laserscale.registration.sift_workers``: a fresh
interpreter, so no fork of a process that holds OpenMP or FAISS threads and no re-run of the
caller's ``__main__``) extract the laser images' features while this process builds the descriptor
index, reads the mesh and registers the images already extracted. Workers take images from
the last one backwards, this process from the first one forwards, so it only waits where they
meet. The features are bit-identical to ``extract_sift`` in this process: the workers run the
same ``read_rgb`` and ``extract_sift``.

A worker that dies (killed, out of memory) gives its image back: this process extracts it
and the run goes on, with a warning naming the worker's last error output.
"""

from __future__ import annotations

import logging
import os
import pickle
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.images import LaserImage, read_rgb
from sfm_laserscale.lifecycle import die_with_parent
from sfm_laserscale.model import ImageFeatures
from sfm_laserscale.provenance import glog_lines
from sfm_laserscale.registration.options import SiftOptions
from sfm_laserscale.registration.sift import extract_sift
from sfm_laserscale.resources import available_cpus, available_memory_bytes

logger = logging.getLogger(__name__)

_READY = "ready"
_PARENT_ENV = "SFM_LASERSCALE_PARENT_PID"


@dataclass(frozen=True)
class SiftWorkerOptions:
    """How many worker processes extract SIFT beside this one; None: as many as fit."""

    workers: int | None = None  # None: min(free cores, images, memory); 0: none
    # memory a worker may use: its imports plus SIFT's working set per pixel (measured:
    # 0.55-0.59 GB at 1920 x 1080, 2.6-3.3 GB at 4000 x 3000, i.e. <= 300 B/px)
    worker_base_bytes: int = 300 * 2**20
    sift_bytes_per_pixel: float = 300.0
    memory_share: float = 0.5  # of the memory available when the run starts

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 0:
            raise InputError(f"SIFT workers must be >= 0, got {self.workers}")
        if not 0.0 < self.memory_share <= 1.0:
            raise InputError(f"memory_share must be in (0, 1], got {self.memory_share}")


def plan_workers(n_images: int, max_pixels: int, cpus: int, available_bytes: int | None,
                 options: SiftWorkerOptions) -> int:
    """Worker processes for ``n_images`` of at most ``max_pixels``: one per free core (this
    process keeps one), fewer than the images (this process extracts at least one, so it
    never sits idle while a worker starts: one image gets no worker), and within
    ``memory_share`` of the memory."""
    if options.workers is not None:
        return min(options.workers, n_images)
    n = min(max(cpus - 1, 0), max(n_images - 1, 0))
    if available_bytes is not None and n > 0:
        per_worker = options.worker_base_bytes + options.sift_bytes_per_pixel * max_pixels
        n = min(n, int(options.memory_share * available_bytes // per_worker))
    return max(n, 0)


@dataclass
class _Worker:
    """One worker process, the image it holds and its stderr (kept for a failure's reason)."""

    proc: subprocess.Popen[bytes]
    stderr: IO[bytes]
    current: int | None = None
    ready: bool = False
    alive: bool = True

    def output(self) -> str:
        """What the worker wrote to stderr so far."""
        try:
            self.stderr.seek(0)
            return self.stderr.read().decode("utf-8", "replace")
        except (OSError, ValueError):
            return ""

    def last_error(self) -> str:
        """The last lines the worker wrote to stderr (its traceback, when it had one)."""
        return " | ".join(self.output().strip().splitlines()[-3:])


class SiftPool:
    """Images' SIFT (the laser images, or the model's when it is re-extracted), shared
    between this process and ``workers`` processes."""

    def __init__(self, paths: Sequence[Path], options: SiftOptions, workers: int) -> None:
        self._paths = list(paths)
        self._index = {p: i for i, p in enumerate(self._paths)}
        self._options = options
        self._cond = threading.Condition()
        self._claimed = [False] * len(self._paths)
        self._results: dict[int, tuple[ImageFeatures | BaseException, float]] = {}
        self._delivered: set[int] = set()  # asked for again: extracted here, never waited for
        self._back = len(self._paths) - 1
        self._closed = False
        self.seconds_here = 0.0  # SIFT wall time spent in this process
        self.seconds_in_workers = 0.0  # SIFT wall time spent in the workers (summed)
        self.images_in_workers = 0
        self.glog_lines: list[str] = []  # pycolmap's (glog) lines of the workers, after close()
        # This process's BLAS and OpenMP (FAISS) threads are left as they are: limited to the
        # cores the workers leave, the index build and the search took 1.5-2x longer (FAISS
        # IVF search at 1M points 1.9 -> 3.1 s, 640 x 480, 2 cores), sharing cost less.
        started = [self._start_worker() for _ in range(workers)]
        self._workers = [w for w in started if w is not None]
        self._threads = [threading.Thread(target=self._serve, args=(w,), daemon=True,
                                          name=f"sift-worker-{i}")
                         for i, w in enumerate(self._workers)]
        for t in self._threads:
            t.start()

    @property
    def workers(self) -> int:
        """Number of worker processes started."""
        return len(self._workers)

    def _start_worker(self) -> _Worker | None:
        """A worker process importing this very package; None (and a warning) if none starts."""
        err = tempfile.TemporaryFile()  # noqa: SIM115 - closed by close()
        here = str(Path(__file__).resolve().parents[2])  # the folder holding sfm_laserscale
        path = os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p)
        # glog keeps writing to stderr (the file above): its lines go into run.log
        env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=path,
                   **{_PARENT_ENV: str(os.getpid())})
        try:
            proc = subprocess.Popen([sys.executable or "python3", "-m", __name__],
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err,
                                    env=env)
        except OSError as exc:
            err.close()
            logger.warning("no SIFT worker process (%s): SIFT runs in this process", exc)
            return None
        return _Worker(proc, err)

    def _claim_from_back(self, w: _Worker) -> int | None:
        """The last image nobody has taken, now ``w``'s; None when there is none left."""
        with self._cond:
            while self._back >= 0 and self._claimed[self._back]:
                self._back -= 1
            if self._closed or self._back < 0:
                return None
            self._claimed[self._back] = True
            w.current = self._back
            return self._back

    def _serve(self, w: _Worker) -> None:
        """Thread: feeds one worker images from the back and stores what it returns."""
        stdin, stdout = w.proc.stdin, w.proc.stdout
        try:
            if stdin is None or stdout is None or pickle.load(stdout) != _READY:
                raise EOFError("the worker did not start")
            w.ready = True
            while (i := self._claim_from_back(w)) is not None:
                pickle.dump((i, self._paths[i], self._options), stdin)
                stdin.flush()
                index, payload, seconds = pickle.load(stdout)
                with self._cond:
                    self._results[index] = (payload, seconds)
                    self.seconds_in_workers += seconds
                    self.images_in_workers += 1
                    w.current = None
                    self._cond.notify_all()
        except Exception as exc:  # noqa: BLE001 - any failure: the image comes back here
            self._worker_died(w, exc)
            return
        self._stop(w)

    def _worker_died(self, w: _Worker, exc: BaseException) -> None:
        with self._cond:
            w.alive = False
            lost = w.current
            if lost is not None and lost not in self._results:
                self._claimed[lost] = False  # given back: this process extracts it
                self._back = max(self._back, lost)
            w.current = None
            self._cond.notify_all()
        self._stop(w)
        if not self._closed:
            logger.warning("SIFT worker %d stopped (exit code %s, %s: %s); its image is "
                           "extracted in this process", w.proc.pid, w.proc.returncode,
                           type(exc).__name__, w.last_error() or "no error output")

    def features(self, path: Path, rgb: Any) -> ImageFeatures:
        """The features of the image at ``path``: extracted here from ``rgb`` (its pixels, or
        a function reading them) when no worker has taken it, else the worker's, waited for;
        a worker's exception is raised here."""
        index = self._index.get(path)
        if index is None:
            raise ValueError(f"{path} is not one of the pool's images")
        with self._cond:
            while (index not in self._results and self._claimed[index]
                   and index not in self._delivered):
                self._cond.wait()
            local = not self._claimed[index] or index in self._delivered
            self._claimed[index] = True
            self._delivered.add(index)
            done = None if local else self._results.pop(index)
        if done is None:
            pixels = rgb() if callable(rgb) else rgb
            t0 = time.perf_counter()
            feats = extract_sift(pixels, self._options)
            self.seconds_here += time.perf_counter() - t0
            return feats
        payload = done[0]
        if isinstance(payload, BaseException):
            raise payload
        return payload

    def _stop(self, w: _Worker) -> None:
        """Close the worker's input (it exits) and collect it; kill it if it is still busy."""
        for stream in (w.proc.stdin, w.proc.stdout):
            try:
                if stream is not None:
                    stream.close()
            except OSError:  # pragma: no cover - broken pipe on close
                pass
        try:
            w.proc.wait(timeout=5.0 if w.alive else 0.5)
        except subprocess.TimeoutExpired:
            w.proc.kill()
            w.proc.wait()

    def close(self) -> None:
        """Stop the workers: unclaimed images are left, a busy worker is killed."""
        with self._cond:
            self._closed = True
            busy = [w for w in self._workers if w.current is not None or not w.ready]
        for w in busy:
            w.proc.kill()  # an extraction nobody will use, or a worker still importing
        for t in self._threads:
            t.join()
        for w in self._workers:
            self.glog_lines += glog_lines(w.output())
            w.stderr.close()

    def __enter__(self) -> SiftPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def start_sift_pool(images: Sequence[LaserImage], sift: SiftOptions,
                    options: SiftWorkerOptions) -> SiftPool | None:
    """A pool for the readable laser ``images`` when ``plan_workers`` gives workers, else
    None."""
    usable = [li for li in images if li.camera is not None]
    pixels = max((li.camera.width * li.camera.height for li in usable if li.camera), default=0)
    return start_pool([li.path for li in usable], pixels, sift, options, "laser images")


def start_pool(paths: Sequence[Path], max_pixels: int, sift: SiftOptions,
               options: SiftWorkerOptions, what: str) -> SiftPool | None:
    """A pool for the images at ``paths`` (of at most ``max_pixels``) when ``plan_workers``
    gives workers, else None."""
    n = plan_workers(len(paths), max_pixels, available_cpus(), available_memory_bytes(), options)
    if n == 0:
        return None
    logger.info("SIFT of %d %s shared with %d worker process(es)", len(paths), what, n)
    return SiftPool(paths, sift, n)


def _picklable(exc: BaseException) -> BaseException:
    """``exc`` when it survives pickling, else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - any pickling failure
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def _serve_requests(inp: IO[bytes], out: IO[bytes]) -> None:
    """Worker loop: (index, path, options) in, (index, features or exception, seconds) out."""
    pickle.dump(_READY, out)
    out.flush()
    while True:
        try:
            index, path, options = pickle.load(inp)
        except EOFError:
            return
        t0 = time.perf_counter()
        payload: ImageFeatures | BaseException
        try:
            payload = extract_sift(read_rgb(path), options)
        except Exception as exc:  # noqa: BLE001 - sent back, raised in the parent
            payload = _picklable(exc)
        pickle.dump((index, payload, time.perf_counter() - t0), out)
        out.flush()


def main() -> None:
    """Worker entry point: results on the original stdout, anything printed goes to stderr."""
    # the kernel kills this worker when the run dies, even by SIGKILL; Ctrl-C is the run's
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    die_with_parent(int(os.environ.get(_PARENT_ENV, os.getppid())))
    # pycolmap's (glog) lines to stderr, which the parent keeps for run.log: glog's default
    # would also leave a log file per worker in the temporary folder, never removed
    import pycolmap

    pycolmap.logging.logtostderr = True
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    _serve_requests(sys.stdin.buffer, out)


if __name__ == "__main__":
    main()
