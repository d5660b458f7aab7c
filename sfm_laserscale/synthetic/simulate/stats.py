"""Error statistics of the estimates against the truth: per setting and method (and laser or
pair), pooled per configuration, antithetic pair biases, the grid heatmaps' mean errors."""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.synthetic.simulate.configs import SimulationOptions
from sfm_laserscale.synthetic.simulate.samples import Collected, SampleTable, SettingKey
from sfm_laserscale.synthetic.simulate.views import grid_angles

F64 = NDArray[np.float64]


#: Methods in the order of tables and figures.
METHOD_ORDER = ("fcm", "fcm_unchecked", "fcm_fused", "fcm_fused_unchecked", "fcm_fused_gls",
                "pcm", "pcm_unchecked", "pcm_fused", "pcm_fused_gls", "pcm_group", "pcm_joint",
                "pcm_joint_view", "direct3d", "direct3d_fused", "direct3d_fused_gls",
                "davis_tusting")

UNCHECKED = "_unchecked"


def method_rows(t: SampleTable, a: dict[str, NDArray[Any]], method: str) -> NDArray[np.bool_]:
    """Rows of a reported method; ``<m>_unchecked`` is ``<m>`` with the depth-edge spots."""
    unchecked = method.endswith(UNCHECKED)
    base = method[: -len(UNCHECKED)] if unchecked else method
    if base not in t.vocab:
        return np.zeros(len(a["value"]), dtype=bool)
    edge_ok = a["edge"] >= 0 if unchecked else a["edge"] <= 0
    return np.asarray((a["method"] == t.code(base)) & edge_ok)


#: Methods with a laser or pair name per row (also reported per laser / pair).
PER_SUB = ("fcm", "pcm", "direct3d", "pcm_joint_view")


def method_stats(value: F64, sigma: F64, lo: F64, hi: F64, truth: float) -> dict[str, float]:
    """Error statistics of n estimates of ``truth``: bias, std, RMSE, mean σ (all in % of the
    truth), std / mean σ, mean and RMS of the normalised error z = (s − truth) / σ, and the
    fraction of 95 % intervals holding the truth. NaN where undefined."""
    e = value / truth - 1.0
    n = len(e)
    nan = float("nan")
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(sigma > 0, (value - truth) / sigma, np.nan)
    has_sigma = np.isfinite(z)
    has_ci = np.isfinite(lo) & np.isfinite(hi)
    std = float(np.std(e, ddof=1)) * 100 if n > 1 else nan
    pred = float(np.mean(sigma[has_sigma] / truth)) * 100 if has_sigma.any() else nan
    return {
        "n": n,
        "bias": float(np.mean(e)) * 100 if n else nan,
        "std": std,
        "rmse": float(np.sqrt(np.mean(e**2))) * 100 if n else nan,
        "predicted_sigma": pred,
        "ratio": std / pred if pred > 0 else nan,
        "z_mean": float(np.mean(z[has_sigma])) if has_sigma.any() else nan,
        "z_rms": float(np.sqrt(np.mean(z[has_sigma] ** 2))) if has_sigma.any() else nan,
        "coverage95": float(np.mean((lo[has_ci] <= truth) & (truth <= hi[has_ci])))
        if has_ci.any() else nan,
    }


