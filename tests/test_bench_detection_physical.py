"""scripts/bench_detection_physical.py: scoring rules and a reduced end-to-end run."""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from functools import partial
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import pytest
from script_loader import load_script

from sfm_laserscale.model import Spot
from sfm_laserscale.synthetic.underwater import Frame


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_script("bench_detection_physical")


def _frame(truth: dict[str, tuple[float, float] | None]) -> Frame:
    return Frame(image_rgb=np.zeros((4, 4, 3), np.uint8), camera_spec="", rig_toml="",
                 truth=truth, meta={})


def test_scoring_found_missed_false(bench: ModuleType) -> None:
    frame = _frame({"L1": (100.0, 100.0), "L2": (200.0, 100.0), "L3": (300.0, 50.0),
                    "L4": None})
    result = SimpleNamespace(
        spots=(Spot("L1", 101.0, 100.5), Spot("L2", 203.0, 100.0), Spot("L4", 10.0, 10.0)),
        missing={"L3": "no candidate near the beam"})
    rec = bench.score_frame(frame, result)
    assert [f["laser"] for f in rec["found"]] == ["L1"]
    assert rec["found"][0]["error_px"] == pytest.approx(np.hypot(1.0, 0.5))
    assert {m["laser"] for m in rec["misses"]} == {"L2", "L3"}
    assert any(m["reason"] == "no candidate near the beam" for m in rec["misses"])
    assert {f["laser"] for f in rec["falses"]} == {"L2", "L4"}  # too far; laser off
    assert rec["truths"] == 3 and rec["reported"] == 3
    # a spot of a laser in view reported off carries its error and stated σ; a laser off none
    off = {f["laser"]: f for f in rec["falses"]}
    assert (off["L2"]["dx"], off["L2"]["dy"]) == (3.0, 0.0)
    assert off["L2"]["sigma_px"] == Spot("L2", 203.0, 100.0).sigma_px
    assert "sigma_px" not in off["L4"]
    # no candidate list on this result: nothing recorded at the misses' truths
    assert all(m["at_truth"] is None for m in rec["misses"])


def test_a_miss_records_the_candidate_at_its_truth(bench: ModuleType) -> None:
    frame = _frame({"L1": (100.0, 100.0), "L2": (200.0, 100.0), "L3": (300.0, 50.0)})

    def cand(x: float, y: float, reason: str, ratio: float = 2.0) -> SimpleNamespace:
        return SimpleNamespace(x=x, y=y, source="bright", reason=reason, score=0.0,
                               clutter_ratio=ratio)

    result = SimpleNamespace(
        spots=(Spot("L1", 100.2, 100.0),), missing={},
        candidates=(cand(100.2, 100.0, "assigned to L1"),
                    cand(200.9, 100.9, "no stronger than the scene's own blobs (response 1.21 "
                         "× clutter level; and weak (SNR 4.9 < 5))", 1.21),
                    cand(200.3, 99.0, "score below min_score for L2: colour"),  # 1.04 px
                    cand(301.6, 50.0, "weak (SNR 3.1 < 5)", float("inf"))))  # beyond 1.5 px
    rec = bench.score_frame(frame, result)
    at = {m["laser"]: m["at_truth"] for m in rec["misses"]}
    assert at["L3"] is None
    assert at["L2"]["test"] == "score below min_score for L#"
    assert at["L2"]["distance_px"] == pytest.approx(np.hypot(0.3, 1.0))
    assert bench.candidate_test("not chosen for L4: the joint choice left it out") == \
        "not chosen for L#"
    assert bench.candidate_test("no stronger than the scene's own blobs (response 1.21 × "
                                "clutter level)") == "no stronger than the scene's own blobs"
    recs = [{"size": "8x8", "truths": 3, "reported": 1, "falses": [],
             "found": [{"error_px": 0.2, "dx": 0.2, "dy": 0.0, "sigma_px": 0.1}], **rec}] * 2
    line = bench.pooled_lines(recs)[-1]
    assert line == ("8x8 misses, the candidate at the truth: 4 misses: score below min_score "
                    "for L# 2; none within 1.5 px 2")  # most first, ties as first met


