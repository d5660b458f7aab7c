"""report.html: rendered from report.json only, every number traceable, plain-word warnings,
legible overlays; on hand-made report dicts and on one real run of the small data set."""

from __future__ import annotations

import json
import math
import re
import statistics
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from sfm_laserscale.model import Camera, Spot
from sfm_laserscale.report import html as html_module
from sfm_laserscale.report.analysis import annotate
from sfm_laserscale.report.html import render_html, template_cache_dir
from sfm_laserscale.report.overlays import draw_overlay, place_labels
from sfm_laserscale.report.style import laser_color_bgr
from sfm_laserscale.report.validate import check_html, parse_report_html
from sfm_laserscale.rig import rig_from_dict

LASERS = ("L1", "L2", "L3", "L4")
PAIR = "L1+L2"

# --------------------------------------------------------------------------- hand-made reports


def _block(
    method: str,
    per_image: dict[str, tuple[float, float]],
    used: list[str],
    rejected: list[dict[str, str]],
    n_est: int,
    notes: list[str] | None = None,
) -> dict[str, Any]:
    """A report.json scale block as writer.fused_to_dict makes it (simple mean fusion)."""
    vals = [per_image[i][0] for i in used]
    if not vals:
        return {
            "value": None,
            "std": None,
            "ci95": [None, None],
            "inverse": None,
            "method": method,
            "n_estimates": 0,
            "n_rejected": len(rejected),
            "n_images": len(per_image),
            "notes": notes or ["no usable estimate"],
            "std_random": None,
            "std_systematic": None,
            "birge_ratio": None,
            "reason": f"no usable {method} estimate",
            "images_used": [],
            "per_image": [],
            "rejected": rejected,
        }
    v = statistics.fmean(vals)
    sd = statistics.stdev(vals) / math.sqrt(len(vals)) if len(vals) > 1 else per_image[used[0]][1]
    return {
        "value": v,
        "std": sd,
        "ci95": [v - 1.96 * sd, v + 1.96 * sd],
        "inverse": 1 / v,
        "method": method,
        "n_estimates": n_est,
        "n_rejected": len(rejected),
        "n_images": len(per_image),
        "notes": notes or [f"{len(vals)} image(s)"],
        "std_random": sd,
        "std_systematic": 0.0,
        "birge_ratio": 1.2,
        "reason": None,
        "images_used": list(used),
        "per_image": [
            {"image": k, "scale": a, "sigma": b, "used": k in used}
            for k, (a, b) in per_image.items()
        ],
        "rejected": rejected,
    }


def _estimate(
    method: str,
    laser: str,
    scale: float,
    sigma: float,
    depth: float,
    residual: float | None = None,
    rejected: bool = False,
    reason: str | None = None,
) -> dict[str, Any]:
    return {
        "method": method,
        "laser": laser,
        "scale": scale,
        "sigma": sigma,
        "direction_residual_deg": residual,
        "depth_m": depth,
        "rejected": rejected,
        "reason": reason,
    }


def _pair_fit(pair: str, joint: bool, per_image: dict[str, tuple[float, float]]) -> dict[str, Any]:
    """methods.pcm_joint.pairs[k] as writer.pcm_joint_to_dict makes it."""
    if not joint:
        return {
            "pair": pair,
            "joint": False,
            "reason": "only 2 usable image(s), the joint fit needs 3",
            "scale": None,
            "sigma_random": None,
            "sigma_rig": None,
            "direction_cam": None,
            "direction_off_axis_deg": None,
            "direction_sigma_deg": None,
            "origins_m": None,
            "chi2": None,
            "dof": 0,
            "n_images": 0,
            "n_rejected": 0,
            "images": [],
        }
    vals = [v for v, _ in per_image.values()]
    return {
        "pair": pair,
        "joint": True,
        "reason": None,
        "scale": statistics.fmean(vals),
        "sigma_random": 4.1e-4,
        "sigma_rig": 0.0,
        "direction_cam": [0.0262, 0.0, 0.99966],
        "direction_off_axis_deg": 1.5013,
        "direction_sigma_deg": 0.0081,
        "origins_m": [[-0.05, 0.0, 0.0], [0.05, 0.0, 0.0]],
        "chi2": 2.93,
        "dof": 4 * len(vals) - 6,
        "n_images": len(vals),
        "n_rejected": 0,
        "images": [
            {
                "image": k,
                "implied_scale": v,
                "implied_sigma": sd,
                "chi2": 0.7,
                "rejected": False,
                "reason": None,
            }
            for k, (v, sd) in per_image.items()
        ],
    }


