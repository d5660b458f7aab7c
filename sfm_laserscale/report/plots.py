"""Report plots as SVG, drawn from the report.json dict: SVG bytes, no files.

Drawn with ``svgchart`` (see there why not matplotlib). Every marker carries its value as
``data-value``, so tests can check each one's position against the axis ticks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from sfm_laserscale.report.analysis import (
    METHOD_LABELS,
    METHOD_ORDER,
    pcm_joint_fell_back,
)
from sfm_laserscale.report.style import WARNING_HEX, laser_color_hex
from sfm_laserscale.report.svgchart import (
    Frame,
    LegendEntry,
    Svg,
    error_bar,
    legend,
    legend_width,
    marker,
    nice_ticks,
    text_width,
    tick_labels,
    x_axis,
    x_labels_height,
    y_axis,
)

_WIDTH = 1000.0
_INK = "#1a1a1a"
_BAND = "#999999"
_MARKER = 10.0  # marker size (user units across)


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@dataclass
class _Point:
    """One marker: position, ±1σ, style; ``kept`` points set the axis range."""

    x: float
    y: float
    err: float | None
    marker: str
    color: str
    kept: bool
    filled: bool = False
    size: float = _MARKER


@dataclass
class _Panel:
    """What one plot area shows: points, values the y range must hold, reference lines
    (value, colour, width, dash) and the shaded 95 % band."""

    points: list[_Point]
    extra: list[Any]
    fmt: str
    ylabel: str
    lines: list[tuple[float, str, float, str | None]] = field(default_factory=list)
    band: tuple[float, float] | None = None


def _limits(points: list[_Point], extra: list[Any]) -> tuple[float, float] | None:
    """y range holding every kept point with its error bar and the ``extra`` values."""
    ys = [float(y) for y in extra if _finite(y)]
    for p in points:
        if p.kept:
            e = float(p.err) if p.err is not None and _finite(p.err) else 0.0
            ys += [p.y - e, p.y + e]
    if not ys:
        return None
    lo, hi = min(ys), max(ys)
    pad = 0.08 * (hi - lo) if hi > lo else max(abs(hi) * 1e-3, 1e-9)
    return lo - pad, hi + pad


def _ylim(panel: _Panel) -> tuple[float, float]:
    lim = _limits(panel.points, panel.extra)
    return lim if lim is not None else (-1.0, 1.0)


def _draw_points(svg: Svg, frame: Frame, points: list[_Point], fmt: str) -> None:
    """Markers with error bars; points beyond the kept points' range (rejected outliers) are
    drawn as arrows at the axis edge with their value, so they do not squash the others."""
    lo, hi = frame.ylim
    for p in sorted(points, key=lambda q: q.filled):  # filled (image) markers on top
        x = frame.x(p.x)
        if lo <= p.y <= hi:
            if p.err is not None and _finite(p.err) and p.err > 0:
                error_bar(svg, x, frame.y(max(p.y - p.err, lo)), frame.y(min(p.y + p.err, hi)),
                          p.color)
            marker(svg, p.marker, x, frame.y(p.y), p.size, p.color, p.filled, data=repr(p.y))
            continue
        top = p.y > hi
        y = frame.top if top else frame.bottom
        marker(svg, "^" if top else "v", x, y, 11.0, p.color, True, 1.0, repr(p.y), True)
        svg.text(x + 9, y + (12 if top else -6), fmt.format(p.y).replace("-", "\u2212"),
                 size=11.5, color=p.color, cls="outlier")


def _draw_panel(svg: Svg, frame: Frame, panel: _Panel) -> None:
    """Grid and y axis, band, reference lines, then the points."""
    y_axis(svg, frame, nice_ticks(*frame.ylim), panel.ylabel)
    if panel.band is not None:
        b_lo, b_hi = (min(max(v, frame.ylim[0]), frame.ylim[1]) for v in panel.band)
        svg.rect(frame.left, frame.y(b_hi), frame.width, frame.y(b_lo) - frame.y(b_hi), _BAND,
                 opacity=0.22, cls="band")
    for value, color, width, dash in panel.lines:
        if frame.ylim[0] <= value <= frame.ylim[1]:
            svg.line(frame.left, frame.y(value), frame.right, frame.y(value), color, width, dash)
    _draw_points(svg, frame, panel.points, panel.fmt)


def _chart(title: str, panels: list[tuple[_Panel, float]], names: list[str],
           entries: list[LegendEntry], height: float) -> bytes:
    """Panels stacked (relative heights) sharing the image axis, title and legend on the right."""
    ylims = [_ylim(p) for p, _ in panels]
    widest = max(text_width(s) for lim in ylims for s in tick_labels(nice_ticks(*lim)) or ["0"])
    left = widest + 48.0
    right = _WIDTH - legend_width(entries) - 24.0
    xlim = (-0.6, len(names) - 0.4)
    spacing = (right - left) / max(len(names), 1)
    rotate = bool(names) and max(text_width(n) for n in names) > 0.92 * spacing
    if rotate:  # the first slanted label must not run off the left edge
        reach = text_width(names[0]) * math.cos(math.radians(35)) - 4.0
        left = max(left, reach + 6.0 - 0.6 * spacing)
    bottom = height - x_labels_height(names, rotate)
    top, gap = 34.0, 18.0
    avail = bottom - top - gap * (len(panels) - 1)
    total = sum(w for _, w in panels)
    svg = Svg(_WIDTH, height, title)
    svg.text(left, 20, title, size=14.5, cls="title")
    for (panel, weight), ylim in zip(panels, ylims, strict=True):
        h = avail * weight / total
        frame = Frame(left, top, right - left, h, xlim, ylim)
        svg.add('<g class="panel">')
        _draw_panel(svg, frame, panel)
        last = panel is panels[-1][0]
        x_axis(svg, frame, list(range(len(names))), names if last else None, rotate)
        svg.add("</g>")
        top += h + gap
    legend(svg, right + 20.0, 34.0, entries)
    return svg.tobytes()


def per_laser_method(report: dict[str, Any]) -> str | None:
    """FCM when any image has an FCM estimate, else PCM (one pair per 'laser')."""
    for method in ("fcm", "pcm"):
        if any(e["method"] == method for im in report["images"] for e in im["estimates"]):
            return method
    return None


def _rejected(image: dict[str, Any], method: str, laser: str, est: dict[str, Any]) -> bool:
    fused = image.get("fused", {}).get(method, {})
    return bool(est["rejected"]) or any(r["laser"] == laser for r in fused.get("rejected", []))


def _laser_points(
    report: dict[str, Any], images: list[dict[str, Any]], method: str, names: list[str]
) -> tuple[list[_Point], list[_Point]]:
    """Circles per laser (scale; deviation from the image) and the images' crosses."""
    top: list[_Point] = []
    dev: list[_Point] = []
    lasers = report["rig"]["lasers"]
    k = len(names)
    for li, laser in enumerate(names):
        color = laser_color_hex(lasers.index(laser) if laser in lasers else li)
        dx = (li - (k - 1) / 2) * min(0.09, 0.5 / max(k, 1))
        for i, im in enumerate(images):
            for e in im["estimates"]:
                if e["method"] != method or e["laser"] != laser or not _finite(e["scale"]):
                    continue
                bad = _rejected(im, method, laser, e)
                c, mk = (WARNING_HEX, "s") if bad else (color, "o")
                err = e["sigma"] if _finite(e["sigma"]) else None
                top.append(_Point(i + dx, e["scale"], err, mk, c, not bad))
                d = im.get("deviation_pct", {}).get(laser) if method == "fcm" else None
                if d is not None and _finite(d):
                    dev.append(_Point(i + dx, float(d), None, mk, c, not bad))
    for i, im in enumerate(images):
        f = im.get("fused", {}).get(method)
        if f and _finite(f["scale"]):
            c = _INK if f["used"] else WARNING_HEX
            err = f["sigma"] if _finite(f["sigma"]) else None
            top.append(_Point(i, f["scale"], err, "x", c, f["used"], True, 14.0))
    return top, dev


