"""docker/Dockerfile (parsed with the `dockerfile` package: no Docker engine runs here) and the
one install script that the Dockerfile and the Makefile share, run with stub system tools."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path
from typing import Any

import pytest

dockerfile = pytest.importorskip("dockerfile", reason="the test extra 'dockerfile' is missing")

REPO = Path(__file__).resolve().parents[1]
DOCKERFILE = REPO / "docker" / "Dockerfile"
INSTALL = "scripts/install.sh"
Commands = tuple[Any, ...]  # dockerfile.Command records


@pytest.fixture(scope="module")
def commands() -> Commands:
    return dockerfile.parse_file(str(DOCKERFILE))


def _runs(commands: Commands) -> list[str]:
    return [c.value[0] for c in commands if c.cmd == "RUN"]


def test_base_image_and_entrypoint(commands: Commands) -> None:
    froms = [c for c in commands if c.cmd == "FROM"]
    assert len(froms) == 1 and froms[0].value[0] == "python:3.11-slim-bookworm"
    entry = [c for c in commands if c.cmd == "ENTRYPOINT"]
    assert len(entry) == 1 and entry[0].json and entry[0].value == ("sfm-laserscale",)
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["sfm-laserscale"] == "sfm_laserscale.cli:main"


def test_docker_and_make_run_the_same_install_script(commands: Commands) -> None:
    runs = _runs(commands)
    installs = [r for r in runs if f"bash {INSTALL}" in r]
    assert len(installs) == 1
    # the script is the only way anything gets installed in the image
    assert not [r for r in runs if re.search(r"pip install|apt-get|apt install", r)]
    makefile = (REPO / "Makefile").read_text()
    recipe = re.search(r"^\$\(STAMP\):(.*)\n((?:\t.*\n)+)", makefile, re.M)
    assert recipe is not None
    assert INSTALL in recipe.group(1), "the install stamp depends on the script"
    assert f"bash {INSTALL}" in recipe.group(2)
    assert "pip install" not in makefile and "apt-get" not in makefile
    assert (REPO / INSTALL).is_file()


def test_install_runs_after_every_file_it_needs_is_copied(commands: Commands) -> None:
    copied: list[str] = []
    for c in commands:
        if c.cmd == "COPY":
            *sources, _ = c.value
            for src in sources:
                assert (REPO / src).exists(), f"COPY source {src} missing from the repository"
            copied += sources
        if c.cmd == "RUN" and INSTALL in c.value[0]:
            break
    for needed in ("pyproject.toml", "README.md", "sfm_laserscale", "scripts", "plugins"):
        assert needed in copied, needed


def test_docker_readme_runs_the_image_with_a_mounted_data_folder() -> None:
    text = (REPO / "docker" / "README.md").read_text()
    assert "docker build -f docker/Dockerfile" in text
    run = re.search(r"docker run [^\n]*-v \"?\$PWD/[^:]+:/data[^\n]*sfm-laserscale", text)
    assert run is not None
    workdirs = [c.value[0] for c in dockerfile.parse_file(str(DOCKERFILE)) if c.cmd == "WORKDIR"]
    assert workdirs[-1] == "/data", "relative paths in `docker run` resolve in the mount"


# --------------------------------------------------------------------------- install.sh logic


def _stub_env(tmp: Path, *, root: bool, installed: set[str], apt_ok: set[str]) -> dict[str, str]:
    """PATH with stub dpkg-query / apt-get / id / python3 and the few real tools the script
    uses; no sudo. The stubs log their calls to tmp/calls.log."""
    stubs = tmp / "bin"
    stubs.mkdir()
    log = tmp / "calls.log"
    for tool in ("grep", "dirname", "mktemp", "cat", "tail", "rm", "sed"):
        real = shutil.which(tool)
        assert real is not None
        (stubs / tool).symlink_to(real)
    inst = " ".join(installed)
    ok = " ".join(apt_ok)
    scripts = {
        "dpkg-query": f'p="${{@: -1}}"; case " {inst} " in *" $p "*) '
                      f'echo "install ok installed";; *) exit 1;; esac',
        "apt-get": f'echo "apt-get $*" >> "{log}"; [ "$1" = update ] && exit 0; '
                   f'p="${{@: -1}}"; case " {ok} " in *" $p "*) exit 0;; *) exit 100;; esac',
        "id": f'echo {0 if root else 1000}',
        "python3": f'echo "python3 $*" >> "{log}"',
    }
    for name, body in scripts.items():
        (stubs / name).write_text(f"#!{shutil.which('bash')}\n{body}\n")
        (stubs / name).chmod(0o755)
    return {"PATH": str(stubs), "HOME": str(tmp)}


def _install(tmp: Path, env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([shutil.which("bash") or "bash", str(REPO / INSTALL), *args], env=env,
                          capture_output=True, text=True, timeout=60)


def test_install_without_root_says_what_to_run(tmp_path: Path) -> None:
    env = _stub_env(tmp_path, root=False, installed=set(), apt_ok=set())
    proc = _install(tmp_path, env)
    assert proc.returncode == 1
    assert "apt-get install libusb-1.0-0 libgomp1" in proc.stderr and "root" in proc.stderr
    assert not (tmp_path / "calls.log").exists(), "nothing installed, no pip run"


def test_install_fails_clearly_when_apt_cannot_install(tmp_path: Path) -> None:
    env = _stub_env(tmp_path, root=True, installed={"libgomp1"}, apt_ok=set())
    proc = _install(tmp_path, env)
    assert proc.returncode == 1 and "could not install libusb-1.0-0" in proc.stderr
    assert "libusb-1.0.so.0" in proc.stderr


def test_install_colmap_is_optional(tmp_path: Path) -> None:
    env = _stub_env(tmp_path, root=True, installed={"libgomp1"}, apt_ok={"libusb-1.0-0"})
    proc = _install(tmp_path, env, "--colmap", "--extras", "test")
    assert proc.returncode == 0, proc.stderr
    assert "WARNING: could not install Debian's colmap" in proc.stderr
    calls = (tmp_path / "calls.log").read_text().splitlines()
    assert calls[0] == "apt-get update -qq", "apt-get update once, before the first install"
    assert sum(c.startswith("apt-get update") for c in calls) == 1
    assert any("install" in c and c.endswith("libusb-1.0-0") for c in calls)
    assert any("install" in c and c.endswith("colmap") for c in calls)
    pip = [c for c in calls if c.startswith("python3 -m pip install")]
    assert pip == [f"python3 -m pip install -q {REPO}[test]"]
    assert calls[-1] == "python3 -c import open3d, pycolmap, cv2"


def test_install_with_everything_present_touches_no_package(tmp_path: Path) -> None:
    env = _stub_env(tmp_path, root=False, installed={"libusb-1.0-0", "libgomp1", "colmap"},
                    apt_ok=set())
    proc = _install(tmp_path, env, "--colmap", "--editable")
    assert proc.returncode == 0, proc.stderr
    calls = (tmp_path / "calls.log").read_text().splitlines()
    assert not [c for c in calls if c.startswith("apt-get")]
    assert f"python3 -m pip install -q -e {REPO}" in calls


def test_install_script_is_valid_bash() -> None:
    assert subprocess.run(["bash", "-n", str(REPO / INSTALL)], timeout=30).returncode == 0
    assert os.access(REPO / INSTALL, os.X_OK)