def make_report(
    n_images: int = 6,
    bias: dict[str, float] | None = None,
    bias_images: int = 4,
    failed: int = 1,
    outlier: bool = True,
    mma: float = 1.6e-4,
    fallback: bool = False,
    residual_deg: float | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """A report.json dict like build_report's, with known content, then annotated.

    ``bias``: laser -> relative bias in its first ``bias_images`` images; ``failed``: images
    that did not register (the last ones); ``outlier``: image 1's Direct 3D is left out by
    fusion; ``residual_deg``: L2's FCM direction residual in image 0 (rejected above 3°)."""
    rng = np.random.default_rng(seed)
    bias = bias or {}
    s_true, rel = 0.3153, 0.002
    images: list[dict[str, Any]] = []
    per: dict[str, dict[str, tuple[float, float]]] = {
        m: {} for m in ("fcm", "pcm", "direct3d", "pcm_joint")
    }
    used: dict[str, list[str]] = {m: [] for m in per}
    rejected: dict[str, list[dict[str, str]]] = {m: [] for m in per}
    n_est = {m: 0 for m in per}
    for i in range(n_images):
        name = f"dive_{i:03d}.jpg"
        ok = i < n_images - failed
        im: dict[str, Any] = {
            "name": name,
            "registered": ok,
            "reason": None if ok else "only 12 inliers (< 30)",
            "num_features": 5000,
            "num_matches": 900 if ok else 40,
            "num_inliers": 850 - 10 * i if ok else 12,
            "reproj_error_px": 0.35 + 0.01 * i,
            "cam_from_world": None,
            "missing_spots": {},
            "estimates": [],
            "overlay": None,
            "spots": [
                {
                    "laser": la,
                    "x": 300.0 + 40 * k,
                    "y": 240.0 + 3 * k,
                    "score": 0.9,
                    "sigma_px": 0.1,
                    "source": "detected",
                }
                for k, la in enumerate(LASERS)
            ],
        }
        if ok:
            depth = 2.0 + 0.3 * i
            vals = []
            for la in LASERS:
                b = bias.get(la, 0.0) if i < bias_images else 0.0
                s = s_true * (1 + b + rel * rng.standard_normal())
                res = 0.1
                bad = False
                if la == "L2" and i == 0 and residual_deg is not None:
                    res = residual_deg
                    bad = residual_deg > 3.0
                im["estimates"].append(
                    _estimate(
                        "fcm",
                        la,
                        s,
                        s_true * rel,
                        depth,
                        res,
                        bad,
                        "direction residual too large" if bad else None,
                    )
                )
                if not bad:
                    vals.append(s)
                    n_est["fcm"] += 1
            s_img = statistics.fmean(vals)
            per["fcm"][name] = (s_img, s_true * rel / 2)
            used["fcm"].append(name)
            s_pcm = s_true * (1 + 0.004 + rel * rng.standard_normal())
            s_d3 = s_true * (1 - 0.045 if (outlier and i == 1) else 1 - 0.002)
            im["estimates"].append(_estimate("pcm", PAIR, s_pcm, s_true * rel, depth))
            im["estimates"].append(_estimate("direct3d", PAIR, s_d3, s_true * rel, depth))
            for m, v in (("pcm", s_pcm), ("direct3d", s_d3), ("pcm_joint", s_pcm * 0.996)):
                per[m][name] = (v, s_true * rel)
                if m == "direct3d" and outlier and i == 1:
                    rejected[m].append(
                        {
                            "image": name,
                            "laser": PAIR,
                            "reason": "image scale deviates from the consensus by 9.1 "
                            "robust sigmas",
                        }
                    )
                else:
                    used[m].append(name)
                    n_est[m] += 1
        else:
            im["spots"] = []
            im["missing_spots"] = {"L4": "no candidate blob near the beam line"}
        images.append(im)
    notes_pj = (
        [
            "fewer than 3 images: midpoint approximation",
            "L1+L2: only 2 usable image(s), the joint fit needs 3",
            "2 image(s)",
        ]
        if fallback
        else ["joint beam direction from 5 images"]
    )
    methods = {
        m: _block(m, per[m], used[m], rejected[m], n_est[m], notes_pj if m == "pcm_joint" else None)
        for m in per
    }
    joint = not fallback and len(per["pcm_joint"]) >= 3
    methods["pcm_joint"].update(
        joint=joint,
        midpoint_fallback=not joint,
        pairs=[_pair_fit(PAIR, joint, per["pcm_joint"])],
    )
    report = {
        "version": "test",
        "scale": dict(methods["fcm"]),
        "methods": methods,
        "images": images,
        "checks": {"mesh_model_agreement": mma},
        "timings_s": {
            "load": 0.3,
            "detect": 0.2,
            "register": 12.9,
            "raycast": 0.4,
            "estimate": 0.02,
            "write": 0.0,
            "total": 14.7,
        },
        "inputs": {
            "model": "/data/sparse/0",
            "mesh": "/data/mesh.ply",
            "laser_images": ["/data/laser"],
            "rig": "/data/rig.toml",
            "images": None,
            "database": "/data/database.db",
            "features": None,
            "spots": None,
        },
        "rig": {"name": "test rig", "lasers": list(LASERS), "pairs": [["L1", "L2"]]},
        "model": {
            "format": "colmap-binary",
            "images": 40,
            "points": 9000,
            "descriptors_indexed": 30000,
        },
        "options": {"method": "all", "seed": 0},
    }
    return annotate(json.loads(json.dumps(report)))


def write_overlays(report: dict[str, Any], out: Path, skip: tuple[str, ...] = ()) -> None:
    """A small JPEG per registered image, named in report['images'][i]['overlay']."""
    (out / "overlays").mkdir(parents=True, exist_ok=True)
    for k, im in enumerate(report["images"]):
        rel = f"overlays/{Path(im['name']).stem}.jpg"
        im["overlay"] = rel
        if im["name"] in skip:
            continue
        img = np.zeros((120, 160, 3), np.uint8)
        img[:, :, 1] = 60 + 20 * k
        cv2.putText(img, im["name"], (5, 60), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255))
        cv2.imwrite(str(out / rel), img)


