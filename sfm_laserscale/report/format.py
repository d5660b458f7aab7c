"""Number formatting of the HTML report: one precision for every scale value of a report (set by
the headline σ, so columns align and the last digit shown is the σ's third significant one)."""

from __future__ import annotations

import json
import math
from typing import Any

from markupsafe import Markup, escape

DASH = "–"


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def scale_decimals(report: dict[str, Any]) -> int:
    """Decimals for every scale value: three significant digits of the headline σ (else six
    significant digits of the value), between 1 and 12."""
    s = report["scale"]
    std, value = s.get("std"), s.get("value")
    if _finite(std) and std > 0:
        d = 2 - math.floor(math.log10(std))
    elif _finite(value) and value != 0:
        d = 5 - math.floor(math.log10(abs(value)))
    else:
        d = 6
    return min(max(d, 1), 12)


def fixed(value: Any, decimals: int) -> str:
    """Fixed-point with ``decimals`` digits; '–' for missing values."""
    return f"{value:.{decimals}f}" if _finite(value) else DASH


def sig(value: Any, digits: int = 3) -> str:
    """``digits`` significant digits, fixed-point when that needs at most 12 decimals."""
    if not _finite(value):
        return DASH
    if value == 0:
        return "0"
    d = digits - 1 - math.floor(math.log10(abs(value)))
    if 0 <= d <= 12:
        return f"{value:.{d}f}"
    if d < 0 and abs(value) < 1e15:
        return f"{round(value, d):.0f}"
    return f"{value:.{digits}g}"


def pct(value: Any, decimals: int = 2, signed: bool = False) -> str:
    """Percentage number (without the % sign)."""
    if not _finite(value):
        return DASH
    return f"{value:+.{decimals}f}" if signed else f"{value:.{decimals}f}"


def number(key: str, value: Any, text: str, cls: str = "") -> Markup:
    """<span> holding a number of report.json: ``data-key`` is its path in report.json
    (dot-separated, list indices as numbers), ``data-value`` its exact JSON value."""
    return Markup(
        '<span class="num{c}" data-key="{k}" data-value="{v}">{t}</span>'.format(
            c=f" {escape(cls)}" if cls else "",
            k=escape(key),
            v=escape(json.dumps(value)),
            t=escape(text),
        )
    )


__all__ = ["DASH", "fixed", "number", "pct", "scale_decimals", "sig"]
