"""Fusion: per-image GLS, robust rejection, Birge inflation, common rig term, coverage."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats
from uncertainty_synth import (
    K_TRUE,
    make_rig,
    make_scene,
    observe,
    perturbed_rig,
    pose_covariance,
)

from sfm_laserscale.fusion import FusionOptions, combine_image, fuse
from sfm_laserscale.report.writer import fused_to_dict
from sfm_laserscale.uncertainty import (
    METHODS,
    Estimate,
    EstimationOptions,
    ImageEstimates,
    estimate_image,
)

OPTS = FusionOptions()


def hand_image(name: str, values, cov_random, rig_jac=None, rig_params=(), method="fcm",
               rejected: dict[int, str] | None = None) -> ImageEstimates:
    """ImageEstimates with given values, random covariance and rig Jacobian (one method)."""
    values = np.atleast_1d(np.asarray(values, dtype=np.float64))
    n = len(values)
    cov_random = np.asarray(cov_random, dtype=np.float64).reshape(n, n)
    g = np.zeros((n, len(rig_params))) if rig_jac is None else np.asarray(rig_jac).reshape(n, -1)
    cov = cov_random + g @ g.T
    rejected = rejected or {}
    ests = tuple(Estimate(name, method, f"L{i + 1}", float(v), float(np.sqrt(cov[i, i])), None,
                          3.0, i in rejected, rejected.get(i)) for i, v in enumerate(values))
    def per(m, a):
        return a if m == method else np.zeros((0, a.shape[1] if a.ndim == 2 else 0))
    return ImageEstimates(name, ests, {m: per(m, cov) if m == method else np.zeros((0, 0))
                                       for m in METHODS},
                          {m: cov_random if m == method else np.zeros((0, 0)) for m in METHODS},
                          {m: g if m == method else np.zeros((0, len(rig_params)))
                           for m in METHODS}, tuple(rig_params))


def scattered_images(rng, n, sigma, spread=1.0, k=K_TRUE):
    """n single-estimate images drawn around k with `spread` × their stated σ."""
    return [hand_image(f"im{i}", k + spread * sigma * rng.normal(), [[sigma**2]])
            for i in range(n)]


# ---------------------------------------------------------------- per image

def _gls_inverse(values, cov):
    """Closed-form GLS of u = 1/s: (fused s, its σ)."""
    values = np.asarray(values, dtype=np.float64)
    u = 1.0 / values
    cu = np.asarray(cov) / np.outer(values**2, values**2)
    w = np.linalg.solve(cu, np.ones(len(u)))
    w /= w.sum()
    s = 1.0 / (w @ u)
    return s, s**2 * np.sqrt(w @ cu @ w)


def test_gls_keeps_the_shared_error():
    a, c = 4e-6, 3e-6  # equal variances, strong positive correlation (shared pose)
    img = hand_image("a", [1.0, 1.002], [[a, c], [c, a]])
    combo = combine_image(img, "fcm", OPTS)
    assert combo is not None
    assert (combo.value, combo.sigma_random) == pytest.approx(
        _gls_inverse([1.0, 1.002], [[a, c], [c, a]]), rel=1e-12)
    assert combo.value == pytest.approx(1.001, rel=5e-5)
    assert combo.sigma_random == pytest.approx(np.sqrt((a + c) / 2), rel=1e-2)  # not √(a/2)
    # unequal variances
    cov = np.array([[4e-6, 1e-6], [1e-6, 9e-6]])
    combo = combine_image(hand_image("b", [1.0, 1.003], cov), "fcm", OPTS)
    assert combo is not None
    assert (combo.value, combo.sigma_random) == pytest.approx(
        _gls_inverse([1.0, 1.003], cov), rel=1e-12)


def test_fusion_is_unbiased_when_sigma_grows_with_the_draw():
    """FCM triangulates: 1/s is Gaussian in the spot noise and σ_s = σ_u s² grows with the draw.
    Weighting s by 1/σ_s² would favour the low draws (about −8 ρ σ for a relative noise ρ:
    −0.24 σ at ρ = 3 %); the fusion of 1/s is unbiased to ρ/2."""
    rng = np.random.default_rng(7)
    k, rho, reps = 0.5, 0.03, 3000
    z = []
    for _ in range(reps):
        u = (1 + rho * rng.normal(size=4)) / k
        sig = rho / k * (1.0 / u) ** 2  # σ_s = σ_u s²
        imgs = [hand_image(f"i{i}", 1.0 / u[i], [[sig[i] ** 2]]) for i in range(4)]
        f = fuse(imgs, "fcm", OPTS)
        z.append((f.value - k) / f.std)
    assert abs(float(np.mean(z))) < 0.03 + 3 / np.sqrt(reps), np.mean(z)
    assert 0.95 < float(np.std(z)) < 1.05


def test_within_image_outlier_rejected_with_reason():
    s = 1e-3
    img = hand_image("a", [0.5, 0.5 + 0.2 * s, 0.5 + 20 * s, 0.5 - 0.3 * s],
                     np.eye(4) * s**2 + 0.2 * s**2)
    combo = combine_image(img, "fcm", OPTS)
    assert combo is not None and [e.laser for e in combo.used] == ["L1", "L2", "L4"]
    assert combo.rejected[0][0] == "L3"
    assert "inconsistent with the image's other fcm estimates" in combo.rejected[0][1]
    fused = fuse([img], "fcm", OPTS)
    assert fused.n_estimates == 3 and fused.n_rejected == 1
    assert fused.rejected[0][:2] == ("a", "L3")


def test_estimates_rejected_upstream_are_reported():
    img = hand_image("a", [0.5, 0.51], np.eye(2) * 1e-6, rejected={1: "spot inconsistent"})
    fused = fuse([img], "fcm", OPTS)
    assert fused.value == pytest.approx(0.5)
    assert fused.rejected == [("a", "L2", "spot inconsistent")]


# ---------------------------------------------------------------- across images

def test_consistent_images_give_the_propagated_interval():
    sig = np.array([1e-3, 2e-3, 1.5e-3])
    imgs = [hand_image(f"i{i}", 0.5, [[s**2]]) for i, s in enumerate(sig)]
    fused = fuse(imgs, "fcm", OPTS)
    expected = 1 / np.sqrt(np.sum(1 / sig**2))
    assert fused.value == pytest.approx(0.5) and fused.inverse == pytest.approx(2.0)
    assert fused.std == pytest.approx(expected, rel=1e-12)
    assert fused.ci95[1] - fused.value == pytest.approx(1.959964 * expected, rel=1e-6)
    assert fused.birge_ratio == pytest.approx(0.0, abs=1e-6)
    assert {"value", "std", "ci95", "inverse", "method", "n_estimates",
            "n_rejected"} <= fused_to_dict(fused).keys()  # report.json's scale block


def test_injected_outlier_image_is_rejected():
    rng = np.random.default_rng(0)
    sigma = 0.002 * K_TRUE
    imgs = scattered_images(rng, 8, sigma)
    imgs.append(hand_image("bad", K_TRUE * 1.03, [[sigma**2]]))
    fused = fuse(imgs, "fcm", OPTS)
    assert "bad" not in fused.images_used and len(fused.images_used) == 8
    assert fused.n_rejected == 1 and fused.rejected[0][0] == "bad"
    assert "robust sigmas" in fused.rejected[0][2]
    assert abs(fused.value - K_TRUE) < 3 * fused.std
    assert "bad" in fused.per_image  # still reported, with its value
    # without the rejection the outlier would have pulled the value by ~0.3 %
    kept_all = fuse(imgs, "fcm", FusionOptions(outlier_threshold=1e9))
    assert abs(kept_all.value - K_TRUE) > abs(fused.value - K_TRUE)


def test_no_rejection_of_consistent_data():
    rng = np.random.default_rng(1)
    total = 0
    for _ in range(200):
        total += fuse(scattered_images(rng, 6, 1e-3), "fcm", OPTS).n_rejected
    assert total <= 6  # 1200 good images; expected ≈ 2 (|z| > 3.5 about a noisy median)


def test_birge_inflation_when_images_scatter_beyond_their_sigma():
    rng = np.random.default_rng(2)
    sigma = 1e-3
    imgs = scattered_images(rng, 10, sigma, spread=3.0)
    fused = fuse(imgs, "fcm", OPTS)
    assert 2.0 < fused.birge_ratio < 4.5 and fused.inflated and fused.birge_p < 0.01
    values = np.array([im.estimates[0].scale for im in imgs])
    value, prop = _gls_inverse(values, np.diag(np.full(10, sigma**2)))
    assert fused.value == pytest.approx(value, rel=1e-12)
    assert fused.std == pytest.approx(fused.birge_ratio * prop, rel=1e-9)
    half = fused.ci95[1] - fused.value
    assert half == pytest.approx(stats.t.ppf(0.975, 9) * fused.std, rel=1e-9)
    assert any("Birge" in n for n in fused.notes)
    # consistent data: no inflation
    calm = fuse(scattered_images(rng, 10, sigma, spread=0.3), "fcm", OPTS)
    assert not calm.inflated
    assert calm.std == pytest.approx(prop, rel=1e-2)
    assert calm.ci95[1] - calm.value == pytest.approx(1.959964 * calm.std, rel=1e-6)


def test_no_inflation_for_scatter_the_sigmas_explain():
    """A Birge ratio above 1 is what consistent data give half of the time: inflating it would
    make the interval too wide. Only an improbable χ² (p < 0.01) inflates."""
    rng = np.random.default_rng(3)
    n_inflated, births = 0, []
    for _ in range(400):
        f = fuse(scattered_images(rng, 6, 1e-3), "fcm", OPTS)
        n_inflated += f.inflated
        births.append(f.birge_ratio)
    assert 0.3 < np.mean(np.array(births) > 1) < 0.6  # R > 1 often …
    assert n_inflated <= 12  # … but inflated ≈ 1 % of the time (expected 4)
    strict = FusionOptions(birge_p_value=1.0)  # the old rule: inflate whenever R > 1
    f = fuse(scattered_images(np.random.default_rng(5), 6, 1e-3, spread=1.5), "fcm", strict)
    assert f.inflated == (f.birge_ratio > 1)


def test_systematic_rig_term_does_not_average_down():
    sigma, g = 1e-3, np.array([[4e-4, -3e-4]])  # same rig sensitivity in every image
    names = ("L1.origin_x", "L1.direction_a")
    out = {}
    for n in (5, 50):
        imgs = [hand_image(f"i{i}", 0.5, [[sigma**2]], g, names) for i in range(n)]
        out[n] = fuse(imgs, "fcm", OPTS)
    assert out[5].std_systematic == pytest.approx(5e-4, rel=1e-12)
    assert out[50].std_systematic == pytest.approx(5e-4, rel=1e-12)
    assert out[50].std_random == pytest.approx(out[5].std_random / np.sqrt(10), rel=1e-9)
    assert out[50].std == pytest.approx(np.hypot(5e-4, sigma / np.sqrt(50)), rel=1e-9)
    # rig parameters are aligned by name across images (a laser seen in one image only)
    imgs = [hand_image("a", 0.5, [[sigma**2]], [[1e-4, 0.0]], names),
            hand_image("b", 0.5, [[sigma**2]], [[2e-4]], ("L1.direction_a",))]
    assert fuse(imgs, "fcm", OPTS).std_systematic == pytest.approx(np.hypot(0.5e-4, 1e-4))


def test_rig_only_uncertainty_is_finite():
    imgs = [hand_image(f"i{i}", 0.5, [[0.0]], [[1e-4 * (1 + i)]], ("L1.origin_x",))
            for i in range(3)]
    fused = fuse(imgs, "fcm", OPTS)
    assert fused.value == pytest.approx(0.5) and fused.std_random == 0.0
    assert np.isfinite(fused.std) and fused.std > 1e-4


def test_nothing_left_gives_nan_and_reasons():
    img = hand_image("a", [0.5], [[1e-6]], rejected={0: "spot inconsistent"})
    fused = fuse([img], "fcm", OPTS)
    assert np.isnan(fused.value) and np.isnan(fused.std) and fused.n_estimates == 0
    assert fused.reason == "no usable fcm estimate"
    assert fused.rejected == [("a", "L1", "spot inconsistent")]
    assert np.isnan(fuse([], "pcm", OPTS).value)
    few = fuse([hand_image("a", [0.5], [[1e-6]])], "fcm", FusionOptions(min_estimates=2))
    assert np.isnan(few.value) and "need 2" in (few.reason or "")
    with pytest.raises(ValueError):
        fuse([img], "davis", OPTS)


# ---------------------------------------------------------------- end-to-end coverage

VIEWS = [(2.2, 10.0, (1.0, 0.3, 0.0)), (3.0, 20.0, (0.3, 1.0, 0.0)),
         (3.6, 30.0, (-0.5, 1.0, 0.0)), (2.6, 40.0, (1.0, -0.4, 0.0))]


def test_fused_interval_coverage_with_spot_pose_and_rig_errors():
    """400 repetitions of 4 images: spot noise 0.3 px, pose noise, and a rig calibration error
    drawn once per repetition (common to its images). The 95 % interval must hold K_TRUE
    92–98 % of the time and the normalised error must have unit spread."""
    rng = np.random.default_rng(20)
    so, sd = 0.0002, 0.0002  # 0.2 mm, 0.2 mrad: about 3/4 of the fused σ is the common rig term
    rig = make_rig(so, sd)
    covs = [pose_covariance(rng) for _ in VIEWS]
    est_opts = EstimationOptions()
    hits = {"fcm": 0, "pcm": 0}
    z: dict[str, list[float]] = {"fcm": [], "pcm": []}
    reps = 400
    for _ in range(reps):
        true_rig = perturbed_rig(rig, rng, so, sd)
        ests = [estimate_image(observe(make_scene(true_rig, d, tilt, ax), rng, 0.3, cov,
                                       name=f"v{i}"), rig, est_opts)
                for i, ((d, tilt, ax), cov) in enumerate(zip(VIEWS, covs, strict=True))]
        for m in hits:
            f = fuse(ests, m, OPTS)
            hits[m] += f.ci95[0] <= K_TRUE <= f.ci95[1]
            z[m].append((f.value - K_TRUE) / f.std)
    for m in hits:
        assert 0.92 <= hits[m] / reps <= 0.98, (m, hits[m] / reps)
        assert 0.85 <= float(np.std(z[m])) <= 1.15, (m, np.std(z[m]))
        assert abs(float(np.mean(z[m]))) < 0.2
