"""Small SVG charts for the report: axes, ticks, markers, error bars, bands and legends.

Written here instead of using matplotlib, which drew the report's two plots until 2026-11-25.
Importing matplotlib and drawing the two figures took ~0.9 s and ~38 MB per run: more than
the rest of the report, and at 640 × 480 a quarter of issue #7's budget for everything but
SIFT. These charts need only markers, error bars, bands, lines and text, which SVG draws
directly (~5 ms), and the result stays sharp at any zoom. matplotlib still draws the
simulation's figures (``simulate_plots``), where time does not matter.

Units are SVG user units (1 unit = 1 CSS px at the chart's natural size).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from xml.sax.saxutils import escape, quoteattr

FONT = "DejaVu Sans, Verdana, Helvetica, Arial, sans-serif"
FONT_SIZE = 13.0
CHAR_WIDTH_EM = 0.6  # average glyph width of the font, for layout only
MINUS = "\u2212"


def text_width(text: str, size: float = FONT_SIZE) -> float:
    """Estimated width of ``text`` in user units (for margins; the browser draws the glyphs)."""
    return len(text) * CHAR_WIDTH_EM * size


def nice_ticks(lo: float, hi: float, max_ticks: int = 8) -> list[float]:
    """Round tick values (steps of 1, 2, 2.5 or 5 × 10^k) inside [lo, hi]: the finest step
    giving at most ``max_ticks + 1`` of them."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    raw = (hi - lo) / max(max_ticks, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * mag >= raw * (1 - 1e-9))
    first, last = math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9)
    return [0.0 if k == 0 else k * step for k in range(first, last + 1)]


def tick_labels(ticks: list[float]) -> list[str]:
    """Tick texts with the decimals their step needs (same for all), with a true minus sign."""
    if not ticks:
        return []
    step = abs(ticks[1] - ticks[0]) if len(ticks) > 1 else (abs(ticks[0]) or 1.0)
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    if abs(step * 10**decimals - round(step * 10**decimals)) > 1e-6:  # 2.5 × 10^k
        decimals += 1
    out = []
    for t in ticks:
        s = f"{t:.{decimals}f}"
        out.append("0" + s[2:] if s.startswith("-0") and float(s) == 0 else s)
    return [s.replace("-", MINUS) for s in out]


@dataclass(frozen=True)
class Frame:
    """A plot area: its box in user units and the data ranges it shows."""

    left: float
    top: float
    width: float
    height: float
    xlim: tuple[float, float]
    ylim: tuple[float, float]

    def x(self, v: float) -> float:
        """User-unit x of data x ``v``."""
        x0, x1 = self.xlim
        return self.left + (v - x0) / (x1 - x0) * self.width

    def y(self, v: float) -> float:
        """User-unit y of data y ``v`` (up is larger)."""
        y0, y1 = self.ylim
        return self.top + (y1 - v) / (y1 - y0) * self.height

    @property
    def right(self) -> float:
        return self.left + self.width

    @property
    def bottom(self) -> float:
        return self.top + self.height


def _n(v: float) -> str:
    return f"{v:.2f}".rstrip("0").rstrip(".")


