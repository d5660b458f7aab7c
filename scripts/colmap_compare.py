#!/usr/bin/env python3
"""Register held-out images with sfm-laserscale and with COLMAP 3.8's own tools, side by side.

COLMAP: ``feature_extractor`` (the new images, the model's camera, CPU SIFT) →
``exhaustive_matcher`` (pairs already in the database are skipped) → ``image_registrator``
(intrinsics fixed). Ours:
``load_model`` + database descriptors + descriptor index + SIFT + ``register_image``, also in a
fresh process. Both wall times include process start-up. Poses are compared as the rotation
angle (degrees) and the camera-centre distance as a percentage of the model extent.

COLMAP 3.8 cannot add images to a pycolmap 4.x database (its ``images`` table lacks the prior
columns), so the demo's database is first copied into a database made by
``colmap database_creator`` (cameras, images, keypoints, descriptors, matches, two-view
geometries). Inputs are never touched: everything COLMAP may write is a copy (docs/DESIGN.md §6).

    .venv/bin/python scripts/colmap_compare.py --demo DIR --work DIR
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sqlite3
import subprocess
import sys
import time
from contextlib import closing
from pathlib import Path
from typing import Any

import numpy as np

COLMAP = shutil.which("colmap")
ENV = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}


def colmap(*args: str | Path) -> str:
    """Run a COLMAP 3.8 command (CPU); its output. Raises on a non-zero exit."""
    if COLMAP is None:
        raise RuntimeError("colmap CLI not installed (Debian: apt-get install colmap)")
    proc = subprocess.run([COLMAP, *map(str, args)], capture_output=True, text=True, env=ENV,
                          timeout=1800)
    if proc.returncode != 0:
        raise RuntimeError(f"colmap {args[0]} exit {proc.returncode}: {proc.stderr[-1500:]}")
    return proc.stdout + proc.stderr


def to_colmap38_database(src: Path, dst: Path) -> None:
    """Copy the rows COLMAP 3.8 needs from a pycolmap 4.x database into a 3.8 one."""
    colmap("database_creator", "--database_path", dst)
    with closing(sqlite3.connect(dst)) as con:
        con.execute("ATTACH DATABASE ? AS src", (f"file:{src}?mode=ro&immutable=1",))
        con.executescript("""
            INSERT INTO cameras SELECT camera_id, model, width, height, params,
                prior_focal_length FROM src.cameras;
            INSERT INTO images (image_id, name, camera_id)
                SELECT image_id, name, camera_id FROM src.images;
            INSERT INTO keypoints SELECT image_id, rows, cols, data FROM src.keypoints;
            INSERT INTO descriptors SELECT image_id, rows, cols, data FROM src.descriptors;
            INSERT INTO matches SELECT pair_id, rows, cols, data FROM src.matches;
            INSERT INTO two_view_geometries (pair_id, rows, cols, data, config, F, E, H, qvec,
                tvec) SELECT pair_id, rows, cols, data, config, F, E, H, qvec, tvec
                FROM src.two_view_geometries;
        """)
        con.commit()



def run_colmap(model: Path, database: Path, laser_dir: Path, work: Path,
               convert: bool) -> dict[str, Any]:
    """COLMAP 3.8's registration of the laser images; wall time per step and the poses."""
    from sfm_laserscale.io.colmap import read_colmap_model
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    db = work / "database.db"
    if convert:
        to_colmap38_database(database, db)
    else:
        shutil.copyfile(database, db)  # COLMAP may write (upgrade) it: a copy, never the input
    names = sorted(p.name for p in laser_dir.iterdir() if p.suffix.lower() in (".png", ".jpg"))
    (work / "list.txt").write_text("\n".join(names) + "\n")
    out = work / "registered"
    out.mkdir()
    times = {}
    t0 = time.perf_counter()
    colmap("feature_extractor", "--database_path", db, "--image_path", laser_dir,
           "--image_list_path", work / "list.txt", "--ImageReader.existing_camera_id", "1",
           "--SiftExtraction.use_gpu", "0")
    times["feature_extractor"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    colmap("exhaustive_matcher", "--database_path", db, "--SiftMatching.use_gpu", "0")
    times["exhaustive_matcher"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    log = colmap("image_registrator", "--database_path", db, "--input_path", model,
                 "--output_path", out, "--Mapper.ba_refine_focal_length", "0",
                 "--Mapper.ba_refine_principal_point", "0", "--Mapper.ba_refine_extra_params",
                 "0")
    times["image_registrator"] = time.perf_counter() - t2
    times["total"] = time.perf_counter() - t0
    poses: dict[str, Any] = {}
    if (out / "images.bin").is_file() or (out / "images.txt").is_file():
        rec = read_colmap_model(out)
        for im in rec.images.values():
            if im.name in names:
                poses[im.name] = {"R": im.cam_from_world.R.tolist(),
                                  "t": im.cam_from_world.t.tolist()}
    return {"seconds": {k: round(v, 3) for k, v in times.items()}, "poses": poses,
            "registered": len(poses), "n_images": len(names),
            "log_tail": log[-300:] if not poses else ""}


def ours_child(model: Path, database: Path, laser_dir: Path) -> dict[str, Any]:
    """Our registration of the laser images (run in a fresh process by run_ours)."""
    t0 = time.perf_counter()
    from sfm_laserscale.io.images import LaserImage, read_rgb
    from sfm_laserscale.io.models import load_model
    from sfm_laserscale.registration.features import load_model_features
    from sfm_laserscale.registration.index import build_descriptor_index
    from sfm_laserscale.registration.pose import register_image
    from sfm_laserscale.registration.sift import extract_sift
    from sfm_laserscale.registration.sift_workers import start_sift_pool
    from sfm_laserscale.run_types import ScaleOptions
    opts = ScaleOptions()
    t_import = time.perf_counter()
    m = load_model(model)
    cam = next(iter(m.cameras.values()))
    paths = [p for p in sorted(laser_dir.iterdir()) if p.suffix.lower() in (".png", ".jpg")]
    # as in ``scale``: worker processes extract SIFT while the index is built (COLMAP's
    # feature_extractor also uses every core)
    pool = start_sift_pool([LaserImage(p.name, p, cam) for p in paths], opts.sift,
                           opts.sift_workers)
    feats = load_model_features(m, model, database, None, None, opts.tie)
    index = build_descriptor_index(m, feats, opts.index)
    t_load = time.perf_counter()
    poses, sift_s, reg_s = {}, 0.0, 0.0
    for p in paths:
        a = time.perf_counter()
        rgb = read_rgb(p)
        f = extract_sift(rgb, opts.sift) if pool is None else pool.features(p, rgb)
        b = time.perf_counter()
        r = register_image(f, cam, index, opts.registration)
        reg_s += time.perf_counter() - b
        sift_s += b - a
        if r.success and r.cam_from_world is not None:
            poses[p.name] = {"R": r.cam_from_world.R.tolist(), "t": r.cam_from_world.t.tolist(),
                             "inliers": r.num_inliers}
    if pool is not None:
        pool.close()
    return {"seconds": {"import": t_import - t0, "load_index": t_load - t_import,
                        "sift": sift_s, "match_pose": reg_s,
                        "in_process": time.perf_counter() - t_import},
            "poses": poses, "index_method": index.method,
            "index_descriptors": index.num_descriptors}


def run_ours(model: Path, database: Path, laser_dir: Path) -> dict[str, Any]:
    """ours_child in a fresh interpreter; its result plus the process wall time."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--ours", str(model),
                           str(database), str(laser_dir)], capture_output=True, text=True,
                          timeout=1800)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-1500:])
    out: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    out["seconds"]["total"] = wall
    out["seconds"] = {k: round(v, 3) for k, v in out["seconds"].items()}
    return out


def pose_differences(a: dict[str, Any], b: dict[str, Any], extent: float) -> dict[str, Any]:
    """Per image in both: rotation angle (deg) and centre distance (% of extent)."""
    out = {}
    for name in sorted(set(a) & set(b)):
        Ra, Rb = np.asarray(a[name]["R"]), np.asarray(b[name]["R"])
        ca = -Ra.T @ np.asarray(a[name]["t"])
        cb = -Rb.T @ np.asarray(b[name]["t"])
        cos = np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1)
        out[name] = {"rotation_deg": round(float(np.degrees(np.arccos(cos))), 5),
                     "centre_pct_extent": round(float(100 * np.linalg.norm(ca - cb) / extent), 5)}
    return out


def truth_poses(truth_json: Path) -> dict[str, Any]:
    """The demo's true laser-image poses in the model frame."""
    from sfm_laserscale.geometry import rotmat_from_qvec
    truth = json.loads(truth_json.read_text())
    out = {}
    for im in truth["laser_images"]:
        p = im["cam_from_model"]
        out[im["name"]] = {"R": rotmat_from_qvec(np.asarray(p["rotation_wxyz"])).tolist(),
                           "t": p["translation"]}
    return out


def compare(model: Path, database: Path, laser_dir: Path, work: Path, convert: bool,
            truth_json: Path | None = None) -> dict[str, Any]:
    """Both registrations, wall-time ratio and pose differences (and against the truth)."""
    from sfm_laserscale.io.colmap import read_colmap_model
    extent = read_colmap_model(model).extent
    load = [round(v, 2) for v in os.getloadavg()]
    ours = run_ours(model, database, laser_dir)
    theirs = run_colmap(model, database, laser_dir, work, convert)
    res: dict[str, Any] = {
        "loadavg_before": load, "loadavg_after": [round(v, 2) for v in os.getloadavg()],
        "extent_model_units": extent, "ours": ours, "colmap": theirs,
        "time_ratio_colmap_over_ours": round(theirs["seconds"]["total"]
                                             / ours["seconds"]["total"], 2),
        "ours_vs_colmap": pose_differences(ours["poses"], theirs["poses"], extent),
    }
    if truth_json is not None:
        t = truth_poses(truth_json)
        res["ours_vs_truth"] = pose_differences(ours["poses"], t, extent)
        res["colmap_vs_truth"] = pose_differences(theirs["poses"], t, extent)
    return res


def strip_poses(res: dict[str, Any]) -> dict[str, Any]:
    """The comparison without the raw pose matrices (for printing)."""
    out = dict(res)
    for side in ("ours", "colmap"):
        out[side] = {k: v for k, v in res[side].items() if k != "poses"}
    return out


def compare_with_colmap(demo: Path, work: Path) -> dict[str, Any]:
    """The demo data set: model sparse/0, its database, its laser images, its truth."""
    return compare(demo / "sparse" / "0", demo / "database.db", demo / "laser_images",
                   work / "colmap_demo", convert=True, truth_json=demo / "truth.json")


def compare_fixture(fixture: Path, work: Path, held_out: str = "03.jpg") -> dict[str, Any]:
    """Real data (../shared/fixtures/maupertuis_colmap): hold one image out of the model and
    register it back from its database features (no extraction: the fixture's JPEGs are too
    compressed for a fresh SIFT, see the fixtures' README), by COLMAP's image_registrator and by
    our matching + pose; both poses against each other and against the original pose."""
    from sfm_laserscale.io.colmap import model_without_images, read_colmap_model
    from sfm_laserscale.io.colmap_database import read_database_features
    from sfm_laserscale.io.colmap_write import write_colmap_model_binary
    from sfm_laserscale.registration.index import build_descriptor_index
    from sfm_laserscale.registration.pose import register_image
    from sfm_laserscale.run_types import ScaleOptions
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    for f in fixture.iterdir():  # COLMAP may write the database: copies only (docs/DESIGN.md §6)
        if f.name.startswith("colmap.db"):
            shutil.copyfile(f, work / f.name)
    model = read_colmap_model(fixture / "reconstruction")
    orig = model.image_by_name(held_out)
    assert orig is not None
    write_colmap_model_binary(model_without_images(model, [held_out]), work / "model")
    t0 = time.perf_counter()
    opts = ScaleOptions()
    held = read_colmap_model(work / "model")
    feats = read_database_features(work / "colmap.db")
    index = build_descriptor_index(held, feats, opts.index)
    reg = register_image(feats[held_out], model.cameras[orig.camera_id], index, opts.registration)
    ours_s = time.perf_counter() - t0
    out = work / "registered"
    out.mkdir()
    t1 = time.perf_counter()
    colmap("image_registrator", "--database_path", work / "colmap.db", "--input_path",
           work / "model", "--output_path", out, "--Mapper.ba_refine_focal_length", "0",
           "--Mapper.ba_refine_principal_point", "0", "--Mapper.ba_refine_extra_params", "0")
    colmap_s = time.perf_counter() - t1
    theirs = read_colmap_model(out).image_by_name(held_out)
    pose = {"R": orig.cam_from_world.R.tolist(), "t": orig.cam_from_world.t.tolist()}
    res: dict[str, Any] = {"held_out": held_out, "ours_s": round(ours_s, 3),
                           "colmap_image_registrator_s": round(colmap_s, 3),
                           "ours_inliers": reg.num_inliers, "extent_model_units": model.extent}
    mine = ({held_out: {"R": reg.cam_from_world.R.tolist(), "t": reg.cam_from_world.t.tolist()}}
            if reg.cam_from_world is not None else {})
    cm = ({held_out: {"R": theirs.cam_from_world.R.tolist(), "t": theirs.cam_from_world.t.tolist()}}
          if theirs is not None else {})
    res["ours_vs_colmap"] = pose_differences(mine, cm, model.extent)
    res["ours_vs_original"] = pose_differences(mine, {held_out: pose}, model.extent)
    res["colmap_vs_original"] = pose_differences(cm, {held_out: pose}, model.extent)
    return res


def main() -> int:
    """Command line entry point."""
    if len(sys.argv) == 5 and sys.argv[1] == "--ours":
        print(json.dumps(ours_child(*map(Path, sys.argv[2:]))))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--demo", type=Path, help="a demo data set folder")
    ap.add_argument("--fixture", type=Path, help="the maupertuis_colmap fixture folder")
    ap.add_argument("--work", type=Path, required=True)
    args = ap.parse_args()
    if args.demo:
        print(json.dumps(strip_poses(compare_with_colmap(args.demo, args.work / "demo")),
                         indent=1))
    if args.fixture:
        for name in ("03.jpg", "01.jpg"):
            print(json.dumps(compare_fixture(args.fixture, args.work / "fixture", name), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
