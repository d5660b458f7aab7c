"""Registration of held-out (laser) images into an existing sparse model.

Descriptor index of the model's 3D points, 2D–3D matching, absolute pose with an
acceptance rule of our own, pose covariance. This is the one module that calls
pycolmap's SIFT extractor and absolute-pose estimators: pycolmap API drift stays
here (checked against pycolmap 4.2.1).

Pose covariance parametrisation (``PoseResult.covariance``, 6×6, ours, not pycolmap's)
    ξ = (ω, δt): ω ∈ R³ a rotation vector in radians, δt ∈ R³ in model units,
    rotation first. The true ``cam_from_world`` is (R, t) = (Exp(ω) R̂, t̂ + δt):
    left (camera-frame) perturbation of the rotation, additive perturbation of the
    translation t (not of the camera centre). Cov = σ̂² (JᵀJ)⁻¹ with J the Jacobian
    of the inlier reprojections (pixels) with respect to ξ at the refined pose and
    σ̂² = Σ‖r‖² / (2n − 6) the observed per-axis residual variance of the n inliers
    (2n − 6 − n_focal when the focal length is refined; then the pose block of the
    joint covariance is returned, i.e. focal uncertainty is marginalised).
    Checked by Monte Carlo in tests/test_registration.py.

pycolmap's own covariance (``return_covariance=True``) is *not* returned: it is
(J̃ᵀJ̃)⁻¹ for unit pixel noise with J̃ the Jacobian corrected by the Cauchy loss
of the refinement, in Ceres' quaternion tangent space, where the rotation
increment δ is *half* the rotation vector (R = Exp(2δ) R̂, left) and the
translation increment is additive; order (rotation, translation). With the loss
made quadratic, diag(2,2,2,1,1,1)·C·diag(2,2,2,1,1,1) equals our (JᵀJ)⁻¹ (tested);
with the default Cauchy loss it is neither the unit-noise covariance nor scaled
to the data, hence our own.

Refinement loss: Cauchy with scale ``PoseOptions.loss_scale_px`` = 4 px (COLMAP uses
1 px). Under 1 px Gaussian noise the spread of the refined pose exceeds σ̂²(JᵀJ)⁻¹
by ~15 % with a 1 px scale, ~4 % with 2 px and ~1 % with 4 px (Monte Carlo, 200
trials), while residuals near the 12 px RANSAC threshold are still down-weighted 10×.

Descriptor index: exact search up to 10k descriptors, above that a FAISS inverted file
(IVF: k-means cells, ``IndexOptions.ivf_probe`` nearest cells searched per query) whose lists
hold the SIFT descriptors as their own uint8 values (``QT_8bit_direct``: 128 bytes each, exact
L2 distances within the searched cells). It replaced OpenCV's FLANN KD-trees, which needed a
float32 copy of the pool plus trees (~1.45 kB per descriptor, 2.9 GB at 2M descriptors) against
~136 bytes here, and built 2× slower (docs/BENCHMARKS.md). The index is built in three
passes over the features, one image at a time (a COLMAP database is never read whole), and
its lists are written once into a buffer that FAISS reads without copying: at 2M
descriptors the build peaks ~0.06 GB above the index itself (see the comment above
``_Selection``).

Determinism: SIFT is deterministic. Exact descriptor search is; the IVF's k-means is seeded
(``IndexOptions.seed``) and its search has no randomness. LO-RANSAC takes
``PoseOptions.seed`` as pycolmap's ``ransac.random_seed`` with one thread, and Ceres'
refinement is single-threaded: same input and seeds give bit-identical poses (tested).
``seed=None`` leaves RANSAC random.
"""

from __future__ import annotations

import logging
import struct
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import faiss
import numpy as np
import pycolmap
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from sfm_laserscale.errors import InputError
from sfm_laserscale.memory import trim_heap
from sfm_laserscale.model import (
    INVALID_POINT3D_ID,
    Camera,
    Image,
    ImageFeatures,
    Pose,
    SparseModel,
)
from sfm_laserscale.provenance import progress_bar

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
DESCRIPTOR_DIM = 128


# --------------------------------------------------------------------------- options


@dataclass(frozen=True)
class SiftOptions:
    """COLMAP SIFT extraction settings (CPU); defaults are COLMAP's."""

    max_num_features: int = 8192  # hard cap on the returned keypoints (largest scales kept)
    first_octave: int = -1
    num_octaves: int = 4
    octave_resolution: int = 3
    peak_threshold: float = 0.02 / 3
    edge_threshold: float = 10.0
    max_num_orientations: int = 2
    upright: bool = False
    normalization: str = "L1_ROOT"  # L1_ROOT (COLMAP default, RootSIFT) | L2
    num_threads: int = -1

    def __post_init__(self) -> None:
        if self.max_num_features < 1:
            raise InputError(f"max_num_features must be >= 1, got {self.max_num_features}")
        if self.normalization not in ("L1_ROOT", "L2"):
            raise InputError(f"SIFT normalization: L1_ROOT or L2, not {self.normalization!r}")


@dataclass(frozen=True)
class TieOptions:
    """Re-extraction of SIFT on model images and tying keypoints to model observations."""

    tie_radius_px: float = 2.0
    sift: SiftOptions = field(default_factory=SiftOptions)
    progress: bool = True  # progress bar (only on a terminal, see provenance.progress_enabled)

    def __post_init__(self) -> None:
        if not self.tie_radius_px > 0:
            raise InputError(f"tie radius must be > 0 px, got {self.tie_radius_px}")


@dataclass(frozen=True)
class IndexOptions:
    """Descriptor index of the model's 3D points."""

    max_descriptors_per_point: int = 8  # the ones closest to the point's mean descriptor
    exact: bool | None = None  # None: exact brute force up to exact_max_pool, else IVF
    exact_max_pool: int = 10000
    ivf_lists: int | None = None  # k-means cells; None: √(pool size), within 16..4096
    # cells searched per query: recall of the exact ratio-test matches 0.990 with 6 probes,
    # 0.992 with 8 for 40 % more search time, 0.983 with 4 (scripts/bench_index.py)
    ivf_probe: int = 6
    train_per_list: int = 40  # k-means training sample: this many descriptors per cell
    # cells are assigned in a PCA projection of this many dimensions (0: all 128): at 2M
    # descriptors 1.7 s instead of 9.5 s to fill the lists, same recall (docs/BENCHMARKS.md)
    coarse_dims: int = 16
    seed: int = 0  # k-means seed

    def __post_init__(self) -> None:
        if self.ivf_lists is not None and self.ivf_lists < 1:
            raise InputError(f"ivf_lists must be >= 1, got {self.ivf_lists}")
        if self.ivf_probe < 1 or self.train_per_list < 1:
            raise InputError("ivf_probe and train_per_list must be >= 1")
        if not 0 <= self.coarse_dims <= DESCRIPTOR_DIM:
            raise InputError(f"coarse_dims must be in 0..128, got {self.coarse_dims}")


