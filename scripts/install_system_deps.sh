#!/usr/bin/env bash
# System libraries sfm-laserscale needs at run time (shared by the Makefile and docker/Dockerfile).
# Open3D's wheel links libusb-1.0.so.0 (Debian package libusb-1.0-0) and libgomp1.
set -u
pkgs=(libusb-1.0-0 libgomp1)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
  echo "sfm-laserscale: missing system libraries (${missing[*]}) and no apt-get here; install them with your package manager." >&2
  exit 1
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1; then SUDO="sudo"; else
    echo "sfm-laserscale: need root to install ${missing[*]} (run: apt-get install ${missing[*]})." >&2; exit 1; fi
fi
echo "Installing system libraries: ${missing[*]}"
if ! { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"; } >/dev/null; then
  echo "sfm-laserscale: could not install ${missing[*]} with apt-get; Open3D will not import without libusb-1.0.so.0." >&2
  exit 1
fi
