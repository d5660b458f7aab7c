#!/usr/bin/env python3
"""Benchmark: image footprints (footprints.csv) per image and per mesh size.

A rough seafloor heightfield of ``--triangles`` triangles (a seeded random relief over a
square of 100 model units) is seen by ``--images`` cameras along a lawn-mower survey (PINHOLE
``--width`` × ``--height``, looking down from 4 units, a little tilted). Times
``footprints()`` on the whole mesh (one caster) and in the cropped groups used for meshes over
``max_crop_triangles`` (forced here with a small limit), and prints the rays per second.

    .venv/bin/python scripts/bench_footprints.py [--triangles N] [--images K] [--repeat R]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from sfm_laserscale.footprints import FootprintOptions, FootprintView, footprints, grid_shape
from sfm_laserscale.geometry import rotmat_from_qvec
from sfm_laserscale.model import Camera, Pose


def heightfield(n_triangles: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices, (F, 3) triangles: a grid over [0, 100]² with a random relief."""
    n = max(2, int(np.sqrt(n_triangles / 2)) + 1)
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, 100, n), np.linspace(0, 100, n))
    z = 0.3 * rng.standard_normal((n, n)) + np.sin(u / 7) + np.cos(v / 5)
    verts = np.column_stack([u.ravel(), v.ravel(), z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    tris = np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])]).astype(np.int32)
    return verts, tris


def survey(k: int, camera: Camera, seed: int) -> list[FootprintView]:
    """``k`` cameras 4 units above the floor, looking down (z down in the world), tilted."""
    rng = np.random.default_rng(seed)
    views = []
    down = np.diag([1.0, -1.0, -1.0])  # camera z along world -z
    for i in range(k):
        x, y = 10 + (i * 3.0) % 80, 10 + 8.0 * ((i * 3) // 80)
        q = np.array([1.0, *rng.normal(0, 0.05, 3)])
        R = rotmat_from_qvec(q / np.linalg.norm(q)) @ down
        centre = np.array([x, y, 4.0])
        views.append(FootprintView(f"{i:05d}.jpg", "model", camera,
                                   Pose(R, -R @ centre)))
    return views


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--triangles", type=int, default=1_000_000)
    p.add_argument("--images", type=int, default=200)
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--repeat", type=int, default=2)
    args = p.parse_args()
    camera = Camera(1, "PINHOLE", args.width, args.height,
                    np.array([1500.0, 1500.0, args.width / 2, args.height / 2]))
    verts, tris = heightfield(args.triangles, 0)
    views = survey(args.images, camera, 1)
    cols, rows = grid_shape(camera, FootprintOptions().grid_columns)
    rays = args.images * ((cols + 1) * (rows + 1) + 4)
    print(f"{len(tris)} triangles, {args.images} images of {args.width}x{args.height}, "
          f"{cols}x{rows} cells, {rays} rays")
    for label, options in (("whole mesh", FootprintOptions()),
                           ("cropped groups", FootprintOptions(
                               max_crop_triangles=max(1, len(tris) // 8)))):
        best = np.inf
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            found = footprints(views, verts, tris, options)
            best = min(best, time.perf_counter() - t0)
        on = [f for f in found if f.area > 0]
        print(f"{label:15s} {best:7.2f} s  {1e3 * best / args.images:6.1f} ms/image  "
              f"{rays / best / 1e6:5.2f} M rays/s  ({len(on)} on the mesh, median area "
              f"{np.median([f.area for f in on]):.2f} units²)")


if __name__ == "__main__":
    main()
