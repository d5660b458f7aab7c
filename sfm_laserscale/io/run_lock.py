"""Lock files that say "a live run owns this" without process ids (``fcntl.flock``).

A run creates its lock file and holds an exclusive ``flock`` on it for as long as it lives; the
kernel drops the lock when the process ends, however it ends (SIGKILL included). Another run
that can take the lock knows the owner is gone. Process ids cannot tell this: in a container
every run is pid 1 and "pid 1 is alive" always holds, and a pid can be reused.

Creating a lock is race-free against a concurrent cleaner: the owner creates the file
(``O_EXCL``), locks it, then checks that the path still names the file it locked (a cleaner
may have claimed and unlinked it in between); if not, it starts again with a new name.
Locks live on the same file system as what they guard (beside ``--out``); ``flock`` works
there on local file systems and on NFS (Linux emulates it with byte-range locks).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import secrets
from pathlib import Path


class HeldLock:
    """An exclusive lock on a file, held by this process until :meth:`release`."""

    def __init__(self, path: Path, fd: int | None) -> None:
        self.path = path
        self._fd = fd  # None: nothing held (the file was already gone)

    @property
    def held(self) -> bool:
        """True until released."""
        return self._fd is not None

    def release(self, unlink: bool = True) -> None:
        """Remove the lock file (while still holding it) and drop the lock."""
        if self._fd is None:
            return
        if unlink:
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> HeldLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _try_lock(fd: int) -> bool:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def new_token() -> str:
    """A unique name part: this process's id (for people reading the folder) and 8 random hex
    digits (what makes it unique; the id plays no part in any decision)."""
    return f"{os.getpid()}-{secrets.token_hex(4)}"


def create_lock(folder: Path, prefix: str, suffix: str = "",
                attempts: int = 20) -> tuple[str, HeldLock]:
    """A new lock file ``folder/<prefix><token><suffix>``, locked by this process: (token,
    lock). OSError when the folder cannot be written."""
    for _ in range(attempts):
        token = new_token()
        path = folder / f"{prefix}{token}{suffix}"
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_RDWR, 0o644)
        except FileExistsError:
            continue
        if not _try_lock(fd):  # a cleaner holds it for a moment: leave it to the cleaner
            os.close(fd)
            continue
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return token, HeldLock(path, fd)
        os.close(fd)  # claimed and unlinked by a cleaner before we locked it: a new name
    raise OSError(f"could not create a lock file in {folder}")


def claim_if_abandoned(path: Path) -> HeldLock | None:
    """The lock at ``path`` when its owner is gone (it can be taken now), else None; a missing
    file counts as abandoned (a lock with its file already removed: returns a released
    lock). The caller tidies up what the lock guarded, then releases it."""
    try:
        fd = os.open(path, os.O_RDWR)
    except FileNotFoundError:
        return HeldLock(path, None)
    except OSError:
        return None  # cannot tell (no permission): leave it alone
    if not _try_lock(fd):
        os.close(fd)
        return None
    return HeldLock(path, fd)