@dataclass(frozen=True)
class MatchOptions:
    """2D–3D descriptor matching."""

    ratio: float = 0.8  # Lowe ratio; second neighbour taken from a different 3D point
    max_distance: float | None = None  # optional absolute L2 cut (uint8 descriptor units)

    def __post_init__(self) -> None:
        if not 0 < self.ratio <= 1:
            raise InputError(f"match ratio must be in (0, 1], got {self.ratio}")


@dataclass(frozen=True)
class PoseOptions:
    """LO-RANSAC P3P + refinement (pycolmap) and our acceptance rule."""

    ransac_max_error_px: float = 12.0  # COLMAP's registrator default
    ransac_min_inlier_ratio: float = 0.1
    ransac_confidence: float = 0.99999
    ransac_max_num_trials: int = 10000
    loss_scale_px: float = 4.0  # Cauchy loss scale of the refinement (COLMAP: 1), see below
    refine_focal_length: bool = False
    seed: int | None = 0  # RANSAC seed; None = non-deterministic
    min_inliers: int = 30
    min_inlier_ratio: float = 0.25
    max_reproj_error_px: float = 4.0  # RMS over inliers

    def __post_init__(self) -> None:
        if self.min_inliers < 4:
            raise InputError(f"min_inliers must be >= 4, got {self.min_inliers}")
        if not (self.ransac_max_error_px > 0 and self.loss_scale_px > 0
                and self.max_reproj_error_px > 0):
            raise InputError("RANSAC error, loss scale and reprojection limit must be > 0 px")
        if not 0 <= self.min_inlier_ratio <= 1:
            raise InputError(f"min_inlier_ratio must be in [0, 1], got {self.min_inlier_ratio}")


@dataclass(frozen=True)
class RegistrationOptions:
    """All registration settings; every function here also accepts it in place of its own."""

    sift: SiftOptions = field(default_factory=SiftOptions)
    tie_radius_px: float = 2.0
    index: IndexOptions = field(default_factory=IndexOptions)
    match: MatchOptions = field(default_factory=MatchOptions)
    pose: PoseOptions = field(default_factory=PoseOptions)

    def with_seed(self, seed: int | None) -> RegistrationOptions:
        """Copy with the RANSAC seed and the KD-tree seed set (None: RANSAC unseeded)."""
        return replace(self, index=replace(self.index, seed=0 if seed is None else int(seed)),
                       pose=replace(self.pose, seed=seed))

    @property
    def tie(self) -> TieOptions:
        """The tie settings of ``features_from_images``."""
        return TieOptions(tie_radius_px=self.tie_radius_px, sift=self.sift)


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class ObservationFeatures:
    """Descriptors tied to some observations of one model image (re-extracted SIFT)."""

    observation_idx: NDArray[np.int64]  # (K,) rows of Image.xy_px / Image.point3D_ids
    descriptors: NDArray[np.uint8]  # (K, 128), COLMAP bin order
    tie_distance_px: F64  # (K,) keypoint-to-observation distance, pixels


@dataclass(frozen=True)
class DescriptorIndex:
    """Descriptors of the model's 3D points, searchable by nearest neighbour."""

    descriptors: NDArray[np.uint8]  # (P, 128) for exact search; (0, 128) when the IVF holds them
    point_rows: NDArray[np.int32]  # (P,) row of each descriptor's point in points_xyz
    points_xyz: F64  # (M, 3) the model's points, model units
    point3D_ids: NDArray[np.uint64]  # noqa: N815 (COLMAP's name) (M,)
    method: str  # "ivf" | "exact"
    ivf_lists: int = 0  # k-means cells of the IVF (0 for exact search)
    ivf_probe: int = 0  # cells searched per query (0 for exact search)
    _searcher: Any = field(default=None, repr=False, compare=False)
    _storage: Any = field(default=None, repr=False, compare=False)  # memory of the IVF's lists

    @property
    def num_descriptors(self) -> int:
        """Number of descriptors in the pool."""
        return int(len(self.point_rows))

    @property
    def num_points(self) -> int:
        """Number of distinct 3D points with at least one descriptor."""
        return int(np.count_nonzero(np.bincount(self.point_rows)))


@dataclass(frozen=True)
class Matches:
    """2D–3D matches: one per 3D point, the best by descriptor distance."""

    query_idx: NDArray[np.int64]  # (n,) keypoint index in the query ImageFeatures
    point_rows: NDArray[np.int64]  # (n,) row in DescriptorIndex.points_xyz
    distance: NDArray[np.float32]  # (n,) L2 descriptor distance (uint8 units)

    def __len__(self) -> int:
        return int(len(self.query_idx))


@dataclass(frozen=True)
class PoseResult:
    """Absolute pose, its covariance (see module docstring) and the acceptance verdict."""

    success: bool
    reason: str | None
    cam_from_world: Pose | None  # None unless success (never a guessed pose)
    covariance: F64 | None  # (6, 6) over (ω, δt), scaled by sigma_px²; None unless success
    num_matches: int
    num_inliers: int
    inlier_mask: NDArray[np.bool_]  # (num_matches,)
    reproj_error_px: float  # RMS of the 2D residual norm over the inliers (nan if no pose)
    sigma_px: float  # σ̂ = sqrt(Σ‖r‖² / (2n − 6)), per-axis (nan if no pose)
    camera: Camera  # the input camera, or with the refined focal length


@dataclass(frozen=True)
class RegistrationResult:
    """Everything the report needs about one registered (or rejected) image."""

    matches: Matches
    pose: PoseResult
    inlier_xy_px: F64  # (K, 2) query keypoints of the inliers, COLMAP pixels
    inlier_xyz: F64  # (K, 3) their 3D points, model units
    inlier_point3D_ids: NDArray[np.uint64]  # noqa: N815 (COLMAP's name) (K,)
    num_features: int
    match_time_s: float
    pose_time_s: float

    @property
    def success(self) -> bool:
        """True when the pose passed the acceptance rule."""
        return self.pose.success

    @property
    def reason(self) -> str | None:
        """Why registration failed, in plain words (None on success)."""
        return self.pose.reason

    @property
    def num_matches(self) -> int:
        """Number of 2D–3D matches fed to RANSAC."""
        return self.pose.num_matches

    @property
    def num_inliers(self) -> int:
        """Number of RANSAC inliers."""
        return self.pose.num_inliers

    @property
    def reproj_error_px(self) -> float:
        """RMS reprojection error over the inliers, pixels."""
        return self.pose.reproj_error_px

    @property
    def cam_from_world(self) -> Pose | None:
        """The accepted pose, or None."""
        return self.pose.cam_from_world

    @property
    def covariance(self) -> F64 | None:
        """(6, 6) pose covariance over (ω, δt), or None."""
        return self.pose.covariance


# --------------------------------------------------------------------------- SIFT


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


# --------------------------------------------------------------------------- features


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


# --------------------------------------------------------------------------- index


