"""raycast.crop_for_rays: a caster on the crop gives the whole mesh's first hits and distances."""

from __future__ import annotations

import numpy as np
import pytest

from sfm_laserscale.model import Camera, Pose, Spot
from sfm_laserscale.raycast import (
    CropOptions,
    MeshRaycaster,
    SpotCastOptions,
    cast_spots,
    crop_for_rays,
    spot_cast_rays,
)

CAMERA = Camera(1, "PINHOLE", 1000, 1000, np.array([1000.0, 1000.0, 500.0, 500.0]))


def camera_looking_down(centre: np.ndarray) -> Pose:
    """cam_from_world of a camera at ``centre`` looking down −z (image y along −world y)."""
    R = np.diag([1.0, -1.0, -1.0])
    return Pose(R, -R @ centre)


def bumpy_grid(n: int, rng: np.random.Generator, size: float = 10.0,
               jitter: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """A height field with an overhanging fin (rays may meet it before the floor)."""
    x, y = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n))
    z = 0.3 * np.sin(3 * x) * np.cos(2 * y) + jitter * rng.normal(size=x.shape)
    v = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    f = np.vstack([np.column_stack([a, b, c]), np.column_stack([b, d, c])])
    # a free-floating vertical fin above the floor and one huge triangle across the box
    fin = np.array([[4.0, 3.0, 1.0], [6.0, 3.0, 1.0], [5.0, 3.0, 2.5],
                    [-1.0, -1.0, 4.0], [11.0, -1.0, 4.0], [5.0, 11.0, 4.0]])
    f = np.vstack([f, len(v) + np.array([[0, 1, 2], [3, 4, 5]])])
    return np.vstack([v, fin]), f.astype(np.int32)