def _names(report: dict[str, Any], images: list[dict[str, Any]], method: str) -> list[str]:
    """Lasers (FCM) or pairs (PCM) that have an estimate, in rig order."""
    pool = (
        report["rig"]["lasers"]
        if method == "fcm"
        else ["+".join(p) for p in report["rig"]["pairs"]]
    )
    return [
        n
        for n in pool
        if any(e["method"] == method and e["laser"] == n for im in images for e in im["estimates"])
    ]


def _legend(report: dict[str, Any], names: list[str], method: str) -> list[LegendEntry]:
    lasers = report["rig"]["lasers"]
    return [
        *(
            LegendEntry("o", laser_color_hex(lasers.index(n) if n in lasers else i), n)
            for i, n in enumerate(names)
        ),
        LegendEntry("x", _INK, "image estimate", True),
        LegendEntry("dash", _INK, f"fused {METHOD_LABELS[method]}"),
        LegendEntry("band", _BAND, "95 % interval"),
        LegendEntry("s", WARNING_HEX, "rejected"),
    ]


def _band_of(block: dict[str, Any], rel_to: float | None = None) -> tuple[
        list[tuple[float, str, float, str | None]], tuple[float, float] | None]:
    """The fused value's dashed line and its 95 % band, optionally in % of ``rel_to``."""
    v: Any = block.get("value")
    lo, hi = block.get("ci95", [None, None])
    if not _finite(v):
        return [], None

    def t(x: float) -> float:
        return x if rel_to is None else 100.0 * (x / rel_to - 1.0)

    band = (t(float(lo)), t(float(hi))) if _finite(lo) and _finite(hi) else None
    return [(t(float(v)), "#262626", 1.4, "6 4")], band