def _as_rows(desc: NDArray[Any]) -> NDArray[Any] | None:
    """(N,) view of (N, 128) uint8 descriptors as one 128-byte item per row, or None.

    Gathering such items is 3-4x faster than numpy's row-wise fancy indexing of the 2-D
    array (0.2 s instead of 0.8 s for 2M rows in random order).
    """
    if desc.dtype != np.uint8 or desc.ndim != 2 or desc.shape[1] != DESCRIPTOR_DIM:
        return None
    return np.ascontiguousarray(desc).view(np.dtype((np.void, DESCRIPTOR_DIM)))[:, 0]


def _rows_of(desc: NDArray[Any], which: NDArray[Any]) -> NDArray[np.uint8]:
    """``desc[which]`` as (M, 128) uint8, for an index or mask array (see ``_as_rows``)."""
    rows = _as_rows(desc)
    if rows is None:
        return np.asarray(desc[which], dtype=np.uint8)
    return rows[which].view(np.uint8).reshape(-1, DESCRIPTOR_DIM)


def _image_selection(
    model: SparseModel, name: str, image: Image, feats: ImageFeatures | ObservationFeatures,
    order: NDArray[np.int64] | None = None,
) -> tuple[NDArray[Any], NDArray[np.bool_], NDArray[np.int64]]:
    """(all descriptors, mask of those with a 3D point, their point rows) of one image."""
    if isinstance(feats, ObservationFeatures):
        obs_idx, desc = np.asarray(feats.observation_idx), np.asarray(feats.descriptors)
        if len(obs_idx) and (obs_idx.min() < 0 or obs_idx.max() >= len(image.xy_px)):
            raise InputError("tied observation index out of range for this image", path=name)
    else:
        desc = np.asarray(feats.descriptors)
        obs_idx = np.arange(len(desc))
        _check_aligned(name, image, feats)
    if desc.ndim != 2 or desc.shape[1] != DESCRIPTOR_DIM or len(desc) != len(obs_idx):
        raise InputError(f"descriptors must be (N, 128), got {desc.shape}", path=name)
    ids = np.asarray(image.point3D_ids, dtype=np.uint64)[obs_idx]
    rows = _point_rows(model, ids, order)  # invalid / removed points -> -1
    ok = rows >= 0
    return desc, ok, rows[ok]


def _check_aligned(name: str, image: Image, feats: ImageFeatures) -> None:
    """Database convention: keypoint i of an image is observation i of the model."""
    if len(feats.xy_px) != len(image.xy_px) or len(feats.descriptors) != len(image.xy_px):
        raise InputError(
            f"{len(feats.xy_px)} keypoints but the model has {len(image.xy_px)} observations "
            "of this image (keypoint i must be observation i): wrong database for this model?",
            path=name,
        )
    if len(image.xy_px):
        offset = float(np.max(np.abs(np.asarray(feats.xy_px) - np.asarray(image.xy_px))))
        if offset > 0.05:
            raise InputError(
                f"keypoints differ from the model's observations by up to {offset:.2f} px: "
                "wrong database for this model?", path=name,
            )


# The pool is built in three passes over the features, so that a lazy mapping (the COLMAP
# database read one image at a time, ``io.colmap_database.open_database_features``) never
# holds more than one image's features beside the index (2M descriptors: 0.27 GB, where the
# features, a gathered pool and FAISS's own lists used to be held two at a time):
#   1. selection: each image's descriptors with a 3D point (alignment checked), and a random
#      training sample for the IVF's k-means (``_select``);
#   2. the descriptors of points seen more than ``max_descriptors_per_point`` times (ranked to
#      keep that many) and every candidate's IVF cell (``_rank_and_cells``);
#   3. every kept descriptor copied once, straight to its final place: the exact pool, or its
#      cell's list inside one buffer that FAISS reads without copying (``_IvfLayout``).


@dataclass(frozen=True)
class _Selection:
    """Pass 1: the candidate descriptors of each image (those of a 3D point).

    int32 rows (half the memory of int64 at 2M descriptors): models of < 2³¹ points."""

    names: tuple[str, ...]
    used: tuple[NDArray[np.int32], ...]  # per image: rows of its descriptors that are candidates
    sizes: tuple[int, ...]  # per image: its number of descriptor rows (checked on later passes)
    point_rows: NDArray[np.int32]  # (N,) point row of every candidate, images concatenated

    @property
    def starts(self) -> NDArray[np.int64]:
        """(images + 1,) offset of each image's candidates in ``point_rows``."""
        return np.r_[0, np.cumsum([len(u) for u in self.used])].astype(np.int64)


def _rank_per_point(
    desc: NDArray[np.float32], rows: NDArray[np.integer[Any]], max_per_point: int
) -> NDArray[np.int64]:
    """Indices keeping, per point, the ``max_per_point`` descriptors nearest its mean."""
    order = np.argsort(rows, kind="stable")
    r = rows[order]
    starts = np.flatnonzero(np.r_[True, r[1:] != r[:-1]])
    counts = np.diff(np.r_[starts, len(r)])
    means = np.add.reduceat(desc[order], starts, axis=0) / counts[:, None]
    group = np.repeat(np.arange(len(starts)), counts)
    dist = np.linalg.norm(desc[order] - means[group], axis=1)
    by_dist = np.lexsort((dist, group))  # within each group, nearest to the mean first
    rank = np.empty(len(r), dtype=np.int64)
    rank[by_dist] = np.arange(len(r)) - starts[group[by_dist]]
    return np.sort(order[rank < max_per_point])


@dataclass(frozen=True)
class DescriptorPool:
    """The descriptors to index: (P, 128) uint8 and the row of each one's 3D point."""

    descriptors: NDArray[np.uint8]
    point_rows: NDArray[np.int64]


def _ivf_lists(pool_size: int, options: IndexOptions) -> int:
    """Number of k-means cells of the IVF over a pool of this size."""
    nlist = options.ivf_lists or int(np.clip(round(np.sqrt(pool_size)), 16, 4096))
    return max(1, min(nlist, pool_size))


def _train_probability(model: SparseModel, names: Sequence[str], options: IndexOptions) -> float:
    """Probability of drawing each candidate into the k-means sample (pass 1).

    Drawn from an upper bound of the candidates (the observations with a point id), 1.5×
    the largest sample the IVF may need, so that at least that many are drawn (then cut down).
    """
    by_name = {im.name: im for im in model.images.values()}
    upper = sum(int(np.count_nonzero(np.asarray(by_name[n].point3D_ids, dtype=np.uint64)
                                     != INVALID_POINT3D_ID)) for n in names if n in by_name)
    if upper == 0 or _use_exact(upper, options):
        return 0.0
    wanted = _ivf_lists(upper, options) * max(1, options.train_per_list)
    return min(1.0, 1.5 * wanted / upper)


