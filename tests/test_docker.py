"""docker/Dockerfile (parsed with the `dockerfile` package: no Docker engine runs here), the
one install script that the Dockerfile and the Makefile share, run with stub system tools, and
requirements.lock (issue #20: non-root user, tini, layer order, locked dependencies, the
version label)."""

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
    assert len(entry) == 1 and entry[0].json
    assert entry[0].value == ("/usr/bin/tini", "--", "sfm-laserscale")  # signals forwarded
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["sfm-laserscale"] == "sfm_laserscale.cli:main"


def test_docker_and_make_run_the_same_install_script(commands: Commands) -> None:
    runs = _runs(commands)
    installs = [r for r in runs if f"bash {INSTALL}" in r]
    assert len(installs) == 2  # the locked dependencies, then the package
    assert all("--locked" in r for r in installs)
    assert "--deps-only" in installs[0] and "--tini" in installs[0]
    # the script is the only way anything gets installed in the image
    assert not [r for r in runs if re.search(r"pip install|apt-get|apt install", r)]
    makefile = (REPO / "Makefile").read_text()
    recipe = re.search(r"^\$\(STAMP\):(.*)\n((?:\t.*\n)+)", makefile, re.M)
    assert recipe is not None
    assert INSTALL in recipe.group(1), "the install stamp depends on the script"
    assert "requirements.lock" in recipe.group(1), "... and on the lock file"
    assert f"bash {INSTALL}" in recipe.group(2) and "--locked" in recipe.group(2)
    assert "pip install" not in makefile and "apt-get" not in makefile
    assert (REPO / INSTALL).is_file()


def _copies_before(commands: Commands, run_index: int) -> list[str]:
    """COPY sources before the ``run_index``-th RUN of the install script."""
    copied: list[str] = []
    seen = 0
    for c in commands:
        if c.cmd == "COPY":
            *sources, _ = c.value
            for src in sources:
                assert (REPO / src).exists(), f"COPY source {src} missing from the repository"
            copied += sources
        if c.cmd == "RUN" and INSTALL in c.value[0]:
            if seen == run_index:
                return copied
            seen += 1
    raise AssertionError(f"no install RUN number {run_index}")


def test_install_runs_after_every_file_it_needs_is_copied(commands: Commands) -> None:
    # the dependencies' layer needs only the script and the lock: code edits keep it
    assert sorted(_copies_before(commands, 0)) == sorted([INSTALL, "requirements.lock"])
    copied = _copies_before(commands, 1)
    for needed in ("pyproject.toml", "README.md", "LICENSE", "sfm_laserscale", "scripts",
                   "plugins"):
        assert needed in copied, needed


def test_image_runs_as_a_user_not_root(commands: Commands) -> None:
    users = [(i, c.value[0]) for i, c in enumerate(commands) if c.cmd == "USER"]
    assert users and users[-1][1] not in ("root", "0", "0:0")
    last_run = max(i for i, c in enumerate(commands) if c.cmd == "RUN")
    assert users[-1][0] > last_run, "nothing runs as root after the USER line"
    useradd = [r for r in _runs(commands) if "useradd" in r]
    assert useradd and users[-1][1] in useradd[0]


def test_image_label_carries_the_package_version(commands: Commands) -> None:
    from sfm_laserscale import __version__

    args = dict(a.split("=", 1) for c in commands if c.cmd == "ARG" for a in c.value if "=" in a)
    assert args["VERSION"] == __version__
    labels = [c.value for c in commands if c.cmd == "LABEL"]
    flat = {k: v.strip('"') for k, v in zip(labels[0][::2], labels[0][1::2], strict=True)}
    assert flat["org.opencontainers.image.version"] == "${VERSION}"
    assert flat["org.opencontainers.image.licenses"] == "BSD-3-Clause"
    # and the build fails if the installed package says another version
    assert any("--version" in r and "${VERSION}" in r for r in _runs(commands))


def test_lock_pins_every_dependency_with_hashes() -> None:
    from packaging.requirements import Requirement

    text = (REPO / "requirements.lock").read_text()
    pattern = r"^([A-Za-z0-9_.\-]+)==([^\s;]+)([^\\\n]*)\\\n((?:\s+--hash=\S+\s*\\?\n?)+)"
    blocks = re.findall(pattern, text, re.M)
    pins = {name.lower(): version for name, version, _, _ in blocks}
    assert len(pins) > 30
    assert all("--hash=sha256:" in hashes for *_, hashes in blocks)
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    deps = [Requirement(d) for d in project["dependencies"]]
    deps += [Requirement(d) for d in project["optional-dependencies"]["simulate"]]
    for req in deps:
        name = req.name.lower()
        assert name in pins, f"{name} is not in requirements.lock: regenerate it"
        assert req.specifier.contains(pins[name]), f"{name}=={pins[name]} breaks {req}"
    marker = {name.lower(): rest for name, _, rest, _ in blocks}
    assert "sys_platform == 'linux'" in marker["open3d-cpu"]


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


