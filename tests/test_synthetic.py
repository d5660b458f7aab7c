"""Synthetic scene, renderer and demo data set: geometry against closed-form answers."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import plyfile
import pycolmap
import pytest

from sfm_laserscale.errors import InputError
from sfm_laserscale.geometry import rotmat_from_qvec
from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.rig import load_rig
from sfm_laserscale.synthetic.dataset import (
    DemoDataOptions,
    DemoDataset,
    make_demo_dataset,
    make_rig,
    overlapping_pairs,
    true_spots,
)
from sfm_laserscale.synthetic.render import (
    RenderOptions,
    SceneRaycaster,
    camera_looking_at,
    nadir_pose,
    render_image,
)
from sfm_laserscale.synthetic.scene import SceneOptions, make_plane_scene, make_scene

PLANE_M = 2.0  # plane side, metres
TEX_PX = 1000  # texels per side (2 mm texels)


def _camera(w: int = 320, h: int = 240, f: float = 300.0) -> Camera:
    return Camera(1, "PINHOLE", w, h, np.array([f, f, w / 2.0, h / 2.0]))


def _patch_texture(row0: int, col0: int, size: int) -> np.ndarray:
    tex = np.full((TEX_PX, TEX_PX, 3), 0.1, dtype=np.float32)
    tex[row0:row0 + size, col0:col0 + size] = 0.9
    return tex


def _texel_world(row: float, col: float) -> np.ndarray:
    """World point of a (fractional) texel-grid position on the plane z = 0."""
    return np.array([-PLANE_M / 2 + col * PLANE_M / TEX_PX,
                     -PLANE_M / 2 + row * PLANE_M / TEX_PX, 0.0])


def _centroid(weights: np.ndarray) -> np.ndarray:
    """Intensity centroid in COLMAP pixels (pixel (i, j) centre at (j + 0.5, i + 0.5))."""
    rows, cols = np.indices(weights.shape)
    total = weights.sum()
    return np.array([((cols + 0.5) * weights).sum(), ((rows + 0.5) * weights).sum()]) / total


@pytest.mark.parametrize("supersampling", [1, 2])
@pytest.mark.parametrize(("position", "target"), [
    ((0.05, -0.03, 1.0), (0.17, 0.07, 0.0)),  # oblique view, patch off-centre
    ((0.211, 0.137, 0.8), (0.211, 0.137, 0.0)),  # nadir view, patch near the centre
])
def test_textured_patch_appears_where_its_centre_projects(
    supersampling: int, position: tuple[float, ...], target: tuple[float, ...]
) -> None:
    row0, col0, size = 527, 598, 9
    opts = RenderOptions(supersampling=supersampling, exposure=1.0)
    cam = _camera()
    pose = camera_looking_at(np.array(position), np.array(target), up_hint=(0.0, 1.0, 0.0))
    with_patch = SceneRaycaster(make_plane_scene((PLANE_M, PLANE_M),
                                                 _patch_texture(row0, col0, size)))
    without = SceneRaycaster(make_plane_scene((PLANE_M, PLANE_M), _patch_texture(0, 0, 0)))
    diff = (render_image(with_patch, cam, pose, opts) - render_image(without, cam, pose, opts))
    weights = diff.sum(axis=2)
    assert weights.max() > 0.1  # the patch is in view
    centre = _texel_world(row0 + size / 2, col0 + size / 2)
    expected = cam.project(pose.transform(centre[None, :]))[0]
    np.testing.assert_allclose(_centroid(weights), expected, atol=0.2)


def test_camera_looking_at_puts_target_on_principal_point_and_keeps_up() -> None:
    cam = _camera()
    pose = camera_looking_at(np.array([1.0, -2.0, 3.0]), np.array([0.2, 0.5, -0.1]),
                             up_hint=(0.0, 0.0, 1.0))
    np.testing.assert_allclose(pose.R @ pose.R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(pose.R) == pytest.approx(1.0)
    xy = cam.project(pose.transform(np.array([[0.2, 0.5, -0.1]])))[0]
    np.testing.assert_allclose(xy, [cam.width / 2, cam.height / 2], atol=1e-9)
    up_world = -pose.R[1]  # image up (−y) in the world
    assert up_world[2] > 0.5  # world +z appears up in the image


def test_nadir_pose_axes() -> None:
    pose = nadir_pose(np.array([0.0, 0.0, 2.0]), heading_deg=90.0)
    np.testing.assert_allclose(pose.R[2], [0, 0, -1], atol=1e-12)  # looks down
    np.testing.assert_allclose(pose.R[0], [0, 1, 0], atol=1e-12)  # image right = world +y
    tilted = nadir_pose(np.array([0.0, 0.0, 2.0]), pitch_deg=15.0, roll_deg=10.0)
    tilt = np.degrees(np.arccos(-tilted.R[2, 2]))
    expected = np.degrees(np.arccos(np.cos(np.radians(15)) * np.cos(np.radians(10))))
    assert tilt == pytest.approx(expected, abs=1e-9)
    np.testing.assert_allclose(tilted.center, [0, 0, 2], atol=1e-12)


def test_first_hit_is_exact_on_a_plane() -> None:
    rc = SceneRaycaster(make_plane_scene((4.0, 4.0), np.zeros((4, 4, 3), np.float32), z=-0.3))
    origins = np.array([[0.1, 0.2, 2.0], [0.0, 0.0, 1.0], [10.0, 0.0, 1.0]])
    dirs = np.array([[0.3, -0.1, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    hits, ok = rc.first_hit(origins, dirs)
    assert ok.tolist() == [True, False, False]
    t = 2.3
    np.testing.assert_allclose(hits[0], [0.1 + 0.3 * t, 0.2 - 0.1 * t, -0.3], atol=1e-12)


@pytest.mark.parametrize("kind", ["rov", "parallel"])
def test_true_spots_on_a_plane_match_closed_form(kind: str) -> None:
    depth = 2.0
    rc = SceneRaycaster(make_plane_scene((6.0, 6.0), np.zeros((4, 4, 3), np.float32)))
    cam = _camera(640, 480, 560.0)
    pose = nadir_pose(np.array([0.3, -0.2, depth]), heading_deg=30.0)
    rig = make_rig(kind)
    spots = true_spots(rc, cam, pose, rig)
    assert [s.laser for s in spots] == rig.names
    for spot, las in zip(spots, rig.lasers, strict=True):
        assert las.origin is not None and las.direction is not None
        hit_cam = las.origin + (depth / las.direction[2]) * las.direction  # plane z_cam = depth
        f, cx, cy = 560.0, 320.0, 240.0
        expected = (cx + f * hit_cam[0] / depth, cy + f * hit_cam[1] / depth)
        assert spot.visible and spot.xy_px is not None
        np.testing.assert_allclose(spot.xy_px, expected, atol=1e-6)


def test_rov_rig_pair_is_parallel_and_misaligned_beams_are_not() -> None:
    rig = make_rig("rov")
    d = {las.name: las.direction for las in rig.lasers}
    np.testing.assert_array_equal(d["L1"], d["L2"])
    for name in ("L1", "L3", "L4"):
        v = d[name]
        assert v is not None
        off_axis = np.degrees(np.arccos(v[2]))
        assert 1.0 <= off_axis <= 3.0
    assert rig.pairs[0].lasers == ("L1", "L2")
    assert rig.pairs[0].separation == pytest.approx(0.234)
    with pytest.raises(InputError):
        make_rig("nope")


def test_scene_is_seeded_and_sized() -> None:
    opts = SceneOptions(size_m=(2.0, 1.0), resolution_m=0.05, texture_px=256, n_pebbles=20000,
                        seed=3)
    a, b = make_scene(opts), make_scene(opts)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.texture, b.texture)
    assert a.vertices.shape == (41 * 21, 3) and a.triangles.shape == (2 * 40 * 20, 3)
    assert a.texture.shape == (128, 256, 3)
    lo, hi = a.bounds
    np.testing.assert_allclose([lo[0], lo[1], hi[0], hi[1]], [-1, -0.5, 1, 0.5])
    np.testing.assert_allclose(np.linalg.norm(a.normals, axis=1), 1.0)
    assert (a.normals[:, 2] > 0).all()
    c = make_scene(SceneOptions(size_m=(2.0, 1.0), resolution_m=0.05, texture_px=256, seed=4))
    assert not np.array_equal(a.vertices, c.vertices)


# --------------------------------------------------------------------------- the demo data set


@pytest.fixture(scope="module")
def small_demo(small_dataset: DemoDataset) -> DemoDataset:
    """conftest's session-wide small data set (seed 0), made once for every test file."""
    return small_dataset


