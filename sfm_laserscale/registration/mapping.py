"""COLMAP incremental mapping options (pycolmap), built once for every SfM this package runs: the
demo's data set (:mod:`sfm_laserscale.synthetic.dataset`) and the pycolmap backend of the
``colmap`` command (:func:`pycolmap_sfm`: extract_features, match_exhaustive or
match_image_pairs, incremental_mapping, on the CPU)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from sfm_laserscale.errors import ToolFailedError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SfmOptions:
    """How the source images are reconstructed (the ``colmap`` command)."""

    backend: str = "auto"  # auto (COLMAP's CLI when found, else pycolmap) | colmap | pycolmap
    colmap: str = "colmap"  # the COLMAP executable
    camera_model: str = "SIMPLE_RADIAL"  # one camera shared by every image
    camera_params: tuple[float, ...] | None = None  # known intrinsics, then held fixed
    max_features: int = 8192  # SIFT features per image
    sift_first_octave: int = -1  # COLMAP's default; 0 is ~5x faster on small images
    threads: int = -1  # threads of each step (-1: every core)
    seed: int = 0


def mapping_options(seed: int, fixed_intrinsics: bool,
                    min_model_size: int | None = None) -> pycolmap.IncrementalPipelineOptions:
    """Incremental mapping seeded wherever pycolmap takes a seed (the pipeline, the mapper and the
    triangulation). ``fixed_intrinsics``: the known camera is held fixed by bundle adjustment and
    absolute-pose refinement; ``min_model_size``: the smallest model kept (None: COLMAP's)."""
    opts = pycolmap.IncrementalPipelineOptions()
    if min_model_size is not None:
        opts.min_model_size = int(min_model_size)
    if fixed_intrinsics:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
    opts.random_seed = int(seed)
    opts.mapper.random_seed = int(seed)
    opts.triangulation.random_seed = int(seed)
    return opts


def pycolmap_sfm(images: Path, names: list[str], pairs: Path | None, work: Path,
                 o: SfmOptions) -> None:
    """Reconstruct the named images into ``work`` (database.db, sparse/<n>/) with pycolmap on
    the CPU; ToolFailedError naming the step that failed."""
    db, sparse = work / "database.db", work / "sparse"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = o.camera_model
    if o.camera_params is not None:
        reader.camera_params = ",".join(f"{p:.12g}" for p in o.camera_params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    extraction.num_threads = o.threads
    extraction.sift.max_num_features = o.max_features
    extraction.sift.first_octave = o.sift_first_octave
    try:
        pycolmap.extract_features(db, images, image_names=names,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
    except (RuntimeError, ValueError) as exc:
        raise ToolFailedError("extract_features", str(exc)) from exc
    _pycolmap_match(db, pairs, o)
    sparse.mkdir(exist_ok=True)
    opts = mapping_options(o.seed, fixed_intrinsics=o.camera_params is not None,
                           min_model_size=3)
    opts.num_threads = o.threads
    try:
        recs = pycolmap.incremental_mapping(db, images, sparse, options=opts)
    except (RuntimeError, ValueError) as exc:
        raise ToolFailedError("incremental_mapping", str(exc)) from exc
    for idx, rec in recs.items():  # written by COLMAP already; make sure every model is
        if not (sparse / str(idx) / "images.bin").is_file():
            (sparse / str(idx)).mkdir(exist_ok=True)
            rec.write(sparse / str(idx))


def _pycolmap_match(db: Path, pairs: Path | None, o: SfmOptions) -> None:
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = o.threads
    step = "match_exhaustive" if pairs is None else "match_image_pairs"
    try:
        if pairs is None:
            pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pycolmap.match_image_pairs(
                db, matching_options=matching, device=pycolmap.Device.cpu,
                pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs))
    except (RuntimeError, ValueError) as exc:
        raise ToolFailedError(step, str(exc)) from exc
