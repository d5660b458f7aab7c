"""scripts/benchmark.py and synthetic/bench_data.py: the smallest case end to end (< 30 s)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from script_loader import load_script

from sfm_laserscale.io.colmap import read_colmap_model
from sfm_laserscale.io.meshes.mesh import load_mesh
from sfm_laserscale.model import ImageFeatures
from sfm_laserscale.registration.index import (
    DescriptorPool,
    _gather_kept,
    _rank_and_cells,
    _rank_per_point,
    _Selection,
    index_pool,
)
from sfm_laserscale.registration.match import match_to_model
from sfm_laserscale.registration.options import IndexOptions, MatchOptions
from sfm_laserscale.synthetic.bench_data import (
    pad_model,
    sift_like_descriptors,
    write_heightfield_mesh,
)


def _bench():  # type: ignore[no-untyped-def]
    return load_script("benchmark")


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory, small_dataset) -> Path:  # type: ignore[no-untyped-def]
    """A benchmark work folder whose demo data set is the session's small one."""
    w = tmp_path_factory.mktemp("bench")
    (w / "demo").symlink_to(small_dataset.out_dir, target_is_directory=True)
    return w


def test_smallest_case_has_every_stage_and_sane_numbers(work: Path) -> None:
    bench = _bench()
    case = {"points": 3000, "triangles": 20000, "images": 1}
    r = bench.run_case_subprocess(work, case, timeout=120)
    assert "error" not in r, r.get("error")
    s = r["seconds"]
    assert not r["not_wrapped"], r["not_wrapped"]  # a stage function was renamed
    assert set(bench.STAGES) <= set(s), set(bench.STAGES) - set(s)
    assert all(s[k] > 0 for k in bench.STAGES if k != "other"), s  # every stage ran
    assert s["other"] >= 0
    assert s["total"] == pytest.approx(sum(s[k] for k in bench.STAGES), rel=1e-3, abs=1e-3)
    assert s["sift"] > 0 and s["match"] > 0 and s["mesh_read"] > 0 and s["mesh_write"] > 0
    assert r["registered"] == 1 and r["n_images"] == 1 and r["inliers"][0] >= 30
    assert 0.30 < r["scale"] < 0.33  # the demo truth is ~0.315 m per model unit
    assert r["peak_rss_bytes"] >= r["baseline_rss_bytes"] > 50 * 2**20
    # per-stage peaks (VmHWM reset between stages): SIFT's own working memory is split out
    assert set(r["stage_peak_bytes"]) >= {"sift", "index_build", "mesh_read", "raycast"}
    assert max(r["stage_peak_bytes"].values()) == r["peak_rss_bytes"]
    assert r["baseline_rss_bytes"] < r["peak_wo_sift_bytes"] <= r["peak_rss_bytes"]
    assert 0 < r["sift_working_bytes"] < r["stage_peak_bytes"]["sift"]
    assert r["mesh_bytes"] == (work / "mesh_20000.ply").stat().st_size
    d = bench.derived(r)
    assert d["mem_budget"] == 2 * r["mesh_bytes"] + r["model_bytes"]
    assert d["rest_s"] == pytest.approx(s["total"] - s["sift"] - s["mesh_read"]
                                        - s["mesh_write"])
    table = bench.markdown([r], {})
    assert all(f"| {st} |" in table or f" {st} |" in table for st in bench.STAGES)
    assert "3k pts / 20k tri / 1 img" in table


def test_loglog_slope_known_answers() -> None:
    bench = _bench()
    x = [1e4, 1e5, 1e6]
    assert bench.slope(x, [3 * v**2 for v in x]) == pytest.approx(2.0)
    assert bench.slope(x, [5.0, 5.0, 5.0]) == pytest.approx(0.0, abs=1e-12)