def _numbers(html: str) -> dict[tuple[Any, ...], tuple[Any, str]]:
    page = parse_report_html(html)
    return {tuple(json.loads(k)): (json.loads(v), t) for k, v, t in page.numbers}


def _decimals(report: dict[str, Any]) -> int:
    """Independent of the renderer: three significant digits of the headline σ."""
    return 2 - math.floor(math.log10(report["scale"]["std"]))


# --------------------------------------------------------------------------- rendering


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], str]:
    """The default hand-made report with overlays, rendered once."""
    out = tmp_path_factory.mktemp("rendered")
    report = make_report()
    write_overlays(report, out)
    return report, render_html(report, out)


def test_key_numbers_shown_from_report_json(rendered: tuple[dict[str, Any], str]) -> None:
    report, html = rendered
    assert check_html(html, report) == []
    nums = _numbers(html)
    d = _decimals(report)
    s = report["scale"]
    for path, value in [
        (("scale", "value"), s["value"]),
        (("scale", "std"), s["std"]),
        (("scale", "ci95", 0), s["ci95"][0]),
        (("scale", "ci95", 1), s["ci95"][1]),
    ]:
        shown_value, text = nums[path]
        assert shown_value == value
        assert text == f"{value:.{d}f}"
    assert float(nums[("scale", "inverse")][1]) == pytest.approx(1 / s["value"], rel=1e-5)
    for i, im in enumerate(report["images"]):
        for k, e in enumerate(im["estimates"]):
            assert nums[("images", i, "estimates", k, "scale")][1] == f"{e['scale']:.{d}f}"
        if im["reason"] is None:
            assert ("images", i, "fused", "fcm", "scale") in nums
    # the headline number is the first number of the page, in the summary
    page = parse_report_html(html)
    assert json.loads(page.numbers[0][0]) == ["scale", "value"]


