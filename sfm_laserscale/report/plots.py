"""Report plots (matplotlib, Agg): PNG bytes, no files."""

from __future__ import annotations

import io
import math
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def per_laser_plot(report: dict[str, Any]) -> bytes | None:
    """The paper's per-laser plot: FCM estimate per laser (circles) per image, mean dashed."""
    images = [im for im in report["images"] if im["estimates"]]
    if not images:
        return None
    fig, ax = plt.subplots(figsize=(8, 3.6), dpi=110)
    lasers = sorted({e["laser"] for im in images for e in im["estimates"] if e["method"] == "fcm"})
    for li, laser in enumerate(lasers):
        xs, ys, es = [], [], []
        for i, im in enumerate(images):
            for e in im["estimates"]:
                if e["method"] == "fcm" and e["laser"] == laser and e["scale"] is not None:
                    xs.append(i + (li - (len(lasers) - 1) / 2) * 0.08)
                    ys.append(e["scale"])
                    es.append(e["sigma"] or 0.0)
        ax.errorbar(xs, ys, yerr=es, fmt="o", mfc="none", label=f"FCM {laser}", capsize=2)
    head = report["scale"]
    if head["value"] is not None:
        ax.axhline(head["value"], ls="--", color="k", lw=1, label=f"fused {head['method'].upper()}")
        lo, hi = head["ci95"]
        if lo is not None and hi is not None and math.isfinite(lo):
            ax.axhspan(lo, hi, color="k", alpha=0.08, label="95 % interval")
    for m, mk in (("pcm", "x"), ("direct3d", "+")):
        pts = [
            (i, e["scale"])
            for i, im in enumerate(images)
            for e in im["estimates"]
            if e["method"] == m and e["scale"] is not None and not e["rejected"]
        ]
        if pts:
            ax.plot(*zip(*pts, strict=True), mk, ms=8, label=m.upper())
    ax.set_xticks(
        range(len(images)), [im["name"] for im in images], rotation=30, ha="right", fontsize=8
    )
    ax.set_ylabel("scale (m per model unit)")
    ax.legend(fontsize=7, ncol=3)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()