def test_summary_rows(bench: ModuleType) -> None:
    recs = [{"condition": "c", "size": "8x8", "index": i, "truths": 2, "reported": 2,
             "found": [{"laser": "L1", "error_px": e, "dx": e, "dy": 0.0, "sigma_px": 0.1}],
             "misses": [{"laser": "L2", "reason": "far 3.2 px"}],
             "falses": [{"laser": "L2"}], "detect_s": 0.1, "render_s": 0.2}
            for i, e in enumerate([0.1, 0.3])]
    (row,) = bench.summarise(recs)
    assert row["spots"] == 4 and row["found"] == 2 and row["found_pct"] == 50.0
    assert row["false_pct"] == 50.0 and row["false_per_image"] == 1.0
    assert row["median_px"] == pytest.approx(0.2) and row["max_px"] == 0.3
    assert row["miss_reasons"] == [("far # px", 2)]
    # per-axis errors 1σ, 0, 3σ, 0: three of four within 1.96σ, all within 3σ
    assert row["within_2sigma_pct"] == 75.0 and row["within_3sigma_pct"] == 100.0
    kind = bench._reason_kind("no green spot accepted within 14.0 px of its beam: (950.4, 234.1)"
                              " score 0.20 < min_score 0.25: colour of the scene; (1.5, 2): x")
    assert kind == "score # < min_score #: colour of the scene"
    assert "| c | 8x8 |" in bench.markdown_table([row])


def test_pooled_lines_per_size_and_wavelength(bench: ModuleType) -> None:
    def rec(size: str, nm: float, dx: float, sigma: float,
            off: tuple[dict, ...] = ({"laser": "L2"},)) -> dict:
        return {"size": size, "wavelength_nm": nm, "truths": 2, "reported": 2,
                "found": [{"error_px": abs(dx), "dx": dx, "dy": 0.0, "sigma_px": sigma}],
                "falses": list(off)}

    # 532 nm: per-axis errors 0.1 / 0.1 px (σ), 0.4 / 0.1 (4σ) and two zeros; 638 nm: 2σ, and
    # its L2 reported 2 px off with σ 0.1 px (20σ and 0 on its axes)
    far = {"laser": "L2", "dx": 2.0, "dy": 0.0, "sigma_px": 0.1}
    recs = [rec("8x8", 532.0, 0.1, 0.1), rec("8x8", 532.0, 0.4, 0.1),
            rec("8x8", 638.0, 0.2, 0.1, (far,)), rec("4x4", 450.0, 0.0, 0.1)]
    lines = bench.pooled_lines(recs)
    assert [ln.split(":")[0] for ln in lines] == [
        "8x8 pooled", "8x8 σ, all", "8x8 σ, every reported spot of a laser in view",
        "8x8 σ, 532 nm", "8x8 σ, 638 nm", "4x4 pooled", "4x4 σ, all",
        "4x4 σ, every reported spot of a laser in view", "4x4 σ, 450 nm"]
    assert lines[0].startswith("8x8 pooled: 3 of 6 spots found (50.0 %), 3 false of 6")
    assert "median 0.200 px" in lines[0]
    assert "2 spots" in lines[3] and "within 1.96σ 75.0 %, within 3σ 75.0 %, worst 4.0σ" in lines[3]
    assert "within 1.96σ 50.0 %, within 3σ 100.0 %, worst 2.0σ" in lines[4]
    assert "3 spots" in lines[1] and "within 1.96σ 66.7 %" in lines[1]
    # the found spots' six axes and the off spot's two: 5 of 8 within 1.96σ, 6 within 3σ
    assert lines[2].endswith("4 spots (1 beyond 1.5 px), within 1.96σ 62.5 %, "
                             "within 3σ 75.0 %, worst 20.0σ")
    assert lines[7].endswith("1 spot (0 beyond 1.5 px), within 1.96σ 100.0 %, "
                             "within 3σ 100.0 %, worst 0.0σ")


