"""COLMAP plugin: source images + laser images + rig -> metric sparse model and mesh, one command.

    python plugins/colmap/colmap_laserscale.py --images IMAGES --laser-images LASER \\
        --rig rig.toml --out OUT [--mesh MESH] [--backend auto|colmap|pycolmap] ...

Stages (each a function below):

1. SfM on the source images, the laser images held out: COLMAP's command line when it is
   installed (``feature_extractor`` / ``exhaustive_matcher`` or ``matches_importer`` /
   ``mapper``, CPU SIFT: Debian's COLMAP 3.8 has no CUDA), else pycolmap
   (``extract_features`` / ``match_exhaustive`` or ``match_image_pairs`` /
   ``incremental_mapping``). The model with the most registered images is kept.
2. The mesh: the user's ``--mesh`` (in the model's frame) when given. Otherwise a COARSE mesh
   is built from the sparse 3D points (Debian's COLMAP has no CUDA and no CGAL, so neither
   ``patch_match_stereo`` nor ``delaunay_mesher`` runs there). It interpolates the sparse
   points only: laser hits between them are as good as the surface is smooth there.
3. The scale stage, ``sfm_laserscale.commands.scale.run`` (exactly what ``sfm-laserscale
   scale`` runs), with the SfM database for the model's descriptors.

Outputs in OUT::

    sfm/database.db            the COLMAP database (SIFT, matches)
    sfm/sparse/<k>/            every model the mapper wrote; the largest is used
    sfm/mesh_coarse.ply        the coarse mesh (only without --mesh)
    sfm/colmap.log             COLMAP's output (command-line backend)
    scale/                     the outputs of ``sfm-laserscale scale`` (report.json, scaled/...)

Exit status: 0 a scale was estimated; 1 SfM failed or no scale could be estimated; 2 bad input.
"""

from __future__ import annotations

import logging
import os
import shutil
import sqlite3
import subprocess
import sys
import time
from collections.abc import Sequence
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.commands import scale as scale_command
from sfm_laserscale.commands.scale import ScaleInputs, ScaleOptions, ScaleResult
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.colmap import read_colmap_model
from sfm_laserscale.io.images import IMAGE_SUFFIXES
from sfm_laserscale.model import INVALID_POINT3D_ID, SparseModel
from sfm_laserscale.registration.mapping import mapping_options

logger = logging.getLogger("sfm_laserscale.plugins.colmap")

F64 = NDArray[np.float64]
BACKENDS = ("auto", "colmap", "pycolmap")
MESH_METHODS = ("delaunay25d", "poisson")


class SfmFailedError(RuntimeError):
    """COLMAP/pycolmap could not reconstruct the source images (exit status 1)."""


# --------------------------------------------------------------------------- options, results


@dataclass(frozen=True)
class PluginInputs:
    """Paths given to the plugin."""

    images: Path  # folder of the source images (laser images inside it are held out)
    laser_images: tuple[Path, ...]  # files and/or folders
    rig: Path
    mesh: Path | None = None  # a mesh in the frame of the model this run builds (rarely known)
    pairs: Path | None = None  # COLMAP pair list "name1 name2" per line (else exhaustive)


@dataclass(frozen=True)
class SfmOptions:
    """How the source images are reconstructed."""

    backend: str = "auto"  # auto (COLMAP's CLI when found, else pycolmap) | colmap | pycolmap
    colmap: str = "colmap"  # the COLMAP executable
    camera_model: str = "SIMPLE_RADIAL"  # one camera shared by every image
    camera_params: tuple[float, ...] | None = None  # known intrinsics, then held fixed
    max_features: int = 8192  # SIFT features per image
    sift_first_octave: int = -1  # COLMAP's default; 0 is ~5x faster on small images
    seed: int = 0


