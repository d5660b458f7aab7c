"""Settings of every registration step: SIFT, ties, descriptor index, matching, pose.

:class:`RegistrationOptions` bundles them; every function of the package also accepts it in
place of its own options.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from sfm_laserscale.errors import InputError

DESCRIPTOR_DIM = 128


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
