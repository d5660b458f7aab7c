"""A scene reference for a laser image: the model images rendered into its pose through the mesh.

A registered laser image sees a seafloor the model images saw without the lasers. For every
pixel of the laser image the ray through it is cast into the mesh (its first hit,
:class:`sfm_laserscale.raycast.MeshRaycaster`); the hit is projected into the ``n_views`` model
images whose centres lie nearest the laser camera's and sampled there (bilinear). The views are
brought to the first one's level (per channel, the ratio of their medians over the pixels both
see: exposure and lamps differ between photographs) and their per-pixel median is the
reference, so what one view alone holds (a particle in the water, a glint) drops out. A pixel
that no view sees (no hit, behind a camera, outside every image) is NaN.

Occlusion is not tested: the nearest views of a survey look at the floor from nearly the
laser camera's place, and a hit hidden from one of them by relief is outvoted by the median
only when the others see it. The detector uses the reference's fine texture only
(:mod:`sfm_laserscale.detection.scene`); docs/DETECTION.md ("A scene reference") has how well
it must fit.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.raycast import MeshRaycaster, pixel_rays

#: rays cast at once (about 100 bytes each in flight)
RAY_CHUNK = 1 << 20


@dataclass(frozen=True)
class ModelView:
    """A model image: its camera, pose (model frame) and pixels (H, W, 3) uint8 RGB."""

    camera: Camera
    cam_from_world: Pose
    image_rgb: NDArray[np.uint8]


@dataclass(frozen=True)
class SceneReferenceOptions:
    """``n_views``: the nearest model images rendered; ``min_shared_px``: pixels two views
    must share before one is brought to the other's level (fewer: left as it is)."""

    n_views: int = 3
    min_shared_px: int = 1000

    def __post_init__(self) -> None:
        if self.n_views < 1:
            raise InputError(f"n_views must be at least 1, got {self.n_views}")


@dataclass(frozen=True)
class SceneReference:
    """The reference (H, W, 3) float32 in 8-bit levels, NaN where no view sees the pixel; the
    indices of the views used (nearest first) and the share of the pixels covered."""

    rgb: NDArray[np.float32]
    views: tuple[int, ...]
    coverage: float


def nearest_views(views: Sequence[ModelView], centre_world: NDArray[np.float64],
                  n: int) -> list[int]:
    """Indices of the ``n`` views whose camera centres lie nearest ``centre_world``."""
    dist = [float(np.linalg.norm(v.cam_from_world.center - centre_world)) for v in views]
    return [int(i) for i in np.argsort(dist, kind="stable")[:n]]


def pixel_hits(camera: Camera, cam_from_world: Pose, caster: MeshRaycaster
               ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The mesh's first hit (H·W, 3; model frame) through every pixel centre, row-major, and
    whether there is one."""
    rows, cols = np.mgrid[0:camera.height, 0:camera.width]
    xy_px = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], axis=1).astype(np.float64)
    xyz = np.full((len(xy_px), 3), np.nan)
    hit = np.zeros(len(xy_px), dtype=bool)
    world_from_cam = cam_from_world.inverse()
    for start in range(0, len(xy_px), RAY_CHUNK):
        part = slice(start, start + RAY_CHUNK)
        origins, directions = pixel_rays(camera, world_from_cam, xy_px[part])
        cast = caster.cast(origins, directions)
        xyz[part], hit[part] = cast.xyz, cast.hit
    return xyz, hit


def sample_view(view: ModelView, xyz_world: NDArray[np.float64], hit: NDArray[np.bool_],
                shape: tuple[int, int]) -> NDArray[np.float32]:
    """``view``'s pixels at the points (N, 3) = H·W, bilinear, as (H, W, 3) float32; NaN
    where there is no point, it lies behind the camera or outside the image."""
    xyz_cam = view.cam_from_world.transform(np.where(hit[:, None], xyz_world, 0.0))
    ahead = hit & (xyz_cam[:, 2] > 0)
    uv = np.full((len(xyz_cam), 2), -1.0)
    uv[ahead] = view.camera.project(xyz_cam[ahead])
    # COLMAP pixels: the centre of the top-left pixel is (0.5, 0.5); OpenCV's is (0, 0)
    map_x = (uv[:, 0] - 0.5).reshape(shape).astype(np.float32)
    map_y = (uv[:, 1] - 0.5).reshape(shape).astype(np.float32)
    height, width = view.image_rgb.shape[:2]
    sampled = cv2.remap(view.image_rgb.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
    inside = (ahead.reshape(shape) & (map_x >= 0) & (map_y >= 0)
              & (map_x <= width - 1) & (map_y <= height - 1))
    sampled[~inside] = np.nan
    return sampled


def match_levels(samples: list[NDArray[np.float32]], min_shared_px: int) -> None:
    """In place: every view after the first scaled, per channel, by the ratio of the first's
    median to its own over the pixels both see (when they share ``min_shared_px``)."""
    first_known = np.isfinite(samples[0]).all(axis=2)
    for other in samples[1:]:
        shared = first_known & np.isfinite(other).all(axis=2)
        if shared.sum() < min_shared_px:
            continue
        for ch in range(3):
            own = float(np.median(other[shared, ch]))
            if own > 0:
                other[..., ch] *= np.float32(float(np.median(samples[0][shared, ch])) / own)


def render_scene_reference(camera: Camera, cam_from_world: Pose, caster: MeshRaycaster,
                           views: Sequence[ModelView],
                           options: SceneReferenceOptions = SceneReferenceOptions(),  # noqa: B008
                           ) -> SceneReference:
    """The model images rendered into a laser image's pose through the mesh (module
    docstring)."""
    if not views:
        raise InputError("a scene reference needs at least one model image")
    chosen = nearest_views(views, cam_from_world.center, options.n_views)
    shape = (camera.height, camera.width)
    xyz, hit = pixel_hits(camera, cam_from_world, caster)
    samples = [sample_view(views[i], xyz, hit, shape) for i in chosen]
    match_levels(samples, options.min_shared_px)
    stack = np.stack(samples)  # (views, H, W, 3): a pixel a view misses is NaN in all three
    with warnings.catch_warnings():  # pixels no view sees are NaN by design
        warnings.filterwarnings("ignore", message="All-NaN slice encountered")
        rgb = np.nanmedian(stack, axis=0).astype(np.float32)
    covered = np.isfinite(rgb[..., 0])
    return SceneReference(rgb=rgb, views=tuple(chosen), coverage=float(covered.mean()))

