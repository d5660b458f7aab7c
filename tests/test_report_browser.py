"""report.html in a real headless browser (Debian's chromium): it loads without console errors,
every image decodes, nothing overflows the page; screenshots go to test-artifacts/."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from test_report import make_report, write_overlays

from sfm_laserscale.report.html import render_html
from sfm_laserscale.report.validate import check_html

CHROMIUM = Path("/usr/bin/chromium")
REPO = Path(__file__).resolve().parents[1]
ARTIFACTS = REPO / "test-artifacts"

pytestmark = pytest.mark.skipif(
    not CHROMIUM.is_file(),
    reason="/usr/bin/chromium not installed (Debian package 'chromium'; optional test)",
)

# Injected into a COPY of the page (the report itself has no script): after load, record which
# images the browser could not decode and whether the page, a table or an image card overflows
# sideways at the window's width.
_PROBE = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var bad = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); })
    .map(function (i) {
      return i.getAttribute('data-overlay') || i.getAttribute('data-plot') || i.alt; });
  var b = document.body;
  b.setAttribute('data-probe-images', String(imgs.length));
  b.setAttribute('data-probe-broken', JSON.stringify(bad));
  var wide = document.documentElement.scrollWidth > window.innerWidth + 1;
  Array.prototype.forEach.call(document.querySelectorAll('.scroll, .card'), function (e) {
    if (e.scrollWidth > e.clientWidth + 1) { wide = true; } });
  b.setAttribute('data-probe-overflow', String(wide));
  b.setAttribute('data-probe-height', String(document.documentElement.scrollHeight));
});
</script>"""

_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--enable-logging=stderr",
    "--v=0",
]


def _chromium(page: Path, profile: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    cmd = [str(CHROMIUM), *_FLAGS, f"--user-data-dir={profile}", *extra, page.as_uri()]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)


def console_messages(stderr: str) -> list[str]:
    """Console output and uncaught JavaScript errors in chromium's log."""
    return [ln for ln in stderr.splitlines() if ":CONSOLE" in ln or "Uncaught" in ln]


def browse(
    html: str, work: Path, screenshot: Path | None = None, size: str = "1400,3000"
) -> dict[str, Any]:
    """Load the page (with the probe) in chromium: the probe's findings, console messages and
    the DOM after load; optionally a screenshot of the page itself (no probe)."""
    work.mkdir(parents=True, exist_ok=True)
    probe = work / "probe.html"
    probe.write_text(html.replace("</body>", _PROBE + "</body>"), encoding="utf-8")
    res = _chromium(
        probe, work / "profile", f"--window-size={size}", "--virtual-time-budget=5000", "--dump-dom"
    )
    body = re.search(r"<body([^>]*)>", res.stdout)
    attrs = dict(re.findall(r'(data-probe-[a-z]+)="([^"]*)"', body.group(1) if body else ""))
    out = {
        "returncode": res.returncode,
        "console": console_messages(res.stderr),
        "images": int(attrs.get("data-probe-images", "-1")),
        "broken": json.loads(attrs.get("data-probe-broken", "null").replace("&quot;", '"')),
        "overflow": attrs.get("data-probe-overflow"),
        "height": int(attrs.get("data-probe-height", "0")),
        "dom": res.stdout,
    }
    if screenshot is not None:
        page = work / "report.html"
        page.write_text(html, encoding="utf-8")
        shot = _chromium(
            page, work / "profile", f"--window-size={size}", f"--screenshot={screenshot}"
        )
        out["console"] += console_messages(shot.stderr)
    return out


def _check_screenshot(path: Path, height: int | None = None) -> None:
    img = cv2.imread(str(path))
    assert img is not None, f"no screenshot at {path}"
    assert img.shape[1] == 1400
    assert height is None or img.shape[0] == height
    assert float(img.std()) > 20.0  # not a blank page


@pytest.fixture(scope="module")
def artifacts() -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS


def test_hand_made_report_in_chromium(tmp_path: Path, artifacts: Path) -> None:
    report = make_report(n_images=6, bias={"L3": 0.021}, mma=0.02, fallback=True, residual_deg=5.2)
    write_overlays(report, tmp_path)
    html = render_html(report, tmp_path)
    shot = artifacts / "report_hand_made.png"
    got = browse(html, tmp_path / "browser", shot)
    assert got["returncode"] == 0
    assert got["console"] == []
    assert got["images"] == 2 + len(report["images"])
    assert got["broken"] == []
    assert got["overflow"] == "false"
    # the DOM the browser built still shows every number as report.json holds it
    assert check_html(got["dom"], report) == []
    _check_screenshot(shot)


def test_browser_catches_a_broken_image(tmp_path: Path) -> None:
    report = make_report(n_images=3, failed=0)
    write_overlays(report, tmp_path)
    html = render_html(report, tmp_path)
    victim = report["images"][1]["name"]
    html = re.sub(
        rf'(data-overlay="{re.escape(victim)}"[^>]*src=")data:[^"]*"',
        r'\1data:image/jpeg;base64,/9j/AAAA"',
        html,
    )
    got = browse(html, tmp_path / "browser")
    assert got["broken"] == [victim]
    assert any(victim in p for p in check_html(html, report))


def test_browser_reports_script_errors(tmp_path: Path) -> None:
    """The console check can fail: a page with a script error is caught."""
    report = make_report(n_images=2, failed=0)
    bad = "<script>noSuchFunction()</script></main>"
    html = render_html(report, tmp_path).replace("</main>", bad)
    got = browse(html, tmp_path / "browser")
    assert any("noSuchFunction" in m for m in got["console"])


def test_real_run_report_in_chromium(small_scale_run: Any, tmp_path: Path, artifacts: Path) -> None:
    run = Path(small_scale_run.out_dir)
    report = json.loads((run / "report.json").read_text())
    html = (run / "report.html").read_text()
    shot = artifacts / "report_real_run.png"
    got = browse(html, tmp_path / "browser", shot, size="1400,3000")
    assert got["returncode"] == 0
    assert got["console"] == []
    assert got["broken"] == []
    plots = 2 + (report.get("footprints") is not None)  # per-laser, methods, footprints
    assert got["images"] == plots + sum(1 for im in report["images"] if im["overlay"])
    assert got["overflow"] == "false"
    assert check_html(got["dom"], report) == []
    _check_screenshot(shot)
    # the whole page too (the probe measured its height), kept with the page itself
    height = min(got["height"], 20000)
    full = artifacts / "report_real_run_full.png"
    browse(html, tmp_path / "browser_full", full, size=f"1400,{height}")
    _check_screenshot(full, height)
    shutil.copy(run / "report.html", artifacts / "report_real_run.html")
    # the overlays are not blank photographs: they carry the drawn legend strip
    first = next(iter(sorted((run / "overlays").glob("*.jpg"))))
    img = cv2.imread(str(first))
    assert img is not None and np.mean(img[-10:]) < 60
