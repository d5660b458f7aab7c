"""Output folder handling: refuse non-empty folders, write beside them, move at the end.

A run that dies leaves either no ``--out`` or the previous complete one, never
a half-written folder. The staging folder ``.<out>.partial-<pid>-<random>`` sits beside
``--out`` (same file system, so the final move is a rename). An existing ``--out``
(``--overwrite``) is swapped with the staged one in one atomic step (Linux ``renameat2``
with ``RENAME_EXCHANGE``); where that is unsupported it is first renamed to
``.<out>.old-<pid>``, so at every instant either the old or the new complete folder exists.
Staging and old folders left by killed runs (their process is gone) are removed by the
next run on the same ``--out``; an old folder is moved back when ``--out`` is missing.
Protects against a killed process, not against power loss (no fsync).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import logging
import os
import re
import shutil
import sys
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
    clean_stale_staging(out)


def pid_alive(pid: int) -> bool:
    """True unless no process has this id (another user's process counts as alive)."""
    if pid <= 0:
        return True  # not a pid we wrote: leave the folder alone
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def clean_stale_staging(out: Path) -> list[Path]:
    """Remove the staging/old folders of dead runs beside ``out``; restore an old ``out`` that
    a killed run had moved aside before its new one was in place. Returns what was removed."""
    out = Path(out).resolve()
    pattern = re.compile(rf"^\.{re.escape(out.name)}\.(partial|old)-(\d+)(-.*)?$")
    removed: list[Path] = []
    try:
        entries = sorted(out.parent.iterdir())
    except OSError:
        return removed
    for entry in entries:
        m = pattern.match(entry.name)
        if m is None or not entry.is_dir() or entry.is_symlink() or pid_alive(int(m[2])):
            continue
        if m[1] == "old" and not out.exists():
            logger.warning("restoring %s, left aside by a killed run", out)
            os.replace(entry, out)
            continue
        logger.info("removing %s, left by a killed run", entry)
        shutil.rmtree(entry, ignore_errors=True)
        removed.append(entry)
    return removed


@contextlib.contextmanager
def staged_output_dir(out: Path, overwrite: bool) -> Iterator[Path]:
    """Yield a temporary folder beside ``out``; on success it replaces ``out`` atomically."""
    check_output_dir(out, overwrite)
    out = out.resolve()
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-{os.getpid()}-",
                                    dir=out.parent))
    except OSError as exc:
        raise InputError(f"output folder cannot be written ({exc.strerror})", out) from None
    try:
        yield tmp
        _replace_dir(tmp, out, overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths atomically (Linux renameat2 RENAME_EXCHANGE); False when the
    system or file system cannot (the caller falls back to two renames)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    if fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _replace_dir(tmp: Path, out: Path, overwrite: bool = True) -> None:
    """Move the complete staged folder ``tmp`` to ``out``; the previous ``out`` (if any) is
    dropped only once the new one is in place."""
    if not out.exists():
        os.replace(tmp, out)  # an empty folder created meanwhile is replaced too
    else:
        if not overwrite and out.is_dir() and any(out.iterdir()):
            raise InputError("output folder is not empty (use --overwrite to replace it)", out)
        if _exchange(tmp, out):
            shutil.rmtree(tmp, ignore_errors=True)  # tmp now holds the previous output
        else:
            old = out.parent / f".{out.name}.old-{os.getpid()}"
            os.replace(out, old)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
    logger.info("outputs written to %s", out)

