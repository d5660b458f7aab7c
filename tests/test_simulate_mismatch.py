"""``simulate --mode mismatch`` (reduced): data with errors the estimator is not told about. The
generator's pieces against known answers, and a few surveys per setting: with nothing mismatched
the headline's σ holds, an understated spot σ is flagged; the paper's configurations A with
adjacent pairs and C with its non-parallel pair."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sfm_laserscale.cli import main
from sfm_laserscale.synthetic.simulate.configs import config_rig
from sfm_laserscale.synthetic.simulate.mismatch import MismatchOptions, run_mismatch
from sfm_laserscale.synthetic.simulate.mismatch_data import (
    Mismatch,
    rigs,
    spot_offsets,
    stretch,
)

UP = np.array([0.0, 0.0, 1.0])


def test_stretch_is_the_nadir_focal_ambiguity() -> None:
    """A nadir camera at height H with focal f sees X; with f (1 + ε) it sees the stretched X at
    the same pixel (the SfM of a nadir survey cannot tell them apart)."""
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-1, 1, (50, 2)), rng.uniform(-0.3, 0.3, 50)])
    h, f, eps = 3.0, 1000.0, 0.004
    s = stretch(pts, UP, h, eps)
    px = f * pts[:, :2] / (h - pts[:, 2:3])
    px_s = f * (1 + eps) * s[:, :2] / (h - s[:, 2:3])
    np.testing.assert_allclose(px_s, px, rtol=1e-12)
    np.testing.assert_allclose(s[:, :2], pts[:, :2])


def test_spot_errors_have_the_stated_spread() -> None:
    rng = np.random.default_rng(1)
    n = 40000
    base = spot_offsets(Mismatch("x"), 0.25, n, rng)
    assert np.std(base) == pytest.approx(0.25, rel=0.02)
    twice = spot_offsets(Mismatch("x", spot_scale=2.0), 0.25, n, rng)
    assert np.std(twice) == pytest.approx(0.5, rel=0.02)
    elong = spot_offsets(Mismatch("x", elongation=3.0), 0.25, n, rng)
    # along a random axis σ 0.25 · 2 more: per axis variance 0.25² (1 + 4 / 2)
    assert np.var(elong) == pytest.approx(0.25**2 * 3.0, rel=0.03)


def test_rig_error_is_drawn_at_the_told_sigma() -> None:
    rig = config_rig("C")
    m = Mismatch("rig", rig_sigma_origin_m=5e-4, rig_sigma_direction_rad=3e-4)
    rng = np.random.default_rng(2)
    dx, angles = [], []
    for _ in range(400):
        true, told = rigs(rig, m, rng)
        assert all(la.sigma_origin == 5e-4 for la in told.lasers)
        for a, b in zip(true.lasers, rig.lasers, strict=True):
            assert a.origin is not None and b.origin is not None
            assert a.direction is not None and b.direction is not None
            assert abs(a.origin[2]) < 1e-12
            dx.append(a.origin[0] - b.origin[0])
            angles.append(np.arccos(np.clip(a.direction @ b.direction, -1, 1)))
    assert np.std(dx) == pytest.approx(5e-4, rel=0.1)
    # the tilt's magnitude over two axes: Rayleigh, RMS √2 σ
    assert np.sqrt(np.mean(np.square(angles))) == pytest.approx(np.sqrt(2) * 3e-4, rel=0.1)


@pytest.fixture(scope="module")
def small_mismatch() -> dict:  # type: ignore[type-arg]
    return run_mismatch(MismatchOptions(settings=("none", "σ_l understated 2×"), surveys=10,
                                        views=5, progress=False))


def test_nothing_mismatched_sigma_holds(small_mismatch: dict) -> None:  # type: ignore[type-arg]
    none = small_mismatch["settings"][0]
    assert none["name"] == "none" and none["n"] >= 8
    assert none["z_rms"] < 1.8
    assert none["coverage95"] >= 0.7
    assert none["flagged_any"] <= 0.3


def test_understated_spot_sigma_is_flagged(small_mismatch: dict) -> None:  # type: ignore[type-arg]
    bad = small_mismatch["settings"][1]
    assert bad["n"] >= 8
    assert bad["flagged_any"] >= 0.8
    assert bad["flag_rates"]["scatter"] >= 0.8


def test_mismatch_command_writes_results_and_table(tmp_path: Path) -> None:
    out = tmp_path / "mm"
    res = CliRunner().invoke(main, ["simulate", "--out", str(out), "--mode", "mismatch",
                                    "--trials", "1", "--group-size", "3", "-q"])
    assert res.exit_code == 0, res.output
    assert "simulate mismatch" in res.output
    table = (out / "table.md").read_text(encoding="utf-8")
    assert "σ_l understated 2×" in table and "coverage" in table
    import json

    results = json.loads((out / "results.json").read_text(encoding="utf-8"))
    assert len(results["settings"]) == 10


# --------------------------------------------------------------------------- paper cases


def test_configuration_a_adjacent_pairs() -> None:
    rig = config_rig("A-adjacent")
    assert [p.lasers for p in rig.pairs] == [("L1", "L3"), ("L3", "L2"), ("L2", "L4"),
                                             ("L4", "L1")]
    assert all(p.separation == pytest.approx(np.hypot(0.1, 0.1)) for p in rig.pairs)


def test_configuration_a_adjacent_pcm_is_unbiased_in_simulate() -> None:
    """Nadir views at 3 m over the smooth area, the four adjacent pairs: PCM's error within
    a few of its σ, and its σ matches the spread."""
    from sfm_laserscale.synthetic.simulate.configs import SimulationInputs, SimulationOptions
    from sfm_laserscale.synthetic.simulate.runner import simulate

    res = simulate(SimulationInputs(), SimulationOptions(
        mode="noise-table", configs=("A-adjacent",), trials=40, distances_m=(3.0,),
        sigma_f_px=(0.5,), sigma_l_px=(0.25,), workers=1, progress=False))
    (row,) = [s for s in res.results["settings"] if s["setting"]["config"] == "A-adjacent"]
    pcm = row["methods"]["pcm"]
    assert pcm["n"] >= 120  # four pairs per view
    assert abs(pcm["bias"]) < 3 * pcm["std"] / np.sqrt(pcm["n"]) + 0.02
    assert 0.7 < pcm["ratio"] < 1.4


def test_configuration_c_nonparallel_pair_is_refused_in_simulate() -> None:
    from sfm_laserscale.synthetic.simulate.configs import SimulationInputs, SimulationOptions
    from sfm_laserscale.synthetic.simulate.runner import simulate

    res = simulate(SimulationInputs(), SimulationOptions(
        mode="noise-table", configs=("C-nonparallel",), trials=3, distances_m=(3.0,),
        sigma_f_px=(0.5,), sigma_l_px=(0.25,), workers=1, progress=False))
    (row,) = [s for s in res.results["settings"] if s["setting"]["config"] == "C-nonparallel"]
    pcm = row["methods"]["pcm"]
    assert pcm["n"] == 3  # one estimate per view: L1+L2 only
    assert pcm["n_rejected"] >= 3  # L3+L4 refused in every view (not parallel)
    assert "pcm:L3+L4" not in row["methods"]
