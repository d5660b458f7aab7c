"""In-memory sparse model shared by every stage (COLMAP conventions, model units).

Readers (``sfm_laserscale.io``) build it from COLMAP or OpenMVG files; no stage
writes files from it directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import pycolmap
from numpy.typing import NDArray

INVALID_POINT3D_ID = np.uint64(2**64 - 1)

#: COLMAP camera model name -> number of parameters.
CAMERA_MODEL_NUM_PARAMS: dict[str, int] = {
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 4,
    "RADIAL": 5,
    "OPENCV": 8,
    "OPENCV_FISHEYE": 8,
    "FULL_OPENCV": 12,
    "FOV": 5,
    "SIMPLE_RADIAL_FISHEYE": 4,
    "RADIAL_FISHEYE": 5,
    "THIN_PRISM_FISHEYE": 12,
    "RAD_TAN_THIN_PRISM_FISHEYE": 16,
    "SIMPLE_DIVISION": 4,
    "DIVISION": 5,
    "SIMPLE_FISHEYE": 3,
    "FISHEYE": 4,
    "EUCM": 6,
    "EQUIRECTANGULAR": 2,
}
#: COLMAP model id (binary files) -> name.
CAMERA_MODEL_NAMES: dict[int, str] = {
    0: "SIMPLE_PINHOLE",
    1: "PINHOLE",
    2: "SIMPLE_RADIAL",
    3: "RADIAL",
    4: "OPENCV",
    5: "OPENCV_FISHEYE",
    6: "FULL_OPENCV",
    7: "FOV",
    8: "SIMPLE_RADIAL_FISHEYE",
    9: "RADIAL_FISHEYE",
    10: "THIN_PRISM_FISHEYE",
    11: "RAD_TAN_THIN_PRISM_FISHEYE",
    12: "SIMPLE_DIVISION",
    13: "DIVISION",
    14: "SIMPLE_FISHEYE",
    15: "FISHEYE",
    16: "EUCM",
    17: "EQUIRECTANGULAR",
}
CAMERA_MODEL_IDS: dict[str, int] = {v: k for k, v in CAMERA_MODEL_NAMES.items()}


@dataclass(frozen=True)
class Camera:
    """Intrinsics in COLMAP's model names and pixel convention (pixel centres at +0.5)."""

    camera_id: int
    model: str
    width: int
    height: int
    params: NDArray[np.float64]

    def to_pycolmap(self) -> pycolmap.Camera:
        """The same camera as a ``pycolmap.Camera`` (projection maths and estimators)."""
        cam = pycolmap.Camera(
            model=self.model,
            width=int(self.width),
            height=int(self.height),
            params=np.asarray(self.params, dtype=np.float64),
        )
        cam.camera_id = int(self.camera_id)
        return cam

    def project(self, xyz_cam: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 3) camera-frame points (z > 0) -> (N, 2) pixels."""
        pts = np.ascontiguousarray(np.atleast_2d(xyz_cam), dtype=np.float64)
        return np.asarray(self.to_pycolmap().img_from_cam(pts), dtype=np.float64)

    def unproject(self, xy_px: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 2) pixels -> (N, 3) camera-frame ray directions with z = 1 (not unit)."""
        pts = np.ascontiguousarray(np.atleast_2d(xy_px), dtype=np.float64)
        xy = np.asarray(self.to_pycolmap().cam_from_img(pts), dtype=np.float64)
        return np.column_stack([xy, np.ones(len(xy))])

    @property
    def focal_px(self) -> float:
        """Mean focal length in pixels."""
        if self.model in (
            "SIMPLE_PINHOLE",
            "SIMPLE_RADIAL",
            "RADIAL",
            "FOV",
            "SIMPLE_RADIAL_FISHEYE",
            "RADIAL_FISHEYE",
            "SIMPLE_DIVISION",
            "SIMPLE_FISHEYE",
        ):
            return float(self.params[0])
        return float(0.5 * (self.params[0] + self.params[1]))