@dataclass(frozen=True)
class CoarseMeshOptions:
    """The mesh built from the sparse points when no mesh is given."""

    method: str = "delaunay25d"  # delaunay25d (surveys: a height field) | poisson (Open3D)
    min_track_length: int = 3  # points seen by fewer images are dropped
    outlier_neighbours: int = 16  # statistical outlier removal (Open3D)
    outlier_std_ratio: float = 2.5
    max_edge_factor: float = 4.0  # delaunay25d: drop triangles with an edge > factor x median
    poisson_depth: int = 7
    poisson_density_quantile: float = 0.05  # poisson: drop the least supported vertices


@dataclass(frozen=True)
class PluginOptions:
    """Every stage's options."""

    sfm: SfmOptions = field(default_factory=SfmOptions)
    mesh: CoarseMeshOptions = field(default_factory=CoarseMeshOptions)
    scale: ScaleOptions = field(default_factory=ScaleOptions)


@dataclass(frozen=True)
class SfmResult:
    """The reconstruction the scale stage used."""

    backend: str  # colmap | pycolmap
    database: Path
    model_dir: Path
    n_images: int  # source images given to SfM
    n_registered: int
    n_points: int
    seconds: float


@dataclass(frozen=True)
class PluginResult:
    """SfM, mesh and scale results of one plugin run."""

    sfm: SfmResult
    mesh_path: Path
    mesh_is_coarse: bool
    scale: ScaleResult
    out_dir: Path
    summary: str


# --------------------------------------------------------------------------- inputs


def _image_files(paths: Sequence[Path]) -> list[Path]:
    """Image files of files and/or folders (folders: their images, not recursive)."""
    files: list[Path] = []
    for p in paths:
        if p.is_dir():
            files += sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        elif p.is_file():
            files.append(p)
        else:
            raise InputError("laser image not found", p)
    return files


def source_image_names(images: Path, laser_images: Sequence[Path]) -> list[str]:
    """Names of the SfM images: the folder's images minus any laser image (held out)."""
    if not images.is_dir():
        raise InputError("source images folder not found", images)
    held = {f.resolve() for f in _image_files(laser_images)}
    names: list[str] = []
    skipped: list[str] = []
    for f in sorted(images.iterdir()):
        if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES:
            (skipped if f.resolve() in held else names).append(f.name)
    if skipped:
        logger.warning("%d laser image(s) inside %s held out of SfM", len(skipped), images)
    if len(names) < 3:
        raise InputError(f"SfM needs at least 3 source images, found {len(names)}", images)
    return names


def _prepare_out(out: Path, overwrite: bool) -> Path:
    """Create OUT; a non-empty OUT is refused unless ``overwrite`` (then sfm/, scale/ go)."""
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out)
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise InputError("output folder is not empty (use --overwrite to replace it)", out)
        for sub in ("sfm", "scale"):
            shutil.rmtree(out / sub, ignore_errors=True)
    (out / "sfm").mkdir(parents=True, exist_ok=True)
    return out / "sfm"


# --------------------------------------------------------------------------- SfM: COLMAP CLI


def colmap_executable(name: str = "colmap") -> str | None:
    """Full path of the COLMAP executable, or None when it is not installed."""
    return shutil.which(name)


def _run_colmap(exe: str, args: list[str], log: Path) -> None:
    """Run one COLMAP command, its output appended to ``log``; SfmFailedError on failure."""
    cmd = [exe, *args]
    logger.info("running %s", " ".join(cmd))
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}  # never needs a display
    with log.open("a", encoding="utf-8") as fh:
        fh.write("$ " + " ".join(cmd) + "\n")
        fh.flush()
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env, check=False)
    if proc.returncode != 0:
        raise SfmFailedError(f"colmap {args[0]} failed (exit {proc.returncode}); see {log}")


def _db_count(database: Path, sql: str) -> int:
    """One integer from the SfM database (read-only); SfmFailedError when there is none."""
    if not database.is_file():
        raise SfmFailedError(f"COLMAP wrote no database at {database}")
    uri = database.resolve().as_uri() + "?mode=ro"
    try:
        with closing(sqlite3.connect(uri, uri=True)) as con:
            return int(con.execute(sql).fetchone()[0])
    except sqlite3.Error as exc:
        raise SfmFailedError(f"cannot read the COLMAP database {database}: {exc}") from exc


