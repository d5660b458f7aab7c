"""Checks of a rendered report.html against its report.json dict (stdlib HTML parser).

- every ``<img>`` holds a non-empty PNG or JPEG data URI that decodes, or an SVG one that
  parses and draws something;
- every overlay named in report.json is on the page, the per-laser plot is there whenever an
  image has an estimate to plot, and the methods plot whenever there is a scale and an image
  has a per-image value of a method;
- every number ``<span data-key=… data-value=…>`` holds the value at that path of report.json,
  and its text shows that value (to the number of decimals displayed).
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import re
import xml.etree.ElementTree as ET
from html.parser import HTMLParser
from typing import Any

import cv2
import numpy as np

_MAGIC = {"image/png": b"\x89PNG\r\n\x1a\n", "image/jpeg": b"\xff\xd8\xff"}
_NUMBER = re.compile(r"^[+\-−]?\d+(?:\.(\d+))?$")


class _Collector(HTMLParser):
    """Collects <img> attributes and the numbers' keys, values and texts."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.images: list[dict[str, str]] = []
        self.numbers: list[tuple[str, str, str]] = []
        self.missing: list[str] = []
        self._open: list[list[str]] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: (v or "") for k, v in attrs}
        if tag == "img":
            self.images.append(a)
        if "data-missing-overlay" in a:
            self.missing.append(a["data-missing-overlay"])
        if tag == "span" and "data-key" in a:
            self._open = [[a["data-key"], a.get("data-value", ""), ""]]

    def handle_data(self, data: str) -> None:
        if self._open is not None:
            self._open[0][2] += data

    def handle_endtag(self, tag: str) -> None:
        if tag == "span" and self._open is not None:
            key, value, text = self._open[0]
            self.numbers.append((key, value, text.strip()))
            self._open = None


def parse_report_html(html: str) -> _Collector:
    """The page's images and numbers."""
    c = _Collector()
    c.feed(html)
    c.close()
    return c


def decode_data_uri(src: str) -> tuple[str, bytes]:
    """(mime, bytes) of a base64 data URI; ValueError when it is not one."""
    m = re.match(r"^data:(image/[a-z+]+);base64,(.*)$", src, re.S)
    if m is None:
        raise ValueError("not a base64 image data URI")
    try:
        data = base64.b64decode(m.group(2), validate=True)
    except (binascii.Error, ValueError) as exc:
        raise ValueError(f"bad base64 ({exc})") from exc
    return m.group(1), data


def _svg_problem(data: bytes) -> str | None:
    """Why SVG bytes are not a drawable SVG document (None when they are)."""
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        return f"image/svg+xml does not parse ({exc})"
    if root.tag != "{http://www.w3.org/2000/svg}svg":
        return "image/svg+xml has no <svg> root"
    if not any(el.tag.rsplit("}", 1)[-1] not in ("title", "desc") for el in root):
        return "image/svg+xml draws nothing"
    return None


def image_problem(src: str) -> str | None:
    """Why a data URI is not a decodable PNG/JPEG or a drawable SVG (None when it is)."""
    if not src:
        return "empty src"
    try:
        mime, data = decode_data_uri(src)
    except ValueError as exc:
        return str(exc)
    if mime == "image/svg+xml":
        return _svg_problem(data)
    magic = _MAGIC.get(mime)
    if magic is None:
        return f"unexpected type {mime}"
    if not data.startswith(magic):
        return f"data is not {mime}"
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        return f"{mime} does not decode"
    return None


def _lookup(report: Any, path: list[Any]) -> Any:
    node = report
    for part in path:
        node = node[part]
    return node


def number_problem(report: dict[str, Any], key: str, value: str, text: str) -> str | None:
    """Why a number span disagrees with report.json (None when it agrees)."""
    try:
        path = json.loads(key)
        expected = _lookup(report, path)
    except (ValueError, KeyError, IndexError, TypeError):
        return f"number {key}: no such path in report.json"
    if json.loads(value) != expected:
        return f"number {key}: data-value {value} != report.json {expected!r}"
    if expected is None or isinstance(expected, bool) or not isinstance(expected, (int, float)):
        return None if text in ("–", str(expected)) else f"number {key}: shows {text!r}"
    m = _NUMBER.match(text)
    if m is None:
        return f"number {key}: text {text!r} is not a plain number"
    shown = float(text.replace("−", "-"))
    decimals = len(m.group(1) or "")
    tol = 0.5 * 10.0 ** (-decimals) * (1 + 1e-9) + 1e-12 * abs(expected)
    if not math.isfinite(shown) or abs(shown - expected) > tol:
        return f"number {key}: shows {text} but report.json holds {expected!r}"
    return None


def _expected_plot(report: dict[str, Any]) -> bool:
    return any(
        e["method"] in ("fcm", "pcm") and e["scale"] is not None
        for im in report["images"]
        for e in im["estimates"]
    )


def _expected_methods_plot(report: dict[str, Any]) -> bool:
    value = report["scale"].get("value")
    if not isinstance(value, (int, float)) or not math.isfinite(value):
        return False
    return any(
        f.get("scale") is not None
        for im in report["images"]
        for m, f in im.get("fused", {}).items()
        if m in ("fcm", "pcm", "direct3d")
    )


def check_html(html: str, report: dict[str, Any]) -> list[str]:
    """Problems of a rendered report (empty list: the page is complete and agrees with json)."""
    page = parse_report_html(html)
    problems = []
    for img in page.images:
        why = image_problem(img.get("src", ""))
        if why is not None:
            what = img.get("data-overlay") or img.get("data-plot") or img.get("alt", "?")
            problems.append(f"image {what!r}: {why}")
    shown = {img.get("data-overlay") for img in page.images if img.get("data-overlay")}
    for im in report["images"]:
        if im.get("overlay") and im["name"] not in shown:
            problems.append(f"overlay of {im['name']} missing ({im['overlay']})")
    plots = {img.get("data-plot") for img in page.images}
    if _expected_plot(report) and "per-laser" not in plots:
        problems.append("per-laser plot missing")
    if _expected_methods_plot(report) and "methods" not in plots:
        problems.append("methods plot missing")
    for key, value, text in page.numbers:
        why = number_problem(report, key, value, text)
        if why is not None:
            problems.append(why)
    return problems


__all__ = ["check_html", "decode_data_uri", "image_problem", "parse_report_html"]
