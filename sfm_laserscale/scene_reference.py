"""A scene reference for a laser image: the model images rendered into its pose through the mesh.

A registered laser image sees a seafloor the model images saw without the lasers. Rays
through a grid of the laser image's pixels, every ``grid_px``, are cast into the mesh (first
hits, :class:`sfm_laserscale.raycast.MeshRaycaster`); the hits are projected into the
``n_views`` model images whose centres lie nearest the laser camera's, each pixel's place in a
view is interpolated bilinearly between the grid's (the mesh is smooth at a few pixels; a
pixel next to a grid ray that misses is unknown), and the view is sampled there (bilinear). The
views are
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
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.raycast import MeshRaycaster, pixel_rays
from sfm_laserscale.scene_fit import SceneFitOptions

#: rays cast at once (about 100 bytes each in flight); on a cropped caster fewer, as its
#: coverage check samples every ray along its length
RAY_CHUNK = 1 << 20
CROP_RAY_CHUNK = 1 << 13
#: the views' levels are matched on every LEVEL_STRIDE-th pixel (rows and columns)
LEVEL_STRIDE = 4


@dataclass(frozen=True)
class ModelView:
    """A model image: its camera, pose (model frame) and pixels (H, W, 3) uint8 RGB."""

    camera: Camera
    cam_from_world: Pose
    image_rgb: NDArray[np.uint8]


@dataclass(frozen=True)
class SceneReferenceOptions:
    """``n_views``: the nearest model images rendered; ``min_shared_px``: pixels two views
    must share before one is brought to the other's level (fewer: left as it is);
    ``grid_px``: rays are cast every ``grid_px`` pixels and the views' coordinates
    interpolated between them."""

    n_views: int = 3
    min_shared_px: int = 1000
    grid_px: int = 4

    def __post_init__(self) -> None:
        if self.n_views < 1:
            raise InputError(f"n_views must be at least 1, got {self.n_views}")
        if self.grid_px < 1:
            raise InputError(f"grid_px must be at least 1, got {self.grid_px}")


@dataclass(frozen=True)
class SceneStageOptions:
    """How ``scale`` uses scene references (scene_stage.py). ``enabled``: render references
    and detect again; ``render``, ``fit``: the render's and the fit's options;
    ``min_coverage``: the share of the image the fitted reference must still cover to be
    used; ``max_whole_triangles``, ``crop_grid_px``: a larger mesh is cropped per image to
    rays every ``crop_grid_px``;
    ``keep_png``: keep each used reference as a 16-bit RGBA PNG (alpha 0: unknown) for
    ``--save-scene-references``."""

    enabled: bool = True
    render: SceneReferenceOptions = field(default_factory=SceneReferenceOptions)
    fit: SceneFitOptions = field(default_factory=SceneFitOptions)
    min_coverage: float = 0.05
    keep_png: bool = False
    # a mesh of more triangles is cropped per laser image to the render's rays, cast every
    # crop_grid_px then (footprints.py's limit: no caster on much more at once)
    max_whole_triangles: int = 4_000_000
    crop_grid_px: int = 8

    def __post_init__(self) -> None:
        if not 0 <= self.min_coverage <= 1:
            raise InputError(f"min_coverage must be in [0, 1], got {self.min_coverage}")
        if self.max_whole_triangles < 0 or self.crop_grid_px < 1:
            raise InputError("max_whole_triangles must be >= 0 and crop_grid_px >= 1, got "
                             f"{self.max_whole_triangles} and {self.crop_grid_px}")



@dataclass(frozen=True)
class SceneReference:
    """The reference (H, W, 3) float32 in 8-bit levels, NaN where no view sees the pixel; the
    indices of the views used (nearest first) and the share of the pixels covered."""

    rgb: NDArray[np.float32]
    views: tuple[int, ...]
    coverage: float


def nearest_views(centres_world: NDArray[np.float64], centre_world: NDArray[np.float64],
                  n: int) -> list[int]:
    """Indices of the ``n`` camera centres (N, 3; model frame) nearest ``centre_world``."""
    dist = np.linalg.norm(np.asarray(centres_world).reshape(-1, 3) - centre_world, axis=1)
    return [int(i) for i in np.argsort(dist, kind="stable")[:n]]


def grid_pixels(size: int, step_px: int) -> NDArray[np.float64]:
    """Pixel centres (COLMAP) every ``step_px`` along an axis of ``size`` px, the last one's
    centre included: 0.5, 0.5 + step, ..., size − 0.5."""
    n = max(2, -(-(size - 1) // step_px) + 1)
    return np.linspace(0.5, size - 0.5, n)


def grid_xy(camera: Camera, step_px: int) -> NDArray[np.float64]:
    """The grid's pixel centres (rows, cols, 2; COLMAP x, y) every ``step_px``
    (:func:`grid_pixels` along each axis)."""
    xs, ys = grid_pixels(camera.width, step_px), grid_pixels(camera.height, step_px)
    return np.stack(np.meshgrid(xs, ys), axis=-1)


def grid_hits(camera: Camera, cam_from_world: Pose, caster: MeshRaycaster, step_px: int
              ) -> NDArray[np.float64]:
    """The mesh's first hit (model frame) through the pixel centres of a grid every
    ``step_px`` (:func:`grid_xy`): (rows, cols, 3), NaN where the ray misses."""
    grid = grid_xy(camera, step_px)
    xy_px = grid.reshape(-1, 2)
    xyz = np.full((len(xy_px), 3), np.nan)
    world_from_cam = cam_from_world.inverse()
    chunk = RAY_CHUNK if caster.coverage is None else CROP_RAY_CHUNK
    for start in range(0, len(xy_px), chunk):
        part = slice(start, start + chunk)
        origins, directions = pixel_rays(camera, world_from_cam, xy_px[part])
        cast = caster.cast(origins, directions)
        xyz[part] = np.where(cast.hit[:, None], cast.xyz, np.nan)
    return xyz.reshape(*grid.shape[:2], 3)


def _grid_maps(camera: Camera, grid_shape: tuple[int, int]
               ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Per pixel (H, W) of the image, its fractional column and row in the grid."""
    cols = np.arange(camera.width, dtype=np.float32) * np.float32(
        (grid_shape[1] - 1) / max(camera.width - 1, 1))
    rows = np.arange(camera.height, dtype=np.float32) * np.float32(
        (grid_shape[0] - 1) / max(camera.height - 1, 1))
    return (np.broadcast_to(cols[None, :], (camera.height, camera.width)).copy(),
            np.broadcast_to(rows[:, None], (camera.height, camera.width)).copy())


