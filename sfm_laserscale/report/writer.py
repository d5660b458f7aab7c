"""Writers of the ``scale`` outputs (docs/OUTPUTS.md): report.json/html, CSVs, transforms,
the rescaled model and mesh, overlays. Pure dict building is kept apart from file writing.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sfm_laserscale.detection.options import TAKEN_ON_OWN
from sfm_laserscale.fusion import FusedScale
from sfm_laserscale.geometry import qvec_from_rotmat
from sfm_laserscale.io.colmap_write import write_scaled_colmap_model
from sfm_laserscale.io.images import read_rgb
from sfm_laserscale.io.meshes.mesh import write_scaled_mesh
from sfm_laserscale.io.openmvg import write_scaled_openmvg_sfm_data
from sfm_laserscale.io.spots_csv import write_spots_csv
from sfm_laserscale.io.transforms import write_matrix_4x4, write_sim3
from sfm_laserscale.methods.pcm_joint import PairJointFit, PcmJointResult
from sfm_laserscale.model import Spot
from sfm_laserscale.provenance import progress_bar
from sfm_laserscale.report.analysis import ReportChecksOptions, annotate
from sfm_laserscale.report.html import render_html
from sfm_laserscale.report.model_report import (
    append_segment_rows,
    budget_dict,
    model_checks_dict,
    model_error_dict,
    pair_checks_dict,
)
from sfm_laserscale.report.overlays import draw_overlay, near_misses, reprojected_points
from sfm_laserscale.report.schema import SCHEMA_VERSION, UNITS
from sfm_laserscale.report.validate import check_html
from sfm_laserscale.run_types import ImageRun, LoadedInputs, ScaleInputs, ScaleOptions, Timer
from sfm_laserscale.version import __version__

logger = logging.getLogger(__name__)


def _num(x: Any) -> float | None:
    """JSON-safe float: NaN/inf -> None."""
    if x is None:
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def fused_to_dict(f: FusedScale) -> dict[str, Any]:
    """The report's scale block of one method (docs/OUTPUTS.md: its keys)."""
    used = set(f.images_used)
    d: dict[str, Any] = {
        "value": _num(f.value),
        "std": _num(f.std),
        "ci95": [_num(f.ci95[0]), _num(f.ci95[1])],
        "inverse": _num(f.inverse),
        "method": f.method,
        "n_estimates": int(f.n_estimates),
        "n_rejected": int(f.n_rejected),
        "n_images": len(f.per_image),
        "notes": list(f.notes),
        "std_random": _num(f.std_random),
        "std_systematic": _num(f.std_systematic),
        "birge_ratio": _num(f.birge_ratio),
        "birge_p": _num(f.birge_p),
        "sigma_inflated": bool(f.inflated),
        "reason": f.reason,
        "images_used": list(f.images_used),
        "per_image": [
            {"image": name, "scale": _num(v), "sigma": _num(sd), "used": name in used}
            for name, (v, sd) in f.per_image.items()
        ],
        "rejected": [{"image": i, "laser": la, "reason": why} for i, la, why in f.rejected],
    }
    d.update(budget_dict(f))
    return d


def _pair_fit_dict(f: PairJointFit) -> dict[str, Any]:
    """One parallel pair's joint fit (``joint`` False: not fitted, ``reason`` says why)."""
    direction = np.asarray(f.direction_cam, dtype=np.float64).reshape(-1)
    ok = direction.size == 3 and bool(np.all(np.isfinite(direction)))
    off_axis = math.degrees(math.acos(min(1.0, abs(float(direction[2]))))) if ok else None
    origins = np.asarray(f.origins_m, dtype=np.float64)
    return {
        "pair": f.pair,
        "joint": bool(f.joint),
        "reason": f.reason,
        "scale": _num(f.scale),
        "sigma_random": _num(f.sigma_random),
        "sigma_rig": _num(f.sigma_rig),
        "direction_cam": [float(v) for v in direction] if ok else None,
        "direction_off_axis_deg": off_axis,
        "direction_sigma_deg": _num(f.direction_sigma_deg),
        "origins_m": (
            origins.tolist() if origins.shape == (2, 3) and np.all(np.isfinite(origins)) else None
        ),
        "chi2": _num(f.chi2),
        "dof": int(f.dof),
        "n_images": sum(1 for im in f.images if not im.rejected),
        "n_rejected": sum(1 for im in f.images if im.rejected),
        "images": [
            {
                "image": im.image,
                "implied_scale": _num(im.implied_scale),
                "implied_sigma": _num(im.implied_sigma),
                "chi2": _num(im.chi2),
                "rejected": bool(im.rejected),
                "reason": im.reason,
            }
            for im in f.images
        ],
    }