def random_rays(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    o = np.array([5.0, 5.0, 3.0]) + rng.normal(size=(n, 3)) * np.array([2.0, 2.0, 0.3])
    d = np.column_stack([rng.normal(size=(n, 2)) * 0.4, -np.ones(n)])
    return o, d


@pytest.mark.parametrize("cells", [8, 64, 256])
def test_crop_gives_the_whole_mesh_first_hits(cells: int) -> None:
    rng = np.random.default_rng(cells)
    v, f = bumpy_grid(120, rng)
    f = f[:-1]  # without the big lid (its hits would hide everything)
    o, d = random_rays(rng, 60)
    whole = MeshRaycaster(v, f).cast(o, d)
    crop = crop_for_rays(v, f, o, d, options=CropOptions(grid_cells=cells))
    got = crop.raycaster().cast(o, d)
    np.testing.assert_array_equal(got.hit, whole.hit)
    np.testing.assert_allclose(got.xyz[got.hit], whole.xyz[whole.hit], atol=1e-12)
    np.testing.assert_allclose(got.normal[got.hit], whole.normal[whole.hit], atol=1e-12)
    assert whole.hit.sum() > 40  # the rays do meet the mesh (some through the fin)
    if cells == 256:  # a few rays keep a small part of the mesh
        assert crop_for_rays(v, f, o[:5], d[:5], options=CropOptions(grid_cells=cells)
                             ).kept_fraction < 0.35


def test_triangles_larger_than_a_cell_are_always_kept() -> None:
    rng = np.random.default_rng(1)
    v, f = bumpy_grid(60, rng)
    o, d = random_rays(rng, 10)
    o[:, 2] = 6.0  # above the lid at z = 4
    crop = crop_for_rays(v, f, o, d, options=CropOptions(grid_cells=128))
    lid = v[f[-1]]
    assert any(np.allclose(np.sort(crop.vertices[t], axis=0), np.sort(lid, axis=0))
               for t in crop.triangles)
    whole = MeshRaycaster(v, f).cast(o, d)
    got = crop.raycaster().cast(o, d)
    np.testing.assert_array_equal(got.hit, whole.hit)
    np.testing.assert_allclose(got.xyz[got.hit], whole.xyz[whole.hit], atol=1e-12)
    assert np.sum(np.isclose(got.xyz[:, 2], 4.0)) >= 7  # most rays meet the lid first


def test_cropped_caster_refuses_rays_and_points_it_was_not_made_for() -> None:
    rng = np.random.default_rng(2)
    v, f = bumpy_grid(80, rng)
    o, d = random_rays(rng, 5)
    crop = crop_for_rays(v, f, o, d, points=np.array([[1.0, 1.0, 0.0]]),
                         options=CropOptions(point_radius=0.3))
    caster = crop.raycaster()
    caster.cast(o[:2], d[:2])  # a subset of its rays is fine
    with pytest.raises(RuntimeError, match="coverage"):
        caster.cast(o + np.array([3.0, 0.0, 0.0]), d)
    with pytest.raises(RuntimeError, match="coverage"):
        caster.distances(np.array([[9.0, 9.0, 0.0]]))


def test_point_distances_are_exact_within_the_radius() -> None:
    rng = np.random.default_rng(3)
    v, f = bumpy_grid(150, rng, jitter=0.0)
    f = f[:-1]
    pts = rng.uniform([1, 1, -0.6], [9, 9, 0.6], size=(300, 3))
    radius = 0.25
    crop = crop_for_rays(v, f, np.zeros((0, 3)), np.zeros((0, 3)), points=pts,
                         options=CropOptions(grid_cells=200, point_radius=radius))
    whole = MeshRaycaster(v, f).distances(pts)
    got = crop.raycaster().distances(pts)
    near = whole <= radius
    assert near.sum() > 100 and (~near).sum() > 20
    np.testing.assert_allclose(got[near], whole[near], atol=1e-5)  # Open3D's float32
    assert np.all(got[~near] >= whole[~near] - 1e-5)  # farther: never underestimated
    assert crop.kept_fraction < 1.0


def test_rays_that_miss_the_mesh_box_give_an_empty_crop_that_misses() -> None:
    rng = np.random.default_rng(4)
    v, f = bumpy_grid(30, rng)
    f = f[:-2]  # the fin and lid are larger than a cell: kept whatever the rays
    o = np.array([[50.0, 50.0, 50.0]])
    d = np.array([[0.0, 0.0, 1.0]])
    crop = crop_for_rays(v, f, o, d, options=CropOptions(size_quantile=1.0))
    assert len(crop.triangles) == 0  # (the 0.1 % largest triangles are kept by default)
    res = crop.raycaster().cast(o, d)
    assert not res.hit.any()


def test_spot_cast_rays_cover_what_cast_spots_casts() -> None:
    rng = np.random.default_rng(5)
    v, f = bumpy_grid(200, rng, jitter=0.0)
    f = f[:-2]  # floor only
    cam, pose = CAMERA, camera_looking_down(np.array([5.0, 5.0, 3.0]))
    spots = [Spot(laser=f"L{k}", x=float(x), y=float(y), sigma_px=0.8)
             for k, (x, y) in enumerate(rng.uniform(100, 900, (4, 2)))]
    opts = SpotCastOptions()
    o, d = spot_cast_rays(spots, cam, pose, opts)
    assert len(o) == 4 * (1 + opts.ring_rays)
    crop = crop_for_rays(v, f, o, d)
    got = cast_spots(spots, cam, pose, crop.raycaster(), opts)  # refuses uncovered rays
    want = cast_spots(spots, cam, pose, MeshRaycaster(v, f), opts)
    assert [h.laser for h in got.hits] == [h.laser for h in want.hits] and len(got.hits) == 4
    for a, b in zip(got.hits, want.hits, strict=True):
        np.testing.assert_allclose(a.hit_world, b.hit_world, atol=1e-12)
    assert crop.kept_fraction < 0.05


@pytest.mark.parametrize("quantile", [0.5, 0.999, 1.0])
def test_random_triangle_soup_crop_is_exact(quantile: float) -> None:
    """Triangles of every size and orientation (many straddle cells; with the median size as
    the cell, half are not compact and are kept whole): the crop's hits are the mesh's."""
    rng = np.random.default_rng(int(quantile * 1000))
    centres = rng.uniform(0, 10, (20000, 3))
    size = rng.lognormal(-2.5, 0.8, (20000, 1, 1))
    v = (centres[:, None, :] + size * rng.normal(size=(20000, 3, 3))).reshape(-1, 3)
    f = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    o = rng.uniform(-2, 12, (80, 3))
    d = rng.normal(size=(80, 3))
    whole = MeshRaycaster(v, f).cast(o, d)
    crop = crop_for_rays(v, f, o, d, points=rng.uniform(0, 10, (50, 3)),
                         options=CropOptions(grid_cells=200, size_quantile=quantile,
                                             point_radius=0.3))
    got = crop.raycaster().cast(o, d)
    np.testing.assert_array_equal(got.hit, whole.hit)
    np.testing.assert_allclose(got.xyz[got.hit], whole.xyz[whole.hit], atol=1e-12)
    assert whole.hit.sum() > 20
    if quantile == 0.5:  # (the lognormal tail makes the higher quantiles' cells the box)
        assert crop.kept_fraction < 0.9


def test_crop_working_memory_is_a_small_part_of_the_mesh() -> None:
    """A seafloor height field of 1M triangles (float32 vertices, int32 faces: 17 MB): the
    crop's numpy working memory stays below the mesh's size (13 MiB on the benchmark's mesh;
    30 MiB when it tested 2^18 triangles at a time and sized them in float64, the peak of the
    small 640 × 480 benchmark cases)."""
    import tracemalloc

    v, f = bumpy_grid(708, np.random.default_rng(3), jitter=0.0)
    v, f = v[:-6].astype(np.float32), f[:-2]  # the height field alone, without the fins
    assert len(f) > 990_000
    rng = np.random.default_rng(4)  # four laser spots' rays, from 3 units above the floor
    o = np.array([5.0, 5.0, 3.0]) + rng.normal(size=(4, 3)) * 0.1
    d = np.column_stack([rng.normal(size=(4, 2)) * 0.05, -np.ones(4)])
    tracemalloc.start()
    try:
        start = tracemalloc.get_traced_memory()[0]
        crop = crop_for_rays(v, f, o, d, np.array([[5.0, 5.0, 0.0]]),
                             CropOptions(point_radius=0.2))
        peak = tracemalloc.get_traced_memory()[1] - start
    finally:
        tracemalloc.stop()
    assert 0 < len(crop.triangles) < len(f) // 10
    assert peak < 1.0 * (v.nbytes + f.nbytes), peak / 2**20
