"""The reconstruction's own error in σ: the mesh depth term, the model intrinsics' directions and
their response (bundle adjustment of a synthetic survey), shared terms that do not average down,
the error budget, and the mesh check against the model's points."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from model_error_synth import (
    CAMERA,
    analytic_gamma,
    diverging_rig,
    laser_view,
    nadir_pose,
    survey,
)
from test_fusion import hand_image
from uncertainty_synth import make_scene, observe

from sfm_laserscale.fusion import FusionOptions, fuse
from sfm_laserscale.geometry import umeyama_sim3
from sfm_laserscale.mesh_error import MeshErrorOptions, spot_mesh_sigma
from sfm_laserscale.model_error import ModelDirection
from sfm_laserscale.raycast import MeshRaycaster, SpotHit
from sfm_laserscale.registration.covariance import IntrinsicsOptions, analyse_intrinsics
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.uncertainty import (
    EstimationOptions,
    ImageObservation,
    estimate_image,
    perturbed_observation,
)

OPTS = EstimationOptions()


def _axis_rig():
    """One beam parallel to the optical axis, 0.165 m from the camera centre."""
    return rig_from_dict({"name": "axis", "laser": [
        {"name": "L1", "origin": [0.165, 0.0, 0.0], "direction": [0.0, 0.0, 1.0]}]})


def _nadir_observation(k: float = 0.37) -> ImageObservation:
    """A noiseless image of the axis beam on a plane 3 m ahead (no pose covariance)."""
    scene = make_scene(_axis_rig(), distance_m=3.0, tilt_deg=0.0, k=k)
    return observe(scene, np.random.default_rng(0), 0.0, None, lasers=("L1",))


# --------------------------------------------------------------------------- mesh depth term


def test_mesh_depth_sigma_gives_delta_over_range_one_to_one() -> None:
    """A mesh depth σ δ along the spot's ray: σ_s / s = δ / |X| (1 cm at 3 m is 0.33 %)."""
    obs = _nadir_observation()
    hit = obs.cam_from_world.transform(obs.hits[0].hit_world[None])[0]
    delta = 0.01 / 0.37  # 1 cm in model units
    est = estimate_image(replace(obs, mesh_sigma=np.array([delta])), _axis_rig(), OPTS)
    (e,) = est.of("fcm")
    assert e.sigma / e.scale == pytest.approx(delta / np.linalg.norm(hit), rel=1e-4)
    assert 100 * e.sigma / e.scale == pytest.approx(100 * 0.01 / 3.0, rel=0.01)
    assert est.covariance_terms["fcm"]["mesh"][0, 0] == pytest.approx(e.sigma**2, rel=1e-9)
    assert est.covariance_terms["fcm"]["spots"][0, 0] == 0.0


def test_bad_mesh_sigma_is_an_input_error() -> None:
    from sfm_laserscale.errors import InputError

    obs = _nadir_observation()
    with pytest.raises(InputError, match="mesh sigma"):
        estimate_image(replace(obs, mesh_sigma=np.array([-1.0])), _axis_rig(), OPTS)


# --------------------------------------------------------------------------- intrinsics


def test_focal_only_direction_gives_fcm_focal_sensitivity_s() -> None:
    """An axis beam on a fronto-parallel plane, camera focal × (1 + ε) alone (pose, plane
    fixed): the hit's lateral offset shrinks by 1 + ε, so dS/dε = s exactly."""
    obs = _nadir_observation()
    d = ModelDirection("camera1.focal", CAMERA_PARAMS_SCALE(obs), np.zeros(6), np.zeros((1, 3)),
                       False)
    est = estimate_image(replace(obs, model_directions=(d,)), _axis_rig(), OPTS)
    (e,) = est.of("fcm")
    assert est.focal_sensitivity["fcm"][0] == pytest.approx(e.scale, rel=1e-6)
    assert not any(p.startswith("camera") for p in est.rig_params)  # not part of σ


