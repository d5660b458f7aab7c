"""Figures of ``simulate`` (matplotlib, Agg): PNG bytes, no files.

Like the paper's figures: the scale error over the pitch/roll grid per method for the smooth
and the rough area (heatmaps), error distributions at each distance (box plots), PCM error
against the depth difference of the two hits (PCM vs PCM-joint), plus the normalised errors
(estimate − truth) / reported σ against N(0, 1), which shows whether the σ is calibrated.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.synthetic.simulate.runner import SimulationResult
from sfm_laserscale.synthetic.simulate.stats import antithetic_pairs, grid_maps, method_rows
from sfm_laserscale.synthetic.simulate.tables import method_label
from sfm_laserscale.synthetic.simulate.views import grid_angles

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

F64 = NDArray[np.float64]
DPI = 90


def _png(fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    return buf.getvalue()


def heatmaps_png(maps: Mapping[str, Mapping[str, F64]], angles_deg: F64,
                 labels: Mapping[str, str], title: str) -> bytes:
    """Rows = areas, columns = methods; colour = mean error % at each (pitch, roll)."""
    areas = list(maps)
    methods = [m for m in labels if any(m in maps[a] for a in areas)]
    fig, axes = plt.subplots(len(areas), len(methods), squeeze=False,
                             figsize=(2.3 * len(methods) + 0.6, 2.3 * len(areas) + 0.5))
    ext = (angles_deg[0], angles_deg[-1], angles_deg[0], angles_deg[-1])
    ticks = [float(angles_deg[0]), 0.0, float(angles_deg[-1])]
    for i, area in enumerate(areas):
        for j, m in enumerate(methods):
            _heatmap_axes(fig, axes[i, j], maps[area].get(m), ext, ticks,
                          f"{labels[m]}\n{area}", first=(j == 0, i == len(areas) - 1))
    fig.suptitle(title + " — mean error (% of the scale); x: pitch (°), y: roll (°)", fontsize=9)
    # fixed margins: tight_layout takes seconds on a dozen axes with colour bars
    fig.subplots_adjust(left=0.05, right=0.97, bottom=0.09, top=0.84, wspace=0.5, hspace=0.55)
    return _png(fig)


def _heatmap_axes(fig: Any, ax: Any, arr: F64 | None, ext: tuple[float, ...],
                  ticks: list[float], title: str, first: tuple[bool, bool]) -> None:
    """One panel (few ticks and labels: text layout dominates matplotlib's drawing time)."""
    if arr is None:
        ax.axis("off")
        return
    # robust colour range: a single edge-spot cell would wash out the rest (it saturates)
    lim = float(np.nanpercentile(np.abs(arr), 98)) if np.isfinite(arr).any() else 1.0
    lim = lim if lim > 0 else 1.0
    im = ax.imshow(arr.T, origin="lower", extent=ext, cmap="RdBu_r", vmin=-lim, vmax=lim,
                   interpolation="nearest")
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03, ticks=[-lim, 0.0, lim],
                      format="%.2g")
    cb.ax.tick_params(labelsize=6)
    ax.set_title(title, fontsize=7)
    ax.set_xticks(ticks, [f"{t:g}" for t in ticks] if first[1] else [], fontsize=6)
    ax.set_yticks(ticks, [f"{t:g}" for t in ticks] if first[0] else [], fontsize=6)


BASELINES = ("direct3d", "davis_tusting")


