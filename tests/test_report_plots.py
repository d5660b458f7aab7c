"""The report's SVG plots: ticks, and every marker where its value says (read back through
the drawn axis), outliers as labelled arrows, a page check that accepts and rejects SVG."""

from __future__ import annotations

import base64
import math
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from sfm_laserscale.report.html import data_uri, render_html
from sfm_laserscale.report.plots import methods_plot, per_laser_plot
from sfm_laserscale.report.svgchart import nice_ticks, text_width, tick_labels
from sfm_laserscale.report.validate import check_html, image_problem
from tests.test_report import make_report

SVG = "{http://www.w3.org/2000/svg}"


def test_nice_ticks_known_answers() -> None:
    assert nice_ticks(0.0, 1.0) == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
    assert nice_ticks(-1.08, 1.08) == pytest.approx([-1.0, -0.5, 0.0, 0.5, 1.0])
    assert nice_ticks(0.31467, 0.31633) == pytest.approx(
        [0.31475 + 0.00025 * k for k in range(7)])
    assert nice_ticks(3.0, 3.0) == [3.0]
    assert nice_ticks(-4.7, 0.2, max_ticks=5) == pytest.approx([-4.0, -3.0, -2.0, -1.0, 0.0])
    assert nice_ticks(-4.7, 0.2, max_ticks=2) == pytest.approx([-2.5, 0.0])
    for lo, hi in ((1e-7, 3e-7), (-250.0, 1e4), (0.3, 0.30001)):
        t = nice_ticks(lo, hi)
        assert 3 <= len(t) <= 9 and lo <= t[0] and t[-1] <= hi
        assert np.allclose(np.diff(t), t[1] - t[0])


def test_tick_labels_share_decimals_and_use_minus() -> None:
    assert tick_labels([0.31475, 0.315, 0.31525]) == ["0.31475", "0.31500", "0.31525"]
    assert tick_labels([-1.0, -0.5, 0.0, 0.5]) == ["\u22121.0", "\u22120.5", "0.0", "0.5"]
    assert tick_labels([-2.0, 0.0, 2.0]) == ["\u22122", "0", "2"]
    assert tick_labels([-1e-17, 0.25]) == ["0.00", "0.25"]  # no "−0.00"


def _translate(el: ET.Element) -> tuple[float, float]:
    m = re.fullmatch(r"translate\(([-\d.]+) ([-\d.]+)\)", el.get("transform", ""))
    assert m is not None
    return float(m.group(1)), float(m.group(2))


def _panels(svg: bytes) -> list[ET.Element]:
    root = ET.fromstring(svg)
    assert root.tag == f"{SVG}svg"
    return root.findall(f"{SVG}g[@class='panel']")


def _axis(panel: ET.Element) -> tuple[float, float]:
    """(value per user unit, value at y = 0) fitted to the drawn tick labels (exact line)."""
    ticks = [(float(t.get("y", "nan")), float(t.text.replace("\u2212", "-")))  # type: ignore[union-attr]
             for t in panel.iter(f"{SVG}text") if t.get("class") == "ytick"]
    assert len(ticks) >= 3
    ys, vals = np.array(ticks).T
    slope, icpt = np.polyfit(ys, vals, 1)
    assert np.allclose(slope * ys + icpt, vals, atol=abs(slope) * 0.02)
    return slope, icpt


def _markers(panel: ET.Element) -> list[tuple[str, float, float]]:
    """(kind, value it carries, value read at its drawn position) per data marker; the kind
    of an arrow for a value off the axis is "beyond"."""
    slope, icpt = _axis(panel)
    out = []
    for g in panel.iter(f"{SVG}g"):
        role = g.get("class", "").split()
        if "marker" in role:
            _, y = _translate(g)
            kind = "beyond" if "outlier" in role else g.get("data-kind", "")
            out.append((kind, float(g.get("data-value", "nan")), slope * y + icpt))
    return out