def _select(
    model: SparseModel, features: Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures],
    train_p: float, rng: np.random.Generator,
) -> tuple[_Selection, NDArray[np.uint8]]:
    """Pass 1 over the features: candidates of each model image (checked) and a random
    sample of them for the k-means, (T, 128), each candidate drawn with ``train_p``."""
    order = np.argsort(np.asarray(model.point3D_ids, dtype=np.uint64), kind="stable")
    by_name = {im.name: im for im in model.images.values()}  # image_by_name is a linear scan
    names, used, sizes, rows, train = [], [], [], [], []
    for name in features:
        image = by_name.get(name)
        if image is None:
            logger.debug("%s: not in the model, its features are not indexed", name)
            continue
        desc, ok, r = _image_selection(model, name, image, features[name], order)
        u = np.flatnonzero(ok)
        names.append(name)
        used.append(u.astype(np.int32))
        sizes.append(len(desc))
        rows.append(r.astype(np.int32))
        if train_p > 0:
            train.append(_rows_of(desc, u[rng.random(len(u)) < train_p]))
    point_rows = np.concatenate(rows) if rows else np.zeros(0, np.int32)
    if len(point_rows) == 0:
        raise InputError("no descriptor of any 3D point of the model: features and model disagree")
    sample = np.concatenate(train) if train else np.zeros((0, DESCRIPTOR_DIM), np.uint8)
    return _Selection(tuple(names), tuple(used), tuple(sizes), point_rows), sample


def _pool_selection(pool: DescriptorPool, options: IndexOptions,
                    rng: np.random.Generator) -> tuple[_Selection, NDArray[np.uint8]]:
    """A materialised pool as a one-image selection, and a k-means sample of it."""
    desc = np.asarray(pool.descriptors)
    if desc.ndim != 2 or desc.shape[1] != DESCRIPTOR_DIM or len(desc) != len(pool.point_rows):
        raise InputError(f"pool descriptors must be (P, 128) with P point rows, got {desc.shape}")
    n = len(desc)
    wanted = 0 if n == 0 or _use_exact(n, options) else \
        _ivf_lists(n, options) * max(1, options.train_per_list)
    pick = np.sort(rng.choice(n, size=min(n, wanted), replace=False))
    sel = _Selection(("pool",), (np.arange(n, dtype=np.int32),), (n,),
                     np.asarray(pool.point_rows, dtype=np.int32))
    return sel, _rows_of(desc, pick)


def _image_descriptors(descriptors_of: Any, sel: _Selection, i: int) -> NDArray[np.uint8]:
    """Image ``i``'s descriptors on a later pass; they must not have changed since pass 1."""
    desc = np.asarray(descriptors_of(sel.names[i]))
    if desc.ndim != 2 or len(desc) != sel.sizes[i]:
        raise InputError(f"{desc.shape[0]} descriptors, {sel.sizes[i]} when first read: "
                         "the features changed while the index was built", path=sel.names[i])
    return desc


def _rank_and_cells(
    sel: _Selection, descriptors_of: Any, max_per_point: int, quantizer: Any | None,
    nlist: int = 0,
) -> tuple[NDArray[np.bool_], NDArray[np.integer[Any]] | None]:
    """Pass 2: (mask of the candidates kept, IVF cell of every candidate or None).

    Only the points with more candidates than ``max_per_point`` are ranked (a small share
    of a large model's points: ranking them all cost ~60 % of the index build time at 1M
    points); the result is the same as ranking every point.
    """
    over = (np.bincount(sel.point_rows) > max_per_point)[sel.point_rows]
    keep = ~over
    if quantizer is None and not over.any():
        return keep, None
    over_idx = np.flatnonzero(over)
    over_desc = np.empty((len(over_idx), DESCRIPTOR_DIM), dtype=np.float32)
    cells = None if quantizer is None else np.empty(len(sel.point_rows), dtype=_cell_type(nlist))
    starts, k = sel.starts, 0
    for i in range(len(sel.names)):
        lo, hi = int(starts[i]), int(starts[i + 1])
        if hi == lo:
            continue
        cand = _rows_of(_image_descriptors(descriptors_of, sel, i), sel.used[i])
        if cells is not None:
            cells[lo:hi] = _assign_cells(quantizer, cand)
        o = over[lo:hi]
        n_over = int(np.count_nonzero(o))
        if n_over:
            over_desc[k:k + n_over] = cand[o]
            k += n_over
    if len(over_idx):
        keep[over_idx[_rank_per_point(over_desc, sel.point_rows[over_idx], max_per_point)]] = True
    return keep, cells


def _cell_type(nlist: int) -> type[np.integer[Any]]:
    """int16 for < 32768 cells: numpy's stable sort of int16 is a radix sort (10× faster)."""
    return np.int16 if nlist <= np.iinfo(np.int16).max else np.int32


def _assign_cells(quantizer: Any, desc: NDArray[np.uint8]) -> NDArray[np.int64]:
    """(N,) nearest cell of each (N, 128) uint8 descriptor, in 16 MB float32 chunks."""
    chunk = 1 << 15
    return np.concatenate([
        quantizer.search(np.ascontiguousarray(desc[s:s + chunk], dtype=np.float32), 1)[1][:, 0]
        for s in range(0, len(desc), chunk)]).astype(np.int64)


