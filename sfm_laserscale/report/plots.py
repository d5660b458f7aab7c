"""Report plots (matplotlib, Agg) drawn from the report.json dict: PNG bytes, no files."""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from sfm_laserscale.report.analysis import (  # noqa: E402
    METHOD_LABELS,
    METHOD_ORDER,
    pcm_joint_fell_back,
)
from sfm_laserscale.report.style import WARNING_HEX, laser_color_hex  # noqa: E402

_DPI = 150
_INK = "#1a1a1a"
_RC: Any = {
    "font.size": 9.5,
    "axes.titlesize": 10.5,
    "axes.labelsize": 9.5,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "legend.fontsize": 8.5,
    "legend.frameon": False,
}


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI)
    plt.close(fig)
    return buf.getvalue()


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
    size: float = 6.5


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


def _draw(ax: Axes, points: list[_Point], extra: list[Any], fmt: str) -> None:
    """Markers with error bars; points beyond the kept points' range (rejected outliers) are
    drawn as arrows at the axis edge with their value, so they do not squash the others."""
    lim = _limits(points, extra)
    inside = [p for p in points if lim is None or lim[0] <= p.y <= lim[1]]
    # one errorbar call per style, not per point: matplotlib's cost is per artist
    # (54 calls took a third of the per-laser plot's time)
    groups: dict[tuple[str, str, bool, float, bool], list[_Point]] = {}
    for p in inside:
        groups.setdefault((p.marker, p.color, p.filled, p.size, p.err is not None), []).append(p)
    for (marker, color, filled, size, has_err), group in groups.items():
        ax.errorbar(
            [p.x for p in group],
            [p.y for p in group],
            yerr=[float(p.err or 0.0) for p in group] if has_err else None,
            fmt=marker,
            ms=size,
            mfc=color if filled else "white",
            mec=color,
            ecolor=color,
            mew=1.6,
            elinewidth=1.0,
            capsize=2,
            zorder=4 if filled else 3,
        )
    drawn = {id(p) for p in inside}
    for p in points:
        if lim is None or id(p) in drawn:
            continue
        top = p.y > lim[1]
        y = lim[1] if top else lim[0]
        ax.plot(p.x, y, "^" if top else "v", ms=8, color=p.color, clip_on=False, zorder=5)
        ax.annotate(
            fmt.format(p.y),
            (p.x, y),
            xytext=(7, -2 if top else 2),
            textcoords="offset points",
            fontsize=8,
            color=p.color,
            va="top" if top else "bottom",
        )
    if lim is not None:
        ax.set_ylim(*lim)


def per_laser_method(report: dict[str, Any]) -> str | None:
    """FCM when any image has an FCM estimate, else PCM (one pair per 'laser')."""
    for method in ("fcm", "pcm"):
        if any(e["method"] == method for im in report["images"] for e in im["estimates"]):
            return method
    return None


def _rejected(image: dict[str, Any], method: str, laser: str, est: dict[str, Any]) -> bool:
    fused = image.get("fused", {}).get(method, {})
    return bool(est["rejected"]) or any(r["laser"] == laser for r in fused.get("rejected", []))


def _image_ticks(ax: Axes, names: list[str]) -> None:
    rot = 0 if len(names) <= 6 and max(len(n) for n in names) <= 16 else 35
    ax.set_xticks(range(len(names)), names, rotation=rot, ha="right" if rot else "center")
    ax.set_xlim(-0.6, len(names) - 0.4)


def _band(ax: Axes, block: dict[str, Any], label: str, rel_to: float | None = None) -> None:
    """Fused value (dashed) and its 95 % interval (grey band), optionally in % of ``rel_to``."""
    v: Any = block.get("value")
    lo, hi = block.get("ci95", [None, None])
    if not _finite(v):
        return

    def t(x: float) -> float:
        return x if rel_to is None else 100.0 * (x / rel_to - 1.0)

    if _finite(lo) and _finite(hi):
        ax.axhspan(t(float(lo)), t(float(hi)), color="0.6", alpha=0.22, lw=0, zorder=0)
    ax.axhline(t(float(v)), ls="--", color="0.15", lw=1.1, zorder=1, label=label)


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
            top.append(_Point(i, f["scale"], err, "x", c, f["used"], True, 10.0))
    return top, dev


def _legend_handles(report: dict[str, Any], names: list[str], method: str) -> list[Line2D]:
    def mk(marker: str, color: str, label: str, mfc: str = "white") -> Line2D:
        return Line2D(
            [],
            [],
            marker=marker,
            ls="none",
            color=color,
            mec=color,
            mfc=mfc,
            mew=1.6,
            ms=7,
            label=label,
        )

    lasers = report["rig"]["lasers"]
    h = [
        mk("o", laser_color_hex(lasers.index(n) if n in lasers else i), n)
        for i, n in enumerate(names)
    ]
    h.append(mk("x", _INK, "image estimate", mfc=_INK))
    h.append(Line2D([], [], ls="--", color="0.15", label=f"fused {METHOD_LABELS[method]}"))
    h.append(Line2D([], [], lw=7, color="0.6", alpha=0.4, label="95 % interval"))
    h.append(mk("s", WARNING_HEX, "rejected"))
    return h


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


