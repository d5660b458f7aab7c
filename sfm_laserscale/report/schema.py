"""report.json's version, units and JSON Schema (``report.schema.json``, shipped in the package).

The schema holds the keys tools may rely on (docs/OUTPUTS.md) with their types; objects that
may grow allow further keys. Versioning (docs/OUTPUTS.md): a key or an allowed value added bumps
the minor version (1.0 -> 1.1), a key removed, renamed or retyped the major one (2.0); the
``$id`` and ``schema_version`` change with it. Validation uses ``jsonschema`` (Draft 2020-12).
"""

from __future__ import annotations

import json
from functools import cache
from importlib import resources
from typing import Any

import jsonschema

#: The version of report.json's layout (not the package's version).
SCHEMA_VERSION = "1.2"

#: report.json's ``units`` block.
UNITS: dict[str, str] = {
    "scale": "metres per model unit",
    "inverse": "model units per metre",
    "length": "metres",
    "area": "square metres",
    "gsd": "millimetres per pixel",
    "angle": "degrees",
    "pixels": "COLMAP convention: the centre of the top-left pixel is (0.5, 0.5)",
    "time": "seconds",
}


@cache
def report_schema() -> dict[str, Any]:
    """The JSON Schema of report.json (a dict; do not modify it)."""
    text = resources.files("sfm_laserscale.report").joinpath("report.schema.json").read_text(
        encoding="utf-8")
    schema: dict[str, Any] = json.loads(text)
    return schema


def report_problems(report: Any) -> list[str]:
    """Every way ``report`` (report.json's content) breaks the schema, as ``path: message``
    lines; empty when it is valid."""
    validator = jsonschema.Draft202012Validator(report_schema())
    errors = sorted(validator.iter_errors(report), key=lambda e: [str(p) for p in e.path])
    return [f"{'/'.join(str(p) for p in err.absolute_path) or '(top)'}: {err.message}"
            for err in errors]


def validate_report(report: Any) -> None:
    """Raise ``ValueError`` naming every problem when ``report`` breaks the schema."""
    problems = report_problems(report)
    if problems:
        raise ValueError("report.json does not follow its schema "
                         f"{SCHEMA_VERSION}: " + "; ".join(problems[:20]))


__all__ = ["SCHEMA_VERSION", "UNITS", "report_problems", "report_schema", "validate_report"]
