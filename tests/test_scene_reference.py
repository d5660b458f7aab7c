"""A scene reference rendered from model images through the mesh, against closed-form views of
a textured plane: where the mesh is, it is the laser view's own texture; elsewhere NaN."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sfm_laserscale.errors import InputError
from sfm_laserscale.geometry import rotmat_from_qvec
from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.raycast import MeshRaycaster
from sfm_laserscale.scene_reference import (
    ModelView,
    SceneReferenceOptions,
    nearest_views,
    render_scene_reference,
)

CAMERA = Camera(1, "PINHOLE", 320, 240, np.array([300.0, 300.0, 160.0, 120.0]))


def _texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N, 3) colour of the floor z = 0 at (x, y) (model units), 8-bit levels."""
    return np.stack([128 + 50 * np.sin(2 * np.pi * x / 0.25) * np.cos(2 * np.pi * y / 0.3),
                     110 + 40 * np.cos(2 * np.pi * (x + y) / 0.2),
                     90 + 30 * np.sin(2 * np.pi * y / 0.17)], axis=1)


def _pose(centre: tuple[float, float, float], yaw_deg: float = 0.0) -> Pose:
    half = math.radians(yaw_deg) / 2
    R = rotmat_from_qvec(np.array([math.cos(half), 0.0, math.sin(half), 0.0]))
    return Pose(R, -R @ np.asarray(centre, dtype=np.float64))


def _view(pose: Pose, gain: float = 1.0) -> np.ndarray:
    """What a camera at ``pose`` sees of the textured floor, exactly (H, W, 3) float."""
    rows, cols = np.mgrid[0:CAMERA.height, 0:CAMERA.width]
    xy = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], axis=1).astype(np.float64)
    d_world = CAMERA.unproject(xy) @ pose.R  # R^T applied to row vectors
    centre = pose.center
    t = -centre[2] / d_world[:, 2]
    hit = centre + t[:, None] * d_world
    return (gain * _texture(hit[:, 0], hit[:, 1])).reshape(CAMERA.height, CAMERA.width, 3)


def _floor(x_max: float) -> MeshRaycaster:
    """The plane z = 0 for -3 <= x <= x_max, -3 <= y <= 3 (two triangles)."""
    verts = np.array([[-3, -3, 0], [x_max, -3, 0], [x_max, 3, 0], [-3, 3, 0]], dtype=float)
    return MeshRaycaster(verts, np.array([[0, 1, 2], [0, 2, 3]]))


def test_the_reference_is_the_laser_views_texture_where_the_mesh_is() -> None:
    """Three nearby model images of a floor 2 units below, two of them 20 % brighter than the
    nearest (whose level the others are brought to); a far one that is not used. Where the
    mesh is, the reference is the laser camera's own view of the floor within interpolation
    and 8-bit rounding (measured: mean 0.16, p99 0.49 levels); beyond the mesh's edge
    (x > 0.2) it is NaN."""
    laser = _pose((0.0, 0.0, -2.0))
    near = [(_pose((0.15, 0.05, -2.1), 2.0), 1.2), (_pose((-0.1, 0.12, -1.95), -3.0), 1.2),
            (_pose((0.05, -0.1, -2.05), 1.0), 1.0)]  # the last is the nearest: its level
    far = (_pose((3.0, 0.0, -2.0)), 1.0)
    views = [ModelView(CAMERA, pose, np.clip(np.rint(_view(pose, gain)), 0, 255).astype(np.uint8))
             for pose, gain in [far, *near]]
    ref = render_scene_reference(CAMERA, laser, _floor(0.2), views)
    assert ref.views[0] != 0 and sorted(ref.views) == [1, 2, 3]
    truth = _view(laser)
    known = np.isfinite(ref.rgb[..., 0])
    cols = np.arange(CAMERA.width)[None, :].repeat(CAMERA.height, axis=0)
    x_floor = (cols + 0.5 - 160.0) / 300.0 * 2.0  # the floor's x under each pixel
    inner = np.zeros_like(known)
    inner[30:-30, 30:] = True  # the model images together see all but the laser view's rim
    # rays every grid_px = 4 px: a pixel within a grid step of the floor's edge may be unknown
    assert not known[x_floor > 0.21].any() and known[inner & (x_floor < 0.17)].all()
    assert ref.coverage == pytest.approx(known.mean())
    err = np.abs(ref.rgb[known] - truth[known])
    assert err.mean() < 0.3 and np.percentile(err, 99) < 1.0


def test_the_nearest_views_and_bad_options() -> None:
    views = [ModelView(CAMERA, _pose((x, 0.0, -2.0)), np.zeros((240, 320, 3), np.uint8))
             for x in (3.0, 0.5, -1.0, 0.1)]
    assert nearest_views(np.array([v.cam_from_world.center for v in views]),
                         np.array([0.0, 0.0, -2.0]), 2) == [3, 1]
    with pytest.raises(InputError, match="n_views"):
        SceneReferenceOptions(n_views=0)
    with pytest.raises(InputError, match="at least one model image"):
        render_scene_reference(CAMERA, _pose((0, 0, -2)), _floor(3.0), [])
