"""The provenance's input hashes, computed in a thread beside the run: same digests as in the
caller's thread, folders expanded in order, a failure raised where the block is built."""

from __future__ import annotations

import hashlib
import threading
from pathlib import Path
from typing import Any

import pytest

from sfm_laserscale import provenance as prov


def _tree(tmp_path: Path) -> list[Path | None]:
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "b.bin").write_bytes(b"\x01" * 5_000_000)
    (tmp_path / "model" / "a.txt").write_text("points\n")
    mesh = tmp_path / "mesh.ply"
    mesh.write_bytes(bytes(range(256)) * 40_000)
    return [tmp_path / "model", mesh, None, tmp_path / "absent.db"]


def test_digests_in_a_thread_equal_the_callers(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    paths = _tree(tmp_path)
    threads: list[str] = []
    digest = prov.file_digest

    def recorded(path: Path) -> dict[str, Any]:
        threads.append(threading.current_thread().name)
        return digest(path)

    monkeypatch.setattr(prov, "file_digest", recorded)
    with prov.digests_in_background(paths) as future:
        block = prov.provenance(paths, {"seed": 0}, future)
    assert threads and all(t.startswith("input-sha256") for t in threads)
    assert block["inputs"] == prov.input_digests(paths)
    assert [d["path"] for d in block["inputs"]] == [
        str(tmp_path / "model" / "a.txt"), str(tmp_path / "model" / "b.bin"),
        str(tmp_path / "mesh.ply")]
    mesh = block["inputs"][2]
    assert mesh["sha256"] == hashlib.sha256((tmp_path / "mesh.ply").read_bytes()).hexdigest()
    assert mesh["bytes"] == 256 * 40_000


def test_a_hash_failure_is_raised_where_the_block_is_built(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def unreadable(path: Path) -> dict[str, Any]:
        raise PermissionError(f"cannot read {path}")

    monkeypatch.setattr(prov, "file_digest", unreadable)
    with pytest.raises(PermissionError, match="cannot read"), \
            prov.digests_in_background(_tree(tmp_path)) as future:
        prov.provenance([], {}, future)
