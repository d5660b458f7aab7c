"""Lock files that live exactly as long as the process holding them.

An ``fcntl`` lock is released by the kernel when its holder exits, however it exits (even
SIGKILL), and it is seen across PID namespaces: containers sharing a temporary folder cannot
check each other's process ids, but they can test each other's locks. :func:`hold` takes the
lock (keep the returned file open while the owner lives); :func:`is_held` tells whether some
living process holds it.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import IO


def hold(path: Path) -> IO[bytes]:
    """Create ``path`` and take its exclusive lock; the lock lasts while the file stays open."""
    handle = open(path, "wb")  # noqa: SIM115 (the caller keeps it open: that is the lock)
    fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    handle.write(str(os.getpid()).encode())
    handle.flush()
    return handle


def is_held(path: Path) -> bool:
    """True when a living process holds the lock of ``path`` (False: missing or free)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False