def test_locked_install_takes_the_lock_then_the_package_alone(tmp_path: Path) -> None:
    env = _stub_env(tmp_path, root=False, installed={"libusb-1.0-0", "libgomp1", "tini"},
                    apt_ok=set())
    proc = _install(tmp_path, env, "--locked", "--tini")
    assert proc.returncode == 0, proc.stderr
    pip = [c for c in (tmp_path / "calls.log").read_text().splitlines()
           if c.startswith("python3 -m pip install")]
    assert pip == [f"python3 -m pip install -q --require-hashes -r {REPO}/requirements.lock",
                   f"python3 -m pip install --no-deps -q {REPO}"]


def test_deps_only_installs_the_lock_alone(tmp_path: Path) -> None:
    env = _stub_env(tmp_path, root=True, installed={"libgomp1"},
                    apt_ok={"libusb-1.0-0", "tini"})
    proc = _install(tmp_path, env, "--deps-only", "--tini")
    assert proc.returncode == 0, proc.stderr
    calls = (tmp_path / "calls.log").read_text().splitlines()
    assert any("install" in c and c.endswith("tini") for c in calls)
    pip = [c for c in calls if c.startswith("python3 -m pip install")]
    assert pip == [f"python3 -m pip install -q --require-hashes -r {REPO}/requirements.lock"]


def _stub_venv(tmp: Path, fail_on: str = "") -> Path:
    """A venv folder whose python logs its calls and fails those holding ``fail_on``."""
    py = tmp / "venv" / "bin" / "python"
    py.parent.mkdir(parents=True)
    fail = f'case "$*" in *"{fail_on}"*) exit 1;; esac' if fail_on else ""
    py.write_text(f"#!{shutil.which('bash')}\necho \"venv $*\" >> \"{tmp / 'calls.log'}\"\n"
                  f"{fail}\n")
    py.chmod(0o755)
    return py


def _venv_installs(tmp: Path, fail_on: str = "") -> tuple[subprocess.CompletedProcess[str],
                                                           list[str]]:
    env = _stub_env(tmp, root=False, installed={"libusb-1.0-0", "libgomp1"}, apt_ok=set())
    py = _stub_venv(tmp, fail_on)
    proc = _install(tmp, env, "--venv", str(py.parents[1]), "--locked", "--extras", "test",
                    "--editable")
    calls = [c.replace(str(py), "PY") for c in (tmp / "calls.log").read_text().splitlines()
             if c.startswith("venv") and " install " in c]
    return proc, calls


LOCK_ARGS = f"-q --require-hashes -r {REPO}/requirements.lock"
UV = "venv -m uv pip install --python PY --compile-bytecode"


def test_venv_install_goes_through_uv(tmp_path: Path) -> None:
    proc, calls = _venv_installs(tmp_path)
    assert proc.returncode == 0, proc.stderr
    uv = re.search(r"^UV_VERSION=(\S+)$", (REPO / INSTALL).read_text(), re.M)
    assert uv is not None
    assert calls == ["venv -m pip install -q --upgrade pip",
                     f"venv -m pip install -q uv=={uv.group(1)}",
                     f"{UV} {LOCK_ARGS}",
                     f"{UV} -q -e {REPO}[test]"]
    assert "WARNING" not in proc.stderr


def test_venv_install_falls_back_to_pip_when_uv_fails(tmp_path: Path) -> None:
    proc, calls = _venv_installs(tmp_path, fail_on="-m uv ")
    assert proc.returncode == 0, proc.stderr
    assert calls[3:] == [f"venv -m pip install {LOCK_ARGS}",
                         f"{UV} -q -e {REPO}[test]",
                         f"venv -m pip install -q -e {REPO}[test]"]
    assert proc.stderr.count("WARNING: uv could not install") == 2


def test_venv_install_without_uv_uses_pip_alone(tmp_path: Path) -> None:
    proc, calls = _venv_installs(tmp_path, fail_on="install -q uv==")
    assert proc.returncode == 0, proc.stderr
    assert "WARNING: could not install uv" in proc.stderr
    assert not [c for c in calls if "-m uv " in c]
    assert calls[2:] == [f"venv -m pip install {LOCK_ARGS}",
                         f"venv -m pip install -q -e {REPO}[test]"]


def test_install_script_is_valid_bash() -> None:
    assert subprocess.run(["bash", "-n", str(REPO / INSTALL)], timeout=30).returncode == 0
    assert os.access(REPO / INSTALL, os.X_OK)