def _pieces(desc: np.ndarray, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """``desc`` split into images whose used rows are scattered among unused ones."""
    cuts = np.sort(rng.choice(np.arange(1, len(desc)), 6, replace=False))
    pieces = []
    for part in np.split(desc, cuts):
        full = rng.integers(0, 256, (2 * len(part) + 3, 128)).astype(np.uint8)
        used = np.sort(rng.choice(len(full), len(part), replace=False))
        full[used] = part
        pieces.append((full, used))
    return pieces


def test_reduce_per_point_equals_ranking_every_point() -> None:
    """Ranking only the over-observed points, image by image, keeps what ranking every point
    of the concatenated descriptors keeps; the kept ones are gathered in order."""
    rng = np.random.default_rng(3)
    rows = rng.integers(0, 400, 3000)
    desc = rng.integers(0, 256, (3000, 128)).astype(np.uint8)
    pieces = _pieces(desc, rng)
    sel = _Selection(tuple(str(i) for i in range(len(pieces))), tuple(u for _, u in pieces),
                     tuple(len(d) for d, _ in pieces), rows.astype(np.int32))
    reads: list[str] = []

    def descriptors_of(name: str) -> np.ndarray:
        reads.append(name)
        return pieces[int(name)][0]

    for k in (1, 3, 8, 50):
        want = _rank_per_point(desc.astype(np.float32), rows, k)
        keep, cells = _rank_and_cells(sel, descriptors_of, k, None)
        got = np.flatnonzero(keep)
        np.testing.assert_array_equal(got, want)
        assert cells is None and np.bincount(rows[got]).max() <= k
        np.testing.assert_array_equal(_gather_kept(sel, descriptors_of, keep), desc[got])
    assert reads[:len(pieces)] == list(sel.names)  # one image at a time, in order


def test_sift_like_descriptors_permute_real_ones() -> None:
    rng = np.random.default_rng(0)
    real = rng.integers(0, 256, (50, 128)).astype(np.uint8)
    out = sift_like_descriptors(real, 200, np.random.default_rng(1))
    assert out.shape == (200, 128) and out.dtype == np.uint8
    real_sorted = {tuple(np.sort(r)) for r in real}
    assert all(tuple(np.sort(r)) in real_sorted for r in out)  # same values, moved bins
    assert not any((out == r).all(axis=1).any() for r in real[:10])


def test_padded_model_and_resampled_mesh(tmp_path: Path, small_dataset) -> None:  # type: ignore[no-untyped-def]
    demo = small_dataset.out_dir
    pm = pad_model(demo / "sparse" / "0", demo / "database.db", tmp_path / "m", 5000)
    model = read_colmap_model(pm.model_dir)
    assert len(model.point3D_ids) == pm.n_points == 5000
    assert len(np.unique(model.point3D_ids)) == 5000
    n = write_heightfield_mesh(demo / "mesh.ply", demo / "truth.json", tmp_path / "m.ply", 50000)
    mesh, ref = load_mesh(tmp_path / "m.ply"), load_mesh(demo / "mesh.ply")
    assert mesh.num_triangles == n and abs(n - 50000) < 0.02 * 50000
    np.testing.assert_allclose(mesh.bounds, ref.bounds, atol=0.01 * ref.extent)


def test_bench_index_recall_is_one_when_every_cell_is_probed() -> None:
    """scripts/bench_index.py's measure: probing all cells is exact search, so recall 1."""
    bench = load_script("bench_index")
    rng = np.random.default_rng(5)
    centres = rng.integers(0, 200, (3000, 128))
    desc = np.clip(centres + rng.integers(-4, 5, (3000, 128)), 0, 255).astype(np.uint8)
    pool = DescriptorPool(desc, np.arange(3000, dtype=np.int64))
    model = SimpleNamespace(points_xyz=np.zeros((3000, 3)), point3D_ids=np.arange(3000))
    query = np.clip(centres[:400] + rng.integers(-6, 7, (400, 128)), 0, 255).astype(np.uint8)
    q = ImageFeatures(np.zeros((400, 2)), query)
    subset = np.arange(0, 400, 2)
    exact_index = index_pool(model, pool, IndexOptions(exact=True))  # type: ignore[arg-type]
    truth = bench._matched(match_to_model(ImageFeatures(q.xy_px[subset], query[subset]),
                                          exact_index, MatchOptions()))
    assert len(truth) > 150
    full = bench.measure(pool, model, [q], 1.0, 10_000, [truth], [subset])
    assert full["recall"] == 1.0 and full["exact_matches"] == len(truth)
    assert full["lists"] == 55 and full["probe"] == 10_000  # round(√3000) cells


def test_index_from_the_database_holds_one_copy_of_the_descriptors(
        tmp_path: Path, small_dataset) -> None:  # type: ignore[no-untyped-def]
    """Read from the database one image at a time, the index build's numpy memory peaks
    near the index's own size (136 bytes per descriptor: the lists' codes and ids); with the
    whole database read first it would also hold every descriptor a second time."""
    import tracemalloc

    from sfm_laserscale.io.colmap_database import open_database_features
    from sfm_laserscale.registration.index import build_descriptor_index

    demo = small_dataset.out_dir
    pm = pad_model(demo / "sparse" / "0", demo / "database.db", tmp_path / "m", 60000)
    model = read_colmap_model(pm.model_dir)
    tracemalloc.start()
    try:
        with open_database_features(pm.database) as lazy:
            before, _ = tracemalloc.get_traced_memory()
            tracemalloc.reset_peak()
            index = build_descriptor_index(model, lazy, IndexOptions())
            _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    n = index.num_descriptors
    assert index.method == "ivf" and n > 110_000 and index._storage is not None
    own = 136 * n  # the buffer FAISS searches in place
    assert index._storage.nbytes < own + 200_000
    # over the index itself: int32/int64 bookkeeping (~45 bytes per descriptor), one image
    # read and the k-means sample in float32 (~40 bytes per descriptor at this small size,
    # ~15 at 2M descriptors): 222 bytes per descriptor in all here. All the descriptors held
    # a second time, as when the whole database was read first, would add 128 or more.
    assert peak - before < own + 128 * n, (peak - before) / n
