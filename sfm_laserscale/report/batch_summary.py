"""The batch's summary: ``summary.csv`` (one row per manifest row) and ``summary.html`` (one
page for the cruise: a table, each model's scale with its interval, links to each report),
both written atomically (a temporary file renamed over the old one)."""

from __future__ import annotations

import csv
import io
import math
import os
import tempfile
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

from jinja2 import Environment, PackageLoader, select_autoescape

from sfm_laserscale.batch.job import STATUSES, JobOutcome

SUMMARY_COLUMNS = ("name", "status", "scale", "std", "ci95_low", "ci95_high", "inverse",
                   "method", "images_used", "estimates", "wall_s", "reason")
_AXIS_PCT = 1.0  # half-width of the interval plots, % of the scale


def _atomic_write(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def summary_csv(outcomes: Sequence[JobOutcome]) -> str:
    """summary.csv's text: the columns of docs/BATCH.md, empty where there is no value."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(SUMMARY_COLUMNS)
    for o in outcomes:
        d = asdict(o)
        w.writerow(["" if d[c] is None else (repr(d[c]) if isinstance(d[c], float) else d[c])
                    for c in SUMMARY_COLUMNS])
    return buf.getvalue()


def _fmt(x: float | None) -> str:
    return "" if x is None or not math.isfinite(x) else f"{x:.6g}"


def _bar(o: JobOutcome, width: float = 160.0) -> tuple[float, float, str] | None:
    """x of the interval's ends on a ±_AXIS_PCT % axis centred on the scale (pixels), and its
    half-width in % of the scale as text."""
    scale = o.scale
    if scale is None or o.ci95_low is None or o.ci95_high is None or not scale:
        return None
    half = width / 2

    def x(v: float) -> float:
        return round(min(width, max(0.0, half + half * (v / scale - 1) * 100 / _AXIS_PCT)), 1)
    pct = 100 * (o.ci95_high - o.ci95_low) / 2 / scale
    return x(o.ci95_low), x(o.ci95_high), f"±{pct:.2g} %"


def summary_html(outcomes: Sequence[JobOutcome], manifest: Path) -> str:
    """summary.html's text."""
    env = Environment(loader=PackageLoader("sfm_laserscale", "report/templates"),
                      autoescape=select_autoescape(["html"]))
    counts = [(s, sum(o.status == s for o in outcomes)) for s in STATUSES]
    return env.get_template("summary.html").render(
        outcomes=outcomes, manifest=str(manifest), manifest_name=manifest.name,
        counts=[(s, n) for s, n in counts if n], bars={o.name: _bar(o) for o in outcomes},
        fmt=_fmt, axis_pct=_AXIS_PCT)


def write_summary(out_dir: Path, outcomes: Sequence[JobOutcome], manifest: Path) -> None:
    """DIR/summary.csv and DIR/summary.html."""
    _atomic_write(out_dir / "summary.csv", summary_csv(outcomes))
    _atomic_write(out_dir / "summary.html", summary_html(outcomes, manifest))
