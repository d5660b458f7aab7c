#!/usr/bin/env bash
# OpenMVG + OpenMVS reconstruction with the laser images held out, then the metric scale from
# sfm-laserscale, then OpenMVS's scene rescaled with TransformScene. See README.md beside it.
#
# usage: openmvg_openmvs_laserscale.sh IMAGES LASER_IMAGES RIG OUT
#
#   IMAGES        folder of the survey images (laser images found in it by name are held out)
#   LASER_IMAGES  folder of the laser images
#   RIG           the laser rig (TOML)
#   OUT           output folder: images_sfm/ sfm/ (OpenMVG) mvs/ (OpenMVS) scale/ (ours)
#
# Camera intrinsics for openMVG_main_SfMInit_ImageListing, one of (environment):
#   INTRINSICS_K="fx;0;cx;0;fy;cy;0;0;1"   calibrated camera, OpenMVG pixel convention
#                                          (cx_openmvg = cx_colmap - 0.5)
#   FOCAL_PX=1200                          focal length in pixels
#   CAMERA_DB=sensor_width_camera_database.txt   EXIF + sensor width database
# Optional: OPENMVG_BIN, OPENMVS_BIN (folders of the tools; default: found on PATH),
#   SFM_LASERSCALE (default: sfm-laserscale), SCALE_ARGS (more `scale` options, e.g.
#   "--method fcm --spots spots.csv").
#
# Exit status: 0 done; 1 a tool failed or no scale could be estimated; 2 bad usage.
set -euo pipefail

die() { echo "openmvg_openmvs_laserscale: $1" >&2; exit "${2:-2}"; }
run() { echo "+ $*" >&2; "$@" || die "$1 failed (exit $?)" 1; }
mvg() { local tool=$1; shift; run "${OPENMVG_BIN:+$OPENMVG_BIN/}$tool" "$@"; }
mvs() { local tool=$1; shift; run "${OPENMVS_BIN:+$OPENMVS_BIN/}$tool" "$@"; }

[ $# -eq 4 ] || die "usage: $0 IMAGES LASER_IMAGES RIG OUT"
if [ -n "${INTRINSICS_K:-}" ]; then listing=(-k "$INTRINSICS_K")
elif [ -n "${FOCAL_PX:-}" ]; then listing=(-f "$FOCAL_PX")
elif [ -n "${CAMERA_DB:-}" ]; then listing=(-d "$CAMERA_DB")
else die "set INTRINSICS_K, FOCAL_PX or CAMERA_DB (camera intrinsics for OpenMVG)"; fi
[ -d "$1" ] || die "images folder not found: $1"
[ -d "$2" ] || die "laser images folder not found: $2"
[ -f "$3" ] || die "rig file not found: $3"
images=$(cd "$1" && pwd)
laser=$(cd "$2" && pwd)
rig="$(cd "$(dirname "$3")" && pwd)/$(basename "$3")"
mkdir -p "$4"
out=$(cd "$4" && pwd)
sfm="$out/sfm"
matches="$sfm/matches"
scene="$out/mvs"

# 1. the SfM input: every survey image except the laser images (their spots would corrupt it)
rm -rf "$out/images_sfm"
mkdir -p "$out/images_sfm" "$matches" "$scene"
for f in "$images"/*; do
  [ -f "$f" ] || continue
  name=${f##*/}
  if [ -e "$laser/$name" ]; then echo "holding out laser image $name" >&2; continue; fi
  ln -s "$f" "$out/images_sfm/$name"
done

# 2. OpenMVG: incremental SfM (v2.x tool names; sfm_data.json is what sfm-laserscale reads)
mvg openMVG_main_SfMInit_ImageListing -i "$out/images_sfm" -o "$matches" "${listing[@]}"
mvg openMVG_main_ComputeFeatures -i "$matches/sfm_data.json" -o "$matches" -m SIFT
mvg openMVG_main_PairGenerator -i "$matches/sfm_data.json" -o "$matches/pairs.bin"
mvg openMVG_main_ComputeMatches -i "$matches/sfm_data.json" -p "$matches/pairs.bin" \
  -o "$matches/matches.putative.bin"
mvg openMVG_main_GeometricFilter -i "$matches/sfm_data.json" -m "$matches/matches.putative.bin" \
  -o "$matches/matches.f.bin"
mvg openMVG_main_SfM -s INCREMENTAL -i "$matches/sfm_data.json" -m "$matches" -o "$sfm"
mvg openMVG_main_ConvertSfM_DataFormat -i "$sfm/sfm_data.bin" -o "$sfm/sfm_data.json"

# 3. OpenMVS: dense cloud, mesh, refined and textured mesh (same frame as sfm_data)
mvg openMVG_main_openMVG2openMVS -i "$sfm/sfm_data.bin" -o "$scene/scene.mvs" -d "$scene/images"
mvs DensifyPointCloud scene.mvs -w "$scene"
mvs ReconstructMesh scene_dense.mvs -w "$scene"
mvs RefineMesh scene_dense_mesh.mvs -w "$scene"
mvs TextureMesh scene_dense_mesh_refine.mvs -w "$scene"

# 4. sfm-laserscale: the scale, the rescaled sfm_data and mesh, transform files, report
# (the OpenMVG regions are found in sfm/matches/, beside sfm/sfm_data.json)
# shellcheck disable=SC2086  # SCALE_ARGS holds several words on purpose
run "${SFM_LASERSCALE:-sfm-laserscale}" scale --model "$sfm/sfm_data.json" \
  --mesh "$scene/scene_dense_mesh_refine_texture.ply" --laser-images "$laser" --rig "$rig" \
  --out "$out/scale" --overwrite ${SCALE_ARGS:-}

# 5. the whole OpenMVS scene (cameras, dense cloud, mesh) made metric
mvs TransformScene scene_dense_mesh_refine_texture.mvs \
  --transform-file "$out/scale/transform_4x4.txt" -o scene_metric.mvs -w "$scene"
echo "metric model: $out/scale/scaled/  metric OpenMVS scene: $scene/scene_metric.mvs" >&2