def pcm_joint_to_dict(result: PcmJointResult) -> dict[str, Any]:
    """Keys added to ``methods.pcm_joint``: whether the joint fit ran (``joint``; False: the
    midpoint approximation was returned, ``midpoint_fallback``) and each pair's fit."""
    return {
        "joint": bool(result.joint),
        "midpoint_fallback": not result.joint,
        "pairs": [_pair_fit_dict(f) for f in result.pairs],
    }


def _estimate_dicts(run: ImageRun) -> list[dict[str, Any]]:
    if run.estimates is None:
        return []
    return [
        {
            "method": e.method,
            "laser": e.laser,
            "scale": _num(e.scale),
            "sigma": _num(e.sigma),
            "direction_residual_deg": _num(e.direction_residual_deg),
            "depth_m": _num(e.depth_m),
            "rejected": bool(e.rejected),
            "reason": e.reason,
        }
        for e in run.estimates.estimates
    ]


def _scene_dict(run: ImageRun) -> dict[str, Any] | None:
    """How the image's scene reference was used (None: not tried, --no-scene-reference)."""
    use = run.scene
    if use is None:
        return None
    return {"used": bool(use.used), "reason": use.reason, "views": list(use.views),
            "coverage": _num(use.coverage), "kept_share": _num(use.kept_share),
            "shift_median_px": _num(use.shift_median_px),
            "residual_ratio_median": _num(use.residual_ratio_median),
            "spots_alone": int(use.spots_alone),
            "file": scene_file(run.name) if use.png is not None else None}


def scene_file(image: str) -> str:
    """Where a laser image's saved scene reference goes in the output folder (the image's
    stem, as ``detect --scene`` looks it up)."""
    return f"scene_references/{Path(image).stem}.png"


def _taken_by(run: ImageRun, spot: Spot) -> str | None:
    """The detector's rule that took a detected spot (options.TAKEN_ON_*); None for a spot
    found by the guided search or given by hand."""
    if spot.source != "detected" or run.detection is None:
        return None
    return run.detection.taken_by().get(spot.laser, TAKEN_ON_OWN)


def _image_dict(run: ImageRun) -> dict[str, Any]:
    reg = run.registration
    pose = None if reg is None else reg.cam_from_world
    d: dict[str, Any] = {
        "name": run.name,
        "registered": bool(pose is not None),
        "reason": run.reason,
        "num_features": None if reg is None else int(reg.num_features),
        "num_matches": None if reg is None else int(reg.num_matches),
        "num_inliers": None if reg is None else int(reg.num_inliers),
        "reproj_error_px": None if reg is None else _num(reg.reproj_error_px),
        "cam_from_world": None,
        "spots": [
            {
                "laser": s.laser,
                "x": s.x,
                "y": s.y,
                "score": _num(s.score),
                "sigma_px": _num(s.sigma_px),
                "source": s.source,
                "taken_by": _taken_by(run, s),
            }
            for s in run.spots
        ],
        "missing_spots": dict(run.spot_reasons),
        "estimates": _estimate_dicts(run),
        "scene_reference": _scene_dict(run),
    }
    if pose is not None:
        d["cam_from_world"] = {
            "rotation_wxyz": [float(q) for q in qvec_from_rotmat(pose.R)],
            "translation": [float(t) for t in pose.t],
        }
    return d