def test_sigma_lines_per_rule_that_took_the_spots(bench: ModuleType) -> None:
    """A line per rule (``taken_by``) over the found and off spots of that rule; records
    without one (older runs) add no line."""
    found = [{"error_px": 0.1, "dx": 0.1, "dy": 0.0, "sigma_px": 0.1, "taken_by": "own evidence"},
             {"error_px": 0.3, "dx": 0.3, "dy": 0.0, "sigma_px": 0.1, "taken_by": "floor search"},
             {"error_px": 0.1, "dx": 0.1, "dy": 0.0, "sigma_px": 0.1}]
    off = [{"laser": "L4", "dx": 2.0, "dy": 0.0, "sigma_px": 1.0, "taken_by": "floor search"}]
    recs = [{"size": "8x8", "truths": 4, "reported": 4, "found": found, "falses": off}]
    lines = [ln for ln in bench.pooled_lines(recs) if ", taken by " in ln]
    # the floor search's axes: 3σ and 0 (found), 2σ and 0 (off)
    assert lines == [
        "8x8 σ, taken by floor search: 2 spots (1 beyond 1.5 px), stated σ 0.550 px (median), "
        "within 1.96σ 50.0 %, within 3σ 100.0 %, worst 3.0σ",
        "8x8 σ, taken by own evidence: 1 spot (0 beyond 1.5 px), stated σ 0.100 px (median), "
        "within 1.96σ 100.0 %, within 3σ 100.0 %, worst 1.0σ"]

    class Result:
        candidates = (SimpleNamespace(laser="L1", taken_by=""),
                      SimpleNamespace(laser="L1", taken_by="second look"), SimpleNamespace())
    assert bench.taken_by(Result(), SimpleNamespace(laser="L1")) == "second look"
    assert bench.taken_by(Result(), SimpleNamespace(laser="L2")) == ""


def test_reduced_run_end_to_end(bench: ModuleType) -> None:
    rows = bench.run_small(("clipped_cores", "no_lasers"), (480, 360), per_condition=1)
    assert [r["condition"] for r in rows] == ["clipped_cores", "no_lasers"]
    spots = {r["condition"]: r["spots"] for r in rows}
    assert spots == {"clipped_cores": 4, "no_lasers": 0}
    for r in rows:
        assert r["found"] + len(r["misses"]) == r["spots"]
        assert r["reported"] >= r["found"] and r["false"] == r["reported"] - r["found"]


def test_reduced_physical_benchmark_quality(bench: ModuleType) -> None:
    """A reduced physical benchmark (960×540, 3 images per condition, seed 0) holds what was
    measured on it (2026-11-26: red 12/12, red in blue water 11/12, turbid 12/12, green_all 8/12
    median 0.34 px, clipped_cores 9/12 median 0.21 px, 4 false spots (green spots 1.5–2 px
    off), none without lasers). Before luma refinement of green spots their medians were 0.49
    and 0.50 px; before the first round the green conditions were 0 of 12."""
    conditions = ("red_clean", "red_blue_water", "turbid_brown", "green_all", "clipped_cores",
                  "no_lasers")
    rows = {r["condition"]: r for r in bench.run_small(conditions, (960, 540), per_condition=3)}
    assert rows["red_clean"]["found"] == 12 and rows["red_clean"]["median_px"] < 0.3
    assert rows["red_blue_water"]["found"] >= 10
    assert rows["green_all"]["found"] >= 7 and rows["clipped_cores"]["found"] >= 7
    assert rows["green_all"]["median_px"] < 0.42 and rows["clipped_cores"]["median_px"] < 0.35
    assert sum(r["found"] for r in rows.values()) >= 48  # of 60 (measured 52)
    assert sum(r["false"] for r in rows.values()) <= 5  # measured 4
    assert rows["no_lasers"]["reported"] == 0
    # the stated sigma is honest on this generator: per-axis errors within 3σ, pooled
    # (measured 93 %; at 1920 × 1080 the noise-only sigma with a 0.05 px floor held 54 % of
    # them within 1.96σ and 72 % within 3σ, docs/DETECTION.md)
    axes = [(2 * r["found"], r["within_3sigma_pct"]) for r in rows.values() if r["found"]]
    assert sum(n * pct for n, pct in axes) / sum(n for n, _ in axes) >= 88.0
    # red spots are centred on a colour difference, sampled in 2 × 2: their σ holds that
    # (within 1.96σ measured 2026-11-27: red_clean 96 %, red_blue_water 95 %; 67 % and 77 %
    # before the colour term)
    red = [(2 * rows[c]["found"], rows[c]["within_2sigma_pct"])
           for c in ("red_clean", "red_blue_water")]
    assert sum(n * pct for n, pct in red) / sum(n for n, _ in red) >= 85.0


