#!/usr/bin/env bash
# The ONE install script of sfm-laserscale: `make install` (Makefile) and docker/Dockerfile
# both run it, so a clean clone, CI and the Docker image are set up the same way.
#
#   1. Debian/Ubuntu system libraries: libusb-1.0-0 (Open3D's wheel links libusb-1.0.so.0)
#      and libgomp1; with --colmap also Debian's `colmap` (3.8 on bookworm, CPU only; about
#      15 s and 42 packages here). colmap is optional: if it cannot be installed the script
#      only warns (the tests that need it skip, the COLMAP plugin falls back to pycolmap).
#      With --browser also Debian's `chromium` (optional, for the report's headless-browser
#      test; the test skips when it is absent).
#      With --tini also Debian's `tini` (the container's init: forwards signals, reaps).
#   2. the Python package with the given extras: into --venv DIR (created when missing) or
#      into the Python given by --python (default python3), editable with --editable.
#      With --locked, every dependency first comes from requirements.lock (exact versions and
#      hashes, `pip install --require-hashes`), so the environment is the one the image and
#      the tests were made with; --deps-only installs only those (the image's first layer).
#      An environment holding Open3D's full wheel gets the CPU-only build instead on Linux
#      x86-64 (the two share the package's files: the old one is removed first).
#      Into a venv, the packages come through uv's pip (uv itself pinned; pip when uv cannot
#      be installed or fails); into an interpreter given by --python, through pip.
#   3. a check that Open3D, pycolmap and OpenCV import.
#
# usage: scripts/install.sh [--venv DIR] [--python PY] [--extras LIST] [--editable] [--colmap]
#                           [--browser] [--tini] [--locked] [--deps-only]
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VENV="" PY=python3 EXTRAS="" EDITABLE=0 COLMAP=0 BROWSER=0 TINI=0 LOCKED=0 DEPS_ONLY=0
LOCK="$ROOT/requirements.lock"
while [ $# -gt 0 ]; do
  case "$1" in
    --venv) VENV=$2; shift 2 ;;
    --python) PY=$2; shift 2 ;;
    --extras) EXTRAS=$2; shift 2 ;;
    --editable) EDITABLE=1; shift ;;
    --colmap) COLMAP=1; shift ;;
    --browser) BROWSER=1; shift ;;
    --tini) TINI=1; shift ;;
    --locked) LOCKED=1; shift ;;
    --deps-only) LOCKED=1; DEPS_ONLY=1; shift ;;
    -h|--help) sed -n '2,24p' "$0"; exit 0 ;;
    *) echo "install.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done

say() { echo "sfm-laserscale install: $*" >&2; }

missing_packages() {  # the Debian packages among "$@" that are not installed
  local p
  for p in "$@"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || echo "$p"
  done
}

SUDO=""
APT_READY=0
apt_possible() {  # 0 when apt-get can install here (as root or through sudo)
  command -v apt-get >/dev/null 2>&1 && command -v dpkg-query >/dev/null 2>&1 || return 1
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null 2>&1 || return 1
    SUDO="sudo"
  fi
}

apt_install() {  # apt-get install "$@" (apt-get update once first); output only on failure
  local log
  log=$(mktemp)
  if [ "$APT_READY" -eq 0 ]; then
    $SUDO apt-get update -qq >"$log" 2>&1 || { cat "$log" >&2; rm -f "$log"; return 1; }
    APT_READY=1
  fi
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "$@" \
    >"$log" 2>&1 || { tail -n 20 "$log" >&2; rm -f "$log"; return 1; }
  rm -f "$log"
}