def _reader_args(o: SfmOptions) -> list[str]:
    args = ["--ImageReader.single_camera", "1", "--ImageReader.camera_model", o.camera_model]
    if o.camera_params is not None:
        args += ["--ImageReader.camera_params", ",".join(f"{p:.12g}" for p in o.camera_params)]
    return args


def _colmap_sfm(images: Path, names: list[str], pairs: Path | None, work: Path,
                o: SfmOptions) -> Path:
    """feature_extractor, matcher, mapper with COLMAP's CLI; returns the sparse/ folder.

    COLMAP 3.8's tools can exit 0 without doing their job, so every step's result is
    checked in the database or on disk, not only its exit status.
    """
    exe = colmap_executable(o.colmap)
    if exe is None:
        raise SfmFailedError(f"COLMAP executable {o.colmap!r} not found")
    db, log, sparse = work / "database.db", work / "colmap.log", work / "sparse"
    image_list = work / "image_list.txt"
    image_list.write_text("".join(n + "\n" for n in names), encoding="utf-8")
    _run_colmap(exe, ["feature_extractor", "--database_path", str(db), "--image_path",
                      str(images), "--image_list_path", str(image_list), *_reader_args(o),
                      "--SiftExtraction.use_gpu", "0",
                      "--SiftExtraction.max_num_features", str(o.max_features),
                      "--SiftExtraction.first_octave", str(o.sift_first_octave)], log)
    n_db = _db_count(db, "SELECT COUNT(*) FROM keypoints WHERE rows > 0")
    if n_db < len(names):
        raise SfmFailedError(f"feature_extractor found features in {n_db} of {len(names)} "
                             f"images; see {log}")
    match = (["matches_importer", "--match_list_path", str(pairs), "--match_type", "pairs"]
             if pairs is not None else ["exhaustive_matcher"])
    _run_colmap(exe, [*match, "--database_path", str(db), "--SiftMatching.use_gpu", "0"], log)
    if _db_count(db, "SELECT COUNT(*) FROM two_view_geometries WHERE rows > 0") == 0:
        raise SfmFailedError(f"no image pair matched; see {log}")
    sparse.mkdir(exist_ok=True)
    _run_colmap(exe, ["mapper", "--database_path", str(db), "--image_path", str(images),
                      "--output_path", str(sparse), "--Mapper.min_model_size", "3",
                      "--random_seed", str(o.seed), *_fixed_intrinsics_args(o)], log)
    return sparse


def _fixed_intrinsics_args(o: SfmOptions) -> list[str]:
    if o.camera_params is None:
        return []
    return ["--Mapper.ba_refine_focal_length", "0", "--Mapper.ba_refine_principal_point", "0",
            "--Mapper.ba_refine_extra_params", "0"]


# --------------------------------------------------------------------------- SfM: pycolmap


