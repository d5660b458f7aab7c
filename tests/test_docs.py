"""The repository's own reference docs hold what the code does: the example rig files load,
every docs/ file the code and docs name exists, docs/OUTPUTS.md names every command, option and
report.json key a real run writes."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sfm_laserscale.cli import main
from sfm_laserscale.rig import load_rig, rig_from_dict

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"


def test_the_example_rig_file_loads() -> None:
    rig = load_rig(DOCS / "examples" / "rig.toml")
    assert rig.names == ["L1", "L2", "L3", "L4"]
    assert [p.lasers for p in rig.pairs] == [("L1", "L2"), ("L3", "L4")]
    l1, l2, l3, l4 = rig.lasers
    assert l1.color == "green" and l1.color_rgb is None  # a name
    assert l2.color == "green" and l2.color_spec == "532 nm"  # a wavelength, as a number
    assert l3.color_spec == "532 nm" and l3.color_rgb == l2.color_rgb  # the same, as a string
    assert l4.color == "green" and l4.color_rgb == (0.12, 1.0, 0.15)  # a triplet
    assert l1.sigma_origin == 0.0005 and l1.sigma_direction == 0.0003
    assert l3.origin is not None and l3.origin[2] == 0.0  # moved along the beam onto z = 0
    np.testing.assert_allclose(l3.origin, [0.117, 0.117, 0.0], atol=1e-12)
    assert not l4.calibrated and all(las.calibrated for las in (l1, l2, l3))


def test_every_toml_example_of_rig_md_is_a_valid_rig() -> None:
    blocks = re.findall(r"```toml\n(.*?)```", (DOCS / "RIG.md").read_text(encoding="utf-8"),
                        re.S)
    assert blocks
    for block in blocks:
        rig_from_dict(tomllib.loads(block), "docs/RIG.md")


def _text_files() -> list[Path]:
    roots = [REPO / "sfm_laserscale", REPO / "tests", REPO / "scripts", REPO / "plugins", DOCS]
    files = [p for r in roots for p in r.rglob("*") if p.suffix in (".py", ".md", ".sh")]
    return [*files, REPO / "README.md"]


def test_every_docs_file_named_exists_and_design_sections_too() -> None:
    design = (DOCS / "DESIGN.md").read_text(encoding="utf-8")
    sections = set(re.findall(r"^## (\d+)\.", design, re.M))
    missing = []
    for path in _text_files():
        text = path.read_text(encoding="utf-8")
        for name in set(re.findall(r"docs/([A-Za-z_/]+\.(?:md|toml))", text)):
            if not (DOCS / name).is_file():
                missing.append(f"{path.relative_to(REPO)}: docs/{name}")
        for n in set(re.findall(r"docs/DESIGN\.md §(\d+)", text)):
            if n not in sections:
                missing.append(f"{path.relative_to(REPO)}: docs/DESIGN.md §{n}")
    assert missing == []


def test_outputs_md_names_every_command_and_option() -> None:
    text = (DOCS / "OUTPUTS.md").read_text(encoding="utf-8")
    missing = []
    for name, command in main.commands.items():
        if f"## `{name}`" not in text:
            missing.append(f"section {name}")
        for param in command.params:
            for opt in param.opts:
                if opt.startswith("--") and opt not in text:
                    missing.append(f"{name} {opt}")
    assert missing == []


def _keys(block: dict[str, Any]) -> set[str]:
    return set(block)


def test_outputs_md_names_every_report_json_key(small_scale_run: Any) -> None:
    report = small_scale_run.report
    text = (DOCS / "OUTPUTS.md").read_text(encoding="utf-8")
    image = report["images"][0]
    keys = (_keys(report) | _keys(report["scale"]) | _keys(report["methods"])
            | _keys(report["methods"]["pcm_joint"]) | _keys(image) | _keys(image["spots"][0])
            | _keys(image["estimates"][0]) | _keys(report["diagnostics"])
            | _keys(report["timings_s"]) | _keys(report["model"]) | _keys(report["provenance"]))
    assert sorted(k for k in keys if f'"{k}"' not in text) == []


@pytest.mark.parametrize("doc", ["DESIGN.md", "RIG.md", "OUTPUTS.md", "REGISTRATION.md",
                                 "OPENMVG.md"])
def test_the_reference_docs_exist(doc: str) -> None:
    assert (DOCS / doc).stat().st_size > 1000