@dataclass
class Svg:
    """An SVG document built element by element (``tobytes`` writes it)."""

    width: float
    height: float
    title: str
    parts: list[str] = field(default_factory=list)

    def add(self, element: str) -> None:
        self.parts.append(element)

    def line(self, x1: float, y1: float, x2: float, y2: float, color: str, width: float = 1.0,
             dash: str | None = None, opacity: float | None = None, cls: str | None = None) -> None:
        extra = (f' stroke-dasharray="{dash}"' if dash else "") + (
            f' stroke-opacity="{_n(opacity)}"' if opacity is not None else "") + (
            f' class="{cls}"' if cls else "")
        self.add(f'<line x1="{_n(x1)}" y1="{_n(y1)}" x2="{_n(x2)}" y2="{_n(y2)}" '
                 f'stroke="{color}" stroke-width="{_n(width)}"{extra}/>')

    def rect(self, x: float, y: float, w: float, h: float, fill: str,
             opacity: float | None = None, cls: str | None = None) -> None:
        extra = (f' fill-opacity="{_n(opacity)}"' if opacity is not None else "") + (
            f' class="{cls}"' if cls else "")
        self.add(f'<rect x="{_n(x)}" y="{_n(y)}" width="{_n(max(w, 0))}" '
                 f'height="{_n(max(h, 0))}" fill="{fill}"{extra}/>')

    def text(self, x: float, y: float, text: str, size: float = FONT_SIZE,
             anchor: str = "start", color: str = "#1a1a1a", rotate: float | None = None,
             baseline: str = "auto", cls: str | None = None) -> None:
        rot = f' transform="rotate({_n(rotate)} {_n(x)} {_n(y)})"' if rotate else ""
        base = f' dominant-baseline="{baseline}"' if baseline != "auto" else ""
        c = f' class="{cls}"' if cls else ""
        self.add(f'<text x="{_n(x)}" y="{_n(y)}" font-size="{_n(size)}" '
                 f'text-anchor="{anchor}" fill="{color}"{base}{rot}{c}>{escape(text)}</text>')

    def tobytes(self) -> bytes:
        head = (f'<svg xmlns="http://www.w3.org/2000/svg" width="{_n(self.width)}" '
                f'height="{_n(self.height)}" viewBox="0 0 {_n(self.width)} {_n(self.height)}" '
                f'font-family={quoteattr(FONT)}>'
                f'<title>{escape(self.title)}</title>'
                f'<rect width="100%" height="100%" fill="#ffffff"/>')
        return (head + "".join(self.parts) + "</svg>").encode("utf-8")


def _polygon(points: list[tuple[float, float]]) -> str:
    return " ".join(f"{_n(x)},{_n(y)}" for x, y in points)


def _shape(kind: str, r: float) -> str:
    """The outline of marker ``kind`` of radius ``r`` around the origin (no attributes)."""
    if kind == "o":
        return f'<circle r="{_n(r)}"'
    if kind == "s":
        return f'<rect x="{_n(-r)}" y="{_n(-r)}" width="{_n(2 * r)}" height="{_n(2 * r)}"'
    if kind == "x":
        return f'<path d="M{_n(-r)} {_n(-r)}L{_n(r)} {_n(r)}M{_n(-r)} {_n(r)}L{_n(r)} {_n(-r)}"'
    outlines = {
        "D": [(0.0, -1.1), (1.1, 0.0), (0.0, 1.1), (-1.1, 0.0)],
        "^": [(0.0, -1.15), (1.05, 0.75), (-1.05, 0.75)],
        "v": [(0.0, 1.15), (1.05, -0.75), (-1.05, -0.75)],
    }
    if kind == "X":  # a bold cross: four arms of half-thickness 0.38 r
        t = 0.38
        arm = [(t, 0.0), (1.0, 1.0 - t), (1.0 - t, 1.0), (0.0, t)]
        pts: list[tuple[float, float]] = []
        for qx, qy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
            quad = [(qx * a, qy * b) for a, b in arm]
            pts += quad if qx * qy > 0 else quad[::-1]
        outlines["X"] = pts
    if kind not in outlines:
        raise ValueError(f"unknown marker {kind!r}")
    return f'<polygon points="{_polygon([(r * a, r * b) for a, b in outlines[kind]])}"'


def marker(svg: Svg, kind: str, x: float, y: float, size: float, color: str,
           filled: bool = False, stroke: float = 1.6, data: str | None = None,
           beyond: bool = False) -> None:
    """One marker centred at (x, y), ``size`` across: o circle, s square, D diamond, ^ v
    triangles, x cross (lines), X bold cross (filled). ``data``: the value it shows, kept as
    ``data-value`` (a legend key has none); ``beyond``: an arrow for a value off the axis."""
    fill = "none" if kind == "x" else (color if filled else "#ffffff")
    width = stroke * 1.5 if kind == "x" else stroke
    role = "marker outlier" if beyond else "marker"
    tag = (f' class="{role}" data-kind="{kind}" data-value={quoteattr(data)}' if data is not None
           else f' class="key" data-kind="{kind}"')
    svg.add(f'<g transform="translate({_n(x)} {_n(y)})"{tag}>{_shape(kind, size / 2.0)} '
            f'fill="{fill}" stroke="{color}" stroke-width="{_n(width)}"/></g>')


