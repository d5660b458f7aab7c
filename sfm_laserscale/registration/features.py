"""The descriptors of a sparse model's observations, whatever holds them: a COLMAP database,
OpenMVG regions, or SIFT re-extracted on the model's source images and tied to the observations
(``open_model_features``, ``load_model_features``)."""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.colmap_database import open_database_features, read_database_features
from sfm_laserscale.io.images import IMAGE_SUFFIXES, image_size, read_rgb
from sfm_laserscale.io.openmvg import (
    find_openmvg_regions_dir,
    openmvg_model_features,
    openmvg_regions_are_sift,
)
from sfm_laserscale.model import ImageFeatures, ObservationFeatures, SparseModel
from sfm_laserscale.registration.options import TieOptions
from sfm_laserscale.registration.sift_workers import SiftWorkerOptions, start_pool
from sfm_laserscale.registration.ties import check_image_size, features_from_images

logger = logging.getLogger(__name__)
ModelFeatures = dict[str, ImageFeatures] | dict[str, ObservationFeatures]


class LazyImages(Mapping[str, NDArray[np.uint8]]):
    """name -> RGB pixels, read when asked for (one image in memory at a time)."""

    def __init__(self, paths: dict[str, Path]) -> None:
        self._paths = paths

    def __getitem__(self, name: str) -> NDArray[np.uint8]:
        return read_rgb(self._paths[name])

    def __iter__(self) -> Iterator[str]:
        return iter(self._paths)

    def __len__(self) -> int:
        return len(self._paths)


def _source_images(model: SparseModel, images_dir: Path) -> dict[str, Path]:
    if not images_dir.is_dir():
        raise InputError("images folder not found", images_dir)
    found: dict[str, Path] = {}
    for im in model.images.values():
        p = images_dir / im.name
        if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file():
            found[im.name] = p
    if not found:
        raise InputError("holds none of the model's images (names as in the model)", images_dir)
    missing = len(model.images) - len(found)
    if missing:
        logger.warning("%d of the model's images are not in %s", missing, images_dir)
    return found


def _reextracted(model: SparseModel, paths: dict[str, Path], tie: TieOptions,
                 workers: SiftWorkerOptions | None) -> dict[str, ObservationFeatures]:
    """SIFT re-extracted on the model's source images and tied to its observations; shared
    with SIFT worker processes when ``workers`` (and ``plan_workers``) give any."""
    by_name = {im.name: im for im in model.images.values()}
    pixels = 0
    for name, path in paths.items():  # sizes from the headers, before any extraction
        camera = model.cameras[by_name[name].camera_id]
        width, height = image_size(path)
        check_image_size(camera, (height, width), name)
        pixels = max(pixels, width * height)
    pool = None if workers is None else start_pool(list(paths.values()), pixels, tie.sift,
                                                   workers, "model images")
    if pool is None:
        return features_from_images(model, LazyImages(paths), tie)
    with pool:
        return features_from_images(
            model, LazyImages(paths), tie,
            extract=lambda name: pool.features(paths[name], lambda: read_rgb(paths[name])))


def load_model_features(
    model: SparseModel,
    model_path: Path,
    database: Path | None,
    images_dir: Path | None,
    features_dir: Path | None,
    tie: TieOptions,
    workers: SiftWorkerOptions | None = None,
) -> ModelFeatures:
    """Descriptors of the model's observations: database (COLMAP) or regions (OpenMVG)
    first, else SIFT re-extracted (``workers``: SIFT worker processes beside this one;
    None: none)."""
    if model.source_format == "openmvg":
        return _openmvg_features(model, model_path, database, images_dir, features_dir, tie,
                                 workers)
    names = [im.name for im in model.images.values()]
    if database is not None:
        feats = read_database_features(database, names)
        logger.info("descriptors of %d model images read from %s", len(feats), database)
        return feats
    if images_dir is not None:
        return _reextracted(model, _source_images(model, images_dir), tie, workers)
    raise InputError(
        "the model's descriptors are needed: give --database (COLMAP) or --images "
        "(the model's source images, SIFT is re-extracted)"
    )


@contextmanager
def open_model_features(
    model: SparseModel,
    model_path: Path,
    database: Path | None,
    images_dir: Path | None,
    features_dir: Path | None,
    tie: TieOptions,
    workers: SiftWorkerOptions | None = None,
) -> Iterator[Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures]]:
    """``load_model_features`` as a mapping valid inside the ``with`` block: a COLMAP
    database is read one image at a time, on access, so its features are never all held
    in memory (the descriptor index reads them image by image)."""
    # this generator's frame outlives its caller's use of the model: it keeps no reference,
    # so the caller can drop the model's observations while the features are open
    if model.source_format == "openmvg" or database is None:
        loaded = load_model_features(model, model_path, database, images_dir, features_dir, tie,
                                     workers)
        del model
        yield loaded
        return
    names = [im.name for im in model.images.values()]
    del model
    with open_database_features(database, names) as feats:
        logger.info("descriptors of %d model images read from %s, one image at a time",
                    len(feats), database)
        yield feats


def _openmvg_features(
    model: SparseModel,
    model_path: Path,
    database: Path | None,
    images_dir: Path | None,
    features_dir: Path | None,
    tie: TieOptions,
    workers: SiftWorkerOptions | None = None,
) -> ModelFeatures:
    """OpenMVG regions (--features, else matches/ found beside sfm_data), else re-extraction."""
    if database is not None:
        raise InputError(
            "a COLMAP database cannot describe an OpenMVG model's features: give the OpenMVG "
            "regions (--features, or matches/ beside sfm_data.json) or --images", database)
    regions = features_dir if features_dir is not None else find_openmvg_regions_dir(model_path)
    if regions is not None and (features_dir is not None or images_dir is None
                                or openmvg_regions_are_sift(regions)):
        feats = openmvg_model_features(model, model_path, regions)
        logger.info("descriptors of %d model images read from OpenMVG regions in %s",
                    len(feats), regions)
        return feats
    if images_dir is not None:
        if regions is not None:
            logger.warning("OpenMVG regions in %s are not SIFT: SIFT is re-extracted", regions)
        return _reextracted(model, _source_images(model, images_dir), tie, workers)
    raise InputError(
        "the model's descriptors are needed: no OpenMVG regions (.feat/.desc) found in "
        "matches/ beside sfm_data.json; give --features DIR or --images", model_path)
