"""What a run needs to be reproduced: version, command, input files (size, SHA-256), options."""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sfm_laserscale import __version__

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


def options_dict(options: Any) -> Any:
    """A frozen options dataclass (nested) as JSON-friendly data."""
    if dataclasses.is_dataclass(options) and not isinstance(options, type):
        return {f.name: options_dict(getattr(options, f.name)) for f in dataclasses.fields(options)}
    if isinstance(options, tuple | list):
        return [options_dict(v) for v in options]
    if isinstance(options, Path):
        return str(options)
    return options


def provenance(input_paths: Iterable[Path | None], options: Any) -> dict[str, Any]:
    """The report's ``provenance`` block."""
    return {
        "version": __version__,
        "command": [Path(sys.argv[0]).name, *sys.argv[1:]],
        "python": sys.version.split()[0],
        "inputs": input_digests(input_paths),
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