def antithetic_pairs(a: dict[str, NDArray[Any]], rows: NDArray[np.bool_]
                     ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Row indices (plus, minus) of the antithetic twins among ``rows`` (same key, view, draw,
    laser or pair; both present)."""
    plus: dict[tuple[int, int, int, int], int] = {}
    minus: dict[tuple[int, int, int, int], int] = {}
    for i in np.flatnonzero(rows):
        k = (int(a["key"][i]), int(a["view"][i]), int(a["round"][i]), int(a["sub"][i]))
        (plus if a["sign"][i] > 0 else minus)[k] = int(i)
    both = [k for k in plus if k in minus]
    return (np.array([plus[k] for k in both], dtype=np.int64),
            np.array([minus[k] for k in both], dtype=np.int64))


def pair_bias(a: dict[str, NDArray[Any]], rows: NDArray[np.bool_], truth: float
              ) -> tuple[float, float, int]:
    """Antithetic pairs: max and mean of |pair-mean error| / σ, and the number of pairs."""
    p, m = antithetic_pairs(a, rows & np.isfinite(a["sigma"]))
    if len(p) == 0:
        return float("nan"), float("nan"), 0
    b = np.abs(0.5 * (a["value"][p] + a["value"][m]) - truth) / (
        0.5 * (a["sigma"][p] + a["sigma"][m]))
    return float(np.max(b)), float(np.mean(b)), len(b)


def _stats_for(a: dict[str, NDArray[Any]], rows: NDArray[np.bool_], options: SimulationOptions
               ) -> dict[str, float]:
    k = options.true_scale
    out = method_stats(a["value"][rows], a["sigma"][rows], a["lo"][rows], a["hi"][rows], k)
    if options.antithetic:
        mx, mean, n = pair_bias(a, rows, k)
        out.update(pair_bias_max_sigma=mx, pair_bias_mean_sigma=mean, n_pairs=n)
    return out


def _counts(col: Collected, key: SettingKey, prefix: str) -> dict[str, int]:
    """Per laser, how often a counter starting with ``prefix`` fired for this setting."""
    return {name[len(prefix):]: n for (k, name), n in col.rejected.items()
            if k == key and name.startswith(prefix)}


def summarize(col: Collected, options: SimulationOptions) -> list[dict[str, Any]]:
    """results.json ``settings``: per setting key, statistics per method (and laser / pair)."""
    t = col.table
    a = t.arrays()
    out = []
    for kid, key in enumerate(t.keys):
        in_key = a["key"] == kid
        methods: dict[str, Any] = {}
        for m in METHOD_ORDER:
            rows = in_key & method_rows(t, a, m)
            if rows.any():
                methods[m] = {**_stats_for(a, rows, options), "n_rejected": col.rejected[(key, m)]}
            subs = sorted({t.vocab[c] for c in a["sub"][rows]}) if m in PER_SUB else []
            for sub in subs if len(subs) > 1 else []:
                sub_rows = rows & (a["sub"] == t.code(sub))
                methods[f"{m}:{sub}"] = _stats_for(a, sub_rows, options)
        out.append({"setting": key._asdict(), "methods": methods,
                    "registration_failures": col.rejected[(key, "registration")],
                    "spots_not_visible": _counts(col, key, "spot:"),
                    "edge_spots": _counts(col, key, "edge:")})
    return out


def overall(col: Collected, options: SimulationOptions) -> dict[str, dict[str, Any]]:
    """Per configuration and method, pooled over every setting: n, mean and RMS of z, coverage."""
    t = col.table
    a = t.arrays()
    out: dict[str, dict[str, Any]] = {}
    for config in sorted({key.config for key in t.keys}):
        in_config = np.isin(a["key"], [i for i, key in enumerate(t.keys) if key.config == config])
        per: dict[str, Any] = {}
        for m in METHOD_ORDER:
            rows = in_config & method_rows(t, a, m)
            if rows.any():
                s = _stats_for(a, rows, options)
                per[m] = {k: s[k] for k in ("n", "z_mean", "z_rms", "coverage95",
                                            "pair_bias_max_sigma") if k in s}
        out[config] = per
    return out


#: Methods drawn in the grid heatmaps.
MAP_METHODS = ("fcm_fused", "fcm", "pcm", "pcm_joint_view", "direct3d", "davis_tusting")


def grid_maps(col: Collected, options: SimulationOptions
              ) -> dict[tuple[str, float], dict[str, dict[str, F64]]]:
    """(config, distance) -> area -> method -> (n, n) mean error % over [pitch, roll] (grid)."""
    t = col.table
    a = t.arrays()
    angles = grid_angles(options)
    n = len(angles)
    out: dict[tuple[str, float], dict[str, dict[str, F64]]] = defaultdict(dict)
    for kid, key in enumerate(t.keys):
        maps: dict[str, F64] = {}
        for m in MAP_METHODS:
            rows = (a["key"] == kid) & method_rows(t, a, m)
            if not rows.any():
                continue
            ip = np.clip(np.round((a["pitch"][rows] - angles[0]) / options.angle_step_deg), 0,
                         n - 1).astype(int)
            ir = np.clip(np.round((a["roll"][rows] - angles[0]) / options.angle_step_deg), 0,
                         n - 1).astype(int)
            total, count = np.zeros((n, n)), np.zeros((n, n))
            np.add.at(total, (ip, ir), 100 * (a["value"][rows] / options.true_scale - 1))
            np.add.at(count, (ip, ir), 1)
            with np.errstate(invalid="ignore"):
                maps[m] = total / count
        out[(key.config, key.distance_m)].setdefault(key.area, {}).update(maps)
    return dict(out)
