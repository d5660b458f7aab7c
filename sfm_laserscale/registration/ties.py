"""Re-extracted SIFT tied to a model's observations: each keypoint of a model image to its
nearest observation with a 3D point (``features_from_images``)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import (
    INVALID_POINT3D_ID,
    Camera,
    Image,
    ImageFeatures,
    ObservationFeatures,
    SparseModel,
)
from sfm_laserscale.provenance import progress_bar
from sfm_laserscale.registration.options import DESCRIPTOR_DIM, RegistrationOptions, TieOptions
from sfm_laserscale.registration.sift import extract_sift

logger = logging.getLogger(__name__)


def _valid_observations(
    model: SparseModel, image: Image
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(observation indices, point rows) of the observations whose 3D point the model holds."""
    ids = np.asarray(image.point3D_ids, dtype=np.uint64)
    obs = np.flatnonzero(ids != INVALID_POINT3D_ID)
    rows = _point_rows(model, ids[obs])
    ok = rows >= 0
    return obs[ok].astype(np.int64), rows[ok]


def _point_rows(model: SparseModel, ids: NDArray[np.uint64],
                order: NDArray[np.int64] | None = None) -> NDArray[np.int64]:
    """Rows in model.points_xyz of these point ids; −1 for ids the model does not hold.

    ``order``: argsort of model.point3D_ids when the caller already has it (sorting 1M ids
    once per image took ~10 s of a 100-image index build).
    """
    all_ids = np.asarray(model.point3D_ids, dtype=np.uint64)
    if len(all_ids) == 0 or len(ids) == 0:
        return np.full(len(ids), -1, dtype=np.int64)
    if order is None:
        order = np.argsort(all_ids, kind="stable")
    pos = np.clip(np.searchsorted(all_ids, ids, sorter=order), 0, len(all_ids) - 1)
    rows = order[pos].astype(np.int64)
    rows[all_ids[rows] != ids] = -1
    return rows


def features_from_images(
    model: SparseModel, images: Mapping[str, NDArray[Any]],
    options: TieOptions | RegistrationOptions,
    extract: Callable[[str], ImageFeatures] | None = None,
) -> dict[str, ObservationFeatures]:
    """Re-extract SIFT on model images and tie keypoints to observations with a 3D point.

    Each keypoint is tied to the nearest observation (that has a 3D point) of the same
    image within ``tie_radius_px``; several keypoints may tie to one observation (SIFT
    orientations). Images: name -> (H, W) grey or (H, W, 3) RGB uint8 pixels. ``extract``:
    name -> that image's SIFT when something else extracts it (the SIFT worker pool; the
    caller checks the image sizes, ``images`` is then only read for its names).
    """
    if isinstance(options, RegistrationOptions):
        options = options.tie
    out: dict[str, ObservationFeatures] = {}
    # Progress bar (on a terminal, not with --quiet): re-extraction takes seconds per image.
    for name in progress_bar(options.progress, "model image SIFT", iterable=list(images),
                             total=len(images), unit="img"):
        image = model.image_by_name(name)
        if image is None:
            raise InputError("not an image of the sparse model", path=name)
        if extract is None:
            pixels = images[name]
            check_image_size(model.cameras[image.camera_id], np.asarray(pixels).shape, name)
            feats = extract_sift(pixels, options.sift)
        else:
            feats = extract(name)
        out[name] = _tie_features(model, image, feats, options)
        logger.info("%s: %d re-extracted keypoints tied to model observations",
                    name, len(out[name].observation_idx))
    return out


def check_image_size(camera: Camera, shape: tuple[int, ...], name: str) -> None:
    """InputError when an image of ``shape`` (H, W, ...) is not its camera's size."""
    if tuple(shape[:2]) != (camera.height, camera.width):
        raise InputError(f"image is {shape[1]}×{shape[0]} px but its camera is "
                         f"{camera.width}×{camera.height}", path=name)


def _tie_features(
    model: SparseModel, image: Image, feats: ImageFeatures, options: TieOptions
) -> ObservationFeatures:
    """Tie each keypoint to its nearest observation with a 3D point within the radius."""
    obs, _ = _valid_observations(model, image)
    if len(obs) == 0 or len(feats.xy_px) == 0:
        return ObservationFeatures(np.zeros(0, np.int64), np.zeros((0, DESCRIPTOR_DIM), np.uint8),
                                   np.zeros(0))
    tree = cKDTree(np.asarray(image.xy_px, dtype=np.float64)[obs])
    dist, nearest = tree.query(feats.xy_px, k=1, distance_upper_bound=options.tie_radius_px)
    tied = np.isfinite(dist)
    return ObservationFeatures(
        observation_idx=obs[nearest[tied]],
        descriptors=np.asarray(feats.descriptors, dtype=np.uint8)[tied],
        tie_distance_px=np.asarray(dist[tied], dtype=np.float64),
    )
