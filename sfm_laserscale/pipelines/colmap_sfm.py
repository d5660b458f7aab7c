"""SfM of the source images (the laser images held out) into a COLMAP workspace layout
(``database.db``, ``sparse/<n>/``), with COLMAP's command line when it is installed
(``feature_extractor``, ``exhaustive_matcher`` or ``matches_importer``, ``mapper``; CPU SIFT:
Debian's COLMAP 3.8 has no CUDA) or pycolmap (:func:`sfm_laserscale.registration.mapping.
pycolmap_sfm`). COLMAP 3.8's tools can exit 0 without doing their job, so each step's result is
checked in the database or on disk; a failed step raises ToolFailedError naming it.
"""

from __future__ import annotations

import logging
import sqlite3
import time
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

from sfm_laserscale.errors import InputError, ToolFailedError
from sfm_laserscale.io.workspace import choose_sparse_model
from sfm_laserscale.pipelines.hold_out import SfmImages
from sfm_laserscale.pipelines.tools import ToolStep, find_program, run_step
from sfm_laserscale.registration.mapping import SfmOptions, pycolmap_sfm

logger = logging.getLogger(__name__)

BACKENDS = ("auto", "colmap", "pycolmap")


@dataclass(frozen=True)
class SfmResult:
    """The reconstruction ``scale`` uses."""

    backend: str  # colmap | pycolmap
    workspace: Path  # database.db, sparse/<n>/
    database: Path
    model_dir: Path
    n_images: int  # source images given to SfM
    n_registered: int
    seconds: float


def resolve_backend(backend: str, colmap: str = "colmap") -> str:
    """``colmap`` or ``pycolmap`` for ``auto``/explicit choices (InputError if impossible)."""
    if backend not in BACKENDS:
        raise InputError(f"unknown SfM backend {backend!r} (known: {', '.join(BACKENDS)})")
    if backend == "pycolmap":
        return backend
    try:
        find_program(colmap)
    except InputError:
        if backend == "colmap":
            raise InputError(f"COLMAP executable {colmap!r} not found (install colmap, or use "
                             "--backend pycolmap)") from None
        return "pycolmap"
    return "colmap"


def _db_count(database: Path, sql: str, step: str) -> int:
    """One integer from the SfM database (read-only); ToolFailedError when there is none."""
    if not database.is_file():
        raise ToolFailedError(step, f"COLMAP wrote no database at {database}")
    uri = database.resolve().as_uri() + "?mode=ro"
    try:
        with closing(sqlite3.connect(uri, uri=True)) as con:
            return int(con.execute(sql).fetchone()[0])
    except sqlite3.Error as exc:
        raise ToolFailedError(step, f"cannot read the COLMAP database {database}: {exc}") \
            from exc


def colmap_steps(images: SfmImages, work: Path, pairs: Path | None,
                 o: SfmOptions) -> list[ToolStep]:
    """The COLMAP 3.8+ command lines: feature_extractor, the matcher, mapper."""
    db = str(work / "database.db")
    reader = ["--ImageReader.single_camera", "1", "--ImageReader.camera_model", o.camera_model]
    if o.camera_params is not None:
        reader += ["--ImageReader.camera_params", ",".join(f"{p:.12g}" for p in o.camera_params)]
    threads = str(o.threads)
    match = (["matches_importer", "--match_list_path", str(pairs), "--match_type", "pairs"]
             if pairs is not None else ["exhaustive_matcher"])
    fixed = (["--Mapper.ba_refine_focal_length", "0", "--Mapper.ba_refine_principal_point", "0",
              "--Mapper.ba_refine_extra_params", "0"] if o.camera_params is not None else [])
    return [
        ToolStep("feature_extractor", "colmap", (
            "feature_extractor", "--database_path", db, "--image_path", str(images.folder),
            "--image_list_path", str(work / "image_list.txt"), *reader,
            "--SiftExtraction.use_gpu", "0", "--SiftExtraction.num_threads", threads,
            "--SiftExtraction.max_num_features", str(o.max_features),
            "--SiftExtraction.first_octave", str(o.sift_first_octave))),
        ToolStep(match[0], "colmap", (*match, "--database_path", db, "--SiftMatching.use_gpu",
                                      "0", "--SiftMatching.num_threads", threads)),
        ToolStep("mapper", "colmap", (
            "mapper", "--database_path", db, "--image_path", str(images.folder),
            "--output_path", str(work / "sparse"), "--Mapper.min_model_size", "3",
            "--Mapper.num_threads", threads, "--random_seed", str(o.seed), *fixed)),
    ]


def _check_step(step: ToolStep, work: Path, n_images: int) -> None:
    """COLMAP 3.8 can exit 0 having done nothing: check the step's result."""
    db = work / "database.db"
    if step.name == "feature_extractor":
        n = _db_count(db, "SELECT COUNT(*) FROM keypoints WHERE rows > 0", step.name)
        if n < n_images:
            raise ToolFailedError(step.name, f"features in {n} of {n_images} images",
                                  work / "colmap.log")
    elif step.name in ("exhaustive_matcher", "matches_importer") and _db_count(
            db, "SELECT COUNT(*) FROM two_view_geometries WHERE rows > 0", step.name) == 0:
        raise ToolFailedError(step.name, "no image pair matched", work / "colmap.log")


def _colmap_cli_sfm(images: SfmImages, work: Path, pairs: Path | None, o: SfmOptions) -> None:
    exe = find_program(o.colmap)
    (work / "image_list.txt").write_text("".join(n + "\n" for n in images.names),
                                         encoding="utf-8")
    (work / "sparse").mkdir(exist_ok=True)
    for step in colmap_steps(images, work, pairs, o):
        run_step(step, exe, work / "colmap.log")
        _check_step(step, work, len(images.names))


def run_sfm(images: SfmImages, work: Path, pairs: Path | None, options: SfmOptions) -> SfmResult:
    """Reconstruct the selected images into ``work``; keep the model with the most images."""
    backend = resolve_backend(options.backend, options.colmap)
    if pairs is not None and not pairs.is_file():
        raise InputError("pair list not found", pairs)
    t0 = time.perf_counter()
    work.mkdir(parents=True, exist_ok=True)
    if backend == "colmap":
        _colmap_cli_sfm(images, work, pairs, options)
    else:
        pycolmap_sfm(images.folder, list(images.names), pairs, work, options)
    model_dir, count, _ = choose_sparse_model(work / "sparse")
    if model_dir is None or count < 2:
        raise ToolFailedError("mapper", f"no model of 2 or more images in {work / 'sparse'} "
                              "(no initial image pair found?)", work / "colmap.log"
                              if backend == "colmap" else None)
    res = SfmResult(backend, work, work / "database.db", model_dir, len(images.names), count,
                    time.perf_counter() - t0)
    logger.info("SfM (%s): %d of %d images, %.1f s", backend, count, len(images.names),
                res.seconds)
    return res
