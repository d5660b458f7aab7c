"""Registration: SIFT pixel convention, descriptor index, matching, pose, acceptance, covariance.

Numbers measured by these tests are printed (run with ``-s`` to see them).
"""

from __future__ import annotations

import shutil
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from sfm_laserscale.errors import InputError
from sfm_laserscale.geometry import rotation_angle_deg
from sfm_laserscale.io.colmap import model_without_images, read_colmap_model
from sfm_laserscale.io.colmap_database import read_database_features
from sfm_laserscale.model import (
    INVALID_POINT3D_ID,
    Camera,
    Image,
    ImageFeatures,
    ObservationFeatures,
    Pose,
    SparseModel,
)
from sfm_laserscale.registration.index import build_descriptor_index
from sfm_laserscale.registration.match import match_to_model
from sfm_laserscale.registration.options import (
    IndexOptions,
    MatchOptions,
    PoseOptions,
    RegistrationOptions,
    SiftOptions,
    TieOptions,
)
from sfm_laserscale.registration.pose import estimate_pose, register_image
from sfm_laserscale.registration.sift import extract_sift
from sfm_laserscale.registration.ties import features_from_images

F64 = NDArray[np.float64]
FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures"
COLMAP_FIX = FIXTURES / "maupertuis_colmap"
OPENMVG_FIX = FIXTURES / "maupertuis_openmvg"


# --------------------------------------------------------------------------- helpers


def _camera() -> Camera:
    return Camera(1, "SIMPLE_RADIAL", 1600, 1200, np.array([1400.0, 800.0, 600.0, -0.05]))


def _true_pose() -> Pose:
    return Pose(Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix(), np.array([0.3, -0.1, 0.5]))


def _scene(rng: np.random.Generator, n: int, camera: Camera, pose: Pose) -> tuple[F64, F64]:
    """n world points seen by the camera (depth 4–7) and their exact pixels."""
    xy = np.column_stack([rng.uniform(50, camera.width - 50, n),
                          rng.uniform(50, camera.height - 50, n)])
    xyz_cam = camera.unproject(xy) * rng.uniform(4.0, 7.0, n)[:, None]
    xyz_world = pose.inverse().transform(xyz_cam)
    return camera.project(pose.transform(xyz_world)), xyz_world


def _textured(rng: np.random.Generator, h: int, w: int, blur: float = 2.5) -> NDArray[np.uint8]:
    """Smoothed noise: plenty of SIFT keypoints."""
    noise = rng.uniform(0, 255, (h, w)).astype(np.float32)
    img = cv2.GaussianBlur(noise, (0, 0), blur)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return np.round(img).astype(np.uint8)


def _copied_fixture(tmp_path: Path) -> Path:
    """Copy of the COLMAP fixture's database (+ -wal/-shm) so nothing can touch the original."""
    for name in ("colmap.db", "colmap.db-wal", "colmap.db-shm"):
        if (COLMAP_FIX / name).exists():
            shutil.copy2(COLMAP_FIX / name, tmp_path / name)
    return tmp_path / "colmap.db"


# --------------------------------------------------------------------------- SIFT


@pytest.mark.parametrize("cx, cy", [(100.3, 80.7), (60.0, 120.0), (150.25, 50.5)])
def test_extract_sift_uses_colmap_pixel_convention(cx: float, cy: float) -> None:
    # A Gaussian blob centred at array index (cx, cy) (pixel (i, j) covers [j, j+1) × [i, i+1)
    # and has its centre at index j) is at (cx + 0.5, cy + 0.5) in COLMAP's convention.
    yy, xx = np.mgrid[0:200, 0:240].astype(np.float64)
    img = 30 + 200 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 3.0**2))
    feats = extract_sift(np.round(img).astype(np.uint8), SiftOptions())
    d = np.linalg.norm(feats.xy_px - [cx + 0.5, cy + 0.5], axis=1)
    assert d.min() < 0.05
    assert np.linalg.norm(feats.xy_px[np.argmin(d)] - [cx, cy]) > 0.6  # not OpenCV's convention


