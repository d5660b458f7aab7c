"""What a run needs to be reproduced: version, command, input files (size, SHA-256), options;
the run's log (the package's records and pycolmap's own glog messages) and its terminal progress
bars (one rule for every step: shown unless ``--quiet`` and only when stderr is a terminal).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import re
import shutil
import sys
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from tqdm import tqdm

from sfm_laserscale.io.run_lock import claim_if_abandoned, create_lock
from sfm_laserscale.version import __version__

logger = logging.getLogger(__name__)
_CHUNK = 1 << 22


def file_digest(path: Path) -> dict[str, Any]:
    """Size (bytes) and SHA-256 of one file."""
    h = hashlib.sha256()
    with path.open("rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    return {"path": str(path), "bytes": path.stat().st_size, "sha256": h.hexdigest()}


def _files(paths: Iterable[Path]) -> Iterator[Path]:
    for p in paths:
        if p.is_dir():
            yield from sorted(f for f in p.rglob("*") if f.is_file())
        elif p.is_file():
            yield p


def input_digests(paths: Iterable[Path | None]) -> list[dict[str, Any]]:
    """Digests of every input file (folders expanded), in a stable order."""
    return [file_digest(f) for f in _files(p for p in paths if p is not None)]


@contextmanager
def digests_in_background(paths: Iterable[Path | None]) -> Iterator[Future[list[dict[str, Any]]]]:
    """``input_digests(paths)`` computed in a thread while the caller goes on; leaving the
    block waits for it. SHA-256 and file reads release the GIL, so on a free core the hashes
    (0.05-0.7 s in the benchmarks, most of it the mesh and the database) cost no wall time."""
    with ThreadPoolExecutor(1, thread_name_prefix="input-sha256") as pool:
        yield pool.submit(input_digests, list(paths))


def options_dict(options: Any) -> Any:
    """A frozen options dataclass (nested) as JSON-friendly data."""
    if dataclasses.is_dataclass(options) and not isinstance(options, type):
        return {f.name: options_dict(getattr(options, f.name)) for f in dataclasses.fields(options)}
    if isinstance(options, tuple | list):
        return [options_dict(v) for v in options]
    if isinstance(options, Path):
        return str(options)
    return options


def provenance(input_paths: Iterable[Path | None], options: Any,
               digests: Future[list[dict[str, Any]]] | None = None) -> dict[str, Any]:
    """The report's ``provenance`` block. ``digests``: the paths' ``input_digests`` being
    computed (``digests_in_background``), waited for here; None: computed here."""
    return {
        "version": __version__,
        "command": [Path(sys.argv[0]).name, *sys.argv[1:]],
        "python": sys.version.split()[0],
        "inputs": input_digests(input_paths) if digests is None else digests.result(),
        "options": options_dict(options),
    }


class _ListHandler(logging.Handler):
    def __init__(self) -> None:
        super().__init__(level=logging.DEBUG)
        self.lines: list[str] = []
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(self.format(record))


@contextmanager
def captured_log(name: str = "sfm_laserscale") -> Iterator[list[str]]:
    """Collect every record of the package's loggers during a run (for the run's log file).

    A run's log file is one of its outputs, so this scoped handler is the one place outside
    the CLI that attaches a handler; it is removed when the run ends.
    """
    log = logging.getLogger(name)
    handler = _ListHandler()
    old_level = log.level
    log.setLevel(logging.DEBUG)
    log.addHandler(handler)
    try:
        yield handler.lines
    finally:
        log.removeHandler(handler)
        log.setLevel(old_level)


#: Header lines glog writes at the top of every log file (not messages).
_GLOG_HEADER = ("Log file created at:", "Running on machine:", "Running duration",
                "Log line format:")


class ColmapLog:
    """pycolmap's own (glog) messages of a run, written to temporary files while it runs.

    glog buffers INFO lines of a log file (FLAGS_logbuflevel, up to logbufsecs = 30 s) and
    pycolmap 4.2 exposes no flush; changing a severity's destination closes the current file
    (``LogFileObject::SetBasename``), which flushes it. So :meth:`lines` moves the destination
    to a fresh prefix and reads the closed files.
    """

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self._part = 0
        self._lines: list[str] = []
        self._read: set[Path] = set()
        self._stopped = False

    def _destination(self, prefix: str) -> None:
        import pycolmap

        pycolmap.logging.set_log_destination(pycolmap.logging.INFO, prefix)

    def start(self) -> None:
        """Send every severity (INFO and up) to a file in ``folder``."""
        self._part += 1
        self._destination(str(self.folder / f"pycolmap-{self._part}."))

    def _collect(self) -> None:
        for path in sorted(self.folder.iterdir()):
            if (path in self._read or not path.name.startswith("pycolmap-")
                    or not path.is_file() or path.is_symlink()):
                continue
            self._read.add(path)
            text = path.read_text(encoding="utf-8", errors="replace")
            self._lines += [ln for ln in text.splitlines()
                            if ln.strip() and not ln.startswith(_GLOG_HEADER)]

    def lines(self) -> list[str]:
        """Every message so far (flushes: the current file is closed, a new one started)."""
        if not self._stopped:
            self.start()
            self._collect()
        return list(self._lines)

    def stop(self) -> list[str]:
        """Close the files (no more glog files) and return every message."""
        if not self._stopped:
            self._destination("")
            self._collect()
            self._stopped = True
        return list(self._lines)


_GLOG_DIR_PREFIX = "sfm_laserscale_glog_"
_GLOG_TIME = re.compile(r"[IWEF](\d{8} \d\d:\d\d:\d\d\.\d{6}) ")


def _remove_stale_glog_dirs(parent: Path) -> None:
    """Remove the temporary glog folders of runs that are gone (killed runs cannot clean up
    after themselves): each folder's run holds the lock ``<folder>.lock`` while it lives
    (:mod:`sfm_laserscale.io.run_lock`; no process ids: in a container every run is pid 1)."""
    for d in parent.glob(_GLOG_DIR_PREFIX + "*"):
        if not d.is_dir() or d.is_symlink():
            continue
        lock = claim_if_abandoned(d.with_name(d.name + ".lock"))
        if lock is not None:
            with lock:
                shutil.rmtree(d, ignore_errors=True)


def _stderr_threshold(logging_: Any) -> int:
    """The lowest glog severity that reaches the terminal with the current settings."""
    if logging_.logtostderr or logging_.alsologtostderr:
        return int(logging_.minloglevel)
    return max(int(logging_.minloglevel), int(logging_.stderrthreshold))


@contextmanager
def captured_colmap_log() -> Iterator[ColmapLog]:
    """Capture pycolmap's (glog) messages of every level during the block into temporary files
    (removed at the end); the terminal keeps showing what it showed before (the CLI's
    ``--verbose`` setting, see ``registration.configure_colmap_logging``)."""
    import pycolmap

    lg = pycolmap.logging
    saved = {k: getattr(lg, k) for k in ("logtostderr", "alsologtostderr", "minloglevel",
                                         "stderrthreshold")}
    threshold = _stderr_threshold(lg)
    _remove_stale_glog_dirs(Path(tempfile.gettempdir()))
    token, lock = create_lock(Path(tempfile.gettempdir()), _GLOG_DIR_PREFIX, ".lock")
    folder = lock.path.with_name(f"{_GLOG_DIR_PREFIX}{token}")  # guarded by <folder>.lock
    folder.mkdir()
    log = ColmapLog(folder)
    try:
        lg.logtostderr, lg.alsologtostderr = False, False
        lg.minloglevel, lg.stderrthreshold = 0, threshold
        log.start()
        yield log
    finally:
        log.stop()
        for key, value in saved.items():
            setattr(lg, key, value)
        shutil.rmtree(folder, ignore_errors=True)
        lock.release()


class _NoGlog:
    """Stands in for :class:`ColmapLog` when nothing is captured."""

    def lines(self) -> list[str]:
        return []


@contextmanager
def glog_without_files() -> Iterator[_NoGlog]:
    """During the block pycolmap's (glog) messages go to stderr only, warnings and up, and no
    log file is written (glog's default writes one per process into the temporary folder):
    a run that writes nothing (the Python API without ``out``). Previous settings come back."""
    import pycolmap

    lg = pycolmap.logging
    saved = (lg.logtostderr, lg.minloglevel)
    lg.logtostderr, lg.minloglevel = True, max(int(lg.minloglevel), 1)
    try:
        yield _NoGlog()
    finally:
        lg.logtostderr, lg.minloglevel = saved


def glog_lines(text: str) -> list[str]:
    """The glog lines (``[IWEF]yyyymmdd hh:mm:ss.uuuuuu ...``) of a text, e.g. a process's
    stderr."""
    return [ln for ln in text.splitlines() if _GLOG_TIME.match(ln)]


def merged_glog(*sources: Sequence[str]) -> list[str]:
    """glog lines of several processes in time order (a line without a timestamp stays with
    the line before it; equal times keep the sources' order)."""
    groups: list[tuple[str, int, list[str]]] = []
    for k, lines in enumerate(sources):
        for ln in lines:
            if groups and groups[-1][1] == k and not _GLOG_TIME.match(ln):
                groups[-1][2].append(ln)
            else:
                m = _GLOG_TIME.match(ln)
                groups.append((m.group(1) if m else "", k, [ln]))
    groups.sort(key=lambda g: g[0])
    return [ln for _, _, block in groups for ln in block]


def run_log_text(lines: Sequence[str], colmap_lines: Sequence[str]) -> str:
    """The run's log file: the package's records, then pycolmap's own messages (marked)."""
    out = list(lines)
    if colmap_lines:
        out.append(f"---- pycolmap's own log (glog, {len(colmap_lines)} lines; "
                   "format [IWEF]yyyymmdd hh:mm:ss.uuuuuu thread file:line] msg) ----")
        out += [f"pycolmap: {ln}" for ln in colmap_lines]
    return "\n".join(out) + "\n"


def progress_enabled(enabled: bool) -> bool:
    """Progress bars are shown when asked for (not ``--quiet``) and stderr is a terminal."""
    isatty = getattr(sys.stderr, "isatty", None)
    return bool(enabled and isatty is not None and isatty())


def progress_bar(enabled: bool, desc: str, **kw: Any) -> tqdm[Any]:
    """A tqdm bar on stderr, disabled unless :func:`progress_enabled` (not left on screen)."""
    kw.setdefault("leave", False)
    return tqdm(desc=desc, disable=not progress_enabled(enabled), file=sys.stderr, **kw)