def test_check_catches_tampered_numbers(rendered: tuple[dict[str, Any], str]) -> None:
    report, html = rendered
    value = report["scale"]["value"]
    shown = f"{value:.{_decimals(report)}f}"
    bumped = f"{value * 1.001:.{_decimals(report)}f}"
    bad_text = html.replace(f">{shown}</span>", f">{bumped}</span>", 1)
    assert any("scale" in p and "shows" in p for p in check_html(bad_text, report))
    other = json.loads(json.dumps(report))
    other["scale"]["std"] *= 2
    assert any('"std"' in p for p in check_html(html, other))


def test_check_catches_missing_and_broken_overlay(
    tmp_path: Path, rendered: tuple[dict[str, Any], str]
) -> None:
    report = make_report()
    gone = report["images"][2]["name"]
    write_overlays(report, tmp_path, skip=(gone,))
    html = render_html(report, tmp_path)
    assert f'data-missing-overlay="{gone}"' in html
    assert check_html(html, report) == [f"overlay of {gone} missing (overlays/dive_002.jpg)"]
    # a file that is not a JPEG
    (tmp_path / "overlays" / "dive_002.jpg").write_bytes(b"not an image")
    problems = check_html(render_html(report, tmp_path), report)
    assert problems == ["image 'dive_002.jpg': data is not image/jpeg"]
    # a plot removed from the page
    report, html = rendered
    no_plot = re.sub(r'<img data-plot="per-laser"[^>]*>', "", html)
    assert check_html(no_plot, report) == ["per-laser plot missing"]


def test_page_is_self_contained(rendered: tuple[dict[str, Any], str]) -> None:
    report, html = rendered
    assert not re.search(r"<script|<link|@import|@font-face|url\(", html, re.I)
    assert not re.search(r"(src|href)=\"(?!data:|#)", html)
    page = parse_report_html(html)
    assert len(page.images) == 2 + len(report["images"])  # two plots + every overlay
    assert all(img["src"].startswith("data:image/") for img in page.images)


def test_no_scale_report_renders_reasons(tmp_path: Path) -> None:
    report = make_report(n_images=2, failed=2)
    assert report["scale"]["value"] is None
    html = render_html(report, tmp_path)
    assert "No scale could be estimated" in html
    assert html.count("only 12 inliers (&lt; 30)") >= 2
    assert check_html(html, report) == []
    assert report["warnings"][0]["code"] == "no_scale"


def _cache_files(cache: Path) -> list[Path]:
    return sorted((cache / "sfm-laserscale" / "templates").glob("*.cache"))


