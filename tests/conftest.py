"""Shared fixtures: the real fixtures folder, one small synthetic data set per session, and the
schema check of every report.json a test writes."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from report_schema_check import schema_problems

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO.parent / "shared" / "fixtures"


@pytest.fixture(scope="session")
def fixtures_dir() -> Path:
    """../shared/fixtures (real COLMAP and OpenMVG outputs); never modified by tests."""
    if not FIXTURES.is_dir():
        pytest.fail(f"real fixtures not found at {FIXTURES} (clone beside ../shared)")
    return FIXTURES


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """The demo's small synthetic data set (real SfM with pycolmap), made once per session."""
    from sfm_laserscale.synthetic.dataset import DemoDataOptions, make_demo_dataset

    out = tmp_path_factory.mktemp("small_dataset") / "data"
    return make_demo_dataset(out, DemoDataOptions(small=True, seed=0, progress=False))


@pytest.fixture(scope="session")
def small_scale_run(small_dataset, tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """One real ``scale`` run (commands.scale.run, no progress bars) of ``small_dataset``, made
    once per session; its ScaleResult (``out_dir`` holds every output). Tests must not modify it."""
    from sfm_laserscale.commands import scale as scale_command
    from sfm_laserscale.commands.demo import scale_inputs_for
    from sfm_laserscale.run_types import ScaleOptions

    out = tmp_path_factory.mktemp("small_scale_run") / "out"
    return scale_command.run(scale_inputs_for(small_dataset), out, ScaleOptions(progress=False))


# ---------------------------------------------------------------------------- report schema

@pytest.fixture(autouse=True)
def _reports_follow_their_schema(request: pytest.FixtureRequest) -> Iterator[None]:
    """Every report.json a test writes into its ``tmp_path`` follows report.schema.json."""
    # asked for now, so that tmp_path is torn down after this check
    folder = request.getfixturevalue("tmp_path") if "tmp_path" in request.fixturenames else None
    yield
    if folder is not None:
        bad = schema_problems(folder)
        if bad:
            pytest.fail(f"report.json breaks its schema: {json.dumps(bad, indent=1)}")


@pytest.fixture(autouse=True, scope="session")
def _session_reports_follow_their_schema(tmp_path_factory: pytest.TempPathFactory
                                         ) -> Iterator[None]:
    """... and so does every report.json written by shared fixtures (module and session
    scoped ones write under the session's base folder too), checked when the session ends."""
    yield
    bad = schema_problems(tmp_path_factory.getbasetemp())
    if bad:
        pytest.fail(f"report.json breaks its schema: {json.dumps(bad, indent=1)}")