def _boxes(ax: Any, errors: Mapping[str, Mapping[float, F64]], methods: Sequence[str],
           labels: Mapping[str, str]) -> None:
    """One box per method and distance (boxes 25–75 %, whiskers 2.5–97.5 %)."""
    dists = sorted({d for m in methods for d in errors[m]})
    width = 0.8 / max(len(dists), 1)
    cmap = plt.get_cmap("viridis")
    for k, d in enumerate(dists):
        colour = cmap(k / max(len(dists) - 1, 1))
        keep = [i for i, m in enumerate(methods) if len(errors[m].get(d, ()))]
        pos = np.arange(len(methods)) + (k - (len(dists) - 1) / 2) * width
        if keep:
            bp = ax.boxplot([errors[methods[i]][d] for i in keep], positions=pos[keep],
                            widths=width * 0.9, showfliers=False, patch_artist=True,
                            whis=(2.5, 97.5))
            for patch in bp["boxes"]:
                patch.set_facecolor(colour)
                patch.set_alpha(0.6)
        ax.plot([], [], "s", color=colour, label=f"{d:g} m")
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xticks(range(len(methods)), [labels[m] for m in methods], fontsize=7, rotation=15)
    ax.grid(alpha=0.3)


def error_boxes_png(errors: Mapping[str, Mapping[str, Mapping[float, F64]]],
                    labels: Mapping[str, str], title: str) -> bytes:
    """Rows = areas; per method one box per distance (error in % of the scale); the baselines
    (Direct 3D, Davis & Tusting) on their own axis, their errors are 10–100× larger."""
    panels = list(errors)
    fig = plt.figure(figsize=(10, 3.0 * len(panels) + 0.4))
    grid = fig.add_gridspec(len(panels), 2, width_ratios=[4, 1.3])
    for row, panel in enumerate(panels):
        ours = [m for m in labels if m in errors[panel] and m not in BASELINES]
        base = [m for m in labels if m in errors[panel] and m in BASELINES]
        for col, methods in enumerate((ours, base)):
            if not methods:
                continue
            ax = fig.add_subplot(grid[row, col])
            _boxes(ax, errors[panel], methods, labels)
            if col == 0:
                ax.set_ylabel("error (%)", fontsize=8)
                ax.set_title(f"{title} — {panel} (boxes 25–75 %, whiskers 2.5–97.5 %)",
                             fontsize=9)
                ax.legend(fontsize=7)
            else:
                ax.set_title("baselines", fontsize=9)
    fig.tight_layout()
    return _png(fig)