def _scatter(sel: _Selection, descriptors_of: Any, keep: NDArray[np.bool_],
             words: NDArray[np.uint64], dest_word: NDArray[np.integer[Any]]) -> None:
    """Pass 3: copy the j-th kept candidate to ``words[dest_word[j]:][:16]``."""
    cols = np.arange(DESCRIPTOR_DIM // 8, dtype=np.int64)
    starts, done = sel.starts, 0  # done: kept candidates of the images before
    for i in range(len(sel.names)):
        lo, hi = int(starts[i]), int(starts[i + 1])
        k = keep[lo:hi]
        n = int(np.count_nonzero(k))
        if n == 0:
            continue
        rows = _rows_of(_image_descriptors(descriptors_of, sel, i), sel.used[i][k])
        dest = dest_word[done:done + n]
        words[dest[:, None].astype(np.int64) + cols] = rows.view(np.uint64).reshape(n, -1)
        done += n


def _word_view(a: NDArray[np.uint8]) -> NDArray[np.uint64]:
    """A C-contiguous, 8-byte aligned uint8 array as uint64 words (same memory)."""
    return a.reshape(-1).view(np.uint64)


def _gather_kept(sel: _Selection, descriptors_of: Any,
                 keep: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """(P, 128) the kept candidates, in candidate order (pass 3 of the exact pool)."""
    pool = np.empty((int(np.count_nonzero(keep)), DESCRIPTOR_DIM), dtype=np.uint8)
    step = DESCRIPTOR_DIM // 8
    _scatter(sel, descriptors_of, keep, _word_view(pool),
             step * np.arange(len(pool), dtype=_word_type(len(pool))))
    return pool


def _training_sample(sel: _Selection, drawn: NDArray[np.uint8], descriptors_of: Any, n: int,
                     rng: np.random.Generator) -> NDArray[np.uint8]:
    """(n, 128) random candidates for the k-means: pass 1's sample, cut down to ``n``.

    When pass 1 drew fewer (features covering far fewer observations than the model holds,
    e.g. re-extracted SIFT), ``n`` candidates are drawn again, one more pass.
    """
    if len(drawn) >= n:
        return drawn[np.sort(rng.choice(len(drawn), size=n, replace=False))]
    pick = np.zeros(len(sel.point_rows), dtype=bool)
    pick[rng.choice(len(pick), size=n, replace=False)] = True
    return _gather_kept(sel, descriptors_of, pick)


def _trained_ivf(train_u8: NDArray[np.uint8], nlist: int, options: IndexOptions) -> Any:
    """An empty FAISS IVF (uint8 codes, ``QT_8bit_direct``) with its k-means cells trained."""
    train = np.ascontiguousarray(train_u8, dtype=np.float32)
    quantizer = _coarse_quantizer(train, options.coarse_dims)
    ivf = faiss.IndexIVFScalarQuantizer(quantizer, DESCRIPTOR_DIM, nlist,
                                        faiss.ScalarQuantizer.QT_8bit_direct, faiss.METRIC_L2,
                                        False)  # store the descriptors, not their residuals
    ivf.cp.seed = int(options.seed)
    ivf.cp.min_points_per_centroid = 1  # small pools: no console warning from FAISS
    ivf.cp.max_points_per_centroid = max(1, options.train_per_list)
    ivf.train(train)  # k-means centroids in 128-d, assigned through the quantizer
    return ivf


def _coarse_quantizer(train: NDArray[np.float32], dims: int) -> Any:
    """The index that assigns descriptors to cells: exact L2 in 128-d, or in the first
    ``dims`` principal components of the training sample (cheaper, consistent for queries
    and pool alike since both go through it)."""
    if dims in (0, DESCRIPTOR_DIM) or len(train) < 4 * DESCRIPTOR_DIM:  # too few for a PCA
        return faiss.IndexFlatL2(DESCRIPTOR_DIM)
    pca = faiss.PCAMatrix(DESCRIPTOR_DIM, dims)
    pca.train(train)
    return faiss.IndexPreTransform(pca, faiss.IndexFlatL2(dims))


@dataclass(frozen=True)
class _IvfLayout:
    """An IVF serialised into one buffer: FAISS's bytes for the trained, empty index with
    its lists section replaced by the lists' sizes, then each list's codes (P_l × 128 bytes)
    and ids (P_l int64), list after list (FAISS's ``ilar``/``full`` format).

    ``faiss.ZeroCopyIOReader`` reads it back with every list a view into this buffer: the
    descriptors are written once, where FAISS searches them, and never copied.
    """

    buffer: NDArray[np.uint8]
    body_at: int  # byte offset of list 0 (8-byte aligned in memory)

    @property
    def words(self) -> NDArray[np.uint64]:
        """The lists as uint64 words: list l's codes start at word 17 × (its first position)."""
        return self.buffer[self.body_at:].view(np.uint64)


def _ivf_layout(ivf: Any, sizes: NDArray[np.int64]) -> _IvfLayout | None:
    """The buffer of ``ivf`` (trained, empty) with lists of these sizes; None when this FAISS
    does not serialise an empty index the way this code expects (then lists are filled)."""
    head = faiss.serialize_index(ivf)
    lists = b"ilar" + struct.pack("<QQ", ivf.nlist, ivf.code_size)
    empty = lists + b"sprs" + struct.pack("<Q", 0)
    if ivf.code_size != DESCRIPTOR_DIM or bytes(head[-len(empty):]) != empty:
        return None
    lists += b"full" + struct.pack("<Q", ivf.nlist) + sizes.astype("<u8").tobytes()
    keep = len(head) - len(empty)
    body_at = keep + len(lists)
    total = body_at + (DESCRIPTOR_DIM + 8) * int(sizes.sum())
    raw = np.empty(total + 8, dtype=np.uint8)
    shift = -(raw.ctypes.data + body_at) % 8
    buf = raw[shift:shift + total]
    buf[:keep] = head[:keep]
    buf[keep:body_at] = np.frombuffer(lists, dtype=np.uint8)
    return _IvfLayout(buf, body_at)


def _read_ivf(layout: _IvfLayout) -> tuple[Any, Any]:
    """(index, the memory its lists live in): zero copy when this FAISS can, else a copy."""
    reader_type = getattr(faiss, "ZeroCopyIOReader", None)
    if reader_type is None:  # older FAISS: the lists are copied, the buffer can go
        return faiss.deserialize_index(layout.buffer), None
    index = faiss.read_index(reader_type(faiss.swig_ptr(layout.buffer), layout.buffer.size))
    return index, (None if _lists_owned(index) else layout.buffer)


def _lists_owned(index: Any) -> bool:
    """True only when the index's first non-empty list is known to own its codes."""
    inv: Any = faiss.downcast_InvertedLists(index.invlists)
    for lst in range(inv.nlist):
        if inv.list_size(lst):
            codes = inv.codes.at(lst)
            return bool(getattr(codes, "is_owned", False))
    return False


def _fill_ivf(sel: _Selection, descriptors_of: Any, keep: NDArray[np.bool_],
              cells: NDArray[np.integer[Any]], ivf: Any) -> tuple[Any, Any, NDArray[np.int32]]:
    """Pass 3 for the IVF: (searchable index, memory its lists live in, point row of each
    pool position). Pool position = place in cell order; FAISS ids are pool positions.

    Peak ~ lists + 40 bytes per descriptor: the arrays over all descriptors are int16 cells,
    the cell order and the destinations (int64), the result's point rows.
    """
    cells_kept = cells[keep]
    order = np.argsort(cells_kept, kind="stable")  # pool position -> kept index
    point_rows = sel.point_rows[keep][order]
    sizes = np.bincount(cells_kept, minlength=ivf.nlist).astype(np.int64)
    first = np.r_[0, np.cumsum(sizes)]  # (nlist + 1,) first pool position of each list
    trim_heap()  # what passes 1-2 freed, before the lists' memory is taken
    layout = _ivf_layout(ivf, sizes)
    # list l's codes start at word 17 × first[l] (the codes and ids of the lists before it),
    # so the code of position p (in list l) is at word first[l] + 16 p; a plain cell-sorted
    # pool (no layout) has it at word 16 p
    dest = _in_chunks(order, lambda o, p: (first[cells_kept[o]] if layout is not None else 0)
                      + (DESCRIPTOR_DIM // 8) * p)
    del order
    trim_heap()
    if layout is None:  # fill FAISS's own lists from a cell-sorted pool (twice the memory)
        logger.debug("FAISS serialises IVFs differently from what this code knows: lists copied")
        pool = np.empty((len(dest), DESCRIPTOR_DIM), dtype=np.uint8)
        _scatter(sel, descriptors_of, keep, _word_view(pool), dest)
        for lst in np.flatnonzero(sizes).tolist():
            a, b = int(first[lst]), int(first[lst + 1])
            ids = np.arange(a, b, dtype=np.int64)
            ivf.invlists.add_entries(lst, b - a, faiss.swig_ptr(ids), faiss.swig_ptr(pool[a:b]))
        ivf.ntotal = len(dest)
        return ivf, None, point_rows
    _scatter(sel, descriptors_of, keep, layout.words, dest)
    del dest
    _write_ids(layout.words, np.sort(cells_kept, kind="stable"), first)
    index, storage = _read_ivf(layout)
    index.ntotal = len(point_rows)
    return index, storage, point_rows


def _word_type(num_descriptors: int) -> type[np.integer[Any]]:
    """int32 word offsets while they fit (17 words per descriptor: < 126M descriptors)."""
    return np.int32 if 17 * num_descriptors < np.iinfo(np.int32).max else np.int64


def _in_chunks(order: NDArray[np.int64],
               fn: Any, chunk: int = 1 << 20) -> NDArray[np.integer[Any]]:
    """``out[order[p]] = fn(order[p], p)`` for every position p, 1M at a time (no
    full-length temporaries)."""
    out = np.empty(len(order), dtype=_word_type(len(order)))
    for a in range(0, len(order), chunk):
        o = order[a:a + chunk]
        out[o] = fn(o, np.arange(a, a + len(o), dtype=np.int64))
    return out


def _write_ids(words: NDArray[np.uint64], sorted_cells: NDArray[np.integer[Any]],
               first: NDArray[np.int64], chunk: int = 1 << 20) -> None:
    """FAISS id of each pool position = the position, after its list's codes: position p of
    list l at word 17 × first[l] + 16 × size_l + (p − first[l]) = 16 × first[l + 1] + p."""
    step = DESCRIPTOR_DIM // 8
    for a in range(0, len(sorted_cells), chunk):
        p = np.arange(a, min(a + chunk, len(sorted_cells)), dtype=np.int64)
        words[step * first[sorted_cells[a:a + chunk].astype(np.int64) + 1] + p] = p.view(np.uint64)


def build_descriptor_index(
    model: SparseModel,
    features: Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures],
    options: IndexOptions | RegistrationOptions,
) -> DescriptorIndex:
    """Index the descriptors of every model observation that has a 3D point.

    ``ImageFeatures`` follow the COLMAP database convention (keypoint i = observation i
    of the image in the model, checked); ``ObservationFeatures`` come from
    ``features_from_images``. Features of images absent from the model are ignored. The
    mapping is read three times, one image at a time: it may read from disk on access.
    """
    return build_index(model, select_index_candidates(model, features, options), features,
                       options)


@dataclass
class IndexCandidates:
    """Pass 1 of the descriptor index (``select_index_candidates``): the descriptors of each
    image that have a 3D point, and a random k-means sample.

    It holds nothing of the model's 2D observations: a caller short of memory drops them
    (``SparseModel.without_observations``, 46 MB at 1M points) before ``build_index``, which
    consumes this (the sample is released during the build).
    """

    selection: _Selection
    sample: NDArray[np.uint8] | None  # (T, 128); None once consumed
    rng: np.random.Generator  # the seeded generator, continued by the build


def select_index_candidates(
    model: SparseModel,
    features: Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures],
    options: IndexOptions | RegistrationOptions,
) -> IndexCandidates:
    """Pass 1 of ``build_descriptor_index``: the only one that reads the observations."""
    if isinstance(options, RegistrationOptions):
        options = options.index
    rng = np.random.default_rng(options.seed)
    p = _train_probability(model, list(features), options)
    sel, sample = _select(model, features, p, rng)
    return IndexCandidates(sel, sample, rng)


def build_index(
    model: SparseModel, candidates: IndexCandidates,
    features: Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures],
    options: IndexOptions | RegistrationOptions,
) -> DescriptorIndex:
    """Passes 2-3 of ``build_descriptor_index`` over the same features; of the model only
    the points are used (its observations may have been dropped)."""
    if isinstance(options, RegistrationOptions):
        options = options.index
    if candidates.sample is None:
        raise ValueError("these index candidates were already built into an index")
    once = [candidates.sample]  # popped by the build, which frees it once trained on
    candidates.sample = None
    return _index(model, lambda _: (candidates.selection, once.pop()), candidates.rng,
                  lambda name: features[name].descriptors, options)


def descriptor_pool(
    model: SparseModel,
    features: Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures],
    options: IndexOptions | RegistrationOptions,
) -> DescriptorPool:
    """The descriptors of the observations with a 3D point, at most
    ``max_descriptors_per_point`` per point (those nearest the point's mean descriptor)."""
    if isinstance(options, RegistrationOptions):
        options = options.index
    sel, _ = _select(model, features, 0.0, np.random.default_rng(options.seed))
    keep, _ = _rank_and_cells(sel, lambda name: features[name].descriptors,
                              max(1, options.max_descriptors_per_point), None)
    return DescriptorPool(_gather_kept(sel, lambda name: features[name].descriptors, keep),
                          sel.point_rows[keep].astype(np.int64))


