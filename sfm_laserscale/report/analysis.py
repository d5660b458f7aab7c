"""What the report derives from report.json for people: per-image fused values, per-laser
deviations, consistency numbers and warnings in plain words.

Everything here is a pure function of the report dict (JSON types only), so every number the
HTML shows is stored in report.json first (keys ``images[i].fused``, ``images[i].deviation_pct``,
``images[i].distance_m``, ``diagnostics`` and ``warnings``) and the page is rendered from it.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import asdict, dataclass
from typing import Any

from sfm_laserscale.report.model_warnings import model_warnings

#: Methods in the order the report shows them (the headline candidates first, baselines last).
METHOD_ORDER = ("fcm", "pcm", "pcm_joint", "direct3d")
METHOD_LABELS = {"fcm": "FCM", "pcm": "PCM", "pcm_joint": "PCM-joint", "direct3d": "Direct 3D",
                 "focal_corrected": "Focal-corrected"}


@dataclass(frozen=True)
class ReportChecksOptions:
    """Thresholds of the report's checks and warnings."""

    laser_deviation_min_pct: float = 1.0  # a laser deviation below this is never flagged
    laser_deviation_nsigma: float = 3.0  # ... nor one below this many of its own σ
    direction_residual_deg: float = 3.0  # FCM direction residual above this: spot off its beam
    mesh_agreement_max: float = 0.005  # median point–mesh distance / model extent
    few_images: int = 2  # this many used images or fewer: "the interval is wide"
    max_reproj_error_px: float = 2.0  # registered image with a larger mean error: warned
    birge_note: float = 2.0  # Birge ratio above this: "scatter larger than the σ says"


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _label(method: str) -> str:
    return METHOD_LABELS.get(method, method.upper())


def image_fused(report: dict[str, Any], name: str) -> dict[str, dict[str, Any]]:
    """Per method: this image's combined value, its σ, whether fusion kept it, what it rejected."""
    out: dict[str, dict[str, Any]] = {}
    for method, block in report["methods"].items():
        row = next((p for p in block.get("per_image", []) if p["image"] == name), None)
        rejected = [
            {"laser": r["laser"], "reason": r["reason"]}
            for r in block.get("rejected", [])
            if r["image"] == name
        ]
        if row is None and not rejected:
            continue
        out[method] = {
            "scale": None if row is None else row["scale"],
            "sigma": None if row is None else row["sigma"],
            "used": bool(row is not None and row["used"]),
            "rejected": rejected,
        }
    return out


def image_distance_m(image: dict[str, Any]) -> float | None:
    """Camera–scene distance (m): median camera–hit distance of the image's usable estimates."""
    ests = [e for e in image["estimates"] if not e["rejected"] and _finite(e["depth_m"])]
    fcm = [e["depth_m"] for e in ests if e["method"] == "fcm"]
    depths = fcm or [e["depth_m"] for e in ests]
    return float(statistics.median(depths)) if depths else None


def laser_deviations_pct(image: dict[str, Any], method: str = "fcm") -> dict[str, float]:
    """Each laser's deviation (%) from its image's combined estimate (the paper's 2nd panel)."""
    ref = image.get("fused", {}).get(method, {}).get("scale")
    if not _finite(ref) or ref == 0:
        return {}
    return {
        e["laser"]: 100.0 * (e["scale"] / ref - 1.0)
        for e in image["estimates"]
        if e["method"] == method and not e["rejected"] and _finite(e["scale"])
    }


def _flagged(image: dict[str, Any], laser: str, dev: float, opt: ReportChecksOptions) -> bool:
    ref = image["fused"]["fcm"]["scale"]
    sig = next(
        (e["sigma"] for e in image["estimates"] if e["method"] == "fcm" and e["laser"] == laser),
        None,
    )
    rel_sigma = 100.0 * float(sig) / ref if sig is not None and _finite(sig) else 0.0
    return abs(dev) > max(opt.laser_deviation_min_pct, opt.laser_deviation_nsigma * rel_sigma)


