"""The schema check of the report.json files tests write (tests/conftest.py runs it after
every test and at the end of the session; issue #20)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from sfm_laserscale.report.schema import report_problems

_CHECKED: set[Path] = set()


def _scale_report(path: Path) -> Any:
    """report.json's content when ``path`` holds a ``scale`` report (tests also write small
    stand-in files of that name to exercise the output folder's moves), else None."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and "scale" in data and "images" in data else None


def schema_problems(folder: Path) -> dict[str, list[str]]:
    """report.json path -> its schema problems, for every scale report under ``folder`` not
    checked yet (none: an empty dict)."""
    found: dict[str, list[str]] = {}
    for path in sorted(folder.rglob("report.json")):
        if path in _CHECKED:
            continue
        _CHECKED.add(path)
        report = _scale_report(path)
        problems = [] if report is None else report_problems(report)
        if problems:
            found[str(path)] = problems[:10]
    return found