def index_pool(model: SparseModel, pool: DescriptorPool,
               options: IndexOptions | RegistrationOptions) -> DescriptorIndex:
    """The searchable index of a descriptor pool: exact search for small pools, else IVF."""
    if isinstance(options, RegistrationOptions):
        options = options.index
    rng = np.random.default_rng(options.seed)
    return _index(model, lambda rng: _pool_selection(pool, options, rng), rng,
                  lambda _: pool.descriptors, options)


def _index(model: SparseModel, select: Any, rng: np.random.Generator, descriptors_of: Any,
           options: IndexOptions) -> DescriptorIndex:
    """The exact pool or the IVF of the candidates: ``select(rng)`` (pass 1) returns them and
    a k-means sample; ``descriptors_of(name)`` gives an image's descriptors (passes 2-3)."""
    sel, drawn = select(rng)
    per_point = max(1, options.max_descriptors_per_point)
    size = int(np.minimum(np.bincount(sel.point_rows), per_point).sum())  # pool size
    searcher = storage = None
    if _use_exact(size, options):
        keep, _ = _rank_and_cells(sel, descriptors_of, per_point, None)
        pool = _gather_kept(sel, descriptors_of, keep)
        point_rows = sel.point_rows[keep]
    else:
        nlist = _ivf_lists(size, options)
        n_train = min(size, nlist * max(1, options.train_per_list))
        train = _training_sample(sel, drawn, descriptors_of, n_train, rng)
        del drawn
        ivf = _trained_ivf(train, nlist, options)
        del train
        keep, cells = _rank_and_cells(sel, descriptors_of, per_point, ivf.quantizer, nlist)
        assert cells is not None  # a quantizer was given
        searcher, storage, point_rows = _fill_ivf(sel, descriptors_of, keep, cells, ivf)
        searcher.nprobe = min(nlist, options.ivf_probe)
        pool = np.zeros((0, DESCRIPTOR_DIM), np.uint8)
    trim_heap()  # the passes' temporaries go back to the OS
    method = "exact" if searcher is None else "ivf"
    logger.info("descriptor index: %d descriptors of %d points (%s%s)", len(point_rows),
                np.count_nonzero(np.bincount(point_rows)), method,
                "" if searcher is None else f", {searcher.nlist} cells, probe {searcher.nprobe}")
    return DescriptorIndex(
        descriptors=pool, point_rows=point_rows,
        points_xyz=np.asarray(model.points_xyz, dtype=np.float64),
        point3D_ids=np.asarray(model.point3D_ids, dtype=np.uint64),
        method=method,
        ivf_lists=0 if searcher is None else int(searcher.nlist),
        ivf_probe=0 if searcher is None else int(searcher.nprobe),
        _searcher=searcher, _storage=storage,
    )