def per_laser_summary(
    report: dict[str, Any], opt: ReportChecksOptions
) -> dict[str, dict[str, Any]]:
    """Per laser: images with an FCM value, median and max |deviation| (%), images flagged."""
    out: dict[str, dict[str, Any]] = {}
    for laser in report["rig"]["lasers"]:
        devs = [
            (im, im["deviation_pct"][laser])
            for im in report["images"]
            if laser in im.get("deviation_pct", {})
        ]
        if not devs:
            continue
        values = [d for _, d in devs]
        others = [v for v in (_vs_others_pct(im, laser) for im, _ in devs) if v is not None]
        out[laser] = {
            "n_images": len(devs),
            "median_deviation_pct": float(statistics.median(values)),
            "max_abs_deviation_pct": float(max(abs(v) for v in values)),
            "median_vs_others_pct": float(statistics.median(others)) if others else None,
            "n_flagged": sum(_flagged(im, laser, d, opt) for im, d in devs),
        }
    return out


def _vs_others_pct(image: dict[str, Any], laser: str) -> float | None:
    """A laser's FCM estimate vs. the mean of the image's other usable FCM estimates (%)."""
    fcm = [
        e
        for e in image["estimates"]
        if e["method"] == "fcm" and not e["rejected"] and _finite(e["scale"])
    ]
    own = [e["scale"] for e in fcm if e["laser"] == laser]
    rest = [e["scale"] for e in fcm if e["laser"] != laser]
    if not own or not rest:
        return None
    return 100.0 * (own[0] / statistics.fmean(rest) - 1.0)


def image_spread_pct(block: dict[str, Any]) -> float | None:
    """Standard deviation (%) of the per-image values fusion kept, relative to their mean."""
    values = [p["scale"] for p in block.get("per_image", []) if p["used"] and _finite(p["scale"])]
    if len(values) < 2:
        return None
    return float(100.0 * statistics.stdev(values) / statistics.fmean(values))


def direction_residual_flags(
    report: dict[str, Any], opt: ReportChecksOptions
) -> list[dict[str, Any]]:
    """FCM spots whose back-projected origin points away from the laser's (beam geometry)."""
    return [
        {
            "image": im["name"],
            "laser": e["laser"],
            "residual_deg": e["direction_residual_deg"],
            "rejected": bool(e["rejected"]),
        }
        for im in report["images"]
        for e in im["estimates"]
        if e["method"] == "fcm"
        and _finite(e.get("direction_residual_deg"))
        and e["direction_residual_deg"] > opt.direction_residual_deg
    ]