def test_per_laser_plot_draws_every_estimate_where_it_is() -> None:
    report = make_report()
    top, dev = _panels(per_laser_plot(report) or b"")
    slope, _ = _axis(top)
    shown = _markers(top)
    expected = [e["scale"] for im in report["images"] for e in im["estimates"]
                if e["method"] == "fcm" and e["scale"] is not None]
    expected += [im["fused"]["fcm"]["scale"] for im in report["images"]
                 if im.get("fused", {}).get("fcm", {}).get("scale") is not None]
    inside = [(k, v, at) for k, v, at in shown if k != "beyond"]
    assert sorted(v for _, v, _ in shown) == pytest.approx(sorted(expected))
    for _, value, at in inside:  # drawn at its value, to 0.02 of a user unit
        assert at == pytest.approx(value, abs=abs(slope) * 0.02)
    crosses = [v for k, v, _ in shown if k == "x"]
    assert len(crosses) == sum(1 for im in report["images"] if im.get("fused", {}).get("fcm"))
    devs = _markers(dev)
    expected_dev = [d for im in report["images"] for d in im.get("deviation_pct", {}).values()
                    if d is not None]
    assert sorted(v for _, v, _ in devs) == pytest.approx(sorted(expected_dev))


def test_methods_plot_outlier_is_a_labelled_arrow_at_the_edge() -> None:
    report = make_report(outlier=True)
    svg = methods_plot(report) or b""
    (panel,) = _panels(svg)
    head = report["scale"]["value"]
    arrows = [(v, at) for k, v, at in _markers(panel) if k == "beyond"]
    left_out = [100.0 * (f["scale"] / head - 1.0) for im in report["images"]
                for f in im["fused"].values() if not f["used"] and f["scale"] is not None]
    assert left_out and sorted(v for v, _ in arrows) == pytest.approx(sorted(left_out))
    texts = [t.text for t in panel.iter(f"{SVG}text") if t.get("class") == "outlier"]
    assert texts == [f"{v:+.2f} %".replace("-", "\u2212") for v, _ in arrows]
    others = [(v, at) for k, v, at in _markers(panel) if k != "beyond"]
    lo, hi = min(at for _, at in others), max(at for _, at in others)
    for value, at in arrows:  # at the axis edge, beyond every value drawn inside
        assert value < at <= lo or value > at >= hi
    slope, _ = _axis(panel)
    assert all(at == pytest.approx(v, abs=abs(slope) * 0.02) for v, at in others)


def test_long_image_names_are_slanted_and_pair_only_plot_has_one_panel() -> None:
    report = make_report(n_images=9, failed=0)
    for i, im in enumerate(report["images"]):
        im["name"] = f"dive_2026_11_25_cam0_{i:05d}.jpg"
    root = ET.fromstring(per_laser_plot(report) or b"")
    labels = [t for t in root.iter(f"{SVG}text") if t.get("class") == "xtick"]
    assert [t.text for t in labels] == [im["name"] for im in report["images"]]
    assert all("rotate(-35" in t.get("transform", "") for t in labels)
    assert float(root.get("height", "0")) >= max(float(t.get("y", "0")) for t in labels)
    first = labels[0]  # its slanted text ends at its tick and does not leave the picture
    assert float(first.get("x", "0")) - text_width(first.text or "") * math.cos(
        math.radians(35)) >= 0.0
    for im in report["images"]:
        im["estimates"] = [e for e in im["estimates"] if e["method"] != "fcm"]
    assert len(_panels(per_laser_plot(report) or b"")) == 1


def test_page_check_accepts_the_svg_plots_and_names_broken_ones(tmp_path: Path) -> None:
    report = make_report()
    html = render_html(report, tmp_path)
    assert html.count('src="data:image/svg+xml;base64,') == 2
    assert check_html(html, report) == []
    svg = per_laser_plot(report) or b""
    assert image_problem(data_uri(svg, "image/svg+xml")) is None
    broken = data_uri(svg[: len(svg) // 2], "image/svg+xml")
    assert (image_problem(broken) or "").startswith("image/svg+xml does not parse")
    empty = b'<svg xmlns="http://www.w3.org/2000/svg"><title>t</title></svg>'
    assert image_problem(data_uri(empty, "image/svg+xml")) == "image/svg+xml draws nothing"
    html_svg = html.replace(data_uri(svg, "image/svg+xml"), broken, 1)
    (problem,) = check_html(html_svg, report)
    assert problem.startswith("image 'per-laser': image/svg+xml does not parse")
    assert base64.b64decode(broken.split(",", 1)[1]) == svg[: len(svg) // 2]


def test_report_rendering_does_not_import_matplotlib(tmp_path: Path) -> None:
    """The report's plots need no plotting library (it cost ~0.9 s and ~38 MB per run)."""
    code = (
        "import sys, json\n"
        "from tests.test_report import make_report\n"
        "from sfm_laserscale.report.html import render_html\n"
        f"html = render_html(make_report(), __import__('pathlib').Path({str(tmp_path)!r}))\n"
        "assert 'data:image/svg+xml' in html\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'matplotlib'))\n"
    )
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True,
                         text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout

