"""report.json's blocks about the reconstruction's own error (docs/OUTPUTS.md): each fused
scale's error budget, ``model_error`` (the model intrinsics' σ, the mesh check at every spot) and
``model_checks`` (methods against each other, lasers, distance, the focal fit, drift), and the
per-segment rows of estimates.csv when the scale drifts."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sfm_laserscale.focal_fit import FocalEstimate
from sfm_laserscale.fusion import FusedScale
from sfm_laserscale.mesh_error import shared_offset
from sfm_laserscale.model_checks import Comparison, LaserCheck, ModelChecks, Segment, Trend
from sfm_laserscale.registration.covariance import IntrinsicsField
from sfm_laserscale.rig import Rig
from sfm_laserscale.rig_checks import check_pairs, pair_warnings
from sfm_laserscale.run_types import ImageRun

#: estimates.csv ``method`` of the per-segment rows (the headline method follows a colon).
SEGMENT_METHOD = "segment"


def _num(x: Any) -> float | None:
    if x is None:
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def budget_dict(f: FusedScale) -> dict[str, Any]:
    """Keys added to a scale block: ``budget`` (variance per term, (m per unit)²),
    ``budget_shares`` (each term's share of std²) and ``budget_sigma_pct`` (√variance, % of
    the value)."""
    shares = f.budget_shares()
    value = f.value if math.isfinite(f.value) and f.value != 0 else float("nan")
    return {
        "budget": {k: _num(v) for k, v in f.budget.items()},
        "budget_shares": {k: _num(v) for k, v in shares.items()},
        "budget_sigma_pct": {k: _num(100 * math.sqrt(max(v, 0.0)) / value)
                             for k, v in f.budget.items()},
    }


def _comparison(c: Comparison) -> dict[str, Any]:
    return {"a": c.a, "b": c.b, "difference_pct": _num(c.difference_pct),
            "sigma_pct": _num(c.sigma_pct), "z": _num(c.z), "ok": bool(c.ok)}


def _laser(c: LaserCheck) -> dict[str, Any]:
    return {"laser": c.laser, "n_images": c.n_images, "value": _num(c.value),
            "sigma": _num(c.sigma), "vs_others_pct": _num(c.vs_others_pct),
            "sigma_pct": _num(c.sigma_pct), "z": _num(c.z), "ok": bool(c.ok)}


def _trend(t: Trend | None) -> dict[str, Any] | None:
    if t is None:
        return None
    return {"variable": t.variable, "slope_pct_per_m": _num(t.slope_pct),
            "sigma_pct_per_m": _num(t.sigma_pct), "change_pct": _num(t.change_pct),
            "p": _num(t.p), "significant": bool(t.significant), "n_images": t.n,
            "points": [{"image": im, "x": _num(x), "deviation_pct": _num(y),
                        "sigma_pct": _num(s), "used": bool(u)}
                       for im, x, y, s, u in zip(t.images, t.x, t.y_pct, t.sigma_y_pct, t.used,
                                                 strict=True)]}


def _segment(s: Segment) -> dict[str, Any]:
    f = s.fused
    return {"index": s.index, "position_m": [_num(s.position_m[0]), _num(s.position_m[1])],
            "images": list(s.images), "value": _num(f.value), "std": _num(f.std),
            "ci95": [_num(f.ci95[0]), _num(f.ci95[1])], "n_images_used": len(f.images_used),
            "reason": f.reason}


def _focal(f: FocalEstimate, checks: ModelChecks, model_sigma: float) -> dict[str, Any]:
    return {"focal_error_pct": _num(100 * f.focal_error), "sigma_pct": _num(100 * f.sigma),
            "z": _num(f.z), "significant": bool(f.significant), "n_estimates": f.n_estimates,
            "sources": list(f.sources), "gamma_range": [_num(f.gamma_range[0]),
                                                        _num(f.gamma_range[1])],
            "chi2": _num(f.chi2), "dof": f.dof, "reason": f.reason,
            "corrected_method": None if f.corrected is None else f.corrected.method,
            "model_sigma_pct": _num(100 * model_sigma),
            "headline_gamma": _num(checks.headline_gamma),
            "headline_widened": bool(any(n.startswith("sigma widened by the model's focal")
                                         for n in checks.headline.notes))}


def model_checks_dict(checks: ModelChecks | None, model_sigma: float) -> dict[str, Any] | None:
    """report.json ``model_checks`` (None when the checks did not run)."""
    if checks is None:
        return None
    drift = _trend(checks.drift)
    if drift is not None:
        drift["segments"] = [_segment(s) for s in checks.segments]
        drift["outliers_in_range"] = list(checks.drift_outliers)
    sc = checks.scatter
    return {"method": checks.method,
            "scatter": None if sc is None else {"chi2": _num(sc.chi2), "dof": sc.dof,
                                                "ratio": _num(sc.ratio), "p": _num(sc.p),
                                                "ok": bool(sc.ok), "gross": list(sc.gross)},
            "comparisons": [_comparison(c) for c in checks.comparisons],
            "lasers": [_laser(c) for c in checks.lasers],
            "distance": _trend(checks.distance),
            "focal": _focal(checks.focal, checks, model_sigma),
            "drift": drift}


def model_error_dict(field: IntrinsicsField | None, runs: Sequence[ImageRun], scale: float
                     ) -> dict[str, Any]:
    """report.json ``model_error``: the intrinsics' σ and the mesh check at every spot (lengths
    in metres at the headline scale; null without it)."""
    k = scale if math.isfinite(scale) else float("nan")
    intr: dict[str, Any] | None = None
    if field is not None:
        intr = {"n_images": field.n_images, "sigma_px": _num(field.sigma_px),
                "notes": list(field.notes),
                "cameras": [{"camera_id": c.camera_id, "parameters": list(c.names),
                             "sigma": [_num(c.sigma(i)) for i in range(len(c.names))],
                             "focal_sigma_pct": _num(100 * c.focal_sigma),
                             "from_covariance": bool(c.from_covariance)}
                            for c in field.cameras.values()]}
    spots = [{"image": r.name, "laser": m.laser, "sigma_m": _num(m.sigma * k),
              "offset_m": _num(m.offset * k), "spread_m": _num(m.spread * k),
              "point_sigma_m": _num(m.point_sigma * k), "n_points": m.n_points}
             for r in runs for m in r.mesh_errors]
    sig = [float(m.sigma * k) for r in runs for m in r.mesh_errors if math.isfinite(m.sigma * k)]
    shared = shared_offset([m for r in runs for m in r.mesh_errors])
    return {"intrinsics": intr,
            "mesh": {"spots": spots, "median_sigma_m": _num(np.median(sig)) if sig else None,
                     "shared_offset_m": _num(shared.offset * k) if shared.n_spots else None,
                     "shared_sigma_m": _num(shared.sigma * k) if shared.n_spots else None}}


def pair_checks_dict(rig: Rig) -> list[dict[str, Any]]:
    """report.json ``rig.pair_checks``: each declared pair's geometry against PCM's assumptions
    (rig_checks.py) and its problems in plain words."""
    return [{"pair": g.pair, "calibrated": g.calibrated, "angle_deg": _num(g.angle_deg),
             "angle_sigma_deg": _num(g.angle_sigma_deg),
             "separation_change_pct_per_m": _num(g.separation_change_pct_per_m),
             "distance_difference_m": _num(g.distance_difference_m),
             "separation_m": _num(g.separation_m),
             "calibrated_separation_m": _num(g.calibrated_separation_m),
             "parallel": g.parallel, "equidistant": g.equidistant, "refused": g.refused,
             "reason": g.reason, "problems": pair_warnings(g)}
            for g in check_pairs(rig)]


def append_segment_rows(path: Path, report: dict[str, Any]) -> None:
    """estimates.csv: one row per drift segment (``image`` the segment's label, ``method``
    ``segment:<method>``, ``laser`` its images), only when the scale drifts significantly."""
    checks = report.get("model_checks") or {}
    drift = checks.get("drift")
    if not drift or not drift.get("significant") or not drift.get("segments"):
        return
    method = f"{SEGMENT_METHOD}:{report['scale']['method']}"
    with path.open("a", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        for s in drift["segments"]:
            lo, hi = s["position_m"]
            w.writerow([f"segment {s['index']} ({lo:+.2f} to {hi:+.2f} m along the survey)",
                        method, " ".join(s["images"]), "" if s["value"] is None else s["value"],
                        "" if s["std"] is None else s["std"], "", "", s["value"] is None,
                        s["reason"] or ""])