def error_bar(svg: Svg, x: float, y_low: float, y_high: float, color: str,
              width: float = 1.3, cap: float = 3.0) -> None:
    """A vertical error bar with caps, between two user-unit y values."""
    svg.line(x, y_low, x, y_high, color, width, cls="err")
    for y in (y_low, y_high):
        svg.line(x - cap, y, x + cap, y, color, width + 0.4)


def y_axis(svg: Svg, frame: Frame, ticks: list[float], label: str,
           grid: bool = True) -> None:
    """Grid lines, left spine, tick marks and labels, and the rotated axis label."""
    labels = tick_labels(ticks)
    for t, s in zip(ticks, labels, strict=True):
        y = frame.y(t)
        if grid:
            svg.line(frame.left, y, frame.right, y, "#000000", 0.8, opacity=0.12)
        svg.line(frame.left - 5, y, frame.left, y, "#1a1a1a", 1.0)
        svg.text(frame.left - 8, y, s, anchor="end", baseline="central", cls="ytick")
    svg.line(frame.left, frame.top, frame.left, frame.bottom, "#1a1a1a", 1.1)
    widest = max((text_width(s) for s in labels), default=0.0)
    lx = frame.left - 14 - widest
    svg.text(lx, frame.top + frame.height / 2, label, anchor="middle", rotate=-90,
             baseline="text-after-edge")


def x_axis(svg: Svg, frame: Frame, positions: list[float], labels: list[str] | None,
           rotate: bool = False) -> None:
    """Bottom spine, tick marks and (optionally, possibly slanted) category labels."""
    svg.line(frame.left, frame.bottom, frame.right, frame.bottom, "#1a1a1a", 1.1)
    for i, p in enumerate(positions):
        x = frame.x(p)
        svg.line(x, frame.bottom, x, frame.bottom + 5, "#1a1a1a", 1.0)
        if labels is None:
            continue
        if rotate:
            svg.text(x + 4, frame.bottom + 14, labels[i], anchor="end", rotate=-35,
                     baseline="central", cls="xtick")
        else:
            svg.text(x, frame.bottom + 9, labels[i], anchor="middle",
                     baseline="text-before-edge", cls="xtick")


def x_labels_height(labels: list[str], rotate: bool) -> float:
    """User units below the axis the category labels need."""
    if not labels:
        return 10.0
    if not rotate:
        return 12.0 + FONT_SIZE * 1.3
    return 18.0 + max(text_width(s) for s in labels) * math.sin(math.radians(35)) + FONT_SIZE


@dataclass(frozen=True)
class LegendEntry:
    """One legend row: ``kind`` is a marker letter, ``dash`` (a dashed line) or ``band``."""

    kind: str
    color: str
    label: str
    filled: bool = False


def legend(svg: Svg, x: float, y: float, entries: list[LegendEntry]) -> None:
    """Legend rows from (x, y) down: key then label."""
    for i, e in enumerate(entries):
        cy = y + 10 + i * 21.0
        if e.kind == "dash":
            svg.line(x, cy, x + 24, cy, e.color, 1.4, dash="5 3")
        elif e.kind == "band":
            svg.rect(x, cy - 6, 24, 12, e.color, opacity=0.35)
        else:
            marker(svg, e.kind, x + 12, cy, 10.0, e.color, e.filled)
        svg.text(x + 32, cy, e.label, baseline="central", cls="legend")


def legend_width(entries: list[LegendEntry]) -> float:
    """User units a legend needs, key and longest label."""
    return 36.0 + max((text_width(e.label) for e in entries), default=0.0)


__all__ = [
    "FONT_SIZE",
    "Frame",
    "LegendEntry",
    "Svg",
    "error_bar",
    "legend",
    "legend_width",
    "marker",
    "nice_ticks",
    "text_width",
    "tick_labels",
    "x_axis",
    "x_labels_height",
    "y_axis",
]
