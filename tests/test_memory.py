"""sfm_laserscale.memory: freed heap memory goes back to the OS between stages."""

from __future__ import annotations

import platform
from pathlib import Path

import numpy as np
import pytest

from sfm_laserscale.memory import trim_heap


def _rss() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                    reason="malloc_trim is glibc's")
def test_trim_returns_freed_heap_blocks_to_the_os() -> None:
    # Raise glibc's mmap threshold (a large block freed), then fill the heap with 2 MB
    # blocks: below the new threshold they live in the heap, and stay there once freed
    # because a block allocated last pins the heap's top.
    big = np.ones(16 << 20, dtype=np.uint8)  # <= 32 MB: raises the threshold to 16 MB
    del big
    blocks = [np.ones(2 << 20, dtype=np.uint8) for _ in range(150)]  # 300 MB
    pin = np.ones(2 << 20, dtype=np.uint8)
    del blocks
    before = _rss()
    assert trim_heap()
    after = _rss()
    assert before - after > 200 << 20, (before >> 20, after >> 20)
    del pin


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                    reason="malloc_trim is glibc's")
def test_trim_finds_libc_without_a_subprocess(monkeypatch: pytest.MonkeyPatch) -> None:
    """ctypes.util.find_library forked ``ldconfig -p`` from the run's process (0.4 GB by then,
    with threads); libc is looked up among the symbols already loaded instead."""
    import subprocess

    import sfm_laserscale.memory as memory

    def no_subprocess(*args: object, **kwargs: object) -> None:
        raise AssertionError(f"subprocess started: {args}")

    monkeypatch.setattr(subprocess.Popen, "__init__", no_subprocess)
    memory._libc.cache_clear()
    try:
        assert trim_heap() is True
    finally:
        memory._libc.cache_clear()