def test_visibility_of_the_misses(bench: ModuleType) -> None:
    # with laser-free captures every miss says how much its spot changes the photograph
    rows = bench.run_small(("green_all",), (960, 540), per_condition=1, laser_free=True)
    (row,) = rows
    assert row["misses_visible"] is not None
    assert all(m["visible_levels"] is not None for m in row["misses"])
    assert bench.visibility_line(rows).startswith(f"{row['misses_visible']} of")
    # without laser-free captures (or without misses) nothing is said
    assert bench.visibility_line([{**row, "misses_visible": None}]) is None
    assert bench._visible_misses([]) is None
    assert bench._visible_misses([{"laser": "L1", "visible_levels": None}]) is None


def test_draws_parse_as_one_range_or_a_list(bench: ModuleType) -> None:
    assert bench._seeds("0") == [0]
    assert bench._seeds("2-5") == [2, 3, 4, 5]
    assert bench._seeds("2,4-5,9") == [2, 4, 5, 9]
    for bad in ("5-2", "x", "2-"):
        with pytest.raises(argparse.ArgumentTypeError):
            bench._seeds(bad)


def _rec(seed: int, index: int, found: dict[str, float], falses: int) -> dict:
    return {"seed": seed, "condition": "c", "size": "8x8", "index": index,
            "found": [{"laser": n, "error_px": e} for n, e in found.items()],
            "falses": [{"laser": "L9"}] * falses}


def test_compare_records_frame_by_frame(bench: ModuleType) -> None:
    old = [_rec(2, 0, {"L1": 0.2, "L2": 0.3}, 0), _rec(2, 1, {"L1": 0.1}, 1),
           _rec(3, 0, {"L1": 0.4}, 0), _rec(3, 1, {}, 0)]
    new = [_rec(2, 0, {"L1": 0.2, "L2": 0.305}, 0),  # moved by less than 0.01 px: the same
           _rec(2, 1, {"L1": 0.1, "L3": 0.5}, 0),  # a spot found, a false spot dropped
           _rec(3, 0, {"L1": 0.9}, 2),  # moved, two false spots more
           _rec(4, 0, {}, 0)]  # a frame of another draw
    lines = bench.compare_records(old, new)
    assert lines == [
        "seed 2 c 8x8 #1: L3 found (0.50 px); false 1 → 0",
        "seed 3 c 8x8 #0: L1 0.40 → 0.90 px; false 0 → 2",
        "2 frames differ: 1 spots found, 0 lost, false spots +1 (2 frames in one run only)"]
    assert bench.compare_records(new, old)[0] == "seed 2 c 8x8 #1: L3 lost (0.50 px); false 0 → 1"
    # records without a draw (runs before draws were pooled) are seed 0
    assert bench.record_key({"condition": "c", "size": "8x8", "index": 3}) == "seed 0 c 8x8 #3"


