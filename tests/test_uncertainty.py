"""Per-image estimates and their first-order uncertainty, against exact Monte-Carlo.

Scene (tests/uncertainty_synth.py): PINHOLE 1024×768 f 900, plane at 3 m tilted 20°, 4-laser rig
(origins 0.165 m, directions 1–3° off the axis, two parallel pairs), spot noise 0.3 px and a
correlated pose covariance (0.017° rotation, 2 mm translation). Monte-Carlo samples recompute
the estimates exactly (noisy ray ∩ true plane, no linearisation).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from uncertainty_synth import (
    K_TRUE,
    make_rig,
    make_scene,
    observe,
    pose_covariance,
    rodrigues,
    sample_hits_cam,
    true_hits_cam_m,
)

from sfm_laserscale.errors import InputError
from sfm_laserscale.fusion import FusionOptions, combine_image
from sfm_laserscale.methods import fcm_scale_batch, pcm_scale_batch
from sfm_laserscale.model import Pose
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.uncertainty import (
    EstimationOptions,
    ImageObservation,
    SpotHit,
    estimate_image,
    perturb_pose,
    rig_parameter_names,
)

OPTS = EstimationOptions()
N_MC = 4000


def sigmas(ie):
    return {(e.method, e.laser): e.sigma for e in ie.estimates}


def scales(ie):
    return {(e.method, e.laser): e.scale for e in ie.estimates}


# ---------------------------------------------------------------- pose convention

def test_perturb_pose_is_left_rotation_and_additive_translation():
    rng = np.random.default_rng(0)
    pose = Pose(rodrigues(rng.normal(size=3)), rng.normal(size=3))
    delta = np.array([0.02, -0.01, 0.03, 0.1, -0.2, 0.3])
    p = perturb_pose(pose, delta)
    np.testing.assert_allclose(p.R, rodrigues(delta[:3]) @ pose.R, atol=1e-14)
    np.testing.assert_allclose(p.t, pose.t + delta[3:], atol=1e-14)
    # small δ: a world point moves in the camera frame by δrot × (R X_w) + δt, i.e. the rotation
    # is about the WORLD origin (camera-frame position t), not about the camera centre
    x_w = rng.normal(size=(1, 3))
    small = 1e-7 * delta
    x_c = pose.transform(x_w)[0]
    moved = perturb_pose(pose, small).transform(x_w)[0] - x_c
    np.testing.assert_allclose(moved, np.cross(small[:3], x_c - pose.t) + small[3:], atol=1e-19)


# ---------------------------------------------------------------- exactness and invariance

def test_noise_free_observation_recovers_the_truth():
    rig = make_rig()
    scene = make_scene(rig)
    obs = observe(scene, np.random.default_rng(1), 0.0, None, sigma_claimed=0.3)
    ie = estimate_image(obs, rig, OPTS)
    assert [(e.method, e.laser) for e in ie.estimates] == [
        ("fcm", "L1"), ("fcm", "L2"), ("fcm", "L3"), ("fcm", "L4"), ("pcm", "L1+L2"),
        ("pcm", "L3+L4"), ("direct3d", "L1+L2"), ("direct3d", "L3+L4")]
    truth_m = true_hits_cam_m(scene)
    for e in ie.estimates:
        assert not e.rejected and e.sigma > 0
        if e.method == "fcm":
            assert e.scale == pytest.approx(K_TRUE, rel=1e-10)
            assert e.direction_residual_deg is not None and e.direction_residual_deg < 1e-8
            assert e.depth_m == pytest.approx(np.linalg.norm(truth_m[e.laser]), rel=1e-9)
        elif e.method == "pcm":
            assert e.scale == pytest.approx(K_TRUE, rel=1e-4)  # the paper's small bias
        else:
            assert abs(e.scale / K_TRUE - 1) > 5e-3  # Direct 3D is wrong on a tilted plane
    for m, n in (("fcm", 4), ("pcm", 2), ("direct3d", 2)):
        cov = ie.covariance[m]
        assert cov.shape == (n, n)
        np.testing.assert_allclose(cov, cov.T, rtol=1e-12, atol=0)
        np.testing.assert_allclose(np.sqrt(np.diag(cov)), [e.sigma for e in ie.of(m)])


def skew(a):
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


def transform_world(obs: ImageObservation, R_w, t_w, c: float = 1.0) -> ImageObservation:
    """The same observation in a world X' = c (R_w X + t_w), pose covariance carried along.

    With R' = exp([δ]ₓ) R, t' = t + δt the rotation turns about the world origin, so moving the
    origin changes the parameters: δt_new = c (δt + [a]ₓ δ) with a = R R_wᵀ t_w.
    """
    pose = obs.cam_from_world
    new_pose = Pose(pose.R @ R_w.T, c * (pose.t - pose.R @ R_w.T @ t_w))
    hits = tuple(replace(h, hit_world=c * (R_w @ h.hit_world + t_w),
                         normal_world=R_w @ h.normal_world) for h in obs.hits)
    cov = obs.pose_covariance
    if cov is not None:
        T = np.eye(6)
        T[3:, :3] = skew(pose.R @ R_w.T @ t_w)
        T[3:] *= c
        cov = T @ cov @ T.T
    return ImageObservation(obs.image, obs.camera, new_pose, cov, hits)


def test_rigid_world_change_leaves_estimates_and_sigmas_unchanged():
    rng = np.random.default_rng(2)
    rig = make_rig(0.0005, 0.0005)
    obs = observe(make_scene(rig), rng, 0.3, pose_covariance(rng))
    a = estimate_image(obs, rig, OPTS)
    moved = transform_world(obs, rodrigues(np.array([0.3, 2.0, -0.7])), np.array([5.0, -3, 8]))
    b = estimate_image(moved, rig, OPTS)
    for ea, eb in zip(a.estimates, b.estimates, strict=True):
        assert eb.scale == pytest.approx(ea.scale, rel=1e-9)
        assert eb.sigma == pytest.approx(ea.sigma, rel=1e-6)
    np.testing.assert_allclose(b.covariance["fcm"], a.covariance["fcm"], rtol=1e-5, atol=1e-16)


@pytest.mark.parametrize("c", [0.05, 7.0])
def test_scaling_the_world_scales_estimates_and_sigmas_by_its_inverse(c):
    rng = np.random.default_rng(3)
    rig = make_rig(0.0005, 0.0005)
    obs = observe(make_scene(rig), rng, 0.3, pose_covariance(rng))
    a = estimate_image(obs, rig, OPTS)
    b = estimate_image(transform_world(obs, np.eye(3), np.zeros(3), c), rig, OPTS)
    for ea, eb in zip(a.estimates, b.estimates, strict=True):
        assert eb.scale == pytest.approx(ea.scale / c, rel=1e-9)
        assert eb.sigma == pytest.approx(ea.sigma / c, rel=1e-6)
        assert eb.depth_m == pytest.approx(ea.depth_m, rel=1e-9)


# ---------------------------------------------------------------- Monte-Carlo calibration

@pytest.fixture(scope="module", params=[1.0, 5.0], ids=["pose-2mm", "pose-1cm"])
def mc_setup(request):
    """Predicted covariances from one noisy observation and N_MC exact noisy re-estimates."""
    rng = np.random.default_rng(10)
    rig = make_rig()
    scene = make_scene(rig)
    pose_cov = pose_covariance(rng) * request.param**2
    ie = estimate_image(observe(scene, rng, 0.3, pose_cov), rig, OPTS)
    hits = sample_hits_cam(scene, rng, N_MC, 0.3, pose_cov)  # (N, 4, 3), L1..L4
    beams = [(np.asarray(las.origin), np.asarray(las.direction)) for las in rig.lasers]
    fcm = np.column_stack([
        fcm_scale_batch(hits[:, i], np.broadcast_to(o, (N_MC, 3)), np.broadcast_to(v, (N_MC, 3)))[0]
        for i, (o, v) in enumerate(beams)])
    pcm = np.column_stack([pcm_scale_batch(hits[:, 0], hits[:, 1], rig.pairs[0].separation),
                           pcm_scale_batch(hits[:, 2], hits[:, 3], rig.pairs[1].separation)])
    return ie, fcm, pcm, request.param


def test_mc_single_laser_fcm_sigma_is_calibrated_and_unbiased(mc_setup):
    ie, fcm, _, pose_factor = mc_setup
    for i, e in enumerate(ie.of("fcm")):
        ratio = fcm[:, i].std(ddof=1) / e.sigma
        assert 0.9 <= ratio <= 1.15, (e.laser, ratio)
        assert abs(fcm[:, i].mean() - K_TRUE) < 0.1 * e.sigma
    # the MC correlations match the predicted joint covariance (shared pose error)
    cov = ie.covariance["fcm"]
    pred_corr = cov / np.outer(np.sqrt(np.diag(cov)), np.sqrt(np.diag(cov)))
    np.testing.assert_allclose(np.corrcoef(fcm.T), pred_corr, atol=0.06)


def test_mc_per_image_fused_fcm_sigma_is_calibrated(mc_setup):
    ie, fcm, _, pose_factor = mc_setup
    cov = ie.covariance["fcm"]
    s = np.array([e.scale for e in ie.of("fcm")])
    cov_u = cov / np.outer(s**2, s**2)  # the fusion's GLS is of u = 1/s
    w = np.linalg.solve(cov_u, np.ones(4))
    w /= w.sum()
    combo = combine_image(ie, "fcm", FusionOptions())
    assert combo is not None and len(combo.used) == 4
    assert combo.value == pytest.approx(1.0 / (w @ (1.0 / s)), rel=1e-12)
    ratio = (1.0 / ((1.0 / fcm) @ w)).std(ddof=1) / combo.sigma
    assert 0.9 <= ratio <= 1.15, ratio
    # shared pose error: with a large pose error the image value is much worse than four
    # independent estimates would give, and the MC agrees with the joint covariance
    naive = 1 / np.sqrt(np.sum(1 / np.diag(cov)))
    if pose_factor > 1:
        assert combo.sigma > 1.3 * naive


def test_mc_pcm_sigma_is_calibrated(mc_setup):
    ie, _, pcm, _ = mc_setup
    for j, e in enumerate(ie.of("pcm")):
        ratio = pcm[:, j].std(ddof=1) / e.sigma
        assert 0.9 <= ratio <= 1.15, (e.laser, ratio)


def test_mc_rig_calibration_term_is_calibrated():
    """True rigs drawn from the nominal rig's calibration σ (isotropic beam tilts); exact hits of
    the true beams, estimates with the nominal rig: the spread is the propagated rig term."""
    rng = np.random.default_rng(11)
    so, sd, n = 0.001, 0.001, 4000
    rig = make_rig(so, sd)
    scene = make_scene(rig)
    ie = estimate_image(observe(scene, rng, 0.0, None, sigma_claimed=0.0), rig, OPTS)
    assert ie.rig_params == rig_parameter_names(rig) and len(ie.rig_params) == 16
    for m in ("fcm", "pcm"):  # no spot / pose noise: the whole σ is the rig term
        np.testing.assert_allclose(ie.covariance_random[m], 0.0, atol=1e-30)
    n_c = scene.pose.R @ scene.plane_normal
    p_c = (scene.pose.R @ scene.plane_point + scene.pose.t) * scene.k
    hits, nominal = [], []
    for las in rig.lasers:
        o, v = np.asarray(las.origin), np.asarray(las.direction)
        tilt = rng.normal(scale=sd, size=(n, 3)) @ (np.eye(3) - np.outer(v, v))
        true_v = (v + tilt) / np.linalg.norm(v + tilt, axis=1, keepdims=True)
        true_o = o + np.column_stack([rng.normal(scale=so, size=(n, 2)), np.zeros(n)])
        r = ((p_c - true_o) @ n_c) / (true_v @ n_c)
        hits.append((true_o + r[:, None] * true_v) / scene.k)
        nominal.append((np.broadcast_to(o, (n, 3)), np.broadcast_to(v, (n, 3))))
    mc = [fcm_scale_batch(hits[i], *nominal[i])[0] for i in range(4)]
    mc += [pcm_scale_batch(hits[0], hits[1], rig.pairs[0].separation),
           pcm_scale_batch(hits[2], hits[3], rig.pairs[1].separation)]
    for e, draws in zip(ie.estimates[:6], mc, strict=True):  # FCM ×4, PCM ×2
        ratio = draws.std(ddof=1) / e.sigma
        assert 0.9 <= ratio <= 1.15, (e.method, e.laser, ratio)


# ---------------------------------------------------------------- rejections and inputs

REASON = "spot inconsistent with beam {} geometry (wrong laser assignment or calibration)"


def test_swapped_spots_are_rejected_by_the_direction_residual():
    rig = make_rig()
    rng = np.random.default_rng(4)
    obs = observe(make_scene(rig), rng, 0.3, pose_covariance(rng))
    h = {x.laser: x for x in obs.hits}
    swapped = (replace(h["L1"], laser="L2"), replace(h["L2"], laser="L1"), h["L3"], h["L4"])
    ie = estimate_image(replace(obs, hits=swapped), rig, OPTS)
    by = {e.laser: e for e in ie.of("fcm")}
    for name in ("L1", "L2"):
        assert by[name].rejected and by[name].reason == REASON.format(name)
        assert (by[name].direction_residual_deg or 0.0) > 90
    assert not by["L3"].rejected and not by["L4"].rejected


def test_miscalibrated_direction_is_rejected():
    rig = make_rig()
    las3 = rig.laser("L3")
    tilt = np.radians(1.0)
    true_v = las3.direction + np.array([tilt, 0.0, 0.0])
    true_rig = replace(rig, lasers=tuple(
        replace(x, direction=true_v / np.linalg.norm(true_v)) if x.name == "L3" else x
        for x in rig.lasers))
    rng = np.random.default_rng(5)
    ie = estimate_image(observe(make_scene(true_rig), rng, 0.3, None), rig, OPTS)
    by = {e.laser: e for e in ie.of("fcm")}
    assert by["L3"].rejected and by["L3"].reason == REASON.format("L3")
    assert not any(by[n].rejected for n in ("L1", "L2", "L4"))


def test_grazing_ray_is_rejected():
    rig = make_rig()
    obs = observe(make_scene(rig), np.random.default_rng(6), 0.3, None)
    ray_w = obs.hits[0].hit_world - obs.cam_from_world.center
    ray_w /= np.linalg.norm(ray_w)
    graze_n = np.cross(ray_w, [0.0, 0.0, 1.0])
    graze_n /= np.linalg.norm(graze_n)
    hits = (replace(obs.hits[0], normal_world=graze_n),) + obs.hits[1:]
    ie = estimate_image(replace(obs, hits=hits), rig, OPTS)
    rejected = {(e.method, e.laser) for e in ie.estimates if e.rejected}
    assert rejected == {("fcm", "L1"), ("pcm", "L1+L2"), ("direct3d", "L1+L2")}
    assert "grazes" in (ie.of("fcm")[0].reason or "")


def test_partial_spots_and_pcm_only_rig():
    rig = make_rig()
    obs = observe(make_scene(rig), np.random.default_rng(7), 0.3, None, lasers=("L1", "L2", "L3"))
    ie = estimate_image(obs, rig, OPTS)
    assert [e.laser for e in ie.of("pcm")] == ["L1+L2"]
    assert len(ie.of("fcm")) == 3
    pcm_rig = rig_from_dict({"laser": [{"name": n} for n in ("L1", "L2", "L3", "L4")],
                             "pair": [{"lasers": list(p.lasers), "separation": p.separation}
                                      for p in rig.pairs]})
    ie2 = estimate_image(obs, pcm_rig, OPTS)
    assert ie2.of("fcm") == () and ie2.rig_params == ()
    assert ie2.of("pcm")[0].scale == pytest.approx(ie.of("pcm")[0].scale, rel=1e-12)
    empty = estimate_image(replace(obs, hits=()), rig, OPTS)
    assert empty.estimates == () and empty.covariance["fcm"].shape == (0, 0)


def test_bad_inputs_raise_input_error():
    rig = make_rig()
    obs = observe(make_scene(rig), np.random.default_rng(8), 0.3, None)
    with pytest.raises(InputError, match="unknown laser"):
        estimate_image(replace(obs, hits=(replace(obs.hits[0], laser="L9"),)), rig, OPTS)
    with pytest.raises(InputError, match="two spots"):
        estimate_image(replace(obs, hits=(obs.hits[0], obs.hits[0])), rig, OPTS)
    bad = np.diag([1.0, 1, 1, 1, 1, -1]) * 1e-6
    with pytest.raises(InputError, match="positive semi-definite"):
        estimate_image(replace(obs, pose_covariance=bad), rig, OPTS)
    with pytest.raises(InputError, match="6×6"):
        estimate_image(replace(obs, pose_covariance=np.eye(5)), rig, OPTS)
    with pytest.raises(InputError, match="sigma"):
        estimate_image(replace(obs, hits=(replace(obs.hits[0], sigma_px=-1.0),)), rig, OPTS)


def test_spot_hit_is_a_frozen_record():
    h = SpotHit("L1", np.zeros(2), 0.3, np.zeros(3), np.array([0.0, 0, 1]))
    with pytest.raises(AttributeError):
        h.laser = "L2"  # type: ignore[misc]
