"""report.html: one self-contained file (images embedded as data URIs, no script, no external
CSS or fonts) rendered from the report.json dict only, plus the overlay images it names.

Every number on the page is a ``<span class="num" data-key=… data-value=…>`` whose key is its
path in report.json (a JSON list) and whose value is the JSON value there; the page shows that
value formatted, so tests and :func:`sfm_laserscale.report.validate.check_html` can check it.
"""

from __future__ import annotations

import base64
import json
import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from jinja2 import (
    Environment,
    FileSystemBytecodeCache,
    PackageLoader,
    StrictUndefined,
    select_autoescape,
)
from jinja2.bccache import Bucket
from markupsafe import Markup

from sfm_laserscale.model_checks import ModelCheckOptions
from sfm_laserscale.report import format as fm
from sfm_laserscale.report.analysis import (
    METHOD_LABELS,
    METHOD_ORDER,
    annotate,
    pcm_joint_fell_back,
)
from sfm_laserscale.report.footprint_plot import footprint_histogram
from sfm_laserscale.report.model_plots import model_plots
from sfm_laserscale.report.plots import methods_plot, per_laser_method, per_laser_plot
from sfm_laserscale.report.style import laser_color_hex

logger = logging.getLogger(__name__)

#: The error budget's terms as the page names them.
BUDGET_LABELS = {"spots": "laser spots", "pose": "registered pose", "mesh": "mesh depth",
                 "rig": "rig calibration", "intrinsics": "model intrinsics (focal, distortion)",
                 "scatter": "observed scatter beyond σ", "random": "random (spots, pose, mesh)"}

Path_ = Sequence[str | int]


SVG_MIME = "image/svg+xml"


def data_uri(data: bytes, mime: str) -> str:
    """``data:<mime>;base64,...``"""
    return f"data:{mime};base64," + base64.b64encode(data).decode("ascii")


def lookup(report: dict[str, Any], path: Path_) -> Any:
    """The value at ``path`` (keys and list indices) of the report dict."""
    node: Any = report
    for part in path:
        node = node[part]
    return node


class _Numbers:
    """The template's number helper: ``n(path, kind)`` shows report[path] formatted."""

    def __init__(self, report: dict[str, Any]) -> None:
        self.report = report
        self.decimals = fm.scale_decimals(report)

    def text(self, value: Any, kind: str) -> str:
        d = self.decimals
        formats = {
            "scale": lambda v: fm.fixed(v, d),
            "inv": lambda v: fm.sig(v, 6),
            "int": lambda v: fm.DASH if v is None else str(int(v)),
            "pct": lambda v: fm.pct(v, 2),
            "spct": lambda v: fm.pct(v, 2, signed=True),
            "pct3": lambda v: fm.sig(v, 3),
            "f2": lambda v: fm.fixed(v, 2),
            "f1": lambda v: fm.fixed(v, 1),
            "sig3": lambda v: fm.sig(v, 3),
        }
        return formats[kind](value)

    def __call__(self, path: Path_, kind: str = "scale", cls: str = "") -> Markup:
        value = lookup(self.report, path)
        return fm.number(json.dumps(list(path)), value, self.text(value, kind), cls)


def find(seq: Sequence[dict[str, Any]], **match: Any) -> int | None:
    """Index of the first dict of ``seq`` whose items include ``match`` (None if none does)."""
    for i, item in enumerate(seq):
        if all(item.get(k) == v for k, v in match.items()):
            return i
    return None


def _overlays(report: dict[str, Any], out_dir: Path) -> dict[str, str | None]:
    """image name -> data URI of its overlay (None when the file named in report is missing)."""
    out: dict[str, str | None] = {}
    for im in report["images"]:
        rel = im.get("overlay")
        if not rel:
            continue
        path = out_dir / rel
        try:
            out[im["name"]] = data_uri(path.read_bytes(), "image/jpeg")
        except OSError as exc:
            logger.warning("overlay of %s not readable (%s): %s", im["name"], path, exc)
            out[im["name"]] = None
    return out


class _QuietBytecodeCache(FileSystemBytecodeCache):
    """Jinja's file cache of compiled templates, where any failure is a cache miss: a
    read-only, full or vanished folder or a damaged file costs the compile, never the report."""

    def load_bytecode(self, bucket: Bucket) -> None:
        try:
            super().load_bytecode(bucket)
        except Exception as exc:  # noqa: BLE001 - a bad cache entry only means recompiling
            logger.debug("template cache %s not used: %s", self.directory, exc)
            bucket.reset()

    def dump_bytecode(self, bucket: Bucket) -> None:
        try:
            super().dump_bytecode(bucket)
        except Exception as exc:  # noqa: BLE001 - the report does not need the cache
            logger.debug("template cache %s not written: %s", self.directory, exc)


def template_cache_dir() -> Path | None:
    """Folder of compiled report templates ($XDG_CACHE_HOME or ~/.cache, then
    sfm-laserscale/templates), or None where none can be made or written."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    folder = Path(base) / "sfm-laserscale" / "templates"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return folder if os.access(folder, os.W_OK | os.X_OK) else None


def _environment() -> Environment:
    # compiling report.html costs ~0.3 s per run, more than rendering it; the compiled code is
    # kept between runs (jinja checks the template source and its own version before reuse)
    cache_dir = template_cache_dir()
    env = Environment(
        loader=PackageLoader("sfm_laserscale", "report/templates"),
        bytecode_cache=None if cache_dir is None else _QuietBytecodeCache(str(cache_dir)),
        autoescape=select_autoescape(["html"]),
        undefined=StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["sig"] = fm.sig
    env.filters["pct"] = fm.pct
    return env


def render_html(report: dict[str, Any], out_dir: Path) -> str:
    """The HTML report for people; every number comes from ``report`` (report.json's dict)."""
    if "diagnostics" not in report:  # a report.json written before the derived keys existed
        report = annotate(json.loads(json.dumps(report)))
    plots = {"per_laser": per_laser_plot(report), "methods": methods_plot(report),
             "footprints": footprint_histogram(report)}
    plots.update(model_plots(report))  # the model checks' plots (report/model_plots.py)
    methods = [m for m in METHOD_ORDER if m in report["methods"]]
    methods += [m for m in report["methods"] if m not in methods]
    lasers = list(report["rig"]["lasers"])
    return (
        _environment()
        .get_template("report.html")
        .render(
            r=report,
            n=_Numbers(report),
            overlays=_overlays(report, out_dir),
            plots={k: None if v is None else data_uri(v, SVG_MIME) for k, v in plots.items()},
            methods=methods,
            labels=METHOD_LABELS,
            lasers=lasers,
            colors={name: laser_color_hex(i) for i, name in enumerate(lasers)},
            pairs=["+".join(p) for p in report["rig"]["pairs"]],
            find=find,
            fell_back=pcm_joint_fell_back,
            plot_method=per_laser_method(report),
            budget_labels=BUDGET_LABELS,
            th_model_z=ModelCheckOptions().z_limit,
        )
    )


__all__ = ["data_uri", "lookup", "render_html"]