def _use_exact(num_descriptors: int, options: IndexOptions) -> bool:
    """Exact brute force or the IVF for a pool of this size."""
    if options.exact is not None:
        return bool(options.exact)
    return num_descriptors <= options.exact_max_pool


def _exact_knn(pool: NDArray[np.float32], query: NDArray[np.float32], k: int) -> tuple[
        NDArray[np.int64], NDArray[np.float32]]:
    """(Q, min(k, P)) exact nearest neighbours and their L2 distances, sorted by distance.

    FAISS's flat L2 index: BLAS distances and a heap per query. numpy's row-wise
    ``argpartition`` over the (Q, P) distance matrix took 0.67 s for one 640 x 480 image
    (6915 queries, 5604 descriptors) against 0.05 s here."""
    k = min(k, len(pool))
    if k == 0:
        return np.zeros((len(query), 0), np.int64), np.zeros((len(query), 0), np.float32)
    flat = faiss.IndexFlatL2(pool.shape[1])
    flat.add(np.ascontiguousarray(pool, dtype=np.float32))
    d2, idx = flat.search(np.ascontiguousarray(query, dtype=np.float32), k)
    return np.asarray(idx, dtype=np.int64), np.sqrt(np.maximum(d2, 0.0)).astype(np.float32)


def _knn(index: DescriptorIndex, query: NDArray[np.float32], k: int) -> tuple[
        NDArray[np.int64], NDArray[np.float32]]:
    """(Q, k) pool indices and L2 distances of the k nearest descriptors (sorted)."""
    if index.method == "exact":
        return _exact_knn(index.descriptors.astype(np.float32), query, k)
    d2, idx = index._searcher.search(query, k)  # FAISS: squared L2, −1 for no neighbour found
    idx = np.asarray(idx, dtype=np.int64)
    dist = np.where(idx >= 0, np.sqrt(np.maximum(d2, 0)), np.inf).astype(np.float32)
    return np.maximum(idx, 0), dist


# --------------------------------------------------------------------------- matching


def match_to_model(
    query: ImageFeatures, index: DescriptorIndex, options: MatchOptions | RegistrationOptions
) -> Matches:
    """Ratio-test matches (second neighbour from another 3D point), one per 3D point."""
    if isinstance(options, RegistrationOptions):
        options = options.match
    q = np.asarray(query.descriptors)
    if q.ndim != 2 or q.shape[1] != DESCRIPTOR_DIM:
        raise InputError(f"query descriptors must be (N, 128), got {q.shape}")
    empty = Matches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
    if len(q) == 0 or index.num_descriptors < 2:
        return empty
    # k > max descriptors of one point guarantees a neighbour from another point when
    # the pool allows; otherwise the k-th distance is a lower bound of that distance,
    # which keeps the test conservative.
    k = int(min(index.num_descriptors, np.bincount(index.point_rows).max() + 1))
    idx, dist = _knn(index, np.ascontiguousarray(q, dtype=np.float32), k)
    prow = index.point_rows[idx]
    other = prow != prow[:, :1]
    j2 = np.where(other.any(axis=1), other.argmax(axis=1), k - 1)
    d1, d2 = dist[:, 0], dist[np.arange(len(dist)), j2]
    ok = d1 < options.ratio * d2
    if options.max_distance is not None:
        ok &= d1 <= options.max_distance
    qi = np.flatnonzero(ok)
    if len(qi) == 0:
        return empty
    order = qi[np.argsort(d1[qi], kind="stable")]
    _, first = np.unique(prow[order, 0], return_index=True)  # best match per 3D point
    sel = np.sort(order[first])
    return Matches(query_idx=sel.astype(np.int64), point_rows=prow[sel, 0].astype(np.int64),
                   distance=d1[sel].astype(np.float32))


# --------------------------------------------------------------------------- pose


def _pycolmap_options(options: PoseOptions) -> tuple[Any, Any]:
    """pycolmap AbsolutePoseEstimation/RefinementOptions from ours."""
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.estimate_focal_length = False
    est.ransac.max_error = float(options.ransac_max_error_px)
    est.ransac.min_inlier_ratio = float(options.ransac_min_inlier_ratio)
    est.ransac.confidence = float(options.ransac_confidence)
    est.ransac.max_num_trials = int(options.ransac_max_num_trials)
    est.ransac.random_seed = -1 if options.seed is None else int(options.seed)
    est.ransac.num_threads = 1
    ref = pycolmap.AbsolutePoseRefinementOptions()
    ref.loss_function_scale = float(options.loss_scale_px)
    ref.refine_focal_length = bool(options.refine_focal_length)
    ref.refine_extra_params = False
    return est, ref


def _run_pycolmap_pose(
    xy: F64, xyz: F64, camera: Camera, options: PoseOptions
) -> tuple[Pose, NDArray[np.bool_], Camera] | None:
    """LO-RANSAC P3P + Cauchy-loss refinement; None when pycolmap finds no pose."""
    est, ref = _pycolmap_options(options)
    cam = camera.to_pycolmap()  # refined in place when the focal length is refined
    try:
        out = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, cam, est, ref)
    except (ValueError, RuntimeError) as exc:  # pycolmap raises on degenerate input
        logger.debug("pycolmap absolute pose raised: %s", exc)
        return None
    if out is None:
        return None
    M = np.asarray(out["cam_from_world"].matrix(), dtype=np.float64)
    refined = Camera(camera.camera_id, camera.model, camera.width, camera.height,
                     np.asarray(cam.params, dtype=np.float64).copy())
    return Pose(M[:, :3].copy(), M[:, 3].copy()), np.asarray(out["inlier_mask"], bool), refined


def _focal_idxs(camera: Camera) -> list[int]:
    """Indices of the focal length parameter(s) in camera.params."""
    return [int(i) for i in camera.to_pycolmap().focal_length_idxs()]


def _projections(pose: Pose, camera: Camera, xyz: F64) -> F64:
    """(N, 2) pixels of world points."""
    return camera.project(pose.transform(xyz))


