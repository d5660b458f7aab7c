"""Plain-word warnings and notes from report.json's ``model_checks`` and error budget: methods that
disagree, lasers that disagree, scale against distance, the model's focal error, scale drift,
and what dominates the uncertainty. A pure function of the report dict (JSON types only)."""

from __future__ import annotations

import math
from typing import Any

LABELS = {"fcm": "FCM", "pcm": "PCM", "pcm_joint": "PCM-joint", "direct3d": "Direct 3D",
          "focal_corrected": "focal-corrected"}
#: |z| of the focal fit above this (and up to the checks' limit): a note, not yet a warning.
FOCAL_NOTE_Z = 2.0
#: A shared term above this share of the headline's variance: a note saying so.
DOMINANT_SHARE = 0.5


def _w(level: str, code: str, message: str) -> dict[str, str]:
    return {"level": level, "code": code, "message": message}


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _label(m: str) -> str:
    return LABELS.get(m, m.upper())


def _focal_hint(checks: dict[str, Any]) -> str:
    f = checks.get("focal") or {}
    if f.get("significant") and _finite(f.get("focal_error_pct")):
        return (f" A focal-length error of the model of {f['focal_error_pct']:+.2f} % would "
                "explain it (see the focal check).")
    return ""


def _comparison_warnings(checks: dict[str, Any]) -> list[dict[str, str]]:
    out = []
    for c in checks.get("comparisons", []):
        if c["ok"] or not _finite(c["z"]):
            continue
        out.append(_w("warning", "methods_disagree",
                      f"{_label(c['a'])} and {_label(c['b'])} disagree: they differ by "
                      f"{c['difference_pct']:+.3f} %, {abs(c['z']):.1f} times their combined "
                      f"sigma ({c['sigma_pct']:.3f} %). They respond differently to the model's "
                      "own errors (focal length, distortion, a rig calibrated in air), so the "
                      f"model or the rig is off by more than the sigma says.{_focal_hint(checks)}"))
    return out


def _scatter_warnings(checks: dict[str, Any]) -> list[dict[str, str]]:
    sc = checks.get("scatter")
    if not sc or sc["ok"]:
        return []
    return [_w("warning", "scatter_test",
               f"The {_label(checks['method'])} estimates scatter {sc['ratio']:.1f} times more "
               f"than their stated sigma (chi2 {sc['chi2']:.0f} for {sc['dof']} degrees of "
               f"freedom, p = {sc['p']:.2g}): the sigma of the spots, the registration or the "
               "mesh is understated (blurred, elongated or speckled spots; a mesh off the "
               "model), or an estimate is wrong.")]


def _laser_warnings(checks: dict[str, Any]) -> list[dict[str, str]]:
    bad = [c for c in checks.get("lasers", []) if not c["ok"] and _finite(c["z"])]
    if not bad:
        return []
    items = "; ".join(f"{c['laser']} {c['vs_others_pct']:+.3f} % ({abs(c['z']):.1f} sigma, "
                      f"{c['n_images']} images)" for c in bad)
    return [_w("warning", "lasers_inconsistent",
               f"The lasers' FCM scales disagree beyond their sigma: {items} against the other "
               "lasers. Check each laser's calibration (origin, direction) and its spots; beams "
               "of different tilts also respond differently to a focal-length error of the "
               f"model.{_focal_hint(checks)}")]


def _distance_warnings(checks: dict[str, Any]) -> list[dict[str, str]]:
    t = checks.get("distance")
    if not t or not t["significant"]:
        return []
    return [_w("warning", "scale_vs_distance",
               f"The {_label(checks['method'])} scale changes with the camera–scene distance: "
               f"{t['slope_pct_per_m']:+.3f} % per metre ± {t['sigma_pct_per_m']:.3f} "
               f"({t['change_pct']:+.3f} % over the distances seen, p = {t['p']:.2g}, "
               f"{t['n_images']} images). This points to a focal-length error of the model, a "
               "refraction error (camera or rig calibrated in air; a flat port changes both) "
               f"or a rig calibration error.{_focal_hint(checks)}")]