def CAMERA_PARAMS_SCALE(obs: ImageObservation) -> np.ndarray:  # noqa: N802
    """d params per unit δf / f of a PINHOLE camera."""
    p = np.asarray(obs.camera.params, dtype=np.float64)
    return np.array([p[0], p[1], 0.0, 0.0])


def test_perturbed_observation_keeps_hits_on_the_new_rays() -> None:
    obs = _nadir_observation()
    d = ModelDirection("camera1.intrinsics1", CAMERA_PARAMS_SCALE(obs),
                       np.array([1e-3, -2e-3, 5e-4, 0.01, 0.0, -0.02]),
                       np.array([[0.0, 0.0, 0.05]]))
    moved = perturbed_observation(obs, d, 0.1)
    x = moved.cam_from_world.transform(moved.hits[0].hit_world[None])[0]
    ray = moved.camera.unproject(moved.hits[0].xy_px[None])[0]
    assert np.linalg.norm(np.cross(x / np.linalg.norm(x), ray / np.linalg.norm(ray))) < 1e-12


def test_shared_intrinsics_term_does_not_average_down() -> None:
    """n images with a random σ and a common intrinsics term g: the fused random σ shrinks as
    1/√n, the intrinsics part stays g (budget)."""
    g, sr = 3e-4, 1e-3
    out = {}
    for n in (4, 16):
        ims = [hand_image(f"im{i}", 0.37, [[sr**2]], [[g]], ("camera1.intrinsics1",))
               for i in range(n)]
        f = fuse(ims, "fcm", FusionOptions())
        out[n] = f
        assert f.std_systematic == pytest.approx(g, rel=1e-6)
        assert f.budget["intrinsics"] == pytest.approx(g**2, rel=1e-6)
        assert f.budget["rig"] == 0.0
        assert sum(f.budget_shares().values()) == pytest.approx(1.0)
    assert out[16].std_random == pytest.approx(out[4].std_random / 2, rel=1e-6)


def test_budget_splits_spots_pose_and_mesh() -> None:
    """With spot, pose and mesh noise, the budget's random terms add up to the random σ² and
    each is the term's own propagation."""
    rng = np.random.default_rng(3)
    scene = make_scene(_axis_rig(), distance_m=3.0, tilt_deg=15.0)
    from uncertainty_synth import pose_covariance

    obs = observe(scene, rng, 0.3, pose_covariance(rng), lasers=("L1",))
    obs = replace(obs, mesh_sigma=np.array([0.004]))
    est = estimate_image(obs, _axis_rig(), OPTS)
    terms = est.covariance_terms["fcm"]
    total = sum(t[0, 0] for t in terms.values())
    assert total == pytest.approx(est.covariance_random["fcm"][0, 0], rel=1e-9)
    only = {k: estimate_image(replace(obs, mesh_sigma=np.array([0.004 if k == "mesh" else 0.0]),
                                      pose_covariance=obs.pose_covariance if k == "pose" else None,
                                      hits=tuple(replace(h, sigma_px=0.3 if k == "spots" else 0.0)
                                                 for h in obs.hits)), _axis_rig(), OPTS)
            for k in ("spots", "pose", "mesh")}
    for k, e in only.items():
        assert terms[k][0, 0] == pytest.approx(e.covariance_random["fcm"][0, 0], rel=1e-6)
    f = fuse([est], "fcm", FusionOptions())
    shares = f.budget_shares()
    for k in ("spots", "pose", "mesh"):
        assert shares[k] == pytest.approx(terms[k][0, 0] / total, rel=1e-6)


# --------------------------------------------------------------------------- BA response


@pytest.fixture(scope="module")
def survey_field():  # type: ignore[no-untyped-def]
    model = survey()
    return model, analyse_intrinsics(lambda: model, model.point3D_ids,
                                     IntrinsicsOptions(refined=("focal",), focal_sigma_floor=0.0))