def test_extract_sift_formats_cap_and_input_checks() -> None:
    rng = np.random.default_rng(3)
    gray = _textured(rng, 300, 320)
    feats = extract_sift(gray, SiftOptions())
    assert feats.descriptors.dtype == np.uint8
    assert feats.descriptors.shape == (len(feats.xy_px), 128)
    assert len(feats.xy_px) > 300
    capped = extract_sift(gray, SiftOptions(max_num_features=100))
    assert 50 <= len(capped.xy_px) <= 100
    rgb = np.repeat(gray[:, :, None], 3, axis=2)  # grey RGB: COLMAP's conversion is exact
    same = extract_sift(rgb, RegistrationOptions())
    np.testing.assert_array_equal(same.descriptors, feats.descriptors)
    as_float = extract_sift(gray.astype(np.float32) / 255.0, SiftOptions())
    assert abs(len(as_float.xy_px) - len(feats.xy_px)) < 0.05 * len(feats.xy_px)
    with pytest.raises(InputError):
        extract_sift(gray.astype(np.float32), SiftOptions())  # float values beyond [0, 1]
    with pytest.raises(InputError):
        extract_sift(gray[:, :, None].repeat(2, axis=2), SiftOptions())


@pytest.mark.slow
def test_extract_sift_on_real_photographs() -> None:
    for name in ("MaupertuisTest_01.jpg", "MaupertuisTest_02.jpg"):
        gray = cv2.imread(str(OPENMVG_FIX / "images" / name), cv2.IMREAD_GRAYSCALE)
        assert gray is not None
        t0 = time.perf_counter()
        feats = extract_sift(gray, SiftOptions())
        dt = time.perf_counter() - t0
        print(f"\n{name}: {len(feats.xy_px)} SIFT keypoints in {dt:.1f} s")
        assert 3000 <= len(feats.xy_px) <= 8192
        assert np.all((feats.xy_px >= 0) & (feats.xy_px <= [gray.shape[1], gray.shape[0]]))


# --------------------------------------------------------------------------- index and matching


def _one_image_model(xy: F64, ids: NDArray[np.uint64], xyz: F64, name: str = "a.jpg",
                     camera: Camera | None = None) -> SparseModel:
    cam = camera or Camera(1, "SIMPLE_PINHOLE", 640, 480, np.array([500.0, 320.0, 240.0]))
    image = Image(1, name, cam.camera_id, Pose(np.eye(3), np.zeros(3)), xy, ids)
    pids = np.unique(ids[ids != INVALID_POINT3D_ID])
    return SparseModel({cam.camera_id: cam}, {1: image}, pids, xyz[: len(pids)])


def _separated_descriptors(rng: np.random.Generator, n: int) -> NDArray[np.uint8]:
    return rng.integers(10, 110, (n, 128)).astype(np.uint8)


@pytest.mark.parametrize("exact", [True, False])
def test_match_ratio_test_uses_another_point_and_keeps_one_match_per_point(exact: bool) -> None:
    rng = np.random.default_rng(0)
    base = _separated_descriptors(rng, 6).astype(np.int16)
    # Observations: point 10 twice (near-identical descriptors), 11, 12, 13 (12 and 13 with
    # close descriptors), 14; one observation without a 3D point.
    desc = np.stack([base[0], base[0] + 2, base[1], base[2] + 2, base[2] - 2, base[3], base[4]])
    ids = np.array([10, 10, 11, 12, 13, 14, INVALID_POINT3D_ID], dtype=np.uint64)
    xy = rng.uniform(10, 400, (7, 2))
    model = _one_image_model(xy, ids, rng.normal(size=(5, 3)))
    feats = {"a.jpg": ImageFeatures(xy, np.clip(desc, 0, 255).astype(np.uint8)),
             "other.jpg": ImageFeatures(xy[:1], desc[:1].astype(np.uint8))}  # not in the model
    index = build_descriptor_index(model, feats, IndexOptions(exact=exact))
    assert index.method == ("exact" if exact else "ivf")
    assert index.num_descriptors == 6 and index.num_points == 5
    query = np.stack([base[0] + 1,  # point 10: both neighbours are point 10 -> accepted
                      base[2],  # equidistant from points 12 and 13: ambiguous -> rejected
                      base[3] + 3,  # point 14, farther
                      base[3],  # point 14, closer: the one kept
                      base[5]])  # unrelated -> rejected
    q = ImageFeatures(rng.uniform(10, 400, (5, 2)), np.clip(query, 0, 255).astype(np.uint8))
    m = match_to_model(q, index, MatchOptions(ratio=0.8))
    pairs = zip(m.query_idx, m.point_rows, strict=True)
    got = {int(index.point3D_ids[r]): int(i) for i, r in pairs}
    assert got == {10: 0, 14: 3}
    assert np.all(np.diff(m.query_idx) > 0) and m.distance.dtype == np.float32


