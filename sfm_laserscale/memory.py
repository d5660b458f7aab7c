"""Returning freed heap memory to the operating system between the scale job's stages.

glibc's malloc keeps freed blocks in its heap, and its mmap threshold grows with the largest
block freed (up to 32 MB), so after building the descriptor index from a million-point
model ~0.6 GB of freed numpy buffers stayed resident (measured: docs/BENCHMARKS.md) and
counted against the peak of every later stage. ``malloc_trim(0)`` gives them back. Other C
libraries (macOS, musl) have no such call; there this is a no-op.
"""

from __future__ import annotations

import ctypes
import functools
import logging

logger = logging.getLogger(__name__)


@functools.cache
def _libc() -> ctypes.CDLL | None:
    # the symbols already loaded in this process (libc among them): ctypes.util.find_library
    # forks ``ldconfig -p`` from a process that may hold gigabytes and threads by then
    try:
        lib = ctypes.CDLL(None)
    except OSError:  # pragma: no cover - no dynamic loader
        return None
    return lib if hasattr(lib, "malloc_trim") else None


def trim_heap() -> bool:
    """Give freed heap memory back to the OS (glibc ``malloc_trim``); False where unavailable."""
    lib = _libc()
    if lib is None:
        return False
    lib.malloc_trim(ctypes.c_size_t(0))
    return True
