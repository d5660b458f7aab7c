"""The report's plots of the model checks (SVG, from report.json only): the per-image scale
against its position along the survey (drift, with the per-segment scales) and against the
camera–scene distance, each with the fitted trend."""

from __future__ import annotations

import math
from typing import Any

from sfm_laserscale.report.style import WARNING_HEX
from sfm_laserscale.report.svgchart import (
    Frame,
    LegendEntry,
    Svg,
    error_bar,
    legend,
    legend_width,
    marker,
    nice_ticks,
    tick_labels,
    y_axis,
)
from sfm_laserscale.report.svgchart import x_axis as draw_x_axis

_INK = "#1f4e79"
_FIT = "#b42318"
_SEG = "#2e7d32"


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _limits(values: list[float], pad: float = 0.08) -> tuple[float, float]:
    lo, hi = min(values), max(values)
    span = hi - lo or max(abs(hi), 1.0) * 0.1
    return lo - pad * span, hi + pad * span


def trend_plot(trend: dict[str, Any] | None, title: str, x_label: str,
               segments: list[dict[str, Any]] | None = None, reference: float | None = None
               ) -> bytes | None:
    """Per-image deviation (%, ±1σ) against x, the fitted line, and segment scales (as
    deviations from ``reference``) when given; None without at least two points."""
    if not trend:
        return None
    pts = [p for p in trend["points"] if _finite(p["x"]) and _finite(p["deviation_pct"])]
    if len(pts) < 2:
        return None
    xs = [p["x"] for p in pts]
    ys = [p["deviation_pct"] + s * (p["sigma_pct"] or 0.0) for p in pts for s in (-1, 1)]
    segs = [s for s in (segments or []) if _finite(s.get("value")) and _finite(reference)]
    ys += [100 * (s["value"] / reference - 1) for s in segs]  # type: ignore[operator]
    entries = [LegendEntry("o", _INK, "image (±1σ)", True), LegendEntry("dash", _FIT, "trend"),
               LegendEntry("s", WARNING_HEX, "left out by fusion")]
    if segs:
        entries.append(LegendEntry("dash", _SEG, "segment scale"))
    width, height = 760.0, 320.0
    frame = Frame(78.0, 34.0, width - 78.0 - legend_width(entries) - 30.0, height - 34.0 - 56.0,
                  _limits(xs), _limits(ys))
    svg = Svg(width, height, title)
    svg.text(frame.left, 20.0, title, size=14.0)
    y_axis(svg, frame, nice_ticks(*frame.ylim, 6), "scale vs. fused (%)")
    ticks = nice_ticks(*frame.xlim, 8)
    draw_x_axis(svg, frame, ticks, tick_labels(ticks))
    svg.text(frame.left + frame.width / 2, height - 8.0, x_label, anchor="middle")
    if frame.ylim[0] < 0 < frame.ylim[1]:
        svg.line(frame.left, frame.y(0.0), frame.right, frame.y(0.0), "#262626", 1.0, dash="6 4")
    _fit_line(svg, frame, trend, pts)
    for s in segs:
        y = frame.y(100 * (s["value"] / reference - 1))  # type: ignore[operator]
        lo, hi = s["position_m"]
        svg.line(frame.x(lo), y, frame.x(hi), y, _SEG, 2.4, dash="7 3")
    for p in pts:
        x, y = frame.x(p["x"]), frame.y(p["deviation_pct"])
        sig = p["sigma_pct"] or 0.0
        color = _INK if p["used"] else WARNING_HEX
        error_bar(svg, x, frame.y(p["deviation_pct"] - sig), frame.y(p["deviation_pct"] + sig),
                  color)
        marker(svg, "o" if p["used"] else "s", x, y, 9.0, color, p["used"],
               data=f"{p['deviation_pct']:.6g}")
    legend(svg, frame.right + 24.0, frame.top, entries)
    return svg.tobytes()


def _fit_line(svg: Svg, frame: Frame, trend: dict[str, Any], pts: list[dict[str, Any]]) -> None:
    """The weighted trend line through the points fusion kept (or all, for drift)."""
    slope = trend.get("slope_pct_per_m")
    if not _finite(slope):
        return
    use = [p for p in pts if p["used"] or trend["variable"] == "position_m"]
    w = [1.0 / p["sigma_pct"] ** 2 for p in use if _finite(p["sigma_pct"]) and p["sigma_pct"]]
    if len(w) != len(use) or not w:
        return
    xm = sum(wi * p["x"] for wi, p in zip(w, use, strict=True)) / sum(w)
    ym = sum(wi * p["deviation_pct"] for wi, p in zip(w, use, strict=True)) / sum(w)
    x0, x1 = frame.xlim
    ya, yb = ym + slope * (x0 - xm), ym + slope * (x1 - xm)
    lo, hi = frame.ylim
    if all(lo <= y <= hi for y in (ya, yb)):
        svg.line(frame.x(x0), frame.y(ya), frame.x(x1), frame.y(yb), _FIT, 1.6, dash="5 3")


def model_plots(report: dict[str, Any]) -> dict[str, bytes | None]:
    """The drift and distance plots of report.json's ``model_checks`` (None where absent)."""
    checks = report.get("model_checks") or {}
    ref = report["methods"].get(checks.get("method", ""), {}).get("value")
    drift = checks.get("drift")
    return {
        "drift": trend_plot(drift, "Per-image scale along the survey",
                            "position along the model's long axis (m)",
                            (drift or {}).get("segments"), ref),
        "distance": trend_plot(checks.get("distance"), "Per-image scale against distance",
                               "camera–scene distance (m)"),
    }