def test_index_keeps_descriptors_nearest_the_point_mean() -> None:
    rng = np.random.default_rng(1)
    centre = rng.integers(60, 120, 128)
    spread = np.array([1, 2, 3, 30, 40, 50])  # the three far ones must go
    desc = np.stack([centre + s * rng.choice([-1, 1], 128) // 2 for s in spread])
    ids = np.full(6, 7, dtype=np.uint64)
    model = _one_image_model(rng.uniform(10, 400, (6, 2)), ids, rng.normal(size=(1, 3)))
    feats = {"a.jpg": ImageFeatures(model.images[1].xy_px, np.clip(desc, 0, 255).astype(np.uint8))}
    index = build_descriptor_index(model, feats, IndexOptions(max_descriptors_per_point=3))
    kept = index.descriptors.astype(np.int64)
    assert len(kept) == 3 and np.abs(kept - centre).max() <= 2  # the far ones are >= 15 off


def test_index_rejects_features_that_do_not_follow_the_model() -> None:
    rng = np.random.default_rng(2)
    xy = rng.uniform(10, 400, (5, 2))
    ids = np.arange(5, dtype=np.uint64)
    model = _one_image_model(xy, ids, rng.normal(size=(5, 3)))
    desc = _separated_descriptors(rng, 5)
    with pytest.raises(InputError, match="observations"):
        build_descriptor_index(model, {"a.jpg": ImageFeatures(xy[:4], desc[:4])}, IndexOptions())
    with pytest.raises(InputError, match="wrong database"):
        build_descriptor_index(model, {"a.jpg": ImageFeatures(xy + 1.0, desc)}, IndexOptions())
    with pytest.raises(InputError, match="no descriptor"):
        build_descriptor_index(model, {"b.jpg": ImageFeatures(xy, desc)}, IndexOptions())
    bad = ObservationFeatures(np.array([9]), desc[:1], np.zeros(1))
    with pytest.raises(InputError, match="out of range"):
        build_descriptor_index(model, {"a.jpg": bad}, IndexOptions())


def test_features_from_images_ties_keypoints_to_observations() -> None:
    rng = np.random.default_rng(4)
    gray = _textured(rng, 480, 640, blur=4.0)
    kps = extract_sift(gray, SiftOptions())
    uniq = np.unique(np.round(kps.xy_px, 3), axis=0)
    # Keypoints more than 6 px from any other keypoint, so that ties are unambiguous.
    isolated = uniq[cKDTree(uniq).query(uniq, k=2)[0][:, 1] > 6]
    assert len(isolated) >= 90
    pts = isolated[rng.permutation(len(isolated))[:90]]
    offset = 0.7 * np.array([np.cos(1.0), np.sin(1.0)])
    obs_xy = pts + offset  # model observations 0.7 px from the keypoints
    ids = np.r_[np.arange(60, dtype=np.uint64), np.full(30, INVALID_POINT3D_ID, dtype=np.uint64)]
    model = _one_image_model(obs_xy, ids, rng.normal(size=(60, 3)))
    tied = features_from_images(model, {"a.jpg": gray}, TieOptions(tie_radius_px=2.0))["a.jpg"]
    assert set(tied.observation_idx.tolist()) == set(range(60))  # every 3D observation, no other
    assert np.all(tied.tie_distance_px <= 2.0)
    assert np.median(tied.tie_distance_px) == pytest.approx(0.7, abs=0.05)
    # The tied descriptors index the model; the image's own SIFT matches back to its points.
    index = build_descriptor_index(model, {"a.jpg": tied}, RegistrationOptions())
    m = match_to_model(kps, index, MatchOptions())
    d = np.linalg.norm(kps.xy_px[m.query_idx] - obs_xy[m.point_rows], axis=1)
    assert len(m) >= 55 and np.all(d < 1.0)
    with pytest.raises(InputError, match="camera"):
        features_from_images(model, {"a.jpg": gray[:400]}, TieOptions())
    with pytest.raises(InputError, match="not an image"):
        features_from_images(model, {"zz.jpg": gray}, TieOptions())


# --------------------------------------------------------------------------- pose


def test_exact_correspondences_give_the_true_pose() -> None:
    rng = np.random.default_rng(5)
    cam, pose = _camera(), _true_pose()
    xy, xyz = _scene(rng, 100, cam, pose)
    res = estimate_pose(xy, xyz, cam, PoseOptions())
    assert res.success and res.reason is None and res.num_inliers == 100
    assert res.cam_from_world is not None and res.covariance is not None
    assert rotation_angle_deg(res.cam_from_world.R, pose.R) < 1e-4  # arccos resolution
    assert np.allclose(res.cam_from_world.t, pose.t, atol=1e-8)
    assert res.reproj_error_px < 1e-6


def test_acceptance_rule_rejects_with_plain_reasons() -> None:
    rng = np.random.default_rng(6)
    cam, pose = _camera(), _true_pose()
    xy, xyz = _scene(rng, 240, cam, pose)
    # 12 perfect correspondences: pycolmap finds a pose, our rule refuses it.
    few = estimate_pose(xy[:12], xyz[:12], cam, PoseOptions())
    assert not few.success and few.cam_from_world is None and few.covariance is None
    assert few.num_inliers == 12
    assert few.reason == "only 12 inliers of 12 matches (need 30)"
    # 40 good matches drowned in 200 outliers: enough inliers, ratio too low.
    bad_xy = xy.copy()
    bad_xy[40:] = rng.uniform([0, 0], [cam.width, cam.height], (200, 2))
    low = estimate_pose(bad_xy, xyz, cam, PoseOptions())
    assert not low.success and low.reason is not None and "inlier ratio" in low.reason
    assert low.num_inliers >= 40 and low.cam_from_world is None
    # Large residuals (σ = 3 px): RMS ≈ 4.2 px > 4 px.
    noisy = estimate_pose(xy + rng.normal(0, 3.0, xy.shape), xyz, cam, PoseOptions())
    assert not noisy.success and noisy.reason is not None and "RMS" in noisy.reason
    # Fewer than 4 matches: no attempt.
    three = estimate_pose(xy[:3], xyz[:3], cam, PoseOptions())
    assert not three.success and three.reason is not None and "at least 4" in three.reason
    with pytest.raises(InputError):
        estimate_pose(xy[:10], xyz[:9], cam, PoseOptions())


def test_nonsense_options_are_input_errors() -> None:
    with pytest.raises(InputError):
        MatchOptions(ratio=1.5)
    with pytest.raises(InputError):
        PoseOptions(min_inliers=2)
    with pytest.raises(InputError):
        TieOptions(tie_radius_px=0)
    with pytest.raises(InputError):
        SiftOptions(normalization="L3")
    opts = RegistrationOptions().with_seed(42)
    assert opts.pose.seed == 42 and opts.index.seed == 42


def test_pure_outliers_fail_with_a_reason() -> None:
    rng = np.random.default_rng(7)
    cam = _camera()
    xy = rng.uniform([0, 0], [cam.width, cam.height], (300, 2))
    xyz = rng.uniform(-5, 5, (300, 3))
    res = estimate_pose(xy, xyz, cam, PoseOptions())
    print(f"\npure outliers: {res.num_inliers} inliers of 300 -> {res.reason}")
    assert not res.success and res.cam_from_world is None and res.covariance is None
    assert res.reason


def _pose_error(est: Pose, truth: Pose) -> F64:
    """ξ = (ω, δt) with est = (Exp(ω) R_true, t_true + δt): the documented parametrisation."""
    return np.r_[Rotation.from_matrix(est.R @ truth.R.T).as_rotvec(), est.t - truth.t]


def test_covariance_matches_monte_carlo() -> None:
    rng = np.random.default_rng(8)
    cam, pose = _camera(), _true_pose()
    xy0, xyz = _scene(rng, 80, cam, pose)
    errs, covs, maha = [], [], []
    for _ in range(200):
        res = estimate_pose(xy0 + rng.normal(0, 1.0, xy0.shape), xyz, cam, PoseOptions())
        assert res.success and res.cam_from_world is not None and res.covariance is not None
        e = _pose_error(res.cam_from_world, pose)
        errs.append(e)
        covs.append(res.covariance)
        maha.append(float(e @ np.linalg.solve(res.covariance, e)))
    E = np.array(errs)
    ratio = E.std(axis=0) / np.sqrt(np.diag(np.mean(covs, axis=0)))
    print(f"\nMonte-Carlo std / predicted std (rx ry rz tx ty tz): {np.round(ratio, 3)}; "
          f"mean Mahalanobis² {np.mean(maha):.2f} (6 expected)")
    assert np.all((ratio > 0.8) & (ratio < 1.25))
    assert 4.8 < np.mean(maha) < 7.5  # full matrix (correlations included) is right too
    assert np.all(np.abs(E.mean(axis=0)) < 0.25 * E.std(axis=0))  # no bias


def test_pycolmap_covariance_parametrisation_as_documented() -> None:
    """pycolmap's covariance: (rotation, translation), rotation increment = half rotation vector."""
    rng = np.random.default_rng(9)
    cam, pose = _camera(), _true_pose()
    xy, xyz = _scene(rng, 80, cam, pose)
    xy = xy + rng.normal(0, 1.0, xy.shape)
    opts = PoseOptions(loss_scale_px=1e6)  # Cauchy loss ≈ quadratic: both are (JᵀJ)⁻¹
    ours = estimate_pose(xy, xyz, cam, opts)
    assert ours.covariance is not None
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.random_seed = 0
    ref = pycolmap.AbsolutePoseRefinementOptions()
    ref.loss_function_scale = 1e6
    out = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, cam.to_pycolmap(), est, ref,
                                                     return_covariance=True)
    assert out is not None
    D = np.diag([2.0, 2, 2, 1, 1, 1])
    theirs = D @ np.asarray(out["covariance"]) @ D
    np.testing.assert_allclose(theirs, ours.covariance / ours.sigma_px**2,
                               rtol=0.02, atol=1e-3 * np.abs(theirs).max())


def test_refined_focal_length_and_seed() -> None:
    rng = np.random.default_rng(10)
    cam, pose = _camera(), _true_pose()
    xy, xyz = _scene(rng, 150, cam, pose)
    xy = xy + rng.normal(0, 0.5, xy.shape)
    wrong = replace(cam, params=cam.params * np.array([1.03, 1, 1, 1]))
    res = estimate_pose(xy, xyz, wrong, PoseOptions(refine_focal_length=True))
    assert res.success and res.cam_from_world is not None and res.covariance is not None
    assert res.camera.params[0] == pytest.approx(1400.0, rel=2e-3)
    assert rotation_angle_deg(res.cam_from_world.R, pose.R) < 0.05
    fixed = estimate_pose(xy, xyz, cam, PoseOptions())
    assert fixed.covariance is not None
    assert np.all(np.diag(res.covariance) >= np.diag(fixed.covariance) * 0.9)  # focal marginalised
    again = estimate_pose(xy, xyz, wrong, PoseOptions(refine_focal_length=True))
    assert again.cam_from_world is not None
    np.testing.assert_array_equal(again.cam_from_world.R, res.cam_from_world.R)


# --------------------------------------------------------------------------- real fixture


@pytest.fixture(scope="module")
def colmap_fixture(tmp_path_factory: pytest.TempPathFactory
                   ) -> tuple[SparseModel, dict[str, ImageFeatures]]:
    db = _copied_fixture(tmp_path_factory.mktemp("db"))
    model = read_colmap_model(COLMAP_FIX / "reconstruction")
    return model, read_database_features(db)


def test_index_in_two_steps_equals_one_and_needs_no_observations(
        colmap_fixture: tuple[SparseModel, dict[str, ImageFeatures]]) -> None:
    """Pass 1 (the only one reading the 2D observations), then passes 2-3 on the model without
    them: the same index as in one call; the candidates are consumed."""
    from sfm_laserscale.registration.index import build_index, select_index_candidates

    model, feats = colmap_fixture
    for opts in (IndexOptions(), IndexOptions(exact=False, ivf_lists=30)):
        whole = build_descriptor_index(model, feats, opts)
        candidates = select_index_candidates(model, feats, opts)
        index = build_index(model.without_observations(), candidates, feats, opts)
        np.testing.assert_array_equal(index.point_rows, whole.point_rows)
        np.testing.assert_array_equal(index.descriptors, whole.descriptors)
        assert (index.method, index.ivf_lists) == (whole.method, whole.ivf_lists)
        if index.method == "ivf":
            q = feats["01.jpg"].descriptors[:200].astype(np.float32)
            np.testing.assert_array_equal(index._searcher.search(q, 3)[1],
                                          whole._searcher.search(q, 3)[1])
        with pytest.raises(ValueError, match="already built"):
            build_index(model, candidates, feats, opts)


@pytest.mark.parametrize("name", ["03.jpg", "01.jpg"])
def test_held_out_fixture_image_registers_on_its_original_pose(
        colmap_fixture: tuple[SparseModel, dict[str, ImageFeatures]], name: str) -> None:
    model, feats = colmap_fixture
    t0 = time.perf_counter()
    held_out = model_without_images(model, [name])
    index = build_descriptor_index(held_out, feats, RegistrationOptions())
    t_index = time.perf_counter() - t0
    truth = model.image_by_name(name)
    assert truth is not None
    res = register_image(feats[name], model.cameras[truth.camera_id], index, RegistrationOptions())
    assert res.success, res.reason
    assert res.cam_from_world is not None and res.covariance is not None
    rot = rotation_angle_deg(res.cam_from_world.R, truth.cam_from_world.R)
    centre = np.linalg.norm(res.cam_from_world.center - truth.cam_from_world.center)
    rel = centre / model.extent
    sd = np.sqrt(np.diag(res.covariance))
    print(f"\n{name}: index {index.num_descriptors} descriptors / {index.num_points} points "
          f"({index.method}, {t_index:.2f} s); {res.num_features} features, "
          f"{res.num_matches} matches, {res.num_inliers} inliers, RMS {res.reproj_error_px:.3f} px "
          f"(σ̂ {res.pose.sigma_px:.3f} px); rotation error {rot:.4f}°, centre error "
          f"{100 * rel:.4f} % of extent {model.extent:.2f}; σ rot {np.degrees(sd[:3]).round(4)}°"
          f", σ t {sd[3:].round(4)}; match {res.match_time_s:.2f} s, pose {res.pose_time_s:.2f} s")
    assert rot < 0.5 and rel < 0.01
    assert res.num_inliers >= 300 and res.reproj_error_px < 2.0
    assert len(res.inlier_xy_px) == len(res.inlier_xyz) == res.num_inliers
    assert set(res.inlier_point3D_ids.tolist()) <= set(held_out.point3D_ids.tolist())
    # Same input and seeds: same pose (the IVF k-means is seeded too).
    flann = build_descriptor_index(held_out, feats, IndexOptions(exact=False))
    a = register_image(feats[name], model.cameras[truth.camera_id], flann, RegistrationOptions())
    flann2 = build_descriptor_index(held_out, feats, IndexOptions(exact=False))
    b = register_image(feats[name], model.cameras[truth.camera_id], flann2, RegistrationOptions())
    assert a.cam_from_world is not None and b.cam_from_world is not None
    np.testing.assert_array_equal(a.matches.query_idx, b.matches.query_idx)
    np.testing.assert_array_equal(a.cam_from_world.t, b.cam_from_world.t)
    assert rotation_angle_deg(a.cam_from_world.R, truth.cam_from_world.R) < 0.5


def test_query_from_another_resolution_is_refused(
        colmap_fixture: tuple[SparseModel, dict[str, ImageFeatures]]) -> None:
    model, feats = colmap_fixture
    index = build_descriptor_index(model_without_images(model, ["03.jpg"]), feats, IndexOptions())
    small = Camera(1, "SIMPLE_PINHOLE", 960, 540, np.array([923.0, 480.0, 270.0]))
    with pytest.raises(InputError, match="outside"):
        register_image(feats["03.jpg"], small, index, RegistrationOptions())


@pytest.mark.parametrize(("coarse_dims", "route"),
                         [(0, "zero copy"), (16, "zero copy"), (16, "copied"), (16, "filled")])
def test_ivf_index_lists_equal_faiss_own_add_and_find_near_duplicates(
        coarse_dims: int, route: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The IVF's lists, written once into a buffer FAISS reads without copying (or, with an
    older FAISS, copied; or filled list by list when FAISS's format is not the one known),
    search exactly like an index filled by FAISS's own ``add`` with the same cells (assigned
    in 128-d or in a PCA projection); a perturbed copy of a pool descriptor finds it, at its
    exact L2 distance."""
    import faiss

    from sfm_laserscale.registration import index as reg

    if route == "copied":
        monkeypatch.delattr(faiss, "ZeroCopyIOReader")
    if route == "filled":
        monkeypatch.setattr(reg, "_ivf_layout", lambda ivf, sizes: None)
    rng = np.random.default_rng(7)
    pool = rng.integers(0, 120, (30000, 128)).astype(np.uint8)
    model = _pool_model(len(pool))
    index = reg.index_pool(model, reg.DescriptorPool(pool, np.arange(len(pool))),  # type: ignore[arg-type]
                           IndexOptions(coarse_dims=coarse_dims))
    ivf = index._searcher
    assert index.method == "ivf" and ivf.ntotal == len(pool)
    assert ivf.nlist == round(np.sqrt(len(pool))) and ivf.nprobe == 6
    assert (index._storage is not None) == (route == "zero copy")  # lists are views into it
    if route == "zero copy":
        assert not reg._lists_owned(ivf)
        assert index._storage.nbytes < len(pool) * 136 + 100_000  # codes + ids, no copy
    np.testing.assert_array_equal(np.sort(index.point_rows), np.arange(len(pool)))
    query = (pool[:300].astype(np.int16) + rng.integers(-3, 4, (300, 128))).clip(0, 255)
    q = query.astype(np.float32)
    d2, idx = ivf.search(q, 2)
    np.testing.assert_array_equal(index.point_rows[idx[:, 0]], np.arange(300))
    np.testing.assert_array_equal(d2[:, 0], ((q - pool[:300]) ** 2).sum(axis=1))  # exact L2²
    ref = faiss.IndexIVFScalarQuantizer(faiss.clone_index(ivf.quantizer), 128, ivf.nlist,
                                        faiss.ScalarQuantizer.QT_8bit_direct, faiss.METRIC_L2,
                                        False)
    ref.train(pool[:1000].astype(np.float32))  # the cells are given: only the codec trains
    ref.add(pool.astype(np.float32))
    ref.nprobe = ivf.nprobe
    d2_ref, idx_ref = ref.search(q, 2)
    np.testing.assert_array_equal(index.point_rows[idx], idx_ref)
    np.testing.assert_array_equal(d2, d2_ref)


def _pool_model(n: int) -> object:
    """The parts of a model that ``index_pool`` reads, for n points."""
    from types import SimpleNamespace
    return SimpleNamespace(points_xyz=np.zeros((n, 3)), point3D_ids=np.arange(n, dtype=np.uint64))