install_system() {
  local required optional
  if ! command -v dpkg-query >/dev/null 2>&1; then
    say "not a Debian/Ubuntu system: make sure libusb-1.0 and libgomp (OpenMP) are installed" \
        "with your package manager (Open3D does not import without libusb-1.0.so.0)"
    return 0
  fi
  mapfile -t required < <(missing_packages libusb-1.0-0 libgomp1)
  if [ ${#required[@]} -gt 0 ]; then
    if ! apt_possible; then
      say "missing system libraries (${required[*]}) and no root/sudo to install them:" \
          "run  apt-get install ${required[*]}  as root, then this again"
      exit 1
    fi
    say "installing system libraries: ${required[*]}"
    apt_install "${required[@]}" || {
      say "could not install ${required[*]} with apt-get; Open3D will not import without" \
          "libusb-1.0.so.0"; exit 1; }
  fi
  [ "$COLMAP" -eq 0 ] || install_optional colmap \
    "the tests that need the colmap CLI will skip and the COLMAP plugin will use pycolmap"
  [ "$BROWSER" -eq 0 ] || install_optional chromium \
    "the report's headless-browser test will skip"
  [ "$TINI" -eq 0 ] || install_optional tini \
    "run the container with docker run --init so that signals reach sfm-laserscale"
}

install_optional() {  # install_optional PACKAGE CONSEQUENCE: apt-get install, warn on failure
  local missing
  mapfile -t missing < <(missing_packages "$1")
  [ ${#missing[@]} -gt 0 ] || return 0
  if apt_possible && { say "installing Debian's $1 (optional)"; apt_install "$1"; }; then
    return 0
  fi
  say "WARNING: could not install Debian's $1; $2"
}

cpu_open3d() {  # 0 where the pins choose open3d-cpu (Linux x86-64; bash's own variables)
  [[ "$OSTYPE" == linux* && "$HOSTTYPE" == x86_64 ]]
}

switch_to_cpu_open3d() {  # an environment made before the switch: the full wheel out first
  local py=$1
  cpu_open3d && "$py" -m pip show -q open3d >/dev/null 2>&1 || return 0
  say "replacing Open3D's full wheel (with CUDA) by open3d-cpu, the same version"
  "$py" -m pip uninstall -q -y open3d open3d-cpu
}

UV_VERSION=0.13.9
USE_UV=0

use_uv_in_venv() {  # a venv of our own installs through uv's pip (below) when uv installs
  if "$1" -m pip install -q "uv==$UV_VERSION"; then
    USE_UV=1
  else
    say "WARNING: could not install uv $UV_VERSION; installing with pip (slower)"
  fi
}

pip_install() {  # pip_install PY ARGS...: `pip install ARGS` through uv when USE_UV, else pip
  local py=$1; shift
  if [ "$USE_UV" -eq 1 ]; then
    # --compile-bytecode: as pip does (uv does not by default); without the .pyc files every
    # process compiles the modules it imports again where PYTHONDONTWRITEBYTECODE is set
    "$py" -m uv pip install --python "$py" --compile-bytecode "$@" && return 0
    say "WARNING: uv could not install ($*); trying pip"
  fi
  "$py" -m pip install "$@"
}

install_python() {
  local py spec
  if [ -n "$VENV" ]; then
    [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
    py="$VENV/bin/python"
    "$py" -m pip install -q --upgrade pip
    # uv installs the same pinned, hashed wheels as pip in about half the time (a fresh
    # .venv: 38 s against 69 s), which a clean clone's `make test` pays on every CI run. Only
    # in a venv of our own: an interpreter given by --python (the Docker image's) keeps pip.
    use_uv_in_venv "$py"
  else
    py="$PY"
  fi
  switch_to_cpu_open3d "$py"
  if [ "$LOCKED" -eq 1 ]; then
    [ -f "$LOCK" ] || { say "no lock file $LOCK"; exit 1; }
    pip_install "$py" -q --require-hashes -r "$LOCK"
  fi
  if [ "$DEPS_ONLY" -eq 0 ]; then
    spec="$ROOT"
    [ -z "$EXTRAS" ] || spec="$ROOT[$EXTRAS]"
    local flags=(-q)
    [ "$EDITABLE" -eq 0 ] || flags+=(-e)
    # locked: the dependencies are in place; only the extras' own packages may come in
    [ "$LOCKED" -eq 0 ] || [ -n "$EXTRAS" ] || flags=(--no-deps "${flags[@]}")
    pip_install "$py" "${flags[@]}" "$spec"
  fi
  "$py" -c "import open3d, pycolmap, cv2" || {
    say "Open3D/pycolmap/OpenCV failed to import: see the message above (Open3D needs" \
        "Debian's libusb-1.0-0)"; exit 1; }
}

install_system
install_python
say "done"
