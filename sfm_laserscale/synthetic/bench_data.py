"""Large synthetic inputs for the speed benchmark (scripts/benchmark.py), made fast with numpy.

Starting from the small demo data set (synthetic/dataset.py, a real pycolmap SfM model with a
database), :func:`pad_model` adds padding 3D points, each seen by two padding images, with
SIFT-like descriptors (real descriptors of the database with their 16 spatial cells permuted and
their 8 orientation bins rotated, so they follow SIFT statistics without matching any real
point), until the model holds ``n_points``; the real points and their descriptors are kept, so
the laser images still register. :func:`write_heightfield_mesh` resamples the demo's height
field (its world grid) to about ``n_triangles`` triangles and writes it in the model frame as an
OpenMVS-like binary PLY (float x y z, uchar colours, uchar-counted int faces).
"""

from __future__ import annotations

import json
import logging
import shutil
import sqlite3
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import plyfile
from numpy.typing import NDArray

from sfm_laserscale.geometry import rotmat_from_qvec
from sfm_laserscale.io.colmap import read_colmap_model
from sfm_laserscale.io.colmap_database import read_database_features
from sfm_laserscale.io.colmap_write import write_colmap_model_binary
from sfm_laserscale.model import Image, SparseModel

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
VERTEX_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                         ("red", "u1"), ("green", "u1"), ("blue", "u1")])
FACE_DTYPE = np.dtype([("n", "u1"), ("vertex_indices", "<i4", (3,))])


@dataclass(frozen=True)
class PaddedModel:
    """Where a padded model and its database were written, and their sizes."""

    model_dir: Path
    database: Path
    n_points: int  # all points, real + padding
    n_real_points: int
    n_images: int  # all images, real + padding


def sift_like_descriptors(real: NDArray[np.uint8], n: int,
                          rng: np.random.Generator) -> NDArray[np.uint8]:
    """(n, 128) uint8: random real descriptors, spatial cells permuted, orientation bins rolled."""
    src = real[rng.integers(0, len(real), n)].reshape(n, 16, 8)
    cells = np.argsort(rng.random((n, 16)), axis=1)
    out = np.take_along_axis(src, cells[:, :, None], axis=1)
    shift = rng.integers(0, 8, n)
    bins = (np.arange(8)[None, :] + shift[:, None]) % 8
    out = np.take_along_axis(out, bins[:, None, :], axis=2)
    return np.ascontiguousarray(out.reshape(n, 128))


def _noisy(desc: NDArray[np.uint8], rng: np.random.Generator, sigma: float) -> NDArray[np.uint8]:
    """Descriptors with Gaussian noise (another view of the same point)."""
    noise = rng.normal(0.0, sigma, desc.shape).astype(np.float32)
    return np.clip(desc.astype(np.float32) + noise, 0, 255).astype(np.uint8)