def _focal_warnings(checks: dict[str, Any], report: dict[str, Any]) -> list[dict[str, str]]:
    f = checks.get("focal") or {}
    if not _finite(f.get("z")):
        return []
    z = abs(f["z"])
    fc = report["methods"].get(f.get("corrected_method") or "")
    corr = ""
    if fc and _finite(fc.get("value")):
        corr = (f" The scale corrected for it is given as the method 'focal_corrected': "
                f"{fc['value']:.6g} ± {fc['std']:.2g}; the headline is not replaced.")
    gamma = f.get("headline_gamma")
    effect = (f" It moves the headline by about {gamma * f['focal_error_pct']:+.3f} %."
              if _finite(gamma) else "")
    widened = (" The headline's sigma includes it." if f.get("headline_widened") else "")
    sources = ", ".join(_label(s) for s in f["sources"])
    text = (f"the model's focal length appears off by {f['focal_error_pct']:+.3f} % ± "
            f"{f['sigma_pct']:.3f} % ({z:.1f} sigma; from {sources} estimates whose sensitivity "
            f"to it differs).{effect}{widened}{corr}")
    if f.get("significant"):
        return [_w("warning", "focal_error", "Focal-length error: " + text)]
    if z > FOCAL_NOTE_Z:
        return [_w("note", "focal_error", "Possibly a focal-length error: " + text)]
    if f.get("headline_widened"):
        return [_w("note", "focal_sigma_widened",
                   "The headline's sigma was widened by the model's focal error as the laser "
                   f"data measure it ({f['focal_error_pct']:+.3f} % ± {f['sigma_pct']:.3f} %).")]
    return []


def _drift_warnings(checks: dict[str, Any]) -> list[dict[str, str]]:
    t = checks.get("drift")
    if not t or not t["significant"]:
        return []
    segs = "; ".join(
        f"segment {s['index']} ({s['position_m'][0]:+.1f} to {s['position_m'][1]:+.1f} m): "
        + (f"{s['value']:.6g} ± {s['std']:.2g}" if _finite(s["value"]) else "no value")
        for s in t.get("segments", []))
    out_ = t.get("outliers_in_range") or []
    outl = (" Images the fusion left out as outliers lie along the same survey "
            f"({', '.join(out_)}): they may be the drift, not outliers." if out_ else "")
    return [_w("warning", "scale_drift",
               f"The scale drifts along the survey: {t['slope_pct_per_m']:+.3f} % per metre "
               f"({t['change_pct']:+.3f} % over {t['n_images']} images along the model, p = "
               f"{t['p']:.2g}). The model's scale is not uniform; one scale does not fit all of "
               f"it. Per-segment scales (report and estimates.csv): {segs}.{outl}")]


def _budget_notes(report: dict[str, Any]) -> list[dict[str, str]]:
    shares = report["scale"].get("budget_shares") or {}
    out = []
    for term, what in (("intrinsics", "the model's own intrinsics (focal length, distortion)"),
                       ("rig", "the rig calibration"), ("mesh", "the mesh's depth error")):
        share = shares.get(term)
        if isinstance(share, (int, float)) and _finite(share) and share > DOMINANT_SHARE:
            more = (" More laser images will not reduce it." if term != "mesh" else "")
            out.append(_w("note", f"budget_{term}",
                          f"{100 * share:.0f} % of the headline's variance comes from {what}."
                          f"{more}"))
    intr = (report.get("model_error") or {}).get("intrinsics") or {}
    out += [_w("note", "intrinsics_prior", n) for n in intr.get("notes", [])]
    return out


def rig_pair_warnings(report: dict[str, Any]) -> list[dict[str, str]]:
    """A warning per problem of a declared pair (not parallel, camera not equidistant)."""
    return [_w("warning", "rig_pair", text)
            for g in (report.get("rig") or {}).get("pair_checks", []) for text in g["problems"]]


def model_warnings(report: dict[str, Any]) -> list[dict[str, str]]:
    """Warnings and notes of the rig's pairs and of the model checks (the latter only when
    report.json has ``model_checks`` and a scale)."""
    checks = report.get("model_checks")
    if not checks or not _finite(report["scale"].get("value")):
        return rig_pair_warnings(report)
    return (rig_pair_warnings(report) + _comparison_warnings(checks) + _laser_warnings(checks)
            + _scatter_warnings(checks) + _distance_warnings(checks)
            + _focal_warnings(checks, report) + _drift_warnings(checks) + _budget_notes(report))
