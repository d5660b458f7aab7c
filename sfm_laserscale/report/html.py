"""report.html: one self-contained file (images embedded as data URIs) from report.json."""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

from jinja2 import Environment, PackageLoader, select_autoescape

from sfm_laserscale.report.plots import per_laser_plot


def _fmt(value: Any, digits: int = 6) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def _data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(data).decode("ascii")


def render_html(report: dict[str, Any], out_dir: Path, overlays: dict[str, str]) -> str:
    """The HTML report for people; every number comes from ``report``."""
    env = Environment(
        loader=PackageLoader("sfm_laserscale", "report/templates"),
        autoescape=select_autoescape(["html"]),
    )
    env.filters["f"] = _fmt
    images = {}
    for name, rel in overlays.items():
        images[name] = _data_uri((out_dir / rel).read_bytes(), "image/jpeg")
    plot = per_laser_plot(report)
    return env.get_template("report.html").render(
        r=report, overlays=images, plot=None if plot is None else _data_uri(plot, "image/png")
    )