def _deviation_panel(dev: list[_Point], report: dict[str, Any]) -> _Panel:
    """Each laser's deviation (%) from its image's estimate; dotted lines at the flag limit."""
    lim = report.get("diagnostics", {}).get("thresholds", {}).get("laser_deviation_min_pct")
    lines: list[tuple[float, str, float, str | None]] = [(0.0, "#262626", 1.2, None)]
    if _finite(lim):
        lines += [(-lim, "#737373", 1.0, "2 3"), (lim, "#737373", 1.0, "2 3")]
    extra = [-lim, lim] if _finite(lim) else [0.0]
    return _Panel(dev, extra, "{:+.2f} %", "deviation from image (%)", lines)


def per_laser_plot(report: dict[str, Any]) -> bytes | None:
    """The paper's per-laser plot (SVG): per image each laser's estimate (circles), the image's
    estimate (cross), the fused scale (dashed) and its 95 % band; below, each laser's
    deviation (%) from its image's estimate. None when nothing can be plotted."""
    method = per_laser_method(report)
    if method is None:
        return None
    images = [im for im in report["images"] if any(e["method"] == method for e in im["estimates"])]
    names = _names(report, images, method)
    block = report["methods"].get(method, {})
    lines, band = _band_of(block)
    top, dev = _laser_points(report, images, method, names)
    main = _Panel(top, [block.get("value"), *block.get("ci95", [])], "{:.6g}",
                  "scale (m per model unit)", lines, band)
    what = "laser" if method == "fcm" else "pair"
    title = f"{METHOD_LABELS[method]} estimate per image and {what}"
    panels = [(main, 3.0), (_deviation_panel(dev, report), 2.0)] if method == "fcm" else [
        (main, 1.0)]  # one pair per image: the pair IS the image estimate, no deviation panel
    return _chart(title, panels, [im["name"] for im in images],
                  _legend(report, names, method), 620.0 if method == "fcm" else 380.0)


_METHOD_MARKERS = {"fcm": "X", "pcm": "o", "pcm_joint": "D", "direct3d": "^"}


def _method_points(images: list[dict[str, Any]], methods: list[str], head: float) -> list[_Point]:
    """Each method's per-image scale as % from the headline, ±1σ, side by side per image."""
    pts = []
    for mi, m in enumerate(methods):
        dx = (mi - (len(methods) - 1) / 2) * 0.12
        for i, im in enumerate(images):
            f = im["fused"].get(m)
            if not f or not _finite(f["scale"]):
                continue
            err = 100.0 * f["sigma"] / head if _finite(f["sigma"]) else None
            pts.append(_Point(i + dx, 100.0 * (f["scale"] / head - 1.0), err,
                              _METHOD_MARKERS.get(m, "o"), _INK if f["used"] else WARNING_HEX,
                              f["used"], m == "fcm", 10.0))
    return pts


def methods_plot(report: dict[str, Any]) -> bytes | None:
    """Every method's per-image scale as a deviation (%) from the headline scale (±1σ), SVG."""
    head = report["scale"]["value"]
    if not _finite(head):
        return None
    images = [im for im in report["images"] if im.get("fused")]
    methods = [m for m in METHOD_ORDER if any(m in im["fused"] for im in images)]
    if pcm_joint_fell_back(report["methods"].get("pcm_joint", {"joint": True})):
        methods = [m for m in methods if m != "pcm_joint"]
    if not images or not methods:
        return None
    _, band = _band_of(report["scale"], head)
    panel = _Panel(_method_points(images, methods, head), [0.0, *(band or ())], "{:+.2f} %",
                   "vs. headline scale (%)", [(0.0, "#262626", 1.2, "6 4")], band)
    entries = [LegendEntry(_METHOD_MARKERS.get(m, "o"), _INK, METHOD_LABELS[m], m == "fcm")
               for m in methods]
    entries += [LegendEntry("band", _BAND, "headline 95 %"),
                LegendEntry("s", WARNING_HEX, "left out")]
    return _chart("Per-image scale of every method", [(panel, 1.0)],
                  [im["name"] for im in images], entries, 360.0)
