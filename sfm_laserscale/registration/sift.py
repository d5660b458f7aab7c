"""SIFT as COLMAP extracts it (pycolmap, CPU): keypoints in COLMAP pixels, uint8 descriptors."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pycolmap
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.memory import trim_heap
from sfm_laserscale.model import ImageFeatures
from sfm_laserscale.registration.options import DESCRIPTOR_DIM, RegistrationOptions, SiftOptions

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


def _extraction_options(options: SiftOptions) -> Any:
    """pycolmap FeatureExtractionOptions (CPU SIFT) from ours."""
    opts = pycolmap.FeatureExtractionOptions()
    opts.use_gpu = False
    opts.num_threads = int(options.num_threads)
    sift = opts.sift
    sift.max_num_features = int(options.max_num_features)
    sift.first_octave = int(options.first_octave)
    sift.num_octaves = int(options.num_octaves)
    sift.octave_resolution = int(options.octave_resolution)
    sift.peak_threshold = float(options.peak_threshold)
    sift.edge_threshold = float(options.edge_threshold)
    sift.max_num_orientations = int(options.max_num_orientations)
    sift.upright = bool(options.upright)
    sift.normalization = getattr(type(sift.normalization), options.normalization)
    return opts


def _run_sift(image: NDArray[Any], options: SiftOptions) -> tuple[F64, NDArray[np.uint8]]:
    """pycolmap SIFT → (N, 4) x, y, scale, orientation and (N, 128) uint8 descriptors."""
    opts = _extraction_options(options)
    if hasattr(pycolmap, "FeatureExtractor"):  # pycolmap >= 3.12 / 4.x
        extractor = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu)
        if image.dtype == np.uint8:
            kps, descs = extractor.extract_from_uint8_array(image)
        else:
            kps, descs = extractor.extract_from_float32_array(image)
        kp = np.array(
            [[k.x, k.y, k.compute_scale(), k.compute_orientation()] for k in kps],
            dtype=np.float64,
        ).reshape(-1, 4)
        return kp, np.asarray(descs.data, dtype=np.uint8).reshape(-1, DESCRIPTOR_DIM)
    # Older pycolmap: Sift.extract returns float descriptors; COLMAP stores them as
    # uint8 via round(512·d) clipped to 255 (FeatureDescriptorsToUnsignedByte).
    sift = pycolmap.Sift(opts, pycolmap.Device.cpu)  # pragma: no cover - old API
    kp32, d32 = sift.extract(image)  # pragma: no cover
    d8 = np.clip(np.round(np.asarray(d32) * 512.0), 0, 255).astype(np.uint8)  # pragma: no cover
    return np.asarray(kp32, dtype=np.float64), d8  # pragma: no cover


def _as_gray(image: NDArray[Any]) -> NDArray[Any]:
    """(H, W) uint8 / float32 image as given, or (H, W, 3) RGB → grey, C-contiguous."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
        # COLMAP's own conversion (Rec. 709 luma, rounded), as its extractor would do it.
        bitmap = pycolmap.Bitmap.from_array(np.ascontiguousarray(img))
        img = np.asarray(bitmap.clone_as_grey().to_array(), dtype=np.uint8).reshape(img.shape[:2])
    elif img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.float32:
        img = img @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)  # Rec. 709 luma
    if img.ndim != 2 or img.shape[0] < 16 or img.shape[1] < 16:
        raise InputError(f"SIFT needs an (H, W) or (H, W, 3) image, got shape {img.shape}")
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    if img.dtype != np.float32:
        raise InputError(f"SIFT needs a uint8 or float32 image, got {img.dtype}")
    if img.size and (float(img.min()) < 0.0 or float(img.max()) > 1.0):
        raise InputError("float32 images for SIFT must have values in [0, 1]")
    return np.ascontiguousarray(img)


def extract_sift(
    image_gray: NDArray[Any], options: SiftOptions | RegistrationOptions
) -> ImageFeatures:
    """COLMAP CPU SIFT: keypoints in COLMAP pixels (+0.5 convention), uint8 (N, 128) descriptors.

    (H, W) uint8, or float32 in [0, 1]; (H, W, 3) RGB is converted to grey as COLMAP does.
    """
    if isinstance(options, RegistrationOptions):
        options = options.sift
    img = _as_gray(image_gray)
    kp, desc = _run_sift(img, options)
    # COLMAP applies max_num_features before assigning orientations, so more can come
    # back; keep the largest-scale ones (COLMAP's own preference), stable order.
    if len(kp) > options.max_num_features:
        keep = np.sort(np.argsort(-kp[:, 2], kind="stable")[: options.max_num_features])
        kp, desc = kp[keep], desc[keep]
    # pycolmap already returns COLMAP's convention (centre of the top-left pixel at
    # (0.5, 0.5)); tests/test_registration.py checks it on blobs at known positions.
    logger.debug("SIFT: %d keypoints on a %s image", len(kp), img.shape)
    out = ImageFeatures(xy_px=kp[:, :2].copy(), descriptors=desc)
    del img, kp, desc
    trim_heap()  # SIFT's working memory (0.1-3 GB with the image size) goes back to the OS
    return out
