"""Whether a model's previous output can be kept on a rerun: its report.json (written last, and
the folder moved into place only when complete, so a killed run leaves none) records every input
file's size and SHA-256 and every option; the output is kept when the same files (same paths,
sizes, hashes) and the same options (but for progress bars and worker processes, which do not
change a number) would be used again, by the same version.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from sfm_laserscale import __version__
from sfm_laserscale.io.images import expand_image_paths
from sfm_laserscale.provenance import file_digest, options_dict
from sfm_laserscale.run_types import ScaleInputs, ScaleOptions

logger = logging.getLogger(__name__)

#: options that change no number (docs/OUTPUTS.md: --workers); left out of the comparison
RUNTIME_OPTIONS = ("progress", "sift_workers")


def comparable_options(options: dict[str, Any]) -> dict[str, Any]:
    """The options that decide the numbers (threads of SIFT extraction left out too)."""
    out = {k: v for k, v in options.items() if k not in RUNTIME_OPTIONS}
    sift = dict(out.get("sift") or {})
    sift.pop("num_threads", None)
    out["sift"] = sift
    return out


def input_files(inputs: ScaleInputs) -> list[Path]:
    """The files ``scale`` hashes for its provenance (folders expanded as it does)."""
    paths = [inputs.model, inputs.mesh, inputs.rig, inputs.database, inputs.spots]
    files: list[Path] = []
    for p in paths:
        if p is None:
            continue
        files += sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    return files + expand_image_paths(inputs.laser_images)


def previous_report(out_dir: Path) -> dict[str, Any] | None:
    """The report.json of a complete previous run, or None."""
    path = out_dir / "report.json"
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return report if isinstance(report, dict) else None


def unchanged_reason(report: dict[str, Any], inputs: ScaleInputs,
                     options: ScaleOptions) -> str | None:
    """None when the previous run used the same inputs and options; else what changed."""
    prov = report.get("provenance") or {}
    if report.get("version") != __version__:
        return f"version {report.get('version')} -> {__version__}"
    if comparable_options(prov.get("options") or {}) != comparable_options(
            options_dict(options)):
        return "options changed"
    before = {(d.get("path"), d.get("bytes")): d.get("sha256") for d in prov.get("inputs", [])}
    files = input_files(inputs)
    now_keys = {(str(f), f.stat().st_size) for f in files}
    if now_keys != set(before):
        changed = sorted(str(k[0]) for k in now_keys ^ set(before))
        return f"input files changed ({changed[0]}{', ...' if len(changed) > 1 else ''})"
    for f in files:
        if file_digest(f)["sha256"] != before[(str(f), f.stat().st_size)]:
            return f"input file changed ({f})"
    return None
