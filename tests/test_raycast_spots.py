"""Spot rays into the mesh: exact hits on closed-form surfaces and the depth-edge check."""

from __future__ import annotations

import numpy as np
import pytest

from sfm_laserscale.model import Camera, Pose, Spot
from sfm_laserscale.raycast import (
    EDGE_REASON,
    MeshRaycaster,
    SpotCastOptions,
    cast_spots,
)

CAMERA = Camera(1, "PINHOLE", 1000, 1000, np.array([1000.0, 1000.0, 500.0, 500.0]))
IDENTITY = Pose(np.eye(3), np.zeros(3))  # camera at the origin looking down +z
OPTS = SpotCastOptions()


def height_mesh(depth, half: float = 3.0, n: int = 601) -> MeshRaycaster:
    """A grid over [−half, half]² at z = depth(x, y) (vectorised), two triangles per cell."""
    g = np.linspace(-half, half, n)
    x, y = np.meshgrid(g, g, indexing="ij")
    verts = np.column_stack([x.ravel(), y.ravel(), depth(x, y).ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    tris = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                           np.stack([a, c, d], -1).reshape(-1, 3)])
    return MeshRaycaster(verts, tris)


def spot_at(x_px: float, y_px: float = 500.0, sigma: float = 1.0, laser: str = "L1") -> Spot:
    return Spot(laser, x_px, y_px, 1.0, sigma)


def test_hit_on_a_plane_is_the_exact_ray_intersection() -> None:
    plane = height_mesh(lambda x, y: 5.0 + 0.2 * x)
    res = cast_spots([spot_at(650.0, 420.0)], CAMERA, IDENTITY, plane, OPTS)
    assert not res.reasons and not res.edge_hits and len(res.hits) == 1
    ray = np.array([0.15, -0.08, 1.0])
    t = 5.0 / (1.0 - 0.2 * ray[0])  # z = t = 5 + 0.2 x = 5 + 0.2 t r_x
    np.testing.assert_allclose(res.hits[0].hit_world, t * ray, rtol=1e-12)
    n = np.array([-0.2, 0.0, 1.0]) / np.hypot(0.2, 1.0)
    np.testing.assert_allclose(np.abs(res.hits[0].normal_world), np.abs(n), atol=1e-12)


def test_spot_across_a_depth_step_is_rejected_with_a_reason() -> None:
    """A step from 5 m to 8 m at x = 0 (pixel column 500): a spot half a pixel from the step
    has a ring of 3 σ on both levels; a spot 100 px away does not."""
    step = height_mesh(lambda x, y: np.where(x < 0, 5.0, 8.0), half=1.0, n=401)
    spots = [spot_at(498.5, laser="L1"), spot_at(400.0, laser="L2")]
    res = cast_spots(spots, CAMERA, IDENTITY, step, OPTS)
    assert [h.laser for h in res.edge_hits] == ["L1"] and res.reasons == {"L1": EDGE_REASON}
    assert [h.laser for h in res.hits] == ["L2"]
    off = cast_spots(spots, CAMERA, IDENTITY, step, SpotCastOptions(edge_check=False))
    assert [h.laser for h in off.hits] == ["L1", "L2"] and not off.reasons


def test_crest_seen_edge_on_is_rejected_but_a_gentle_crease_is_kept() -> None:
    """A ridge seen nearly edge-on (steep faces, the far one hidden) breaks the tangent plane;
    a roof of ±0.2 slopes under the spot is a crease the first-order σ still describes."""
    gentle = height_mesh(lambda x, y: 5.0 + 0.2 * np.abs(x))
    assert cast_spots([spot_at(500.0, sigma=0.5)], CAMERA, IDENTITY, gentle, OPTS).hits
    steep = height_mesh(lambda x, y: 5.0 - 6.0 * np.clip(0.3 - np.abs(x - 0.3), 0, None),
                        half=1.0, n=801)
    # the camera ray at x_px = 500 + 1000 * 0.3 / 3.2 meets the near face close to the ridge
    res = cast_spots([spot_at(593.0, sigma=1.0)], CAMERA, IDENTITY, steep, OPTS)
    assert res.edge_hits and not res.hits


def test_missing_spot_and_no_sigma() -> None:
    plane = height_mesh(lambda x, y: 5.0 + 0 * x, half=0.5)
    far = spot_at(990.0)  # ray leaves the small plane
    zero = Spot("L2", 500.0, 500.0, 1.0, 0.0)  # no σ: the check cannot apply, the hit is kept
    res = cast_spots([far, zero], CAMERA, IDENTITY, plane, OPTS)
    assert res.reasons == {"L1": "ray through the spot misses the mesh"}
    assert [h.laser for h in res.hits] == ["L2"]
    assert cast_spots([], CAMERA, IDENTITY, plane, OPTS).hits == ()


@pytest.fixture(scope="module")
def floor() -> MeshRaycaster:
    """A gently undulating floor: 1 cm bumps over 20 cm at 5 m."""
    return height_mesh(lambda x, y: 5.0 + 0.01 * np.sin(x / 0.2 * 2 * np.pi)
                       * np.cos(y / 0.2 * 2 * np.pi), half=2.5, n=801)


@pytest.mark.parametrize("sigma", [0.3, 1.0, 2.0])
def test_smooth_rough_plane_never_rejected(floor: MeshRaycaster, sigma: float) -> None:
    """Bumps are not edges, at any σ."""
    xs = np.linspace(100, 900, 9)
    spots = [spot_at(float(x), float(x), sigma, laser=f"L{i}") for i, x in enumerate(xs)]
    res = cast_spots(spots, CAMERA, IDENTITY, floor, OPTS)
    assert len(res.hits) == 9 and not res.edge_hits
