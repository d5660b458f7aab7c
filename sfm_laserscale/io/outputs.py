"""Output folder handling: refuse non-empty folders, write beside them, move at the end.

A run that dies leaves either no ``--out`` or the previous complete one, never
a half-written folder. The staging folder ``.<out>.partial-<token>`` sits beside
``--out`` (same file system, so the final move is a rename). An existing ``--out``
(``--overwrite``) is swapped with the staged one in one atomic step (Linux ``renameat2``
with ``RENAME_EXCHANGE``); where that is unsupported it is first renamed to
``.<out>.old-<token>``, so at every instant either the old or the new complete folder exists.

Who owns a staging folder is told by a lock, not by a process id: the run holds an ``flock``
on ``.<out>.lock-<token>`` (:mod:`sfm_laserscale.io.run_lock`) from before the folder exists
until after it is gone, and the kernel drops the lock when the run dies, even by SIGKILL. The
next run on the same ``--out`` removes the staging and old folders whose lock it can take (or
whose lock file is missing: folders of older versions), and moves an old folder back when
``--out`` is missing. (A process-id check kept them forever in containers, where every run is
pid 1.) Protects against a killed process, not against power loss (no fsync).
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
from collections.abc import Iterator
from pathlib import Path

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.run_lock import claim_if_abandoned, create_lock

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


def _staging_names(out: Path) -> re.Pattern[str]:
    """``.<out>.partial-<token>``, ``.<out>.old-<token>`` and ``.<out>.lock-<token>``."""
    return re.compile(rf"^\.{re.escape(out.name)}\.(partial|old|lock)-(.+)$")


def clean_stale_staging(out: Path) -> list[Path]:
    """Remove the staging/old folders of dead runs beside ``out`` (their lock can be taken, or
    has no file); restore an old ``out`` that a killed run had moved aside before its new one
    was in place. Returns what was removed (lock files not listed)."""
    out = Path(out).resolve()
    pattern = _staging_names(out)
    try:
        entries = sorted(out.parent.iterdir())
    except OSError:
        return []
    by_token: dict[str, dict[str, Path]] = {}
    for entry in entries:
        m = pattern.match(entry.name)
        if m is not None and not entry.is_symlink():
            by_token.setdefault(m[2], {})[m[1]] = entry
    removed: list[Path] = []
    for token, found in by_token.items():
        lock = claim_if_abandoned(out.parent / f".{out.name}.lock-{token}")
        if lock is None:
            continue  # a live run holds it
        with lock:
            removed += _tidy_dead_run(out, found)
    return removed


def _tidy_dead_run(out: Path, found: dict[str, Path]) -> list[Path]:
    """The staging and old folders of one dead run: the old output goes back in place when
    ``out`` is missing, the rest is removed."""
    removed = []
    for kind in ("partial", "old"):
        entry = found.get(kind)
        if entry is None or not entry.is_dir():
            continue
        if kind == "old" and not out.exists():
            logger.warning("restoring %s, left aside by a killed run", out)
            os.replace(entry, out)
            continue
        logger.info("removing %s, left by a killed run", entry)
        shutil.rmtree(entry, ignore_errors=True)
        removed.append(entry)
    return removed


@contextlib.contextmanager
def staged_output_dir(out: Path, overwrite: bool) -> Iterator[Path]:
    """Yield a temporary folder beside ``out``; on success it replaces ``out`` atomically. The
    folder is guarded by a lock this process holds until the folder is gone."""
    check_output_dir(out, overwrite)
    out = out.resolve()
    try:
        token, lock = create_lock(out.parent, f".{out.name}.lock-")
    except OSError as exc:
        raise InputError(f"output folder cannot be written ({exc})", out) from None
    with lock:
        tmp = out.parent / f".{out.name}.partial-{token}"
        try:
            tmp.mkdir()
        except OSError as exc:
            raise InputError(f"output folder cannot be written ({exc.strerror})", out) from None
        try:
            yield tmp
            _replace_dir(tmp, out, overwrite, token)
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


def _replace_dir(tmp: Path, out: Path, overwrite: bool = True, token: str = "0") -> None:
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
            old = out.parent / f".{out.name}.old-{token}"
            os.replace(out, old)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
    logger.info("outputs written to %s", out)