def view_coordinates(view: ModelView, xyz_grid: NDArray[np.float64],
                     maps: tuple[NDArray[np.float32], NDArray[np.float32]]
                     ) -> NDArray[np.float32]:
    """Where each pixel of the laser image lies in ``view`` (H, W, 2; COLMAP px): the grid's
    hits projected into the view, interpolated bilinearly between grid points; NaN next to a
    grid point without a hit or behind the view's camera."""
    flat = xyz_grid.reshape(-1, 3)
    known: NDArray[np.bool_] = np.asarray(np.isfinite(flat).all(axis=1))
    xyz_cam = view.cam_from_world.transform(np.where(known[:, None], flat, 0.0))
    ahead = known & (xyz_cam[:, 2] > 0)
    uv = np.full((len(flat), 2), np.nan)
    uv[ahead] = view.camera.project(xyz_cam[ahead])
    uv_grid = uv.reshape(*xyz_grid.shape[:2], 2).astype(np.float32)
    # bilinear with NaN: a pixel with an unknown grid corner is unknown
    return cv2.remap(uv_grid, maps[0], maps[1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def sample_view(view: ModelView, uv_px: NDArray[np.float32]) -> NDArray[np.float32]:
    """``view``'s pixels at the COLMAP coordinates ``uv_px`` (H, W, 2), bilinear, as
    (H, W, 3) float32; NaN where the coordinates are unknown or outside the image."""
    # COLMAP pixels: the centre of the top-left pixel is (0.5, 0.5); OpenCV's is (0, 0)
    map_x = uv_px[..., 0] - np.float32(0.5)
    map_y = uv_px[..., 1] - np.float32(0.5)
    height, width = view.image_rgb.shape[:2]
    inside: NDArray[np.bool_] = ((map_x >= 0) & (map_y >= 0) & (map_x <= width - 1)
                                 & (map_y <= height - 1))
    # float pixels: OpenCV rounds a uint8 remap to whole levels
    sampled = cv2.remap(view.image_rgb.astype(np.float32),
                        np.where(inside, map_x, -1).astype(np.float32),
                        np.where(inside, map_y, -1).astype(np.float32), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
    sampled[~inside] = np.nan
    return sampled


def match_levels(samples: list[NDArray[np.float32]], min_shared_px: int) -> None:
    """In place: every view after the first scaled, per channel, by the ratio of the first's
    median to its own over the pixels both see (when they share ``min_shared_px``; the
    medians over every LEVEL_STRIDE-th pixel of each row and column)."""
    first = samples[0][::LEVEL_STRIDE, ::LEVEL_STRIDE]
    first_known = np.isfinite(first).all(axis=2)
    for other in samples[1:]:
        thin = other[::LEVEL_STRIDE, ::LEVEL_STRIDE]
        shared = first_known & np.isfinite(thin).all(axis=2)
        if shared.sum() * LEVEL_STRIDE ** 2 < min_shared_px:
            continue
        for ch in range(3):
            own = float(np.median(thin[shared, ch]))
            if own > 0:
                other[..., ch] *= np.float32(float(np.median(first[shared, ch])) / own)


def render_scene_reference(camera: Camera, cam_from_world: Pose, caster: MeshRaycaster,
                           views: Sequence[ModelView],
                           options: SceneReferenceOptions = SceneReferenceOptions(),  # noqa: B008
                           ) -> SceneReference:
    """The model images rendered into a laser image's pose through the mesh (module
    docstring)."""
    if not views:
        raise InputError("a scene reference needs at least one model image")
    centres = np.array([v.cam_from_world.center for v in views])
    chosen = nearest_views(centres, cam_from_world.center, options.n_views)
    xyz_grid = grid_hits(camera, cam_from_world, caster, options.grid_px)
    maps = _grid_maps(camera, xyz_grid.shape[:2])
    samples = [sample_view(views[i], view_coordinates(views[i], xyz_grid, maps))
               for i in chosen]
    match_levels(samples, options.min_shared_px)
    stack = np.stack(samples)  # (views, H, W, 3): a pixel a view misses is NaN in all three
    with warnings.catch_warnings():  # pixels no view sees are NaN by design
        warnings.filterwarnings("ignore", message="All-NaN slice encountered")
        rgb = np.nanmedian(stack, axis=0).astype(np.float32)
    covered = np.isfinite(rgb[..., 0])
    return SceneReference(rgb=rgb, views=tuple(chosen), coverage=float(covered.mean()))