def test_ba_response_to_the_focal_is_the_nadir_depth_stretch(survey_field) -> None:  # type: ignore[no-untyped-def]
    """Nadir cameras at one altitude: a focal change δf / f = ε stretches every depth below
    them by 1 + ε; aligned to the model, each point moves by ε (z − z̄) vertically. The images
    cannot determine the focal length (it trades exactly with the altitude): the covariance is
    rank deficient and the prior σ(δf/f) is used, with a note."""
    model, field = survey_field
    cam = field.cameras[1]
    assert cam.names == ("focal",) and not cam.from_covariance
    assert cam.focal_sigma == pytest.approx(IntrinsicsOptions().focal_sigma_prior)
    assert any("prior" in n for n in field.notes)
    assert np.allclose(cam.dparams[0], [700.0, 700.0, 0.0, 0.0])  # the model's focal, kept
    d = cam.displacement[0]
    pts = field.points_xyz
    # the exact stretch about the camera plane, aligned back by a similarity (which takes up
    # the part of it that is a rotation of the tilted surface), per unit ε
    h = 1e-4
    stretched = pts + h * np.column_stack([np.zeros((len(pts), 2)), pts[:, 2] - 3.0])
    s, R, t = umeyama_sim3(stretched, pts)
    expected = (s * stretched @ R.T + t - pts) / h
    assert np.std(expected[:, 2]) > 0.5 * np.std(pts[:, 2] - np.polyval(
        np.polyfit(pts[:, 0], pts[:, 2], 1), pts[:, 0]))  # a real relief signal
    slope = float(np.polyfit(expected[:, 2], d[:, 2], 1)[0])
    assert slope == pytest.approx(1.0, abs=0.05)
    assert np.corrcoef(expected[:, 2], d[:, 2])[0, 1] > 0.99
    assert np.sqrt(np.mean((d - expected) ** 2)) < 0.1 * np.sqrt(np.mean(expected**2))
    # σ̂ of the residuals: the synthetic points are the true ones, not adjusted, so the
    # residuals' sum of squares is n σ² over n − p degrees of freedom (p/n ≈ 0.3 here)
    assert 0.3 < field.sigma_px < 0.3 * 1.3


def test_fcm_focal_sensitivity_matches_the_analytic_gamma(survey_field) -> None:  # type: ignore[no-untyped-def]
    """A beam tilted 3° outwards, laser camera at the survey's altitude: FCM moves by
    γ = Z (v_lat·O)/|O|² per unit focal error (≈ 1 here); the σ term is γ s σ(δf/f)."""
    model, field = survey_field
    rig = diverging_rig(3.0)
    obs, xy, xyz, depth = laser_view(rig)
    hits = np.array([h.hit_world for h in obs.hits])
    dirs = field.directions(CAMERA, obs.cam_from_world, xy, xyz, hits)
    est = estimate_image(replace(obs, model_directions=dirs), rig, OPTS)
    (e,) = est.of("fcm")
    gamma = est.focal_sensitivity["fcm"][0] / e.scale
    assert gamma == pytest.approx(analytic_gamma(rig, depth), rel=0.05)
    assert gamma > 0.9
    intr = [k for k, p in enumerate(est.rig_params) if p.startswith("camera1.intrinsics")]
    g = float(np.linalg.norm(est.rig_jacobian["fcm"][0, intr]))
    assert g == pytest.approx(abs(gamma) * e.scale * field.cameras[1].focal_sigma, rel=0.02)


def test_focal_floor_and_prior() -> None:
    """The floor bounds σ(δf/f) from below; a model too small for a covariance gets the prior."""
    model = survey()
    field = analyse_intrinsics(lambda: model, model.point3D_ids,
                               IntrinsicsOptions(refined=("focal",), focal_sigma_floor=0.02))
    assert field is not None and field.cameras[1].focal_sigma == pytest.approx(0.02)
    assert analyse_intrinsics(lambda: model, model.point3D_ids,
                              IntrinsicsOptions(enabled=False)) is None