@pytest.mark.slow
def test_small_demo_sfm_registered_everything(small_demo: DemoDataset) -> None:
    ds = small_demo
    assert ds.sfm.n_registered == ds.sfm.n_images == 8
    assert ds.sfm.n_points > 300
    assert ds.sfm.mean_reprojection_error_px < 1.0
    rec = pycolmap.Reconstruction(str(ds.model_dir))
    assert rec.num_reg_images() == 8
    assert sorted(im.name for im in rec.images.values()) == sorted(
        p.name for p in ds.images_dir.glob("*.png"))
    cam = next(iter(rec.cameras.values()))
    np.testing.assert_allclose(cam.params, ds.camera.params)  # intrinsics held fixed


@pytest.mark.slow
def test_small_demo_alignment_and_true_scale(small_demo: DemoDataset) -> None:
    ds = small_demo
    truth = json.loads(ds.truth_path.read_text())
    world = {r["name"]: _pose(r["cam_from_world"]).center for r in truth["reference_images"]}
    baseline = max(np.linalg.norm(a - b) for a in world.values() for b in world.values())
    assert ds.alignment_rms_m < 0.01 * baseline
    rec = pycolmap.Reconstruction(str(ds.model_dir))
    model = {im.name: np.asarray(im.projection_center()) for im in rec.images.values()}
    names = sorted(world)
    d_world = np.linalg.norm(world[names[0]] - world[names[-1]])
    d_model = np.linalg.norm(model[names[0]] - model[names[-1]])
    assert ds.true_scale == pytest.approx(d_world / d_model, rel=0.005)
    assert truth["true_scale"] == pytest.approx(ds.true_scale)


