"""What a lab checks before adopting the package (issue #20): the licence file matches the
metadata, the citation file cites the tool at its version and the method's paper, every
third-party module the package imports is a declared dependency, matplotlib is optional with a
clear message, and the package's version is one string."""

from __future__ import annotations

import ast
import importlib.metadata
import sys
import tomllib
from pathlib import Path

import pytest
from click.testing import CliRunner
from packaging.requirements import Requirement

import sfm_laserscale
from sfm_laserscale.cli import main

REPO = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def test_licence_file_matches_the_metadata() -> None:
    assert PROJECT["license"] == "BSD-3-Clause"
    text = (REPO / "LICENSE").read_text()
    assert text.startswith("BSD 3-Clause License")
    assert "Neither the name of the copyright holder" in text  # the third clause


def _cff_fields() -> dict[str, str]:
    fields: dict[str, str] = {}
    for line in (REPO / "CITATION.cff").read_text(encoding="utf-8").splitlines():
        key, sep, value = line.strip().partition(": ")
        if sep and not key.startswith("#"):
            fields.setdefault(key.lstrip("- "), value.strip('"'))
    return fields


def test_citation_file() -> None:
    fields = _cff_fields()
    assert fields["cff-version"] == "1.2.0" and fields["type"] == "software"
    assert fields["version"] == sfm_laserscale.__version__
    assert fields["license"] == PROJECT["license"]
    assert fields["doi"] == "10.1016/j.isprsjprs.2019.10.007"  # Istenič et al. 2020
    assert fields["journal"] == "ISPRS Journal of Photogrammetry and Remote Sensing"
    assert "Istenič" in (REPO / "CITATION.cff").read_text(encoding="utf-8")
    assert "## Unreleased" in (REPO / "CHANGELOG.md").read_text()


def _third_party_imports() -> set[str]:
    """Top-level names of every module the package imports that is not its own or stdlib."""
    names: set[str] = set()
    for path in (REPO / "sfm_laserscale").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n != "sfm_laserscale"}


def test_every_imported_package_is_declared() -> None:
    """Pillow, MarkupSafe, jsonschema ... are imported, so they are dependencies of their own
    (not only through other packages)."""
    declared = {Requirement(r).name.lower().replace("_", "-")
                for r in PROJECT["dependencies"] + PROJECT["optional-dependencies"]["simulate"]}
    providers = importlib.metadata.packages_distributions()
    missing = {}
    for module in sorted(_third_party_imports()):
        dists = {d.lower().replace("_", "-") for d in providers.get(module, [])}
        assert dists, f"no installed distribution provides {module}"
        if not dists & declared:
            missing[module] = sorted(dists)
    assert missing == {}, f"imported but not declared in pyproject.toml: {missing}"
    for name in ("pillow", "markupsafe", "jsonschema"):
        assert name in declared
    assert "matplotlib" not in {Requirement(r).name for r in PROJECT["dependencies"]}


def test_simulate_without_matplotlib_says_how_to_install_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    result = CliRunner().invoke(main, ["simulate", "--out", str(tmp_path / "s"), "--mode",
                                       "random", "--trials", "10"])
    assert result.exit_code == 2, result.output
    assert "sfm-laserscale[simulate]" in result.stderr and "matplotlib" in result.stderr
    assert not (tmp_path / "s").exists()


def test_version_is_one_string() -> None:
    assert PROJECT["dynamic"] == ["version"] and "version" not in PROJECT
    assert importlib.metadata.version("sfm-laserscale") == sfm_laserscale.__version__
    out = CliRunner().invoke(main, ["--version"]).output
    assert out == f"sfm-laserscale, version {sfm_laserscale.__version__}\n"