def depth_scatter_png(series: Mapping[str, tuple[F64, F64]], title: str) -> bytes:
    """Error (%) against |depth difference| of the two hits along the beams (m)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for (label, (depth, err)), mk in zip(series.items(), ("o", "x", "+", "s"), strict=False):
        ax.plot(depth, err, mk, ms=2.5, alpha=0.4, label=f"{label} (n {len(err)})")
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xlabel("|depth difference of the two hits along the beams| (m)")
    ax.set_ylabel("scale error (%)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, markerscale=3)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _png(fig)


def calibration_png(z: Mapping[str, F64], labels: Mapping[str, str], title: str) -> bytes:
    """Histograms of z = (estimate − truth) / reported σ with the N(0, 1) density."""
    methods = [m for m in labels if m in z and len(z[m])]
    fig, axes = plt.subplots(1, max(len(methods), 1), squeeze=False,
                             figsize=(2.8 * max(len(methods), 1) + 0.5, 2.9))
    x = np.linspace(-5, 5, 201)
    for ax, m in zip(axes[0], methods, strict=False):
        v = z[m][np.isfinite(z[m])]
        ax.hist(np.clip(v, -5, 5), bins=50, range=(-5, 5), density=True, alpha=0.6)
        ax.plot(x, np.exp(-x**2 / 2) / np.sqrt(2 * np.pi), "k", lw=1)
        cover = float(np.mean(np.abs(v) <= 1.959964))
        ax.set_title(f"{labels[m]}\nRMS z {np.sqrt(np.mean(v**2)):.2f}, |z|≤1.96: {cover:.3f}",
                     fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_xlabel("z", fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return _png(fig)


# --------------------------------------------------------------------------- from a result

HEATMAP_METHODS = ("fcm_fused", "fcm", "pcm", "pcm_joint_view", "direct3d",
                   "davis_tusting")
BOX_METHODS = ("fcm", "fcm_fused", "pcm", "pcm_joint", "pcm_joint_view", "direct3d",
               "davis_tusting")
Z_METHODS = ("fcm", "fcm_fused", "pcm", "pcm_joint")


def _labels(methods: Sequence[str], group_size: int) -> dict[str, str]:
    return {m: method_label(m, group_size) for m in methods}


def _rows(result: SimulationResult, a: dict[str, NDArray[Any]], method: str, **match: Any
          ) -> NDArray[np.bool_]:
    """Rows of one method whose setting key matches every given field."""
    t = result.collected.table
    kids = [i for i, k in enumerate(t.keys) if all(getattr(k, f) == v for f, v in match.items())]
    return np.asarray(method_rows(t, a, method) & np.isin(a["key"], kids))


def _error_figures(result: SimulationResult, a: dict[str, NDArray[Any]]) -> dict[str, bytes]:
    t, opts = result.collected.table, result.options
    labels = _labels(BOX_METHODS, opts.group_size)
    out = {}
    for config in sorted({k.config for k in t.keys}):
        errors: dict[str, dict[str, dict[float, F64]]] = {}
        for area in sorted({k.area for k in t.keys}):
            per = {m: {d: 100 * (a["value"][rows] / opts.true_scale - 1)
                       for d in opts.distances_m
                       if (rows := _rows(result, a, m, config=config, area=area,
                                         distance_m=d)).any()}
                   for m in BOX_METHODS}
            errors[area] = {m: v for m, v in per.items() if v}
        out[f"errors_{config}.png"] = error_boxes_png(errors, labels, f"configuration {config}")
    return out


def _scatter_figures(result: SimulationResult, a: dict[str, NDArray[Any]]) -> dict[str, bytes]:
    """PCM and PCM-joint error against the depth difference; with antithetic draws, the
    means of the twins (the systematic error of each view, noise cancelled to first order)."""
    opts = result.options
    what = "antithetic pair means" if opts.antithetic else "single draws"
    out = {}
    for config in sorted({k.config for k in result.collected.table.keys}):
        series = {}
        for m, label in (("pcm", "PCM (midpoint)"),
                         ("pcm_joint_view", f"PCM-joint direction ({opts.group_size} views)")):
            rows = _rows(result, a, m, config=config) & np.isfinite(a["depth"])
            if opts.antithetic:
                p, q = antithetic_pairs(a, rows)
                value, depth = 0.5 * (a["value"][p] + a["value"][q]), a["depth"][p]
            else:
                value, depth = a["value"][rows], a["depth"][rows]
            if len(value):
                series[label] = (depth, 100 * (value / opts.true_scale - 1))
        if series:
            out[f"pcm_depth_{config}.png"] = depth_scatter_png(
                series, f"configuration {config}: PCM error against the hits' depth difference "
                        f"({what})")
    return out


def _heatmap_figures(result: SimulationResult) -> dict[str, bytes]:
    opts = result.options
    labels = _labels(HEATMAP_METHODS, opts.group_size)
    return {f"heatmap_{c}_{d:g}m.png": heatmaps_png(maps, grid_angles(opts), labels,
                                                    f"configuration {c}, {d:g} m")
            for (c, d), maps in grid_maps(result.collected, opts).items()}


def simulation_figures(result: SimulationResult) -> dict[str, bytes]:
    """File name -> PNG of every figure of a simulation."""
    t, opts = result.collected.table, result.options
    if len(t) == 0:
        return {}
    a = t.arrays()
    out = _heatmap_figures(result) if opts.mode == "grid" else {}
    out.update(_error_figures(result, a))
    if opts.mode != "noise-table":
        out.update(_scatter_figures(result, a))
    z = {}
    for m in Z_METHODS:
        rows = _rows(result, a, m) & (a["sigma"] > 0)
        z[m] = (a["value"][rows] - opts.true_scale) / a["sigma"][rows]
    out["calibration.png"] = calibration_png(z, _labels(Z_METHODS, opts.group_size),
                                             f"normalised errors, {opts.mode} (all settings)")
    return out