def outlier_images(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Per method, the images whose combined estimate fusion left out (outliers), with the
    reason fusion gave; the headline method first."""
    head = report["scale"]["method"]
    order = sorted(
        report["methods"],
        key=lambda m: (m != head, METHOD_ORDER.index(m) if m in METHOD_ORDER else 99),
    )
    out = []
    for m in order:
        block = report["methods"][m]
        for row in block.get("per_image", []):
            if row["used"]:
                continue
            why = next(
                (r["reason"] for r in block.get("rejected", []) if r["image"] == row["image"]),
                "left out by fusion",
            )
            out.append(
                {
                    "method": m,
                    "image": row["image"],
                    "scale": row["scale"],
                    "reason": why,
                    "headline": m == head,
                }
            )
    return out


def diagnostics(report: dict[str, Any], opt: ReportChecksOptions) -> dict[str, Any]:
    """The ``diagnostics`` block: consistency numbers and the checks' verdicts."""
    per_laser = per_laser_summary(report, opt)
    all_dev = [d for im in report["images"] for d in im.get("deviation_pct", {}).values()]
    mma = report["checks"].get("mesh_model_agreement")
    used = [im["name"] for im in report["images"] if im["reason"] is None]
    return {
        "thresholds": asdict(opt),
        "images_total": len(report["images"]),
        "images_with_estimates": len(used),
        "per_laser": per_laser,
        "laser_deviation_rms_pct": (
            float(math.sqrt(statistics.fmean(d * d for d in all_dev))) if all_dev else None
        ),
        "laser_deviation_max_abs_pct": float(max(abs(d) for d in all_dev)) if all_dev else None,
        "image_spread_pct": {m: image_spread_pct(b) for m, b in report["methods"].items()},
        "direction_residuals": direction_residual_flags(report, opt),
        "outlier_images": outlier_images(report),
        "mesh_model_agreement_pct": _relative(mma, 1.0),
        "mesh_model_limit_pct": _relative(opt.mesh_agreement_max, 1.0),
        "mesh_model_agreement_ok": (
            None if not _finite(mma) else bool(mma <= opt.mesh_agreement_max)
        ),
    }


def _w(level: str, code: str, message: str) -> dict[str, str]:
    return {"level": level, "code": code, "message": message}


def _scale_warnings(report: dict[str, Any], opt: ReportChecksOptions) -> list[dict[str, str]]:
    s = report["scale"]
    label = _label(s["method"])
    if not _finite(s["value"]):
        why = s.get("reason") or "no usable estimate"
        return [
            _w(
                "warning",
                "no_scale",
                f"No scale could be estimated ({why}). Each image's reason is listed under Images.",
            )
        ]
    out = []
    n = len(s.get("images_used", []))
    if n <= opt.few_images:
        out.append(
            _w(
                "warning",
                "few_images",
                f"Only {n} image{'s' if n != 1 else ''} gave the {label} scale: the interval "
                "rests on few images and is wide; add laser images if you can.",
            )
        )
    birge = s.get("birge_ratio")
    if _finite(birge) and birge > opt.birge_note:
        out.append(
            _w(
                "note",
                "scatter",
                f"The {label} estimates scatter {birge:.1f} times more than their own "
                "uncertainties predict; the interval was widened accordingly.",
            )
        )
    return out


def _image_warnings(report: dict[str, Any], opt: ReportChecksOptions) -> list[dict[str, str]]:
    out = []
    failed = [im for im in report["images"] if im["reason"] is not None]
    if failed:
        names = ", ".join(f"{im['name']} ({im['reason']})" for im in failed[:6])
        more = f" and {len(failed) - 6} more" if len(failed) > 6 else ""
        out.append(
            _w(
                "warning",
                "images_failed",
                f"{len(failed)} of {len(report['images'])} laser images gave no estimate: "
                f"{names}{more}.",
            )
        )
    head = report["scale"]["method"]
    for im in report["images"]:
        f = im.get("fused", {}).get(head)
        if f is not None and f["scale"] is not None and not f["used"]:
            why = f["rejected"][0]["reason"] if f["rejected"] else "outlier"
            out.append(
                _w(
                    "warning",
                    "image_outlier",
                    f"Image {im['name']} was left out as an outlier: {why}.",
                )
            )
        err = im.get("reproj_error_px")
        if im["registered"] and _finite(err) and err > opt.max_reproj_error_px:
            out.append(
                _w(
                    "warning",
                    "reprojection",
                    f"Image {im['name']} registered with a mean reprojection error of "
                    f"{err:.2f} px (limit {opt.max_reproj_error_px:g} px): its pose is "
                    "doubtful.",
                )
            )
    return out


def _rejection_notes(report: dict[str, Any], diag: dict[str, Any]) -> list[dict[str, str]]:
    """Single estimates of the headline method left out (images left out are warned apart)."""
    head = report["scale"]["method"]
    flagged = {(r["image"], r["laser"]) for r in diag["direction_residuals"]}
    items = []
    for im in report["images"]:
        for e in im["estimates"]:
            if e["method"] == head and e["rejected"] and (im["name"], e["laser"]) not in flagged:
                items.append(f"{e['laser']} in {im['name']}: {e['reason'] or 'rejected'}")
        f = im.get("fused", {}).get(head)
        if f is not None and f["used"]:
            items += [
                f"{r['laser']} in {im['name']}: {r['reason']}"
                for r in f["rejected"]
                if not any(
                    e["method"] == head and e["laser"] == r["laser"] and e["rejected"]
                    for e in im["estimates"]
                )
            ]
    if not items:
        return []
    more = f" and {len(items) - 5} more" if len(items) > 5 else ""
    label = _label(head)
    return [
        _w(
            "note",
            "estimates_rejected",
            f"{len(items)} {label} estimate{'s' if len(items) > 1 else ''} left out: "
            f"{'; '.join(items[:5])}{more}.",
        )
    ]


def _laser_warnings(report: dict[str, Any], diag: dict[str, Any]) -> list[dict[str, str]]:
    out = []
    for laser, st in diag["per_laser"].items():
        k, n = st["n_flagged"], st["n_images"]
        if k >= 1 and 2 * k >= n:
            vs = st["median_vs_others_pct"]
            by = (
                f"the other lasers by {vs:+.1f} %"
                if vs is not None
                else f"its images' estimates by {st['median_deviation_pct']:+.1f} %"
            )
            out.append(
                _w(
                    "warning",
                    "laser_deviation",
                    f"Laser {laser} disagrees with {by} (median) and is off in {k} of "
                    f"{n} images: check its calibration and its spot detection.",
                )
            )
    for r in diag["direction_residuals"]:
        what = "rejected" if r["rejected"] else "kept"
        out.append(
            _w(
                "warning",
                "beam_geometry",
                f"In {r['image']}, the spot of {r['laser']} is {r['residual_deg']:.1f}° off "
                f"its beam's geometry ({what}): wrong spot, swapped lasers or calibration.",
            )
        )
    return out


def _check_warnings(report: dict[str, Any], opt: ReportChecksOptions) -> list[dict[str, str]]:
    out = []
    mma = report["checks"].get("mesh_model_agreement")
    if _finite(mma) and mma > opt.mesh_agreement_max:
        out.append(
            _w(
                "warning",
                "mesh_model",
                "Mesh–model agreement is poor: the model points matched in the laser images "
                f"near the spots lie a median {100 * mma:.2f} % of the model's extent from the "
                f"mesh (expected below {100 * opt.mesh_agreement_max:.1f} %). Is the mesh from "
                "this model, in the same frame?",
            )
        )
    pj = report["methods"].get("pcm_joint")
    if pj is not None and pcm_joint_fell_back(pj):
        level = "warning" if report["scale"]["method"] == "pcm_joint" else "note"
        out.append(
            _w(
                level,
                "pcm_joint_fallback",
                f"PCM-joint fell back to the midpoint approximation ({pcm_joint_why(pj)}); it "
                "can overestimate the separation by up to 1.5 % on rough terrain.",
            )
        )
    return out


def pcm_joint_fell_back(block: dict[str, Any]) -> bool:
    """Whether PCM-joint returned the midpoint approximation: the explicit ``joint`` field
    (``midpoint_fallback`` in a report.json without it)."""
    if "joint" in block:
        return not block["joint"]
    return bool(block.get("midpoint_fallback"))


def pcm_joint_why(block: dict[str, Any]) -> str:
    """Why no pair was fitted jointly, from the per-pair fits (each pair's reason)."""
    pairs = block.get("pairs")
    if pairs is None:  # a report.json without per-pair fits: the fallback's first note
        return (block.get("notes") or ["midpoint approximation"])[0]
    if not pairs:
        return "the rig has no parallel pair"
    return "; ".join(f"{p['pair']}: {p['reason'] or 'not fitted'}" for p in pairs)


def warnings(
    report: dict[str, Any], diag: dict[str, Any], opt: ReportChecksOptions
) -> list[dict[str, str]]:
    """Plain-word warnings ("warning") and notes ("note"), most important first."""
    return (
        _scale_warnings(report, opt)
        + _image_warnings(report, opt)
        + _laser_warnings(report, diag)
        + _rejection_notes(report, diag)
        + _check_warnings(report, opt)
        + model_warnings(report)  # the reconstruction's own error (report/model_warnings.py)
    )


def _relative(value: Any, ref: Any) -> float | None:
    """100 · value / ref (None unless both are finite and ref is not 0)."""
    if not (_finite(value) and _finite(ref)) or ref == 0:
        return None
    return float(100.0 * value / ref)


def annotate_methods(report: dict[str, Any]) -> None:
    """σ in % of the value for every scale block; each method's difference from the headline."""
    head = report["scale"]["value"]
    for block in [report["scale"], *report["methods"].values()]:
        block["std_pct"] = _relative(block["std"], block["value"])
        block["n_images_used"] = len(block.get("images_used", []))
    for block in report["methods"].values():
        diff = block["value"] - head if _finite(block["value"]) and _finite(head) else None
        block["vs_headline_pct"] = _relative(diff, head)


def annotate(report: dict[str, Any], opt: ReportChecksOptions | None = None) -> dict[str, Any]:
    """Add the derived keys to ``report`` in place (and return it)."""
    opt = opt or ReportChecksOptions()
    annotate_methods(report)
    for im in report["images"]:
        im["fused"] = image_fused(report, im["name"])
        im["distance_m"] = image_distance_m(im)
        im["deviation_pct"] = laser_deviations_pct(im)
    report["diagnostics"] = diagnostics(report, opt)
    report["warnings"] = warnings(report, report["diagnostics"], opt)
    return report


__all__ = [
    "METHOD_LABELS",
    "METHOD_ORDER",
    "ReportChecksOptions",
    "annotate",
    "pcm_joint_fell_back",
]