def build_report(
    inputs: ScaleInputs,
    options: ScaleOptions,
    loaded: LoadedInputs,
    runs: Sequence[ImageRun],
    headline: FusedScale,
    fused: dict[str, FusedScale],
    checks: dict[str, float],
    timer: Timer,
    pcm_joint: PcmJointResult | None = None,
    model: Any = None,
) -> dict[str, Any]:
    """report.json content (docs/OUTPUTS.md: every key, with the inputs, options and the report's
    checks); ``pcm_joint``: the joint fit behind ``fused["pcm_joint"]`` (its per-pair details);
    ``model``: the run's ``MethodFusion`` (its model checks and the model intrinsics' error)."""
    report: dict[str, Any] = {
        "version": __version__,
        "schema_version": SCHEMA_VERSION,  # report.schema.json (report/schema.py)
        "units": dict(UNITS),
        "scale": fused_to_dict(headline),
        "methods": {m: fused_to_dict(f) for m, f in fused.items()},
        "images": [_image_dict(r) for r in runs],
        "checks": {k: _num(v) for k, v in checks.items()},
        "timings_s": timer.as_dict(),
        "inputs": {
            k: (None if v is None else ([str(p) for p in v] if isinstance(v, tuple) else str(v)))
            for k, v in vars(inputs).items()
        },
        "rig": {
            "name": loaded.rig.name,
            "lasers": loaded.rig.names,
            "pairs": [list(p.lasers) for p in loaded.rig.pairs],
            "pair_checks": pair_checks_dict(loaded.rig),
        },
        "model": {
            "format": loaded.model.source_format,
            "images": len(loaded.model.images),
            "points": int(len(loaded.model.points_xyz)),
            "descriptors_indexed": int(loaded.descriptors_indexed),
        },
        "options": {"method": options.method, "seed": options.seed},
    }
    if pcm_joint is not None and "pcm_joint" in report["methods"]:
        report["methods"]["pcm_joint"].update(pcm_joint_to_dict(pcm_joint))
    if model is not None:  # the reconstruction's own error (docs/OUTPUTS.md)
        report["model_error"] = model_error_dict(model.intrinsics, runs, headline.value)
        focal_sigma = (report["model_error"]["intrinsics"] or {}).get("cameras") or [{}]
        report["model_checks"] = model_checks_dict(
            model.model_checks, (focal_sigma[0].get("focal_sigma_pct") or math.nan) / 100)
    # Derived keys (per-image fused values, deviations, diagnostics, warnings) are computed
    # from the JSON form of the dict, so the HTML and report.json hold the same numbers.
    report = json.loads(json.dumps(report, allow_nan=False))
    checks_opt = ReportChecksOptions(
        direction_residual_deg=options.estimation.max_direction_residual_deg
    )
    return annotate(report, checks_opt)


def summary_line(headline: FusedScale, runs: Sequence[ImageRun]) -> str:
    """One line for the terminal."""
    used = sum(1 for r in runs if r.reason is None)
    if not math.isfinite(headline.value):
        why = "; ".join(sorted({f"{r.name}: {r.reason}" for r in runs if r.reason}))[:400]
        return f"no scale could be estimated ({why})"
    return (
        f"scale = {headline.value:.6g} ± {headline.std:.2g} m per model unit "
        f"(95 % [{headline.ci95[0]:.6g}, {headline.ci95[1]:.6g}], {headline.method.upper()}, "
        f"{used}/{len(runs)} images); 1/s = {1.0 / headline.value:.6g}"
    )


def write_estimates_csv(path: Path, runs: Sequence[ImageRun]) -> None:
    """One row per (image, method, laser or pair)."""
    cols = [
        "image",
        "method",
        "laser",
        "scale",
        "sigma",
        "direction_residual_deg",
        "depth_m",
        "rejected",
        "reason",
    ]
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for run in runs:
            for e in _estimate_dicts(run):
                w.writerow([run.name] + [("" if e[c] is None else e[c]) for c in cols[1:]])


def _overlay_labels(image: dict[str, Any]) -> tuple[dict[str, float], dict[str, str]]:
    """FCM scale per laser and laser -> reason for the rejected ones (estimation or fusion)."""
    fcm = [e for e in image["estimates"] if e["method"] == "fcm"]
    scales = {e["laser"]: e["scale"] for e in fcm if e["scale"] is not None}
    rejected = {e["laser"]: e["reason"] or "rejected" for e in fcm if e["rejected"]}
    for r in image.get("fused", {}).get("fcm", {}).get("rejected", []):
        rejected.setdefault(r["laser"], r["reason"])
    return scales, rejected


def _overlay_name(image: str, taken: set[str]) -> str:
    """``<stem>.jpg``, or ``<stem>_2.jpg``… when images of two folders share a stem."""
    stem = Path(image).stem
    name, k = f"{stem}.jpg", 1
    while f"overlays/{name}" in taken:
        k += 1
        name = f"{stem}_{k}.jpg"
    return name


def _registration_points(run: ImageRun) -> tuple[np.ndarray | None, bool]:
    """The overlay's registration points: the inliers' model points reprojected with the
    accepted pose, or the inlier keypoints of a rejected pose (True); None without matches."""
    reg = run.registration
    if reg is None or run.camera is None:
        return None, False
    pose = reg.cam_from_world
    if pose is None:
        return (reg.inlier_xy_px if len(reg.inlier_xy_px) else None), True
    return reprojected_points(run.camera, pose, reg.inlier_xyz), False


