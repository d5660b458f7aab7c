#!/usr/bin/env bash
# OpenMVG + OpenMVS reconstruction with the laser images held out, then the metric scale, then
# OpenMVS's scene rescaled with TransformScene: kept for existing scripts, it runs
# `sfm-laserscale openmvg` (sfm_laserscale/commands/openmvg.py). See README.md beside it.
#
# usage: openmvg_openmvs_laserscale.sh IMAGES LASER_IMAGES RIG OUT
#
# Camera intrinsics (environment), one of: INTRINSICS_K="fx;0;cx;0;fy;cy;0;0;1" (OpenMVG
# pixels: cx = cx_colmap - 0.5), FOCAL_PX=1200, CAMERA_DB=sensor_width_camera_database.txt.
# Optional: OPENMVG_BIN, OPENMVS_BIN (folders of the tools; default: the PATH),
#   SFM_LASERSCALE (default: sfm-laserscale), SCALE_ARGS (more options, e.g. "--method fcm").
#
# Exit status: 0 done; 1 no scale could be estimated; 2 bad usage; 3 a bug; 4 a tool failed
# (the message names the step).
set -euo pipefail

die() { echo "openmvg_openmvs_laserscale: $1" >&2; exit "${2:-2}"; }

[ $# -eq 4 ] || die "usage: $0 IMAGES LASER_IMAGES RIG OUT"
if [ -n "${INTRINSICS_K:-}" ]; then intrinsics=(--intrinsics-k "$INTRINSICS_K")
elif [ -n "${FOCAL_PX:-}" ]; then intrinsics=(--focal-px "$FOCAL_PX")
elif [ -n "${CAMERA_DB:-}" ]; then intrinsics=(--camera-db "$CAMERA_DB")
else die "set INTRINSICS_K, FOCAL_PX or CAMERA_DB (camera intrinsics for OpenMVG)"; fi
bins=()
[ -n "${OPENMVG_BIN:-}" ] && bins+=(--openmvg-bin "$OPENMVG_BIN")
[ -n "${OPENMVS_BIN:-}" ] && bins+=(--openmvs-bin "$OPENMVS_BIN")

# shellcheck disable=SC2086  # SCALE_ARGS holds several words on purpose
exec "${SFM_LASERSCALE:-sfm-laserscale}" openmvg --images "$1" --laser-images "$2" --rig "$3" \
  --out "$4" --overwrite "${intrinsics[@]}" "${bins[@]}" ${SCALE_ARGS:-}