def _jacobian(pose: Pose, camera: Camera, xyz: F64, with_focal: bool) -> F64:
    """(2N, 6[+f]) d(pixels)/d(ω, δt[, f]) by central differences (any camera model)."""
    depth = float(np.median(np.abs(pose.transform(xyz)[:, 2])))
    cols = []
    for k in range(6):
        h = 1e-6 if k < 3 else 1e-6 * max(depth, 1e-12)
        d = np.zeros(6)
        d[k] = h
        plus = Pose(Rotation.from_rotvec(d[:3]).as_matrix() @ pose.R, pose.t + d[3:])
        minus = Pose(Rotation.from_rotvec(-d[:3]).as_matrix() @ pose.R, pose.t - d[3:])
        diff = _projections(plus, camera, xyz) - _projections(minus, camera, xyz)
        cols.append(diff.ravel() / (2 * h))
    for i in _focal_idxs(camera) if with_focal else []:
        h = 1e-6 * float(camera.params[i])
        p_plus, p_minus = camera.params.copy(), camera.params.copy()
        p_plus[i] += h
        p_minus[i] -= h
        c_plus = Camera(camera.camera_id, camera.model, camera.width, camera.height, p_plus)
        c_minus = Camera(camera.camera_id, camera.model, camera.width, camera.height, p_minus)
        diff = _projections(pose, c_plus, xyz) - _projections(pose, c_minus, xyz)
        cols.append(diff.ravel() / (2 * h))
    return np.column_stack(cols)


def _pose_covariance(
    pose: Pose, camera: Camera, xy: F64, xyz: F64, with_focal: bool
) -> tuple[F64 | None, float, float]:
    """(σ̂²-scaled 6×6 covariance or None if singular, σ̂ px, RMS residual norm px)."""
    res = _projections(pose, camera, xyz) - xy
    n = len(xy)
    J = _jacobian(pose, camera, xyz, with_focal)
    dof = 2 * n - J.shape[1]
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    if dof <= 0:
        return None, float("nan"), rms
    sigma2 = float(np.sum(res**2) / dof)
    JtJ = J.T @ J
    if not np.all(np.isfinite(JtJ)) or np.linalg.cond(JtJ) > 1e14:
        return None, float(np.sqrt(sigma2)), rms
    cov = sigma2 * np.linalg.inv(JtJ)[:6, :6]
    return 0.5 * (cov + cov.T), float(np.sqrt(sigma2)), rms


def _check_pose_inputs(xy: F64, xyz: F64) -> None:
    """Shapes and finiteness of the correspondences."""
    if xy.ndim != 2 or xy.shape[1] != 2 or xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"estimate_pose needs (N, 2) and (N, 3) arrays, got {xy.shape}, "
                         f"{xyz.shape}")
    if len(xy) != len(xyz):
        raise InputError(f"{len(xy)} image points but {len(xyz)} 3D points")
    if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(xyz))):
        raise InputError("non-finite 2D or 3D coordinates")


def _failed(reason: str, n: int, camera: Camera, mask: NDArray[np.bool_] | None = None,
            rms: float = float("nan"), sigma: float = float("nan")) -> PoseResult:
    """A rejected pose: diagnostics kept, no pose, no covariance."""
    mask = np.zeros(n, dtype=bool) if mask is None else mask
    return PoseResult(False, reason, None, None, n, int(mask.sum()), mask, rms, sigma, camera)


def _acceptance_reason(n: int, k: int, rms: float, options: PoseOptions) -> str | None:
    """Our acceptance rule (COLMAP's registrator thresholds); None when accepted."""
    if k < options.min_inliers:
        return f"only {k} inliers of {n} matches (need {options.min_inliers})"
    if k < options.min_inlier_ratio * n:
        return (f"inlier ratio {k / n:.2f} ({k} of {n} matches) below "
                f"{options.min_inlier_ratio:.2f}")
    if not rms <= options.max_reproj_error_px:
        return (f"RMS reprojection error {rms:.2f} px over {k} inliers exceeds "
                f"{options.max_reproj_error_px:.2f} px")
    return None


def estimate_pose(
    xy_px: F64, xyz_model: F64, camera: Camera, options: PoseOptions | RegistrationOptions
) -> PoseResult:
    """cam_from_world from 2D–3D matches: LO-RANSAC P3P + refinement, our acceptance rule."""
    if isinstance(options, RegistrationOptions):
        options = options.pose
    xy = np.ascontiguousarray(xy_px, dtype=np.float64)
    xyz = np.ascontiguousarray(xyz_model, dtype=np.float64)
    _check_pose_inputs(xy, xyz)
    n = len(xy)
    if n < 4:
        return _failed(f"only {n} matches (a pose needs at least 4; acceptance needs "
                       f"{options.min_inliers} inliers)", n, camera)
    found = _run_pycolmap_pose(xy, xyz, camera, options)
    if found is None:
        return _failed(f"RANSAC found no pose consistent with the {n} matches", n, camera)
    pose, mask, cam = found
    with_focal = options.refine_focal_length
    cov, sigma, rms = _pose_covariance(pose, cam, xy[mask], xyz[mask], with_focal)
    reason = _acceptance_reason(n, int(mask.sum()), rms, options)
    if reason is None and cov is None:
        reason = "pose covariance is singular (degenerate inlier geometry)"
    if reason is not None:
        logger.info("pose rejected: %s", reason)
        return _failed(reason, n, cam, mask, rms, sigma)
    return PoseResult(True, None, pose, cov, n, int(mask.sum()), mask, rms, sigma, cam)


def register_image(
    query: ImageFeatures, camera: Camera, index: DescriptorIndex, options: RegistrationOptions
) -> RegistrationResult:
    """Match a query image's features to the model and estimate its pose."""
    xy_all = np.asarray(query.xy_px, dtype=np.float64).reshape(-1, 2)
    if len(xy_all) and (xy_all.min() < -1 or xy_all[:, 0].max() > camera.width + 1
                        or xy_all[:, 1].max() > camera.height + 1):
        raise InputError(f"query keypoints fall outside the camera's {camera.width}×"
                         f"{camera.height} image: wrong camera or resized image?")
    t0 = time.perf_counter()
    matches = match_to_model(query, index, options.match)
    t1 = time.perf_counter()
    xy = xy_all[matches.query_idx]
    xyz = index.points_xyz[matches.point_rows]
    pose = estimate_pose(xy, xyz, camera, options.pose)
    t2 = time.perf_counter()
    m = pose.inlier_mask
    logger.info("registration: %d features, %d matches, %d inliers, %s", len(xy_all),
                len(matches), pose.num_inliers, "accepted" if pose.success else pose.reason)
    return RegistrationResult(
        matches=matches, pose=pose, inlier_xy_px=xy[m], inlier_xyz=xyz[m],
        inlier_point3D_ids=index.point3D_ids[matches.point_rows[m]],
        num_features=len(xy_all), match_time_s=t1 - t0, pose_time_s=t2 - t1,
    )


# --------------------------------------------------------------------------- logging


def configure_colmap_logging(verbose: bool) -> None:
    """Route COLMAP's own (glog) messages: warnings and up normally, everything when verbose."""
    pycolmap.logging.minloglevel = 0 if verbose else 2
    pycolmap.logging.stderrthreshold = 0 if verbose else 2