def _pycolmap_sfm(images: Path, names: list[str], pairs: Path | None, work: Path,
                  o: SfmOptions) -> Path:
    """extract_features, match_exhaustive / match_image_pairs, incremental_mapping (CPU)."""
    import pycolmap

    db, sparse = work / "database.db", work / "sparse"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = o.camera_model
    if o.camera_params is not None:
        reader.camera_params = ",".join(f"{p:.12g}" for p in o.camera_params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    extraction.sift.max_num_features = o.max_features
    extraction.sift.first_octave = o.sift_first_octave
    pycolmap.extract_features(db, images, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    if pairs is None:
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_image_pairs(
            db, matching_options=matching, device=pycolmap.Device.cpu,
            pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs))
    sparse.mkdir(exist_ok=True)
    mapping = mapping_options(o.seed, fixed_intrinsics=o.camera_params is not None,
                              min_model_size=3)
    recs = pycolmap.incremental_mapping(db, images, sparse, options=mapping)
    for idx, rec in recs.items():  # written by COLMAP already; make sure every model is
        if not (sparse / str(idx) / "images.bin").is_file():
            (sparse / str(idx)).mkdir(exist_ok=True)
            rec.write(sparse / str(idx))
    return sparse


# --------------------------------------------------------------------------- SfM: both


def largest_model(sparse: Path) -> tuple[Path, SparseModel]:
    """The model folder under ``sparse`` with the most registered images."""
    best: tuple[Path, SparseModel] | None = None
    for sub in sorted(p for p in sparse.iterdir() if p.is_dir()) if sparse.is_dir() else []:
        try:
            model = read_colmap_model(sub)
        except InputError as exc:
            logger.warning("skipping %s: %s", sub, exc)
            continue
        if best is None or len(model.images) > len(best[1].images):
            best = (sub, model)
    if best is None:
        raise SfmFailedError(f"the mapper wrote no model in {sparse}")
    return best


def resolve_backend(backend: str, colmap: str = "colmap") -> str:
    """``colmap`` or ``pycolmap`` for ``auto``/explicit choices (InputError if unknown)."""
    if backend not in BACKENDS:
        raise InputError(f"unknown SfM backend {backend!r} (known: {', '.join(BACKENDS)})")
    if backend == "auto":
        return "colmap" if colmap_executable(colmap) else "pycolmap"
    if backend == "colmap" and colmap_executable(colmap) is None:
        raise InputError(f"COLMAP executable {colmap!r} not found (install colmap, or use "
                         "--backend pycolmap)")
    return backend


def run_sfm(images: Path, names: list[str], pairs: Path | None, work: Path,
            options: SfmOptions) -> SfmResult:
    """Reconstruct the named images of ``images`` into ``work``; keep the largest model."""
    backend = resolve_backend(options.backend, options.colmap)
    if pairs is not None and not pairs.is_file():
        raise InputError("pair list not found", pairs)
    t0 = time.perf_counter()
    run = _colmap_sfm if backend == "colmap" else _pycolmap_sfm
    sparse = run(images, names, pairs, work, options)
    model_dir, model = largest_model(sparse)
    if len(model.images) < 2 or len(model.points_xyz) == 0:
        raise SfmFailedError(f"the largest model ({model_dir}) has {len(model.images)} images "
                             f"and {len(model.points_xyz)} points")
    res = SfmResult(backend=backend, database=work / "database.db", model_dir=model_dir,
                    n_images=len(names), n_registered=len(model.images),
                    n_points=len(model.points_xyz), seconds=time.perf_counter() - t0)
    logger.info("SfM (%s): %d of %d images, %d points, %.1f s", backend, res.n_registered,
                res.n_images, res.n_points, res.seconds)
    return res


# --------------------------------------------------------------------------- coarse mesh


def _track_lengths(model: SparseModel) -> NDArray[np.int64]:
    """Number of images observing each 3D point (rows of ``model.points_xyz``)."""
    obs = np.concatenate([im.point3D_ids for im in model.images.values()]
                         or [np.zeros(0, np.uint64)])
    uniq, counts = np.unique(obs[obs != INVALID_POINT3D_ID], return_counts=True)
    pos = np.searchsorted(uniq, model.point3D_ids)
    found = pos < len(uniq)
    found[found] = uniq[pos[found]] == model.point3D_ids[found]
    out = np.zeros(len(model.point3D_ids), np.int64)
    out[found] = counts[pos[found]]
    return out


def mesh_points(model: SparseModel, options: CoarseMeshOptions) -> F64:
    """Sparse points fit for meshing: long enough tracks, statistical outliers removed."""
    import open3d as o3d

    xyz = model.points_xyz[_track_lengths(model) >= options.min_track_length]
    if len(xyz) < 4:
        raise SfmFailedError(f"only {len(xyz)} sparse points with track length >= "
                             f"{options.min_track_length}: too few for a mesh")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    _, keep = pcd.remove_statistical_outlier(options.outlier_neighbours, options.outlier_std_ratio)
    return np.asarray(xyz[np.asarray(keep, dtype=np.int64)], dtype=np.float64)


def _view_axis(model: SparseModel, xyz: F64) -> F64:
    """Unit normal of the points' best plane, pointing towards the cameras."""
    centred = xyz - xyz.mean(0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    centres = np.array([im.cam_from_world.center for im in model.images.values()])
    return normal if float((centres.mean(0) - xyz.mean(0)) @ normal) >= 0 else -normal


def delaunay_25d(xyz: F64, axis: F64, max_edge_factor: float) -> NDArray[np.int64]:
    """Triangles of a 2.5D Delaunay triangulation of the points seen along ``axis``.

    The points are projected onto the plane normal to ``axis`` and triangulated there
    (scipy's Qhull); triangles with an edge longer than ``max_edge_factor`` x the median
    edge (gaps, the concave outline) are dropped. Exact for a height field over that plane.
    """
    from scipy.spatial import Delaunay

    u = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    tri = Delaunay(np.column_stack([xyz @ u, xyz @ v])).simplices.astype(np.int64)
    edges = np.stack([np.linalg.norm(xyz[tri[:, a]] - xyz[tri[:, b]], axis=1)
                      for a, b in ((0, 1), (1, 2), (2, 0))], axis=1)
    keep = edges.max(1) <= max_edge_factor * float(np.median(edges))
    return tri[keep]


def poisson_mesh(xyz: F64, axis: F64, options: CoarseMeshOptions) -> tuple[F64, NDArray[np.int64]]:
    """Open3D screened Poisson surface of the points, normals turned towards the cameras."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=20))
    normals = np.asarray(pcd.normals)
    normals[normals @ axis < 0] *= -1
    pcd.normals = o3d.utility.Vector3dVector(normals)
    mesh, o3d_density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        pcd, depth=options.poisson_depth)
    density = np.asarray(o3d_density, dtype=np.float64)
    low = density < float(np.quantile(density, options.poisson_density_quantile))
    mesh.remove_vertices_by_mask(low.tolist())
    box = o3d.geometry.AxisAlignedBoundingBox(xyz.min(0), xyz.max(0))
    mesh = mesh.crop(box)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int64)


def coarse_mesh(model: SparseModel, options: CoarseMeshOptions) -> tuple[F64, NDArray[np.int64]]:
    """A coarse mesh (vertices (V, 3) model units, triangles (F, 3)) from the sparse points."""
    if options.method not in MESH_METHODS:
        raise InputError(f"unknown mesh method {options.method!r} "
                         f"(known: {', '.join(MESH_METHODS)})")
    xyz = mesh_points(model, options)
    axis = _view_axis(model, xyz)
    if options.method == "poisson":
        vertices, triangles = poisson_mesh(xyz, axis, options)
    else:
        vertices, triangles = xyz, delaunay_25d(xyz, axis, options.max_edge_factor)
    if len(triangles) == 0:
        raise SfmFailedError("the coarse mesh has no triangles")
    return vertices, triangles


def write_ply(path: Path, vertices: F64, triangles: NDArray[np.int64]) -> Path:
    """Binary PLY: float64 x y z, int32 triangle indices."""
    import plyfile

    vert = np.empty(len(vertices), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    for k, name in enumerate("xyz"):
        vert[name] = vertices[:, k]
    faces = np.empty(len(triangles), dtype=[("vertex_indices", "<i4", (3,))])
    faces["vertex_indices"] = triangles
    plyfile.PlyData([plyfile.PlyElement.describe(vert, "vertex"),
                     plyfile.PlyElement.describe(faces, "face",
                                                 len_types={"vertex_indices": "u1"})],
                    text=False, byte_order="<").write(str(path))
    return path


# --------------------------------------------------------------------------- the job


def run_colmap_plugin(inputs: PluginInputs, out_dir: Path,
                      options: PluginOptions = PluginOptions(),  # noqa: B008
                      overwrite: bool = False) -> PluginResult:
    """SfM (laser images held out), mesh (given or coarse), then the scale stage."""
    names = source_image_names(inputs.images, inputs.laser_images)
    if inputs.mesh is not None and not inputs.mesh.is_file():
        raise InputError("mesh not found", inputs.mesh)
    resolve_backend(options.sfm.backend, options.sfm.colmap)  # bad choice: fail before work
    work = _prepare_out(out_dir, overwrite)
    sfm = run_sfm(inputs.images, names, inputs.pairs, work, options.sfm)
    mesh_path, coarse = inputs.mesh, inputs.mesh is None
    if mesh_path is None:
        vertices, triangles = coarse_mesh(read_colmap_model(sfm.model_dir), options.mesh)
        mesh_path = write_ply(work / "mesh_coarse.ply", vertices, triangles)
        logger.warning("no --mesh: a COARSE mesh (%s, %d triangles) was built from the sparse "
                       "points; give an MVS mesh for the best scale", options.mesh.method,
                       len(triangles))
    scale = scale_command.run(ScaleInputs(model=sfm.model_dir, mesh=mesh_path,
                                          laser_images=inputs.laser_images, rig=inputs.rig,
                                          database=sfm.database), out_dir / "scale", options.scale)
    summary = (f"SfM ({sfm.backend}): {sfm.n_registered}/{sfm.n_images} images, "
               f"{sfm.n_points} points; mesh: {'coarse ' if coarse else ''}{mesh_path.name}; "
               f"{scale.summary}")
    return PluginResult(sfm=sfm, mesh_path=mesh_path, mesh_is_coarse=coarse, scale=scale,
                        out_dir=out_dir, summary=summary)


# --------------------------------------------------------------------------- command line


def _params(text: str | None) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise InputError(f"--camera-params must be comma-separated numbers, got {text!r}") \
            from None


def main(argv: Sequence[str] | None = None) -> int:
    """Command line of the plugin (see the module docstring)."""
    import argparse

    p = argparse.ArgumentParser(prog="colmap_laserscale.py", description=__doc__.split("\n")[0])
    p.add_argument("--images", type=Path, required=True, help="source images folder")
    p.add_argument("--laser-images", type=Path, nargs="+", required=True,
                   help="laser image files and/or folders (held out of SfM)")
    p.add_argument("--rig", type=Path, required=True, help="laser rig TOML")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--mesh", type=Path, help="a mesh in the frame of the model built here")
    p.add_argument("--pairs", type=Path, help="image pairs to match (default: all pairs)")
    p.add_argument("--backend", choices=BACKENDS, default="auto")
    p.add_argument("--colmap", default="colmap", help="the COLMAP executable")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL")
    p.add_argument("--camera-params", help="known intrinsics fx,fy,cx,cy,... (held fixed)")
    p.add_argument("--max-features", type=int, default=8192)
    p.add_argument("--sift-first-octave", type=int, default=-1)
    p.add_argument("--mesh-method", choices=MESH_METHODS, default="delaunay25d")
    p.add_argument("--method", choices=("fcm", "pcm", "all"), default="all")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--verbose", "-v", action="store_true")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        sfm = SfmOptions(backend=a.backend, colmap=a.colmap, camera_model=a.camera_model,
                         camera_params=_params(a.camera_params), max_features=a.max_features,
                         sift_first_octave=a.sift_first_octave, seed=a.seed)
        options = PluginOptions(sfm=sfm, mesh=CoarseMeshOptions(method=a.mesh_method),
                                scale=ScaleOptions(method=a.method, seed=a.seed,
                                                   progress=False))
        result = run_colmap_plugin(PluginInputs(a.images, tuple(a.laser_images), a.rig,
                                                a.mesh, a.pairs), a.out, options, a.overwrite)
    except InputError as exc:
        print(f"colmap_laserscale: error: {exc}", file=sys.stderr)
        return 2
    except SfmFailedError as exc:
        print(f"colmap_laserscale: SfM failed: {exc}", file=sys.stderr)
        return 1
    print(result.summary)
    return 0 if result.scale.success else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
