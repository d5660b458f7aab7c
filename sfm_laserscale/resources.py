"""CPUs and memory this process may use: its affinity mask, /proc/meminfo, and the limits of
its control group (a container's ``--cpus`` and ``--memory``), which neither
``os.sched_getaffinity`` nor MemAvailable shows. Both cgroup v2 (unified) and v1 are read; a
limit set on an ancestor group counts too.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from pathlib import Path

logger = logging.getLogger(__name__)

CGROUP_ROOT = Path("/sys/fs/cgroup")
_UNLIMITED_V1 = 1 << 60  # cgroup v1 writes "no limit" as a page-rounded 2^63 - 1


def _read(path: Path) -> str | None:
    try:
        return path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return None


def _group_dirs(root: Path, proc_cgroup: str, controller: str) -> list[Path]:
    """The process's group folder for ``controller`` and its ancestors: in the v1 hierarchy
    of that controller if it has one, else in the v2 unified tree. A path not mounted here
    (a container without a cgroup namespace) falls back to the mount's root."""
    lines = [ln.split(":", 2) for ln in proc_cgroup.splitlines() if ln.count(":") >= 2]
    v1 = [(c, p) for h, c, p in lines if controller in c.split(",")]
    v2 = [p for h, c, p in lines if h == "0" and c == ""]
    if v1:
        controllers, path = v1[0]
        base = root / controllers if (root / controllers).is_dir() else root / controller
    elif v2:
        path = v2[0]
        base = root if (root / "cgroup.controllers").exists() else root / "unified"
    else:
        return []
    here = base / path.lstrip("/")
    if not here.is_dir():
        return [base]
    dirs = [here, *here.parents]
    return dirs[: dirs.index(base) + 1] if base in dirs else [here]


def _proc_cgroup() -> str:
    return _read(Path("/proc/self/cgroup")) or ""


def _cpu_quota(folder: Path) -> float | None:
    """CPUs of one group's quota: v2 ``cpu.max`` ("max 100000" or "200000 100000"), v1
    ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` (-1: none)."""
    v2 = _read(folder / "cpu.max")
    if v2 is not None:
        quota, _, period = v2.partition(" ")
        return None if quota == "max" or not period else int(quota) / int(period)
    v1_quota, v1_period = _read(folder / "cpu.cfs_quota_us"), _read(folder / "cpu.cfs_period_us")
    if v1_quota is None or v1_period is None or int(v1_quota) <= 0 or int(v1_period) <= 0:
        return None
    return int(v1_quota) / int(v1_period)


def _memory_left(folder: Path) -> float | None:
    """Bytes one group may still take: its limit minus its usage (v2 ``memory.max`` and
    ``memory.current``, v1 ``memory.limit_in_bytes`` and ``memory.usage_in_bytes``)."""
    for limit_name, usage_name in (("memory.max", "memory.current"),
                                   ("memory.limit_in_bytes", "memory.usage_in_bytes")):
        limit, usage = _read(folder / limit_name), _read(folder / usage_name)
        if limit is None:
            continue
        if limit == "max" or int(limit) >= _UNLIMITED_V1 or usage is None:
            return None
        return max(0.0, float(int(limit) - int(usage)))
    return None


def _over_groups(root: Path, proc_cgroup: str | None, controller: str,
                 read: Callable[[Path], float | None]) -> float | None:
    text = _proc_cgroup() if proc_cgroup is None else proc_cgroup
    try:
        values = [v for d in _group_dirs(root, text, controller) if (v := read(d)) is not None]
    except (OSError, ValueError) as exc:  # an unreadable or unexpected cgroup file: no limit
        logger.debug("cgroup %s limit not read: %s", controller, exc)
        return None
    return min(values) if values else None


def cgroup_cpu_limit(root: Path = CGROUP_ROOT, proc_cgroup: str | None = None) -> float | None:
    """CPUs the process's control group may use (the smallest quota up its tree), None if
    there is no quota. ``proc_cgroup``: /proc/self/cgroup's text (read when None)."""
    return _over_groups(root, proc_cgroup, "cpu", _cpu_quota)


def cgroup_memory_left(root: Path = CGROUP_ROOT, proc_cgroup: str | None = None) -> int | None:
    """Bytes the process's control group may still allocate (the smallest limit − usage up its
    tree), None if there is no memory limit."""
    left = _over_groups(root, proc_cgroup, "memory", _memory_left)
    return None if left is None else int(left)


def available_cpus() -> int:
    """Cores this process may use: its affinity mask, capped by a cgroup CPU quota (whole
    CPUs, at least one)."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        n = os.cpu_count() or 1
    quota = cgroup_cpu_limit()
    return max(1, min(n, math.floor(quota))) if quota is not None else max(1, n)


def available_memory_bytes() -> int | None:
    """Memory this process may still take: MemAvailable of /proc/meminfo, capped by what its
    control group has left; None where neither is known."""
    known = [v for v in (_meminfo_available(), cgroup_memory_left()) if v is not None]
    return min(known) if known else None


def _meminfo_available() -> int | None:
    text = _read(Path("/proc/meminfo")) or ""
    for line in text.splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) * 1024
    return None
