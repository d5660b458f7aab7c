"""The footprint areas' histogram of report.html (SVG, from report.json's ``footprints``
block): laser images and model images stacked per bin."""

from __future__ import annotations

from typing import Any

from sfm_laserscale.report.svgchart import (
    Frame,
    LegendEntry,
    Svg,
    legend,
    legend_width,
    nice_ticks,
    tick_labels,
    x_axis,
    y_axis,
)

_WIDTH, _HEIGHT = 760.0, 300.0
_COLORS = {"model": "#7a8fa6", "laser": "#c0392b"}


def footprint_histogram(report: dict[str, Any]) -> bytes | None:
    """SVG bytes of the histogram of footprint areas (m²), or None without footprints."""
    block = report.get("footprints") or {}
    hist = block.get("histogram_area_m2")
    if not hist:
        return None
    edges = [float(e) for e in hist["edges"]]
    model, laser = hist["model"], hist["laser"]
    top_count = max((m + la for m, la in zip(model, laser, strict=True)), default=0)
    yticks = [t for t in nice_ticks(0.0, max(top_count, 1)) if t == int(t)]  # counts
    entries = [LegendEntry("band", _COLORS[k], f"{k} images") for k in ("model", "laser")]
    left, right = 64.0, _WIDTH - legend_width(entries) - 24.0
    frame = Frame(left, 34.0, right - left, _HEIGHT - 34.0 - 46.0, (edges[0], edges[-1]),
                  (0.0, max(yticks[-1], 1.0)))
    svg = Svg(_WIDTH, _HEIGHT, "Footprint area of each image (m²)")
    svg.text(left, 20, "Footprint area of each image on the scaled mesh (m²)", size=14.5,
             cls="title")
    y_axis(svg, frame, yticks, "images")
    for i in range(len(edges) - 1):
        x0, x1 = frame.x(edges[i]), frame.x(edges[i + 1])
        base = 0
        for kind, counts in (("model", model), ("laser", laser)):
            if counts[i]:
                y_hi, y_lo = frame.y(base + counts[i]), frame.y(base)
                svg.rect(x0 + 1, y_hi, x1 - x0 - 2, y_lo - y_hi, _COLORS[kind], cls=kind)
                base += counts[i]
    xticks = [t for t in nice_ticks(edges[0], edges[-1]) if edges[0] <= t <= edges[-1]]
    x_axis(svg, frame, xticks, tick_labels(xticks))
    svg.text(left + frame.width / 2, _HEIGHT - 8, "area (m²)", anchor="middle")
    legend(svg, right + 20.0, 34.0, entries)
    return svg.tobytes()
