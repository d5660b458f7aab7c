#!/usr/bin/env python3
"""Benchmark: rescale a large binary PLY (write_scaled_mesh) versus a plain file copy.

Generates an OpenMVS-like binary little-endian PLY in a temporary folder (default: 10 M
vertices with float x y z, float nx ny nz, uchar red green blue; 20 M triangles with a
``vertex_indices`` list and optionally a per-face ``texcoord`` list), then times
``shutil.copyfile`` and ``write_scaled_mesh`` (best of ``--repeat`` runs each, files in the
page cache) and, optionally, ``load_mesh``. Prints the times and throughputs.

    .venv/bin/python scripts/bench_mesh_rescale.py [--vertices N] [--faces-first] [--load]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from sfm_laserscale.io.meshes.mesh import load_mesh, write_scaled_mesh

VERTEX_DTYPE = np.dtype([
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
    ("red", "u1"), ("green", "u1"), ("blue", "u1"),
])


def make_ply(path: Path, n_vertices: int, texcoord: bool, faces_first: bool, seed: int) -> None:
    """Write a synthetic binary PLY with 2 * n_vertices triangles."""
    rng = np.random.default_rng(seed)
    n_faces = 2 * n_vertices
    face_fields = [("n", "u1"), ("vertex_indices", "<i4", (3,))]
    if texcoord:
        face_fields += [("m", "u1"), ("texcoord", "<f4", (6,))]
    face_dtype = np.dtype(face_fields)
    header = ["ply", "format binary_little_endian 1.0", "comment made by bench_mesh_rescale"]
    vertex_header = [f"element vertex {n_vertices}"] + [
        f"property {'float' if VERTEX_DTYPE[name].kind == 'f' else 'uchar'} {name}"
        for name in VERTEX_DTYPE.names or ()
    ]
    face_header = [f"element face {n_faces}", "property list uchar int vertex_indices"]
    if texcoord:
        face_header.append("property list uchar float texcoord")
    blocks = [face_header, vertex_header] if faces_first else [vertex_header, face_header]
    header += blocks[0] + blocks[1] + ["end_header"]

    vertices = np.zeros(n_vertices, dtype=VERTEX_DTYPE)
    for name in ("x", "y", "z", "nx", "ny", "nz"):
        vertices[name] = rng.standard_normal(n_vertices, dtype=np.float32)
    faces = np.zeros(n_faces, dtype=face_dtype)
    faces["n"] = 3
    faces["vertex_indices"] = rng.integers(0, n_vertices, size=(n_faces, 3), dtype=np.int32)
    if texcoord:
        faces["m"] = 6
        faces["texcoord"] = rng.random((n_faces, 6), dtype=np.float32)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        for block in ([faces, vertices] if faces_first else [vertices, faces]):
            block.tofile(f)


def best_time(fn: object, repeat: int, output: Path | None = None) -> float:
    """Best wall time of ``repeat`` calls of ``fn()`` (``output`` deleted before each, untimed)."""
    times = []
    for _ in range(repeat):
        if output is not None:
            output.unlink(missing_ok=True)
        t0 = time.perf_counter()
        fn()  # type: ignore[operator]
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--vertices", type=int, default=10_000_000)
    parser.add_argument("--texcoord", action="store_true", help="add a per-face texcoord list")
    parser.add_argument("--faces-first", action="store_true",
                        help="face element before the vertex element (its length is scanned)")
    parser.add_argument("--load", action="store_true", help="also time load_mesh")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--tmp", type=Path, default=Path(tempfile.gettempdir()))
    args = parser.parse_args()

    args.tmp.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench_rescale_", dir=args.tmp))
    try:
        src_dir, out_dir = work / "in", work / "out"
        src_dir.mkdir()
        src = src_dir / "mesh.ply"
        t0 = time.perf_counter()
        make_ply(src, args.vertices, args.texcoord, args.faces_first, seed=0)
        size_mb = src.stat().st_size / 1e6
        print(f"generated {src} ({size_mb:.0f} MB, {args.vertices} vertices, "
              f"{2 * args.vertices} faces) in {time.perf_counter() - t0:.1f} s")

        out_dir.mkdir()
        copy = out_dir / "copy.ply"
        t_copy = best_time(lambda: shutil.copyfile(src, copy), args.repeat, copy)
        copy.unlink()
        t_scale = best_time(lambda: write_scaled_mesh(src, out_dir, 2.5), args.repeat,
                            out_dir / src.name)

        head = np.fromfile(src, dtype=np.uint8, count=4096).tobytes()
        offset = head.index(b"end_header\n") + len(b"end_header\n")
        if not args.faces_first:  # spot-check the first vertices
            a = np.fromfile(src, VERTEX_DTYPE, count=1000, offset=offset)
            b = np.fromfile(out_dir / "mesh.ply", VERTEX_DTYPE, count=1000, offset=offset)
            assert np.array_equal(b["x"], (a["x"] * 2.5).astype(np.float32))
            assert np.array_equal(b["nx"], a["nx"])
        print(f"plain copy         : {t_copy:6.2f} s  {size_mb / t_copy:7.0f} MB/s")
        print(f"write_scaled_mesh  : {t_scale:6.2f} s  {size_mb / t_scale:7.0f} MB/s  "
              f"({t_scale / t_copy:.2f} x copy time)")
        if args.load:
            t_load = best_time(lambda: load_mesh(src), 1)
            print(f"load_mesh          : {t_load:6.2f} s  {size_mb / t_load:7.0f} MB/s")
    finally:
        shutil.rmtree(work)


if __name__ == "__main__":
    main()
