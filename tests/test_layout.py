"""The package's layout (docs/DESIGN.md §5): no import cycle (imports inside functions and under
``TYPE_CHECKING`` count), io/ imports only io/ and the shared types, no module over 800 lines,
a module in commands/ for every command of the CLI. Each checker is also run on a small fake
package with the fault it looks for, so every test here can fail."""

from __future__ import annotations

import ast
from collections.abc import Iterable
from pathlib import Path

import pytest

from sfm_laserscale.cli import main

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "sfm_laserscale"
MAX_LINES = 800
#: what io/ may import of the package: io/ itself and the shared types
IO_MAY_IMPORT = ("io", "model", "errors", "geometry")


def module_files(package_dir: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package (packages: __init__.py)."""
    root = package_dir.parent
    out = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _resolve(name: str, modules: Iterable[str]) -> str | None:
    """The module an import of ``name`` loads: the longest module prefix of ``name``."""
    known = set(modules)
    while name and name not in known:
        name = name.rpartition(".")[0]
    return name or None


def _imported_names(node: ast.Import | ast.ImportFrom, module: str, is_package: bool) -> list[str]:
    """Dotted names an import statement of ``module`` refers to (``from a import b``: a.b)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:  # relative: from the module's package, one level up per extra dot
        parts = module.split(".") if is_package else module.split(".")[:-1]
        parts = parts[:len(parts) - (node.level - 1)]
        base = ".".join(parts + ([node.module] if node.module else []))
    return [f"{base}.{a.name}" for a in node.names] + [base]


def import_graph(package_dir: Path) -> dict[str, set[str]]:
    """Module -> the package's modules it imports, from every import statement of the module:
    at the top, inside functions and under ``if TYPE_CHECKING``."""
    files = module_files(package_dir)
    package = package_dir.name
    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.Import | ast.ImportFrom):
                continue
            names = _imported_names(node, module, path.name == "__init__.py")
            if isinstance(node, ast.ImportFrom):  # from a import b: module a.b, else a
                names = [n for n in names[:-1] if n in files] or names[-1:]
            for name in names:
                if name == package or name.startswith(package + "."):
                    target = _resolve(name, files)
                    if target is not None and target != module:
                        deps.add(target)
        graph[module] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles: strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def layering_violations(graph: dict[str, set[str]], layer: str,
                        allowed: Iterable[str]) -> list[str]:
    """``a -> b`` for every import of a module of ``layer`` (a dotted prefix) outside
    ``allowed`` (dotted prefixes)."""
    prefixes = tuple(allowed)

    def inside(name: str, prefix: str) -> bool:
        return name == prefix or name.startswith(prefix + ".")

    return [f"{a} -> {b}" for a in sorted(graph) if inside(a, layer)
            for b in sorted(graph[a]) if not any(inside(b, p) for p in prefixes)]


def long_modules(package_dir: Path, max_lines: int) -> list[str]:
    """``file: n lines`` for every module longer than ``max_lines``."""
    out = []
    for path in module_files(package_dir).values():
        n = len(path.read_text(encoding="utf-8").splitlines())
        if n > max_lines:
            out.append(f"{path.relative_to(package_dir.parent)}: {n} lines")
    return out


def cli_commands_without_module(package_dir: Path, commands: Iterable[str]) -> list[str]:
    """CLI commands with no ``commands/<name>.py``, or whose click function does not import it
    (cli.py is a thin layer over the command modules)."""
    package = package_dir.name
    tree = ast.parse((package_dir / "cli.py").read_text(encoding="utf-8"))
    functions = {f.name: f for f in tree.body if isinstance(f, ast.FunctionDef)}
    missing = []
    for name in commands:
        module = f"{package}.commands.{name}"
        if not (package_dir / "commands" / f"{name}.py").is_file():
            missing.append(f"{name}: no commands/{name}.py")
            continue
        fn = functions.get(name)
        imports = {n.module for n in ast.walk(fn) if isinstance(n, ast.ImportFrom)} if fn else set()
        if module not in imports:
            missing.append(f"{name}: cli.{name} does not import {module}")
    return missing