def test_compiled_template_is_kept_between_runs(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    report = make_report(n_images=2, failed=2)
    first = render_html(report, tmp_path)
    assert len(_cache_files(tmp_path / "cache")) == 1

    def no_compile(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the template was compiled again")

    monkeypatch.setattr(html_module.Environment, "compile", no_compile)
    assert render_html(report, tmp_path) == first  # from the cache: nothing compiled


def test_damaged_or_unwritable_template_cache_only_costs_the_compile(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    report = make_report(n_images=2, failed=2)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    reference = render_html(report, tmp_path)
    (cached,) = _cache_files(tmp_path / "cache")
    data = cached.read_bytes()
    for damaged in (b"", b"\x00" * 64, data[: len(data) // 2], data[:40] + b"\xff" * 200):
        cached.write_bytes(damaged)
        assert render_html(report, tmp_path) == reference
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("x")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))
    assert template_cache_dir() is None
    assert render_html(report, tmp_path) == reference


def test_pair_only_rig_renders(tmp_path: Path) -> None:
    """No calibrated laser: PCM is the headline, the per-laser plot shows the pair."""
    base = make_report(failed=0, outlier=False)
    for im in base["images"]:
        im["estimates"] = [e for e in im["estimates"] if e["method"] != "fcm"]
        for key in ("fused", "deviation_pct", "distance_m"):
            im.pop(key)
    base["methods"]["fcm"] = _block("fcm", {}, [], [], 0)
    base["scale"] = dict(base["methods"]["pcm"])
    for key in ("diagnostics", "warnings"):
        base.pop(key)
    report = annotate(base)
    html = render_html(report, tmp_path)
    assert check_html(html, report) == []
    assert 'data-plot="per-laser"' in html
    assert report["diagnostics"]["per_laser"] == {}
    assert "(parallel laser pair)" in html


# --------------------------------------------------------------------------- derived numbers


def test_deviation_distance_and_spread_known_answers() -> None:
    report = make_report()
    im = report["images"][0]
    ref = im["fused"]["fcm"]["scale"]
    for e in im["estimates"]:
        if e["method"] == "fcm":
            assert im["deviation_pct"][e["laser"]] == pytest.approx(100 * (e["scale"] / ref - 1))
    assert im["distance_m"] == pytest.approx(2.0)
    vals = [p["scale"] for p in report["methods"]["pcm"]["per_image"]]
    spread = 100 * statistics.stdev(vals) / statistics.fmean(vals)
    assert report["diagnostics"]["image_spread_pct"]["pcm"] == pytest.approx(spread)
    # the left-out Direct 3D image does not count in its spread
    d3 = [p["scale"] for p in report["methods"]["direct3d"]["per_image"] if p["used"]]
    assert report["diagnostics"]["image_spread_pct"]["direct3d"] == pytest.approx(
        100 * statistics.stdev(d3) / statistics.fmean(d3)
    )
    assert report["scale"]["std_pct"] == pytest.approx(
        100 * report["scale"]["std"] / report["scale"]["value"]
    )


def _codes(report: dict[str, Any]) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for w in report["warnings"]:
        out.setdefault(w["code"], []).append(w["message"])
    return out


def test_clean_report_has_no_warnings() -> None:
    report = make_report(failed=0, outlier=False)
    assert report["warnings"] == []


def test_warnings_in_plain_words() -> None:
    report = make_report(
        n_images=7,
        bias={"L3": 0.021},
        bias_images=4,
        failed=1,
        mma=0.02,
        fallback=True,
        residual_deg=5.2,
    )
    codes = _codes(report)
    (laser_msg,) = codes["laser_deviation"]
    # L3 is 2.1 % high in 4 images (noise 0.2 % per laser): vs. the other three lasers
    vs = report["diagnostics"]["per_laser"]["L3"]["median_vs_others_pct"]
    assert vs == pytest.approx(2.1, abs=0.35)
    assert laser_msg.startswith(f"Laser L3 disagrees with the other lasers by {vs:+.1f} %")
    assert "in 4 of 6 images" in laser_msg and "calibration" in laser_msg
    assert (
        "1 of 7 laser images gave no estimate: dive_006.jpg (only 12 inliers"
        in (codes["images_failed"][0])
    )
    assert "Mesh–model agreement is poor" in codes["mesh_model"][0]
    assert "2.00 %" in codes["mesh_model"][0]
    assert "dive_000.jpg" in codes["beam_geometry"][0] and "5.2°" in codes["beam_geometry"][0]
    (fb,) = [w for w in report["warnings"] if w["code"] == "pcm_joint_fallback"]
    assert fb["level"] == "note"  # FCM is the headline
    assert "only 2 usable image(s)" in fb["message"]
    assert "image_outlier" not in codes  # the Direct 3D outlier is not the headline method's
    assert report["diagnostics"]["per_laser"]["L3"]["n_flagged"] == 4


def test_few_images_warns_wide_interval() -> None:
    report = make_report(n_images=3, failed=1, outlier=False)
    (msg,) = _codes(report)["few_images"]
    assert msg.startswith("Only 2 images gave the FCM scale: the interval")


def test_single_rejected_estimate_is_a_note() -> None:
    report = make_report(failed=0, outlier=False)
    reason = "inconsistent with the image's other fcm estimates (4.2 sigma)"
    report["methods"]["fcm"]["rejected"].append(
        {"image": "dive_002.jpg", "laser": "L4", "reason": reason}
    )
    report["scale"] = dict(report["methods"]["fcm"])
    annotate(report)
    (w,) = report["warnings"]
    assert w["level"] == "note"
    assert w["message"] == f"1 FCM estimate left out: L4 in dive_002.jpg: {reason}."


def test_headline_outlier_image_is_warned() -> None:
    report = make_report(outlier=True)
    report["scale"] = dict(report["methods"]["direct3d"])
    annotate(report)
    (msg,) = _codes(report)["image_outlier"]
    assert msg.startswith("Image dive_001.jpg was left out as an outlier: image scale deviates")


def test_warnings_render_red_and_numbers_still_match(tmp_path: Path) -> None:
    report = make_report(bias={"L3": 0.021}, mma=0.02, residual_deg=5.2)
    html = render_html(report, tmp_path)
    assert check_html(html, report) == []
    n_warn = sum(w["level"] == "warning" for w in report["warnings"])
    assert f"{n_warn} warnings</h2>" in html
    assert html.count('<li class="warning"') == n_warn


# --------------------------------------------------------------------------- overlays


def test_place_labels_do_not_overlap() -> None:
    anchors = [(100.0, 100.0), (108.0, 103.0), (96.0, 110.0), (104.0, 95.0), (112.0, 112.0)]
    sizes = [(40.0, 24.0)] * len(anchors)
    boxes = place_labels(anchors, sizes, 12.0, 400, 300)
    for a in range(len(boxes)):
        x0, y0, x1, y1 = boxes[a]
        assert x0 >= 0 and y0 >= 0 and x1 <= 400 and y1 <= 300
        for b in range(a):
            u0, v0, u1, v1 = boxes[b]
            assert min(x1, u1) <= max(x0, u0) or min(y1, v1) <= max(y0, v0)


def test_labels_stay_inside_at_the_image_corner() -> None:
    boxes = place_labels([(3.0, 3.0), (637.0, 477.0)], [(50.0, 20.0)] * 2, 10.0, 640, 480)
    for x0, y0, x1, y1 in boxes:
        assert x0 >= 0 and y0 >= 0 and x1 <= 640 and y1 <= 480


def _rig() -> Any:
    return rig_from_dict(
        {
            "laser": [
                {"name": n, "origin": [x, y, 0.0], "direction": [0.0, 0.0, 1.0]}
                for n, x, y in (("L1", -0.1, -0.1), ("L2", 0.1, -0.1), ("L3", 0.1, 0.1))
            ]
        }
    )


@pytest.mark.parametrize(("width", "height", "long_out"), [(640, 480, 1200), (3840, 2160, 1600)])
def test_overlay_size_and_spot_position(width: int, height: int, long_out: int) -> None:
    """Spots are drawn where they are (COLMAP pixels), at any input size."""
    f_px = 0.9 * width
    cam = Camera(1, "PINHOLE", width, height, np.array([f_px, f_px, width / 2, height / 2]))
    rgb = np.full((height, width, 3), 90, np.uint8)
    spot = Spot("L2", 0.25 * width + 0.5, 0.5 * height + 0.5)
    img = draw_overlay(rgb, cam, _rig(), [spot], {"L2": 0.3153}, None, 0.5, 20.0)
    f = long_out / max(width, height)
    assert img.shape[1] == round(width * f)
    assert img.shape[0] > round(height * f)  # legend strip below the photo
    # the circle (radius 20 units of long/1200) passes right of the spot centre
    r = 20.0 * long_out / 1200
    cx, cy = spot.x * f - 0.5, spot.y * f - 0.5
    ring = img[int(round(cy)), int(round(cx + r)) - 1 : int(round(cx + r)) + 2].astype(int)
    color = np.array(laser_color_bgr(1))
    assert np.min(np.abs(ring - color).sum(axis=1)) < 60
    assert np.abs(img[int(round(cy)), int(round(cx))].astype(int) - 90).max() < 5  # centre clear


def test_rejected_laser_is_red_on_the_overlay() -> None:
    cam = Camera(1, "PINHOLE", 640, 480, np.array([576.0, 576.0, 320.0, 240.0]))
    rgb = np.full((480, 640, 3), 90, np.uint8)
    spot = Spot("L1", 200.5, 240.5)
    img = draw_overlay(
        rgb,
        cam,
        _rig(),
        [spot],
        {},
        None,
        0.5,
        20.0,
        rejected={"L1": "direction residual too large"},
    )
    f = 1200 / 640
    r = 20.0
    y, x = int(round(240.5 * f - 0.5)), int(round(200.5 * f - 0.5 + r))
    ring = img[y, x - 1 : x + 2].astype(int)
    red = np.array([0x2B, 0x39, 0xC0])  # WARNING_HEX in BGR
    assert np.min(np.abs(ring - red).sum(axis=1)) < 60


def test_overlay_names_do_not_collide() -> None:
    from sfm_laserscale.report.writer import _overlay_name

    taken = {"overlays/img_001.jpg"}
    assert _overlay_name("a/img_001.png", set()) == "img_001.jpg"
    assert _overlay_name("b/img_001.jpg", taken) == "img_001_2.jpg"
    assert _overlay_name("c/img_001.tif", taken | {"overlays/img_001_2.jpg"}) == "img_001_3.jpg"


# --------------------------------------------------------------------------- a real run


@pytest.fixture(scope="module")
def real_run(small_scale_run: Any) -> Path:
    """The output folder of the session's shared real run (conftest.small_scale_run)."""
    return Path(small_scale_run.out_dir)


def test_real_run_html_agrees_with_json(real_run: Path) -> None:
    report = json.loads((real_run / "report.json").read_text())
    html = (real_run / "report.html").read_text()
    assert check_html(html, report) == []
    nums = _numbers(html)
    d = _decimals(report)
    assert nums[("scale", "value")] == (
        report["scale"]["value"],
        f"{report['scale']['value']:.{d}f}",
    )
    page = parse_report_html(html)
    shown = {img["data-overlay"] for img in page.images if "data-overlay" in img}
    assert shown == {im["name"] for im in report["images"]}
    assert {img.get("data-plot") for img in page.images} >= {"per-laser", "methods"}
    # the added keys are in report.json
    for key in ("diagnostics", "warnings"):
        assert key in report
    im0 = report["images"][0]
    assert {"fused", "distance_m", "deviation_pct", "overlay"} <= set(im0)
    assert im0["fused"]["fcm"]["scale"] is not None
    assert set(report["methods"]["fcm"]) >= {"per_image", "images_used", "rejected", "std_pct"}


def test_real_run_overlay_files_are_legible_size(real_run: Path) -> None:
    for path in sorted((real_run / "overlays").glob("*.jpg")):
        img = cv2.imread(str(path))
        assert img is not None and max(img.shape[:2]) >= 1200


def test_real_run_pcm_joint_pair_fit_in_json_and_page(real_run: Path) -> None:
    """report.json carries the explicit joint flag and each pair's fit; the page shows them."""
    report = json.loads((real_run / "report.json").read_text())
    pj = report["methods"]["pcm_joint"]
    assert pj["joint"] is True and pj["midpoint_fallback"] is False
    (pair,) = pj["pairs"]
    assert pair["pair"] == "L1+L2" and pair["joint"] is True and pair["reason"] is None
    assert pair["n_images"] + pair["n_rejected"] == len(pair["images"]) == 3
    # one pair: the fused PCM-joint value is that pair's scale
    assert pj["value"] == pytest.approx(pair["scale"], rel=1e-12)
    # the small data set's L1/L2 beams are tilted 1.5° (rig.toml: direction (0, 0.02618, 0.99966))
    assert pair["direction_off_axis_deg"] == pytest.approx(1.5, abs=0.1)
    assert pair["direction_cam"] == pytest.approx([0.0, 0.0261769, 0.9996573], abs=2e-3)
    html = (real_run / "report.html").read_text()
    assert 'id="pcm-joint-pairs"' in html and 'data-pair="L1+L2"' in html
    nums = _numbers(html)
    assert nums[("methods", "pcm_joint", "pairs", 0, "scale")][0] == pair["scale"]
    assert "pcm_joint_fallback" not in {w["code"] for w in report["warnings"]}


def test_real_run_log_holds_pycolmap_messages(real_run: Path, small_dataset: Any) -> None:
    """pycolmap's own (glog) lines of the registrations end up in run.log, marked as its."""
    log = (real_run / "run.log").read_text()
    head, marker, tail = log.partition("---- pycolmap's own log (glog")
    assert marker, "no pycolmap section in run.log"
    assert "sfm_laserscale.commands.scale: run finished" in head
    lines = [ln for ln in tail.splitlines()[1:] if ln]
    assert lines and all(ln.startswith("pycolmap: ") for ln in lines)
    n_laser = len(list(small_dataset.laser_images_dir.glob("*.png")))
    # one SIFT extractor per laser image registered (registration.extract_sift)
    sift = [ln for ln in lines if "Creating SIFT CPU feature extractor" in ln]
    assert len(sift) == n_laser
    assert all(re.match(r"pycolmap: [IWEF]\d{8} \d\d:\d\d:\d\d\.\d{6} ", ln) for ln in lines)


def test_pcm_joint_fallback_from_the_explicit_field(tmp_path: Path) -> None:
    """The fallback warning follows methods.pcm_joint.joint, not the notes' wording."""
    joint = make_report(fallback=False)
    joint["methods"]["pcm_joint"]["notes"] = ["fewer than 3 images: midpoint approximation"]
    assert "pcm_joint_fallback" not in _codes(annotate(joint))
    fell = make_report(fallback=True)
    fell["methods"]["pcm_joint"]["notes"] = ["joint beam direction from 5 images"]
    (msg,) = _codes(annotate(fell))["pcm_joint_fallback"]
    assert "(L1+L2: only 2 usable image(s), the joint fit needs 3)" in msg
    html = render_html(fell, tmp_path)
    assert check_html(html, fell) == []
    assert "midpoint fallback</span>" in html and 'data-pair="L1+L2" class="bad"' in html
    # a report.json from before the field: the old key and the fallback's first note
    old = make_report(fallback=True)
    for key in ("joint", "pairs"):
        del old["methods"]["pcm_joint"][key]
    (msg,) = _codes(annotate(old))["pcm_joint_fallback"]
    assert "(fewer than 3 images: midpoint approximation)" in msg


def test_check_catches_missing_methods_plot(rendered: tuple[dict[str, Any], str]) -> None:
    report, html = rendered
    no_plot = re.sub(r'<img data-plot="methods"[^>]*>', "", html)
    assert check_html(no_plot, report) == ["methods plot missing"]


def test_overlay_draws_reprojected_model_points() -> None:
    """Registration points are the inliers' 3D points projected with the pose (known pixels)."""
    from sfm_laserscale.model import Pose
    from sfm_laserscale.report.overlays import reprojected_points
    from sfm_laserscale.report.style import INLIER_HEX, hex_to_bgr

    cam = Camera(1, "PINHOLE", 640, 480, np.array([500.0, 500.0, 320.0, 240.0]))
    pose = Pose(np.eye(3), np.array([0.0, 0.0, 2.0]))  # world origin 2 units ahead
    xyz = np.array([[0.4, -0.2, 0.0], [-0.8, 0.4, 0.0], [0.0, 0.0, -5.0]])  # last: behind
    xy = reprojected_points(cam, pose, xyz)
    assert xy == pytest.approx(np.array([[420.0, 190.0], [120.0, 340.0]]))
    rgb = np.full((480, 640, 3), 90, np.uint8)
    img = draw_overlay(rgb, cam, _rig(), [], {}, xy, 0.5, 20.0)
    f = 1200 / 640
    green = np.array(hex_to_bgr(INLIER_HEX))
    for x, y in xy:
        px = img[int(round(y * f - 0.5)), int(round(x * f - 0.5))].astype(int)
        assert np.abs(px - (0.65 * green + 0.35 * 90)).max() < 12
    red = draw_overlay(rgb, cam, _rig(), [], {}, xy, 0.5, 20.0, pose_rejected=True)
    px = red[int(round(190 * f - 0.5)), int(round(420 * f - 0.5))].astype(int)
    assert px[2] > px[1] + 40  # red, not green


def test_outlier_images_listed_under_checks(tmp_path: Path) -> None:
    """Images fusion left out are listed per method (headline first) with fusion's reason."""
    report = make_report(outlier=True)
    (x,) = report["diagnostics"]["outlier_images"]
    assert (x["method"], x["image"], x["headline"]) == ("direct3d", "dive_001.jpg", False)
    assert x["reason"].startswith("image scale deviates from the consensus by 9.1")
    assert x["scale"] == pytest.approx(0.3153 * (1 - 0.045))
    html = render_html(report, tmp_path)
    assert check_html(html, report) == []
    table = html[html.index('id="outlier-images"') :].split("</table>")[0]
    assert "dive_001.jpg" in table and "Direct 3D" in table
    assert make_report(outlier=False)["diagnostics"]["outlier_images"] == []
    head = make_report(outlier=True)
    head["scale"] = dict(head["methods"]["direct3d"])
    annotate(head)
    assert head["diagnostics"]["outlier_images"][0]["headline"] is True