@pytest.mark.slow
def test_small_demo_truth_spots_are_consistent(small_demo: DemoDataset) -> None:
    ds = small_demo
    truth = json.loads(ds.truth_path.read_text())
    assert len(truth["laser_images"]) == 3
    for entry in truth["laser_images"]:
        img = cv2.imread(str(ds.laser_images_dir / entry["name"]))
        assert img is not None and img.shape == (480, 640, 3)
        cam_from_model = _pose(entry["cam_from_model"])
        visible = [s for s in entry["spots"] if s["visible"]]
        assert len(visible) == 4
        for s in visible:
            assert 0 < s["x"] < 640 and 0 < s["y"] < 480
            x_cam = cam_from_model.transform(np.array([s["hit_model"]]))[0]  # model units
            xy = ds.camera.project(x_cam[None, :])[0]
            np.testing.assert_allclose(xy, [s["x"], s["y"]], atol=1e-6)
            assert img[int(s["y"]), int(s["x"]), 2] >= 250  # saturated red channel (BGR)
            las = ds.rig.laser(s["laser"])
            assert las.origin is not None and las.direction is not None
            o_hat = x_cam - (x_cam[2] / las.direction[2]) * las.direction  # FCM, docs/DESIGN.md §3
            np.testing.assert_allclose(o_hat * ds.true_scale, las.origin, atol=1e-9)
    rows = ds.spots_path.read_text().strip().splitlines()
    assert rows[0] == "image,laser,x,y" and len(rows) == 1 + 3 * 4
    rig = load_rig(ds.rig_path)
    assert rig.names == ["L1", "L2", "L3", "L4"] and len(rig.pairs) == 1


@pytest.mark.slow
def test_small_demo_mesh_agrees_with_sparse_points(small_demo: DemoDataset) -> None:
    ds = small_demo
    ply = plyfile.PlyData.read(str(ds.mesh_path))
    vert = ply["vertex"].data
    assert vert.dtype["x"] == np.dtype("<f8")
    xyz = np.column_stack([vert["x"], vert["y"], vert["z"]])
    faces = np.vstack(ply["face"].data["vertex_indices"]).astype(np.uint32)
    scene = o3d.t.geometry.RaycastingScene()
    offset = xyz.mean(axis=0)
    scene.add_triangles(o3d.core.Tensor.from_numpy((xyz - offset).astype(np.float32)),
                        o3d.core.Tensor.from_numpy(faces))
    rec = pycolmap.Reconstruction(str(ds.model_dir))
    pts = np.array([p.xyz for p in rec.points3D.values()])
    query = o3d.core.Tensor.from_numpy((pts - offset).astype(np.float32))
    dist = scene.compute_distance(query).numpy()
    extent = np.linalg.norm(xyz.max(axis=0) - xyz.min(axis=0))
    assert np.median(dist) < 0.01 * extent
    assert np.median(dist) * ds.true_scale < 0.005  # metres: below 5 mm
    truth = json.loads(ds.truth_path.read_text())
    for entry in truth["laser_images"]:  # the ray through a true spot meets the mesh at its hit
        pose = _pose(entry["cam_from_model"])
        for s in entry["spots"]:
            ray = pose.R.T @ ds.camera.unproject(np.array([[s["x"], s["y"]]]))[0]
            ray /= np.linalg.norm(ray)
            rays = np.hstack([pose.center - offset, ray])[None, :].astype(np.float32)
            t = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()[0]
            hit = pose.center + float(t) * ray
            assert np.linalg.norm(hit - np.array(s["hit_model"])) < 1e-5 * extent


def test_overlapping_pairs_follow_the_footprints() -> None:
    rc = SceneRaycaster(make_plane_scene((20.0, 20.0), np.zeros((4, 4, 3), np.float32)))
    cam = _camera(320, 240, 300.0)  # footprint at 2 m: 2.13 m × 1.6 m
    poses = [nadir_pose(np.array([x, 0.0, 2.0])) for x in (0.0, 0.5, 1.9, 5.0)]
    assert overlapping_pairs(rc, cam, poses, 0.15) == [(0, 1), (1, 2)]
    assert overlapping_pairs(rc, cam, poses, 0.6) == [(0, 1)]  # 0.5 m shift keeps 77 %


def test_demo_refuses_a_non_empty_out_dir(tmp_path: Path) -> None:
    (tmp_path / "keep.txt").write_text("x")
    with pytest.raises(InputError):
        make_demo_dataset(tmp_path, DemoDataOptions(small=True, progress=False))
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]


def _pose(d: dict[str, list[float]]) -> Pose:
    return Pose(R=rotmat_from_qvec(np.array(d["rotation_wxyz"])), t=np.array(d["translation"]))
