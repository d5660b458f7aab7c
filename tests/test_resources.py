"""CPUs and memory the run may use: cgroup v2 and v1 limits read from fake group trees."""

from __future__ import annotations

from pathlib import Path

import pytest

from sfm_laserscale import resources
from sfm_laserscale.resources import (
    available_cpus,
    available_memory_bytes,
    cgroup_cpu_limit,
    cgroup_memory_left,
)

GB = 2**30


def _write(folder: Path, **files: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (folder / name.replace("_", ".", 1)).write_text(text + "\n")


def _v2(root: Path) -> Path:
    _write(root, cgroup_controllers="cpu memory")
    return root


def test_v2_container_limits_at_the_root(tmp_path: Path) -> None:
    """A container with a cgroup namespace: /proc/self/cgroup says "0::/"."""
    root = _v2(tmp_path)
    _write(root, cpu_max="150000 100000", memory_max=str(4 * GB), memory_current=str(GB))
    assert cgroup_cpu_limit(root, "0::/\n") == pytest.approx(1.5)
    assert cgroup_memory_left(root, "0::/\n") == 3 * GB


def test_v2_the_smallest_limit_up_the_tree_counts(tmp_path: Path) -> None:
    root = _v2(tmp_path)
    _write(root / "a", cpu_max="400000 100000", memory_max=str(2 * GB),
           memory_current=str(GB // 2))
    _write(root / "a" / "b", cpu_max="max 100000", memory_max="max",
           memory_current=str(GB // 4))
    assert cgroup_cpu_limit(root, "0::/a/b") == pytest.approx(4.0)
    assert cgroup_memory_left(root, "0::/a/b") == 2 * GB - GB // 2


def test_v2_no_limits(tmp_path: Path) -> None:
    root = _v2(tmp_path)
    _write(root / "user.slice", cpu_max="max 100000", memory_max="max", memory_current="5")
    assert cgroup_cpu_limit(root, "0::/user.slice") is None
    assert cgroup_memory_left(root, "0::/user.slice") is None


def test_v1_hierarchies_per_controller(tmp_path: Path) -> None:
    """cgroup v1 (as on this machine): one hierarchy per controller, "no limit" is 2^63 − 4096;
    a group path not mounted here falls back to the mount's root (a container)."""
    _write(tmp_path / "cpu,cpuacct", cpu_cfs_quota_us="200000", cpu_cfs_period_us="100000")
    _write(tmp_path / "memory", memory_limit_in_bytes=str(8 * GB),
           memory_usage_in_bytes=str(3 * GB))
    text = "0::/\n4:memory:/docker/abc\n2:cpu,cpuacct:/docker/abc\n"  # v1 first, any order
    assert cgroup_cpu_limit(tmp_path, text) == pytest.approx(2.0)
    assert cgroup_memory_left(tmp_path, text) == 5 * GB
    _write(tmp_path / "memory", memory_limit_in_bytes="9223372036854771712")
    _write(tmp_path / "cpu,cpuacct", cpu_cfs_quota_us="-1")
    assert cgroup_memory_left(tmp_path, text) is None
    assert cgroup_cpu_limit(tmp_path, text) is None


def test_nothing_readable_means_no_limit(tmp_path: Path) -> None:
    assert cgroup_cpu_limit(tmp_path, "") is None
    assert cgroup_memory_left(tmp_path / "none", "0::/x\n") is None
    _write(_v2(tmp_path), cpu_max="garbage 1")
    assert cgroup_cpu_limit(tmp_path, "0::/\n") is None


def test_available_resources_take_the_cgroup_caps(monkeypatch: pytest.MonkeyPatch) -> None:
    """A container's --cpus 1.5 on a machine of many cores gives one CPU; its memory left caps
    MemAvailable."""
    monkeypatch.setattr(resources, "cgroup_cpu_limit", lambda: 1.5)
    monkeypatch.setattr(resources, "cgroup_memory_left", lambda: 123 * 2**20)
    assert available_cpus() == 1
    assert available_memory_bytes() == 123 * 2**20
    monkeypatch.setattr(resources, "cgroup_cpu_limit", lambda: None)
    monkeypatch.setattr(resources, "cgroup_memory_left", lambda: None)
    assert available_cpus() >= 1
    mem = available_memory_bytes()
    assert mem is None or mem > 123 * 2**20