def test_several_draws_pooled_and_frames_cached(bench: ModuleType, tmp_path: Path) -> None:
    run = partial(bench.run_benchmark, ("clipped_cores",), ((320, 240),), 2, [0, 1], 1)
    records, (row,) = run(cache=tmp_path)
    assert [(r["seed"], r["index"]) for r in records] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert row["images"] == 4 and row["spots"] == 16
    lines = bench.pooled_lines(records)
    assert [ln.split(":")[0] for ln in lines[:3]] == ["320x240 pooled", "320x240 seed 0",
                                                      "320x240 seed 1"]
    # two draws of the same condition are different photographs
    assert records[0]["spot_meta"] != records[2]["spot_meta"]
    cached = sorted(p.name for p in tmp_path.glob("*/*.pkl"))
    assert cached == [f"s{s}_clipped_cores_320x240_z0_{i:03d}.pkl" for s in (0, 1)
                      for i in (0, 1)]
    assert [p.name for p in tmp_path.iterdir()] == [bench.generator_version()]
    # a second run reads the frames back and scores them the same, spot for spot
    again, _ = run(cache=tmp_path)
    assert bench.compare_records(records, again)[-1].startswith("0 frames differ")
    assert [r["spot_meta"] for r in again] == [r["spot_meta"] for r in records]
    assert all(b["render_s"] < a["render_s"] for a, b in zip(records, again, strict=True))
    # and without the cache the same frames are rendered again
    fresh, _ = run()
    assert [r["found"] for r in fresh] == [r["found"] for r in records]


def test_command_line_draws_cache_and_compare(bench: ModuleType, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--sizes", "320x240", "--conditions", "clipped_cores", "--per-condition", "1",
            "--seed", "0-1", "--workers", "1", "--cache", str(tmp_path / "frames")]
    first = tmp_path / "first.json"
    assert bench.main([*args, "--out", str(first)]) == 0
    saved = json.loads(first.read_text())
    assert saved["seeds"] == [0, 1] and len(saved["images"]) == 2
    out = capsys.readouterr().out
    assert "320x240 seed 0:" in out and "320x240 seed 1:" in out
    assert bench.main([*args, "--compare", str(first)]) == 0
    out = capsys.readouterr().out
    assert f"against {first}:" in out and "0 frames differ: 0 spots found, 0 lost" in out
    with pytest.raises(SystemExit):
        bench.main([*args, "--seed", "3-1"])
    # a run of draw 0 alone with a tiny cache limit keeps its own frame, drops draw 1's
    assert bench.main([*args, "--seed", "0", "--cache-max-gb", "1e-9"]) == 0
    assert "cache: 1 frame(s) removed" in capsys.readouterr().err
    assert [p.name for p in (tmp_path / "frames").glob("*/*.pkl")] == [
        "s0_clipped_cores_320x240_z0_000.pkl"]


def test_the_frame_cache_is_pruned_least_recently_used_first(bench: ModuleType,
                                                              tmp_path: Path) -> None:
    """Frames of another generator go first, then this generator's least recently used until
    the folder fits its limit; the frames of the run stay whatever the limit."""
    import os

    current = tmp_path / bench.generator_version()
    stale = tmp_path / "000000000000"
    current.mkdir()
    stale.mkdir()
    (stale / "s0_old.pkl").write_bytes(b"x" * 500)
    frames = [current / f"s0_f{i}.pkl" for i in range(4)]
    for age, path in enumerate(frames):  # f0 used last, f3 longest ago
        path.write_bytes(b"x" * 1000)
        os.utime(path, (1e9 - 100 * age, 1e9 - 100 * age))
    removed, freed = bench.prune_cache(tmp_path, 3000, keep=[frames[3]])
    assert (removed, freed) == (2, 1500)  # the stale frame, then f2 (f3 is the run's own)
    assert sorted(p.name for p in current.iterdir()) == ["s0_f0.pkl", "s0_f1.pkl", "s0_f3.pkl"]
    assert not stale.exists()
    assert bench.prune_cache(tmp_path, 0, keep=[]) == (0, 0)  # no limit: nothing else goes
    assert bench.prune_cache(tmp_path, 1, keep=frames) == (0, 0)  # all the run's own


