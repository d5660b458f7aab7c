"""Output folder handling: refuse non-empty folders, write beside them, move at the end.

A run that dies leaves either no ``--out`` or the previous complete one, never
a half-written folder.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from sfm_laserscale.errors import InputError

logger = logging.getLogger(__name__)


def check_output_dir(out: Path, overwrite: bool) -> None:
    """Raise InputError when ``out`` cannot be used as a fresh output folder."""
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out)
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise InputError("output folder is not empty (use --overwrite to replace it)", out)
    parent = out.resolve().parent
    if not parent.exists():
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(
                f"cannot create the output folder's parent ({exc.strerror})", out
            ) from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError("output folder cannot be written (no permission)", out)


@contextlib.contextmanager
def staged_output_dir(out: Path, overwrite: bool) -> Iterator[Path]:
    """Yield a temporary folder beside ``out``; on success it replaces ``out`` atomically."""
    check_output_dir(out, overwrite)
    out = out.resolve()
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    except OSError as exc:
        raise InputError(f"output folder cannot be written ({exc.strerror})", out) from None
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _replace_dir(tmp, out)


def _replace_dir(tmp: Path, out: Path) -> None:
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    logger.info("outputs written to %s", out)