def _write_overlays(
    out: Path,
    runs: Sequence[ImageRun],
    loaded: LoadedInputs,
    options: ScaleOptions,
    report: dict[str, Any],
) -> dict[str, str]:
    folder = out / "overlays"
    folder.mkdir()
    written: dict[str, str] = {}
    by_name = {im["name"]: im for im in report["images"]}
    for run in progress_bar(options.progress, "overlays", iterable=runs, unit="img"):
        if run.camera is None:
            continue
        rgb = read_rgb(run.path, check=False)  # a damaged image's overlay shows the damage
        scales, rejected = _overlay_labels(by_name[run.name])
        points, pose_rejected = _registration_points(run)
        img = draw_overlay(
            rgb,
            run.camera,
            loaded.rig,
            run.spots,
            scales,
            points,
            options.detection.min_range_m,
            options.detection.max_range_m,
            rejected=rejected,
            pose_rejected=pose_rejected,
            near_misses=near_misses(run.detection),
        )
        name = _overlay_name(run.name, set(written.values()))
        cv2.imwrite(str(folder / name), img, [cv2.IMWRITE_JPEG_QUALITY, 88])
        written[run.name] = f"overlays/{name}"
    return written


def _write_scaled(
    out: Path, inputs: ScaleInputs, loaded: LoadedInputs, scale: float, progress: bool
) -> None:
    scaled = out / "scaled"
    scaled.mkdir()
    if loaded.model.source_format == "openmvg":
        write_scaled_openmvg_sfm_data(inputs.model, scaled / "model" / "sfm_data.json", scale)
    else:
        write_scaled_colmap_model(inputs.model, scaled / "model", scale)
    size = inputs.mesh.stat().st_size
    with progress_bar(progress, "scaled mesh", total=size, unit="B", unit_scale=True) as bar:
        write_scaled_mesh(inputs.mesh, scaled, scale, progress=bar.update)


def write_scene_references(out: Path, runs: Sequence[ImageRun]) -> None:
    """The scene references kept for saving (--save-scene-references), one PNG per image."""
    for r in runs:
        if r.scene is None or r.scene.png is None:
            continue
        path = out / scene_file(r.name)
        path.parent.mkdir(exist_ok=True)
        if path.exists():
            logger.warning("scene reference %s: two laser images share the stem %s; the first "
                           "is kept", r.name, path.stem)
            continue
        path.write_bytes(r.scene.png)


def write_outputs(
    out: Path,
    inputs: ScaleInputs,
    loaded: LoadedInputs,
    runs: Sequence[ImageRun],
    headline: FusedScale,
    report: dict[str, Any],
    options: ScaleOptions,
    timer: Timer,
    write_scaled: Callable[[Path, float], None] | None = None,
) -> None:
    """Every output file of ``scale`` (docs/OUTPUTS.md) into ``out`` (report.json last, with
    final timings). ``write_scaled(scaled_dir, scale)``: writes ``scaled/`` instead of the
    rescaling of the input files (a model or mesh given in memory, commands/scale.py)."""
    t0 = time.perf_counter()
    write_estimates_csv(out / "estimates.csv", runs)
    append_segment_rows(out / "estimates.csv", report)
    write_spots_csv(out / "spots.csv", {r.name: list(r.spots) for r in runs})
    write_scene_references(out, runs)
    if math.isfinite(headline.value):
        write_sim3(out / "transform.sim3", headline.value)
        write_matrix_4x4(out / "transform_4x4.txt", headline.value)
        if write_scaled is None:
            _write_scaled(out, inputs, loaded, headline.value, options.progress)
        else:
            (out / "scaled").mkdir()
            write_scaled(out / "scaled", headline.value)
    overlays = _write_overlays(out, runs, loaded, options, report) if options.overlays else {}
    for im in report["images"]:
        im["overlay"] = overlays.get(im["name"])
    report["timings_s"] = timer.as_dict()
    # the caller's "write" stage is still open: count this function's own time
    report["timings_s"]["write"] = round(
        max(report["timings_s"].get("write", 0.0), time.perf_counter() - t0), 4
    )
    text = json.dumps(report, indent=2, allow_nan=False) + "\n"
    # The page is rendered from the very JSON written, so every number in it is in report.json.
    html = render_html(json.loads(text), out)
    for problem in check_html(html, json.loads(text)):
        logger.warning("report.html: %s", problem)
    (out / "report.html").write_text(html, encoding="utf-8")
    (out / "report.json").write_text(text, encoding="utf-8")


__all__ = ["build_report", "fused_to_dict", "pcm_joint_to_dict", "summary_line", "write_outputs"]