@dataclass(frozen=True)
class Pose:
    """Rigid transform ``cam_from_world``: X_cam = R X_world + t."""

    R: NDArray[np.float64]  # (3, 3)
    t: NDArray[np.float64]  # (3,)

    @property
    def center(self) -> NDArray[np.float64]:
        """Camera centre in world coordinates, −Rᵀ t."""
        return np.asarray(-self.R.T @ self.t, dtype=np.float64)

    def transform(self, xyz_world: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 3) world points -> (N, 3) camera-frame points."""
        return np.asarray(np.atleast_2d(xyz_world) @ self.R.T + self.t, dtype=np.float64)

    def inverse(self) -> Pose:
        """``world_from_cam``."""
        return Pose(self.R.T.copy(), -self.R.T @ self.t)


@dataclass(frozen=True)
class Image:
    """A registered image of the model with its 2D observations."""

    image_id: int
    name: str
    camera_id: int
    cam_from_world: Pose
    xy_px: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))  # (N, 2)
    point3D_ids: NDArray[np.uint64] = field(
        default_factory=lambda: np.zeros(0, dtype=np.uint64)
    )  # (N,), INVALID_POINT3D_ID where the observation has no 3D point


@dataclass(frozen=True)
class SparseModel:
    """Cameras, registered images and 3D points of one reconstruction (model units)."""

    cameras: dict[int, Camera]
    images: dict[int, Image]
    point3D_ids: NDArray[np.uint64]  # (M,)
    points_xyz: NDArray[np.float64]  # (M, 3), model units
    source_format: str = "memory"  # colmap-text | colmap-binary | openmvg | memory

    @cached_property
    def point_index(self) -> dict[int, int]:
        """3D point id -> row in ``points_xyz``."""
        return {int(p): i for i, p in enumerate(self.point3D_ids)}

    def image_by_name(self, name: str) -> Image | None:
        """The image with this file name, or None."""
        for im in self.images.values():
            if im.name == name:
                return im
        return None

    def without_observations(self) -> SparseModel:
        """The same cameras, poses and points without the images' 2D observations (at 1M
        points 46 MB of the model's 76), for work after the descriptor index."""
        images = {k: replace(im, xy_px=np.zeros((0, 2)),
                             point3D_ids=np.zeros(0, dtype=np.uint64))
                  for k, im in self.images.items()}
        return replace(self, images=images)

    def scaled(self, scale: float) -> SparseModel:
        """The same model with every length times ``scale``: image translations and points
        (rotations, cameras and observations unchanged)."""
        images = {k: replace(im, cam_from_world=Pose(im.cam_from_world.R,
                                                     im.cam_from_world.t * scale))
                  for k, im in self.images.items()}
        return replace(self, images=images, points_xyz=self.points_xyz * scale)

    @cached_property
    def extent(self) -> float:
        """Diagonal of the 2–98 % percentile box of the 3D points (model units)."""
        if len(self.points_xyz) == 0:
            return 0.0
        xyz = np.asarray(self.points_xyz)
        lo, hi = np.array([np.percentile(xyz[:, j], [2, 98]) for j in range(3)]).T
        return float(np.linalg.norm(hi - lo))


@dataclass(frozen=True)
class ImageFeatures:
    """Keypoints and SIFT descriptors of one image (COLMAP pixel convention, COLMAP bin order)."""

    xy_px: NDArray[np.float64]  # (N, 2)
    descriptors: NDArray[np.uint8]  # (N, 128)


@dataclass(frozen=True)
class ObservationFeatures:
    """Descriptors tied to some observations of one model image (re-extracted SIFT)."""

    observation_idx: NDArray[np.int64]  # (K,) rows of Image.xy_px / Image.point3D_ids
    descriptors: NDArray[np.uint8]  # (K, 128), COLMAP bin order
    tie_distance_px: NDArray[np.float64]  # (K,) keypoint-to-observation distance, pixels


@dataclass(frozen=True)
class Spot:
    """A laser spot in one image: sub-pixel centre (COLMAP convention), score and pixel sigma."""

    laser: str
    x: float
    y: float
    score: float = 1.0  # detector confidence in [0, 1]; 1.0 for spots given by hand
    sigma_px: float = 0.3  # 1-sigma localisation uncertainty per axis, pixels
    source: str = "detected"  # detected | guided (found where the model puts it) | manual