def test_intrinsics_on_the_real_colmap_fixture(fixtures_dir) -> None:  # type: ignore[no-untyped-def]
    """Real COLMAP model (4 images of a roof, SIMPLE_RADIAL or the like): a finite, positive
    σ(δf/f) from the bundle-adjustment covariance, and a displacement per unit of each
    parameter for every sub-model point."""
    from sfm_laserscale.io.models import load_model

    path = fixtures_dir / "maupertuis_colmap" / "reconstruction"
    model = load_model(path)
    field = analyse_intrinsics(lambda: load_model(path), model.point3D_ids, IntrinsicsOptions())
    assert field is not None
    (cam,) = field.cameras.values()
    assert cam.from_covariance and np.all(np.isfinite(cam.covariance))
    assert 0 < cam.focal_sigma < 0.05
    assert cam.displacement.shape == (len(cam.names), len(field.points_xyz), 3)
    assert np.all(np.isfinite(cam.displacement))


# --------------------------------------------------------------------------- mesh check


def _plane_mesh(z: float, size: float = 4.0) -> MeshRaycaster:
    v = np.array([[-size, -size, z], [size, -size, z], [size, size, z], [-size, size, z]])
    return MeshRaycaster(v, np.array([[0, 1, 2], [0, 2, 3]]))


def test_mesh_check_measures_an_offset_mesh_and_removes_point_noise() -> None:
    """Points on z = 0 (noise σ_p known), a nadir camera at 3 m: a mesh at z = −δ gives
    σ_mesh ≈ δ; the mesh at z = 0 gives σ_mesh ≈ 0 once the points' own σ is removed."""
    rng = np.random.default_rng(5)
    pose = nadir_pose(0.0, 0.0)
    xy = rng.uniform(-1.0, 1.0, (400, 2))
    sigma_p = 0.004
    pts = np.column_stack([xy, rng.normal(scale=sigma_p, size=len(xy))])
    px = CAMERA.project(pose.transform(pts))
    hit = SpotHit("L1", np.array([400.0, 300.0]), 0.3, np.array([0.0, 0.0, 0.0]),
                  np.array([0.0, 0.0, 1.0]))
    opts = MeshErrorOptions(neighbours=200, max_radius=0.5)
    off = spot_mesh_sigma(_plane_mesh(-0.02), CAMERA, pose, (hit,), px, pts,
                          np.full(len(pts), sigma_p), opts)[0]
    assert off.sigma == pytest.approx(0.02, rel=0.1) and off.offset > 0
    same = spot_mesh_sigma(_plane_mesh(0.0), CAMERA, pose, (hit,), px, pts,
                           np.full(len(pts), sigma_p), opts)[0]
    raw = spot_mesh_sigma(_plane_mesh(0.0), CAMERA, pose, (hit,), px, pts, np.zeros(len(pts)),
                          opts)[0]
    assert same.sigma < 0.25 * sigma_p < raw.sigma
    assert raw.spread == pytest.approx(sigma_p, rel=0.2)
    few = spot_mesh_sigma(_plane_mesh(0.0), CAMERA, pose, (hit,), px[:3], pts[:3],
                          np.zeros(3), opts)[0]
    assert few.sigma == 0.0 and few.n_points == 3