# ----------------------------------------------------------------------------- the package


def test_no_import_cycle() -> None:
    assert cycles(import_graph(PACKAGE_DIR)) == []


def test_io_imports_only_io_and_the_shared_types() -> None:
    allowed = [f"sfm_laserscale.{m}" for m in IO_MAY_IMPORT]
    assert layering_violations(import_graph(PACKAGE_DIR), "sfm_laserscale.io", allowed) == []


def test_no_module_over_800_lines() -> None:
    assert long_modules(PACKAGE_DIR, MAX_LINES) == []


def test_every_cli_command_has_its_module_in_commands() -> None:
    assert sorted(main.commands) == ["apply", "batch", "calibrate", "colmap", "demo", "detect",
                                     "mesh", "openmvg", "scale", "simulate"]
    assert cli_commands_without_module(PACKAGE_DIR, main.commands) == []


def test_the_graph_sees_the_imports_it_must() -> None:
    """Spot checks against known imports, so an empty graph cannot pass the tests above."""
    graph = import_graph(PACKAGE_DIR)
    assert "sfm_laserscale.report.writer" in graph["sfm_laserscale.commands.scale"]
    assert "sfm_laserscale.run_types" in graph["sfm_laserscale.report.writer"]
    assert "sfm_laserscale.io.colmap" in graph["sfm_laserscale.io.models"]
    # inside a function: cli's commands import their modules lazily
    assert "sfm_laserscale.commands.scale" in graph["sfm_laserscale.cli"]


# ----------------------------------------------------------------------------- the checkers


def _fake_package(root: Path, files: dict[str, str]) -> Path:
    package_dir = root / "fakepkg"
    for name, text in {"__init__.py": "", **files}.items():
        path = package_dir / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return package_dir


def test_cycles_through_function_level_and_type_checking_imports_are_found(
        tmp_path: Path) -> None:
    package_dir = _fake_package(tmp_path, {
        "a.py": "def f():\n    from fakepkg.b import g\n    return g\n",
        "b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from fakepkg import a\n"
                "def g():\n    pass\n",
        "c.py": "from . import d\n",
        "d.py": "import fakepkg.c\n",
        "e.py": "from fakepkg.a import f\n",
    })
    assert cycles(import_graph(package_dir)) == [["fakepkg.a", "fakepkg.b"],
                                                 ["fakepkg.c", "fakepkg.d"]]


def test_layering_violations_are_found(tmp_path: Path) -> None:
    package_dir = _fake_package(tmp_path, {
        "io/__init__.py": "", "io/x.py": "from fakepkg.io.y import z\nfrom fakepkg import model\n",
        "io/y.py": "z = 1\ndef late():\n    from fakepkg.stage import s\n",
        "model.py": "", "stage.py": "s = 1\n",
    })
    graph = import_graph(package_dir)
    assert layering_violations(graph, "fakepkg.io", ["fakepkg.io", "fakepkg.model"]) == [
        "fakepkg.io.y -> fakepkg.stage"]


def test_long_modules_are_found(tmp_path: Path) -> None:
    package_dir = _fake_package(tmp_path, {"short.py": "x = 1\n" * MAX_LINES,
                                           "long.py": "x = 1\n" * (MAX_LINES + 1)})
    assert long_modules(package_dir, MAX_LINES) == [f"fakepkg/long.py: {MAX_LINES + 1} lines"]


@pytest.mark.parametrize("cli_body, expected", [
    ("def scale():\n    from fakepkg.commands.scale import run\n", []),
    ("def scale():\n    from fakepkg.pipeline import run\n",
     ["scale: cli.scale does not import fakepkg.commands.scale"]),
])
def test_commands_without_module_are_found(tmp_path: Path, cli_body: str,
                                           expected: list[str]) -> None:
    package_dir = _fake_package(tmp_path, {"cli.py": cli_body, "commands/__init__.py": "",
                                           "commands/scale.py": "def run():\n    pass\n"})
    assert cli_commands_without_module(package_dir, ["scale"]) == expected
    assert cli_commands_without_module(package_dir, ["detect"]) == ["detect: no commands/detect.py"]
