"""report.json carries ``schema_version`` and ``units`` and follows the JSON Schema shipped in
the package (issue #20); the schema check can fail."""

from __future__ import annotations

import copy
import json
import re
from importlib import resources
from pathlib import Path
from typing import Any

import pytest
from report_schema_check import schema_problems

from sfm_laserscale.report.schema import (
    SCHEMA_VERSION,
    UNITS,
    report_problems,
    report_schema,
    validate_report,
)
from sfm_laserscale.version import __version__

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def report(small_scale_run: Any) -> dict[str, Any]:
    return dict(json.loads((small_scale_run.out_dir / "report.json").read_text()))


def test_real_report_is_versioned_and_valid(report: dict[str, Any]) -> None:
    assert report["schema_version"] == SCHEMA_VERSION == "1.2"
    assert report["version"] == __version__
    assert report["units"]["scale"] == "metres per model unit"
    assert report["units"]["length"] == "metres"
    assert report["units"] == UNITS
    assert report_problems(report) == []
    validate_report(report)


def test_each_detected_spot_names_the_rule_that_took_it(report: dict[str, Any]) -> None:
    """Schema 1.2: ``images[].spots[].taken_by`` names the detector's rule for a detected spot
    (the small scene's spots all stand on their own evidence), null for the others."""
    spots = [s for im in report["images"] for s in im["spots"]]
    assert spots
    for spot in spots:
        assert (spot["taken_by"] is not None) == (spot["source"] == "detected")
    assert {s["taken_by"] for s in spots if s["source"] == "detected"} == {"own evidence"}
    bad = _broken(report, ["images", 0, "spots", 0, "taken_by"], "by luck")
    assert any("taken_by" in p for p in report_problems(bad))


def _broken(report: dict[str, Any], path: list[Any], value: Any) -> dict[str, Any]:
    bad = copy.deepcopy(report)
    node = bad
    for key in path[:-1]:
        node = node[key]
    if value is KeyError:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return bad


@pytest.mark.parametrize(("path", "value", "named"), [
    (["schema_version"], KeyError, "schema_version"),
    (["units", "scale"], "model units per metre", "units/scale"),
    (["units", "length"], "millimetres", "units/length"),
    (["scale", "value"], "0.3", "scale/value"),
    (["scale", "value"], -1.0, "scale/value"),
    (["scale", "ci95"], [0.1], "scale/ci95"),
    (["scale", "method"], "magic", "scale/method"),
    (["methods", "fcm"], KeyError, "methods"),
    (["images", 0, "cam_from_world"], {"rotation_wxyz": [1, 0, 0]}, "images/0"),
    (["images", 0, "estimates", 0, "rejected"], "no", "images/0/estimates/0/rejected"),
    (["timings_s", "total"], KeyError, "timings_s"),
    (["checks"], {}, "checks"),
])
def test_schema_catches_a_broken_report(report: dict[str, Any], path: list[Any], value: Any,
                                        named: str) -> None:
    problems = report_problems(_broken(report, path, value))
    assert problems and any(p.startswith(named) or p.startswith("(top)") and named in p
                            for p in problems), problems
    with pytest.raises(ValueError, match="does not follow its schema"):
        validate_report(_broken(report, path, value))


def test_objects_that_grow_allow_new_keys(report: dict[str, Any]) -> None:
    """Additive changes (other issues add keys) keep old readers and this schema working."""
    grown = copy.deepcopy(report)
    grown["error_budget"] = {"anything": 1}
    grown["scale"]["new_number"] = 1.5
    grown["images"][0]["new_flag"] = True
    grown["warnings"].append({"level": "note", "code": "new", "message": "m", "extra": 1})
    assert report_problems(grown) == []


def test_schema_ships_in_the_package_with_its_version() -> None:
    shipped = resources.files("sfm_laserscale.report").joinpath("report.schema.json")
    assert json.loads(shipped.read_text()) == report_schema()
    assert report_schema()["$id"].endswith(f":{SCHEMA_VERSION}")
    assert f"Schema version {SCHEMA_VERSION}." in report_schema()["description"]
    assert re.match(report_schema()["properties"]["schema_version"]["pattern"], SCHEMA_VERSION)
    outputs_md = (REPO / "docs" / "OUTPUTS.md").read_text()
    assert f'"schema_version": "{SCHEMA_VERSION}"' in outputs_md


def test_the_tests_schema_sweep_fails_on_a_bad_report(report: dict[str, Any],
                                                      tmp_path: Path) -> None:
    """The check conftest.py runs on every report.json tests write can fail."""
    folder = tmp_path / "sweep"
    (folder / "good").mkdir(parents=True)
    (folder / "bad").mkdir()
    (folder / "stand-in").mkdir()
    (folder / "good" / "report.json").write_text(json.dumps(report))
    (folder / "bad" / "report.json").write_text(json.dumps(_broken(report, ["units"], KeyError)))
    (folder / "stand-in" / "report.json").write_text('{"tag": "x"}')  # not a scale report
    found = schema_problems(folder)
    assert list(found) == [str(folder / "bad" / "report.json")]
    assert schema_problems(folder) == {}  # each file once