def _padding_layout(n_pad: int, obs_per_image: int) -> tuple[int, NDArray[np.int64],
                                                            NDArray[np.int64]]:
    """(number of padding images K, image of the 1st and of the 2nd view of each pad point)."""
    k = max(2, int(np.ceil(2 * n_pad / obs_per_image)))
    first = np.arange(n_pad) * k // max(n_pad, 1)
    second = (first + k // 2) % k  # always another image (k >= 2)
    return k, first.astype(np.int64), second.astype(np.int64)


def _insert_db_image(con: sqlite3.Connection, image_id: int, name: str, camera_id: int,
                     xy: F64, desc: NDArray[np.uint8]) -> None:
    """One padding image's row, keypoints (x, y float32) and descriptors (SIFT, type 0)."""
    con.execute("INSERT INTO images (image_id, name, camera_id) VALUES (?, ?, ?)",
                (image_id, name, camera_id))
    kp = np.ascontiguousarray(xy, dtype="<f4")
    con.execute("INSERT INTO keypoints VALUES (?, ?, ?, ?)", (image_id, len(kp), 2, kp.tobytes()))
    cols = {r[1] for r in con.execute("PRAGMA table_info(descriptors)")}
    if "type" in cols:
        con.execute("INSERT INTO descriptors (image_id, type, rows, cols, data) VALUES "
                    "(?, 0, ?, 128, ?)", (image_id, len(desc), desc.tobytes()))
    else:
        con.execute("INSERT INTO descriptors (image_id, rows, cols, data) VALUES (?, ?, 128, ?)",
                    (image_id, len(desc), desc.tobytes()))


def pad_model(model_dir: Path, database: Path, out_dir: Path, n_points: int, seed: int = 0,
              obs_per_image: int = 20000) -> PaddedModel:
    """Copy the model and database into ``out_dir`` with padding points up to ``n_points``."""
    rng = np.random.default_rng(seed)
    model = read_colmap_model(model_dir)
    n_real = len(model.point3D_ids)
    n_pad = max(0, n_points - n_real)
    out_dir.mkdir(parents=True, exist_ok=True)
    db_out = out_dir / "database.db"
    shutil.copyfile(database, db_out)  # our own copy: sqlite may write it freely
    feats = read_database_features(database)
    real_desc = np.concatenate([f.descriptors for f in feats.values()])
    k, first, second = _padding_layout(n_pad, obs_per_image)
    ids = np.uint64(int(model.point3D_ids.max()) + 1) + np.arange(n_pad, dtype=np.uint64)
    spread = 0.02 * model.extent
    base = model.points_xyz[rng.integers(0, n_real, n_pad)]
    xyz = base + rng.normal(0.0, spread, base.shape)
    desc = sift_like_descriptors(real_desc, n_pad, rng)
    real_images = sorted(model.images.values(), key=lambda im: im.image_id)
    cam_id = real_images[0].camera_id
    cam = model.cameras[cam_id]
    images = dict(model.images)
    next_id = max(model.images) + 1
    with closing(sqlite3.connect(db_out)) as con:
        for j in range(k):
            obs = np.concatenate([np.flatnonzero(first == j), np.flatnonzero(second == j)])
            xy = rng.uniform((0.5, 0.5), (cam.width - 0.5, cam.height - 0.5), (len(obs), 2))
            d = _noisy(desc[obs], rng, 4.0)
            name = f"pad_{j:05d}.png"
            pose = real_images[j % len(real_images)].cam_from_world
            images[next_id + j] = Image(next_id + j, name, cam_id, pose, xy, ids[obs].copy())
            _insert_db_image(con, next_id + j, name, cam_id, xy, d)
        con.commit()
    padded = SparseModel(dict(model.cameras), images,
                         np.concatenate([model.point3D_ids, ids]),
                         np.concatenate([model.points_xyz, xyz]))
    write_colmap_model_binary(padded, out_dir / "sparse")
    logger.info("padded model: %d real + %d padding points, %d padding images", n_real, n_pad, k)
    return PaddedModel(out_dir / "sparse", db_out, n_real + n_pad, n_real, len(images))


def _demo_world_heights(mesh_ply: Path, truth_json: Path) -> tuple[F64, F64, F64, F64]:
    """(z grid (ny, nx) metres, xs, ys, model_from_world as a 3×4 s·R|t) of the demo mesh."""
    truth = json.loads(truth_json.read_text(encoding="utf-8"))["model_from_world"]
    s, R = float(truth["scale"]), rotmat_from_qvec(np.asarray(truth["rotation_wxyz"]))
    t = np.asarray(truth["translation"], dtype=np.float64)
    v = plyfile.PlyData.read(str(mesh_ply))["vertex"]
    xyz_model = np.column_stack([np.asarray(v[c], dtype=np.float64) for c in "xyz"])
    world = (xyz_model - t) @ R / s  # R^T (X - t) / s, row vectors
    xs, ys = np.unique(np.round(world[:, 0], 6)), np.unique(np.round(world[:, 1], 6))
    if len(xs) * len(ys) != len(world):
        raise ValueError("the demo mesh is not a regular row-major height-field grid")
    z = world[:, 2].reshape(len(ys), len(xs))
    return z, xs, ys, np.column_stack([s * R, t])


def write_heightfield_mesh(mesh_ply: Path, truth_json: Path, out_path: Path,
                           n_triangles: int) -> int:
    """Resample the demo height field to about ``n_triangles`` triangles; returns the count."""
    z, xs, ys, sim = _demo_world_heights(mesh_ply, truth_json)
    n = max(2, int(round(np.sqrt(n_triangles / 2.0))) + 1)  # vertices per side
    gx = np.linspace(0, len(xs) - 1, n, dtype=np.float32)
    gy = np.linspace(0, len(ys) - 1, n, dtype=np.float32)
    mx, my = np.meshgrid(gx, gy)
    zz = cv2.remap(z.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    del mx, my
    wx, wy = np.meshgrid(np.linspace(xs[0], xs[-1], n), np.linspace(ys[0], ys[-1], n))
    world = np.column_stack([wx.ravel(), wy.ravel(), zz.ravel().astype(np.float64)])
    del wx, wy
    model = world @ sim[:, :3].T + sim[:, 3]
    vert = np.empty(len(model), dtype=VERTEX_DTYPE)
    for k, c in enumerate("xyz"):
        vert[c] = model[:, k]
    grey = np.clip(128 + 300 * zz.ravel(), 0, 255).astype(np.uint8)
    vert["red"], vert["green"], vert["blue"] = grey, grey, grey
    del model, world
    idx = np.arange(n * n, dtype=np.int32).reshape(n, n)
    i00, i01, i10, i11 = (idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(),
                          idx[1:, 1:].ravel())
    faces = np.empty(2 * len(i00), dtype=FACE_DTYPE)
    faces["n"] = 3
    faces["vertex_indices"][: len(i00)] = np.stack([i00, i01, i11], 1)
    faces["vertex_indices"][len(i00):] = np.stack([i00, i11, i10], 1)
    header = ("ply\nformat binary_little_endian 1.0\ncomment sfm_laserscale bench_data\n"
              f"element vertex {len(vert)}\nproperty float x\nproperty float y\n"
              "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    with out_path.open("wb") as f:
        f.write(header.encode("ascii"))
        vert.tofile(f)
        faces.tofile(f)
    return int(len(faces))


def replicate_laser_images(src_dir: Path, out_dir: Path, n: int) -> list[Path]:
    """``n`` laser images in ``out_dir``: the demo's, copied cyclically under new names."""
    src = sorted(p for p in src_dir.iterdir() if p.suffix.lower() == ".png")
    if not src:
        raise ValueError(f"no PNG laser image in {src_dir}")
    out_dir.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n):
        dst = out_dir / f"laser_{i:03d}{src[i % len(src)].suffix}"
        shutil.copyfile(src[i % len(src)], dst)
        out.append(dst)
    return out