def _grid_mesh(heights: np.ndarray, size: float = 2.0) -> MeshRaycaster:
    """A height-field mesh over [-size, size]² with the given (n, n) vertex heights."""
    n = heights.shape[0]
    g = np.linspace(-size, size, n)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    v = np.column_stack([xx.ravel(), yy.ravel(), heights.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return MeshRaycaster(v, tris)


def test_mesh_errors_of_an_image_are_correlated_as_the_mesh_is() -> None:
    """Two spots 0.3 m apart: a mesh off by one smooth offset gives ρ ≈ 1 (they must not average
    down); a mesh whose error changes every 2 cm gives ρ ≈ 0."""
    from sfm_laserscale.mesh_error import mesh_check

    rng = np.random.default_rng(6)
    pose = nadir_pose(0.0, 0.0)
    pts = np.column_stack([rng.uniform(-1.0, 1.0, (600, 2)), np.zeros(600)])
    pts[:, 2] += rng.normal(scale=0.001, size=len(pts))
    px = CAMERA.project(pose.transform(pts))
    hits = tuple(SpotHit(f"L{i}", CAMERA.project(pose.transform(np.array([[x, 0.0, 0.0]])))[0],
                         0.3, np.array([x, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
                 for i, x in enumerate((-0.15, 0.15)))
    opts = MeshErrorOptions(neighbours=150, max_radius=0.3)
    sig = np.full(len(pts), 0.001)
    smooth = mesh_check(_grid_mesh(np.full((201, 201), -0.01)), CAMERA, pose, hits, px, pts, sig,
                        opts)
    assert smooth.correlation[0, 1] > 0.9
    assert all(s.sigma == pytest.approx(0.01, rel=0.15) for s in smooth.spots)
    rough = mesh_check(_grid_mesh(rng.normal(scale=0.01, size=(201, 201))), CAMERA, pose, hits,
                       px, pts, sig, opts)
    assert rough.correlation[0, 1] < 0.3
    # the estimators see it: two FCM lasers on one image do not average their mesh error down
    rig = rig_from_dict({"name": "two", "laser": [
        {"name": "L0", "origin": [-0.15, 0.0, 0.0], "direction": [0.0, 0.0, 1.0]},
        {"name": "L1", "origin": [0.15, 0.0, 0.0], "direction": [0.0, 0.0, 1.0]}]})
    exact = tuple(replace(h, sigma_px=0.0) for h in hits)  # the mesh term alone
    obs = ImageObservation("im", CAMERA, pose, None, exact, np.array([0.01, 0.01]))
    from sfm_laserscale.fusion import combine_image

    indep = combine_image(estimate_image(obs, rig, OPTS), "fcm", FusionOptions())
    corr = combine_image(estimate_image(replace(obs, mesh_correlation=np.ones((2, 2))), rig, OPTS),
                         "fcm", FusionOptions())
    assert indep is not None and corr is not None
    assert corr.sigma_random == pytest.approx(np.sqrt(2) * indep.sigma_random, rel=0.02)


def test_mesh_sigma_keeps_only_the_roughness_its_points_cannot_tell() -> None:
    """A mesh tilted against its points (error 0 at the spot, ±1.3 cm across its neighbours):
    their spread is the tilt, which the semivariogram at the spot's distance from them halves,
    so σ drops to about half of √(m² + ρ²) and still covers the error there (0); a mesh whose
    error changes at every vertex keeps its full spread."""
    from sfm_laserscale.mesh_error import mesh_check

    rng = np.random.default_rng(7)
    pose = nadir_pose(0.0, 0.0)
    pts = np.column_stack([rng.uniform(-1.0, 1.0, (800, 2)), np.zeros(800)])
    px = CAMERA.project(pose.transform(pts))
    hit = SpotHit("L1", CAMERA.project(pose.transform(np.zeros((1, 3))))[0], 0.3,
                  np.zeros(3), np.array([0.0, 0.0, 1.0]))
    opts = MeshErrorOptions(neighbours=60, max_radius=0.5)
    g = np.linspace(-2.0, 2.0, 201)
    xx = np.meshgrid(g, g, indexing="ij")[0]
    tilt = mesh_check(_grid_mesh(-0.01 * xx / 0.3), CAMERA, pose, (hit,), px, pts,
                      np.zeros(len(pts)), opts).spots[0]
    assert tilt.sigma < 0.7 * np.hypot(tilt.offset, tilt.spread)
    assert abs(tilt.offset) < 2.0 * tilt.sigma  # the error at the spot is 0
    rough = mesh_check(_grid_mesh(rng.normal(scale=0.01, size=xx.shape)), CAMERA, pose, (hit,),
                       px, pts, np.zeros(len(pts)), opts).spots[0]
    assert rough.sigma == pytest.approx(np.hypot(rough.offset, rough.spread), rel=0.05)