def test_a_cached_frame_read_back_counts_as_used(bench: ModuleType, tmp_path: Path) -> None:
    import os

    job = bench.Job("clipped_cores", 320, 240, 0, 0, 0, 0, cache=str(tmp_path))
    bench.cached_frame(job)
    path = bench.cache_path(job)
    os.utime(path, (1e9, 1e9))
    bench.cached_frame(job)  # read back
    assert path.stat().st_mtime > 1e9 + 1e6


def test_a_scene_reference_as_a_render_from_the_model(bench: ModuleType, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """``as_rendered`` shifts, blurs and relights the seafloor's capture as described; with
    ``--scene-reference`` each frame is rendered with its seafloor alone (the frame itself
    unchanged) and the detector is given it."""
    rows, cols = np.mgrid[0:60, 0:80]
    ramp = np.repeat((2 * cols + rows).astype(np.uint8)[..., None], 3, axis=2)
    rng = np.random.default_rng(0)
    same = bench.as_rendered(ramp, bench.SceneReference(0.0, 0.0, 0.0), rng)
    assert same.dtype == np.float32
    np.testing.assert_array_equal(same, ramp)
    shifted = bench.as_rendered(ramp, bench.SceneReference(1.0, 0.0, 0.0), rng)
    step = shifted[10:50, 10:70, 0] - ramp[10:50, 10:70, 0]  # -(2 dx + dy), |d| = 1
    assert np.allclose(step, step[0, 0], atol=1e-3) and 0.9 < abs(step[0, 0]) <= math.sqrt(5)
    lit = bench.as_rendered(np.full((60, 80, 3), 100, np.uint8),
                            bench.SceneReference(0.0, 0.0, 0.1), rng)
    assert 89.9 < lit.min() < 95.0 and 105.0 < lit.max() < 110.1
    args = ["--sizes", "320x240", "--conditions", "clipped_cores", "--per-condition", "1",
            "--workers", "1", "--cache", str(tmp_path / "frames")]
    plain, scene, whole = (tmp_path / f"{n}.json" for n in ("plain", "scene", "whole"))
    assert bench.main([*args, "--out", str(plain)]) == 0
    assert bench.main([*args, "--out", str(scene), "--scene-reference", "0.5,0.7,0.1"]) == 0
    assert bench.main([*args, "--out", str(whole), "--scene-reference", "0.5,0.7,0.1",
                       "--no-scene-fit", "--no-scene-scaling"]) == 0
    saved = json.loads(scene.read_text())
    assert saved["scene_reference"] == {"shift_px": 0.5, "blur_px": 0.7, "gain": 0.1,
                                        "fit": True, "scaled": True}
    assert json.loads(whole.read_text())["scene_reference"]["fit"] is False
    assert json.loads(whole.read_text())["scene_reference"] == {
        "shift_px": 0.5, "blur_px": 0.7, "gain": 0.1, "fit": False, "scaled": False}
    assert json.loads(plain.read_text())["scene_reference"] is None
    # as scale does, the reference is kept where it fits the frame, and the fit is recorded
    [fitted] = saved["images"]
    assert 0.0 < fitted["scene_fit"]["kept_share"] <= 1.0
    assert fitted["scene_fit"]["shift_median_px"] == pytest.approx(0.5, abs=0.25)
    assert json.loads(whole.read_text())["images"][0]["scene_fit"] is None
    assert sorted(p.name for p in (tmp_path / "frames").glob("*/*.pkl")) == [
        "s0_clipped_cores_320x240_z0_000.pkl", "s0_clipped_cores_320x240_z0_000_sc.pkl"]
    job = bench.jobs_for(["clipped_cores"], [(320, 240)], 1, 0)[0]
    with_scene = bench.cached_frame(replace(job, cache=str(tmp_path / "frames"),
                                            scene=bench.SceneReference()))
    alone = bench.cached_frame(job)
    np.testing.assert_array_equal(with_scene.image_rgb, alone.image_rgb)
    assert with_scene.image_scene_rgb is not None and alone.image_scene_rgb is None
    capsys.readouterr()
    for bad in ("0.5,0.7", "0.5,-1,0.1"):
        with pytest.raises(SystemExit):
            bench.main([*args, "--scene-reference", bad])