def _deviation_panel(ax: Axes, dev: list[_Point], report: dict[str, Any]) -> None:
    """Each laser's deviation (%) from its image's estimate; dotted lines at the flag limit."""
    lim = report.get("diagnostics", {}).get("thresholds", {}).get("laser_deviation_min_pct")
    ax.axhline(0.0, color="0.15", lw=1.0)
    if _finite(lim):
        for y in (-lim, lim):
            ax.axhline(y, color="0.45", lw=0.9, ls=":")
    _draw(ax, dev, [-lim, lim] if _finite(lim) else [0.0], "{:+.2f} %")
    ax.set_ylabel("deviation from image (%)")
    ax.grid(axis="y", alpha=0.3)


def per_laser_plot(report: dict[str, Any]) -> bytes | None:
    """The paper's per-laser plot: per image each laser's estimate (circles), the image's
    estimate (cross), the fused scale (dashed) and its 95 % band; below, each laser's
    deviation (%) from its image's estimate. None when nothing can be plotted."""
    method = per_laser_method(report)
    if method is None:
        return None
    images = [im for im in report["images"] if any(e["method"] == method for e in im["estimates"])]
    names = _names(report, images, method)
    with plt.rc_context(_RC):
        if method == "fcm":
            fig, (ax, ax_dev) = plt.subplots(
                2,
                1,
                figsize=(10.0, 6.2),
                sharex=True,
                gridspec_kw={"height_ratios": [3, 2]},
                layout="constrained",
            )
        else:  # one pair per image: the pair IS the image estimate, no deviation panel
            fig, ax = plt.subplots(figsize=(10.0, 3.8), layout="constrained")
            ax_dev = None
        block = report["methods"].get(method, {})
        _band(ax, block, f"fused {METHOD_LABELS[method]}")
        top, dev = _laser_points(report, images, method, names)
        _draw(ax, top, [block.get("value"), *block.get("ci95", [])], "{:.6g}")
        ax.set_ylabel("scale (m per model unit)")
        what = "laser" if method == "fcm" else "pair"
        ax.set_title(f"{METHOD_LABELS[method]} estimate per image and {what}", loc="left")
        ax.grid(axis="y", alpha=0.3)
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.legend(
            handles=_legend_handles(report, names, method),
            loc="upper left",
            bbox_to_anchor=(1.01, 1.0),
        )
        if ax_dev is not None:
            _deviation_panel(ax_dev, dev, report)
        _image_ticks(ax if ax_dev is None else ax_dev, [im["name"] for im in images])
        return _png(fig)


def methods_plot(report: dict[str, Any]) -> bytes | None:
    """Every method's per-image scale as a deviation (%) from the headline scale (±1σ)."""
    head = report["scale"]["value"]
    if not _finite(head):
        return None
    images = [im for im in report["images"] if im.get("fused")]
    methods = [m for m in METHOD_ORDER if any(m in im["fused"] for im in images)]
    if pcm_joint_fell_back(report["methods"].get("pcm_joint", {"joint": True})):
        methods = [m for m in methods if m != "pcm_joint"]
    if not images or not methods:
        return None
    markers = {"fcm": "X", "pcm": "o", "pcm_joint": "D", "direct3d": "^"}
    with plt.rc_context(_RC):
        fig, ax = plt.subplots(figsize=(10.0, 3.6), layout="constrained")
        _band(ax, report["scale"], f"headline {METHOD_LABELS[report['scale']['method']]}", head)
        pts = []
        for mi, m in enumerate(methods):
            dx = (mi - (len(methods) - 1) / 2) * 0.12
            for i, im in enumerate(images):
                f = im["fused"].get(m)
                if not f or not _finite(f["scale"]):
                    continue
                c = _INK if f["used"] else WARNING_HEX
                err = 100.0 * f["sigma"] / head if _finite(f["sigma"]) else None
                pts.append(
                    _Point(
                        i + dx,
                        100.0 * (f["scale"] / head - 1.0),
                        err,
                        markers.get(m, "o"),
                        c,
                        f["used"],
                        m == "fcm",
                        7.0,
                    )
                )
        lo, hi = report["scale"]["ci95"]
        band = [100.0 * (x / head - 1.0) for x in (lo, hi) if _finite(x)]
        _draw(ax, pts, [0.0, *band], "{:+.2f} %")
        handles = [
            Line2D(
                [],
                [],
                marker=markers.get(m, "o"),
                ls="none",
                color=_INK,
                mfc=_INK if m == "fcm" else "white",
                ms=7,
                label=METHOD_LABELS[m],
            )
            for m in methods
        ]
        handles.append(Line2D([], [], lw=7, color="0.6", alpha=0.4, label="headline 95 %"))
        handles.append(
            Line2D(
                [],
                [],
                marker="s",
                ls="none",
                color=WARNING_HEX,
                mfc="white",
                ms=7,
                label="left out",
            )
        )
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        ax.axhline(0.0, color="0.15", lw=1.0, ls="--")
        ax.set_ylabel("vs. headline scale (%)")
        ax.set_title("Per-image scale of every method", loc="left")
        ax.grid(axis="y", alpha=0.3)
        _image_ticks(ax, [im["name"] for im in images])
        return _png(fig)
