"""sfm-laserscale: metric scale for monocular SfM models from laser scaler images.

The Python API (docs/API.md): :func:`scale`, :func:`detect`, :func:`calibrate`, :func:`apply`
(:mod:`sfm_laserscale.api`), :func:`report_schema` and :func:`validate_report`
(:mod:`sfm_laserscale.report.schema`). They are imported on first use, so ``import
sfm_laserscale`` (and the CLI's start) stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from sfm_laserscale.version import __version__

if TYPE_CHECKING:
    from sfm_laserscale.api import ApplyOutcome, apply, calibrate, detect, scale
    from sfm_laserscale.errors import InputError
    from sfm_laserscale.report.schema import (
        SCHEMA_VERSION,
        report_problems,
        report_schema,
        validate_report,
    )

_LAZY = {
    "scale": "sfm_laserscale.api", "detect": "sfm_laserscale.api",
    "calibrate": "sfm_laserscale.api", "apply": "sfm_laserscale.api",
    "ApplyOutcome": "sfm_laserscale.api", "InputError": "sfm_laserscale.errors",
    "SCHEMA_VERSION": "sfm_laserscale.report.schema",
    "report_problems": "sfm_laserscale.report.schema",
    "report_schema": "sfm_laserscale.report.schema",
    "validate_report": "sfm_laserscale.report.schema",
}

__all__ = ["SCHEMA_VERSION", "ApplyOutcome", "InputError", "__version__", "apply", "calibrate",
           "detect", "report_problems", "report_schema", "scale", "validate_report"]


def __getattr__(name: str) -> Any:
    """The API's names, imported when first used (PEP 562)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'sfm_laserscale' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
