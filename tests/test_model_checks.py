"""Checks that catch the model's own error: methods against each other, lasers, trends against
distance and along the survey (drift, segments), the focal-error fit and its corrected scale,
the rig's pair geometry, and the plain-word warnings they give."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sfm_laserscale.focal_fit import FocalFitOptions, fit_focal_error, focal_rms, widen_for_focal
from sfm_laserscale.fusion import FusedScale, FusionOptions, fuse
from sfm_laserscale.model_checks import (
    ImagePoint,
    ModelCheckOptions,
    compare,
    laser_checks,
    run_model_checks,
    trend,
)
from sfm_laserscale.report.model_warnings import model_warnings
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.rig_checks import check_pairs, pair_warnings, refused_pairs
from sfm_laserscale.uncertainty import METHODS, Estimate, ImageEstimates

S = 0.4  # true scale, metres per model unit
FUSION = FusionOptions()


def _fused(method: str, value: float, std: float, grad: dict[str, float] | None = None,
           images: tuple[str, ...] = ("a", "b")) -> FusedScale:
    g = grad or {}
    sys_ = math.sqrt(sum(v * v for v in g.values()))
    rand = math.sqrt(std**2 - sys_**2)
    return FusedScale(value, std, (value - 2 * std, value + 2 * std), 1 / value, method, 4, 0,
                      {}, [], [], rand, sys_, 1.0, 0.5, False, images, None, {}, g)


def _image(name: str, values: dict[str, float], sigma: float, gamma: dict[str, float],
           rig_g: float = 0.0, depth: float = 3.0) -> ImageEstimates:
    """FCM estimates of one image (independent, σ each), relative focal sensitivity γ per laser
    and a common rig term of ``rig_g`` per estimate (parameter "L1.origin_x")."""
    lasers = list(values)
    ests = tuple(Estimate(name, "fcm", la, values[la], math.hypot(sigma, rig_g), None, depth,
                          False, None) for la in lasers)
    n = len(lasers)
    cov_r = np.eye(n) * sigma**2
    g = np.full((n, 1), rig_g)
    empty = np.zeros((0, 0))
    return ImageEstimates(
        name, ests, {m: (cov_r + g @ g.T if m == "fcm" else empty) for m in METHODS},
        {m: (cov_r if m == "fcm" else empty) for m in METHODS},
        {m: (g if m == "fcm" else np.zeros((0, 1))) for m in METHODS}, ("L1.origin_x",),
        {"fcm": {"spots": cov_r}},
        {"fcm": np.array([gamma[la] * values[la] for la in lasers])})


# --------------------------------------------------------------------------- comparisons


def test_compare_uses_random_parts_and_the_difference_of_shared_gradients() -> None:
    a = _fused("fcm", 0.402, 0.0005, {"camera1.intrinsics1": 0.0004})
    b = _fused("pcm", 0.400, 0.0006, {"camera1.intrinsics1": 0.0001})
    c = compare(a, b, 3.0)
    assert c is not None
    sigma = math.sqrt(0.0003**2 + (0.0006**2 - 0.0001**2) + 0.0003**2)
    assert c.z == pytest.approx(0.002 / sigma)
    assert c.difference_pct == pytest.approx(0.5)
    assert c.ok  # 2.75 σ, within the limit of 3
    tight = compare(a, b, 2.5)
    assert tight is not None and not tight.ok


def test_compare_flags_the_issue_case() -> None:
    """FCM +0.199 % with σ 0.017 % against PCM +0.010 %: 10+ σ apart, flagged."""
    fcm = _fused("fcm", S * 1.00199, S * 0.00017)
    pcm = _fused("pcm", S * 1.00010, S * 0.00012)
    c = compare(fcm, pcm, 3.0)
    assert c is not None and not c.ok and c.z > 9


# --------------------------------------------------------------------------- trends


def _points(x: np.ndarray, y_pct: np.ndarray, sigma_pct: float) -> list[ImagePoint]:
    return [ImagePoint(f"im{i}", S * (1 + yi / 100), S * sigma_pct / 100, 3.0,
                       np.array([xi, 0.0, 0.0]), True)
            for i, (xi, yi) in enumerate(zip(x, y_pct, strict=True))]


def test_trend_recovers_a_slope_and_its_significance() -> None:
    rng = np.random.default_rng(1)
    x = np.linspace(0, 20, 12)
    y = 0.02 * x + rng.normal(scale=0.05, size=len(x))
    t = trend(_points(x, y, 0.05), x, "position_m", ModelCheckOptions(), S)
    assert t is not None and t.significant
    assert t.slope_pct == pytest.approx(0.02, abs=3 * t.sigma_pct)
    assert t.change_pct == pytest.approx(t.slope_pct * 20)


def test_trend_false_alarm_rate_is_the_p_value() -> None:
    """No trend, σ right: significant in about 1 % of 2000 draws (binomial bounds)."""
    rng = np.random.default_rng(7)
    x = np.linspace(0, 10, 8)
    hits = sum(trend(_points(x, rng.normal(scale=0.1, size=8), 0.1), x, "distance_m",
                     ModelCheckOptions(), S).significant for _ in range(2000))  # type: ignore[union-attr]
    assert 5 <= hits <= 45


def test_trend_is_not_fooled_by_an_understated_sigma() -> None:
    """Scatter 5 × the stated σ and no trend: the Birge widening keeps false alarms rare."""
    rng = np.random.default_rng(8)
    x = np.linspace(0, 10, 10)
    hits = sum(trend(_points(x, rng.normal(scale=0.5, size=10), 0.1), x, "distance_m",
                     ModelCheckOptions(), S).significant for _ in range(500))  # type: ignore[union-attr]
    assert hits <= 15


# --------------------------------------------------------------------------- lasers


def test_laser_check_flags_the_one_laser_off() -> None:
    rng = np.random.default_rng(2)
    ims = []
    for i in range(6):
        vals = {la: S * (1 + 0.001 * rng.normal()) for la in ("L1", "L2", "L3", "L4")}
        vals["L3"] *= 1.01
        ims.append(_image(f"im{i}", vals, S * 0.001, dict.fromkeys(vals, 0.0)))
    fcm = fuse(ims, "fcm", FUSION)
    checks = {c.laser: c for c in laser_checks(ims, fcm, 3.0)}
    assert not checks["L3"].ok and checks["L3"].vs_others_pct == pytest.approx(1.0, abs=0.2)
    assert all(checks[la].ok for la in ("L1", "L2", "L4"))  # L3 does not drag them off


# --------------------------------------------------------------------------- focal fit


def _focal_images(eps: float, rng: np.random.Generator, n: int = 8, noise: float = 3e-4
                  ) -> list[ImageEstimates]:
    """Beams of γ = 0.5 … 1.5 at several ranges, each estimate S (1 + γ ε) + noise."""
    out = []
    for i in range(n):
        depth = 2.0 + 0.3 * i
        gam = {"L1": 0.3 * depth, "L2": 0.5 * depth, "L3": -0.1 * depth, "L4": 0.2 * depth}
        vals = {la: S * (1 + g * eps) * (1 + noise * rng.normal()) for la, g in gam.items()}
        out.append(_image(f"im{i}", vals, S * noise, gam, depth=depth))
    return out


def test_focal_fit_recovers_the_focal_error_and_the_corrected_scale() -> None:
    rng = np.random.default_rng(4)
    ims = _focal_images(0.004, rng)
    fused = {"fcm": fuse(ims, "fcm", FUSION)}
    f = fit_focal_error(ims, fused, FocalFitOptions(), FUSION)
    assert f.focal_error == pytest.approx(0.004, abs=3 * f.sigma)
    assert f.significant and f.sigma < 0.001
    assert f.corrected is not None and f.corrected.method == "focal_corrected"
    assert f.corrected.value == pytest.approx(S, abs=3 * f.corrected.std)
    assert abs(fused["fcm"].value / S - 1) > 0.001  # the uncorrected FCM is off


def test_focal_fit_coverage_on_repeated_draws() -> None:
    """ε̂ ± σ holds the true ε in about 95 % of 300 draws (z rms ≈ 1)."""
    rng = np.random.default_rng(11)
    z = []
    for _ in range(300):
        ims = _focal_images(0.002, rng, n=5)
        f = fit_focal_error(ims, {"fcm": fuse(ims, "fcm", FUSION)}, FocalFitOptions(), FUSION)
        z.append((f.focal_error - 0.002) / f.sigma)
    z_arr = np.array(z)
    assert 0.85 < float(np.sqrt(np.mean(z_arr**2))) < 1.2
    assert 0.9 < float(np.mean(np.abs(z_arr) < 1.96)) < 0.99


def test_focal_fit_refuses_when_every_estimate_responds_alike() -> None:
    rng = np.random.default_rng(5)
    ims = [_image(f"im{i}", {"L1": S, "L2": S * 1.0001}, S * 1e-3, {"L1": 0.7, "L2": 0.7})
           for i in range(4)]
    f = fit_focal_error(ims, {"fcm": fuse(ims, "fcm", FUSION)}, FocalFitOptions(), FUSION)
    assert f.corrected is None and "alike" in (f.reason or "")
    assert rng is not None


def test_widening_keeps_the_value_and_adds_the_excess() -> None:
    rng = np.random.default_rng(4)
    ims = _focal_images(0.004, rng)
    head = fuse(ims, "fcm", FUSION)
    f = fit_focal_error(ims, {"fcm": head}, FocalFitOptions(), FUSION)
    wide = widen_for_focal(head, 0.8, f, 0.001, FUSION)
    assert wide.value == head.value
    rms = focal_rms(f, 0.001)
    assert rms > 0.003
    excess = (0.8 * head.value) ** 2 * (rms**2 - 0.001**2)
    assert wide.std == pytest.approx(math.sqrt(head.std**2 + excess))
    assert wide.budget["intrinsics"] == pytest.approx(head.budget["intrinsics"] + excess)
    assert any("focal error" in n for n in wide.notes)
    small = replace(f, focal_error=0.0, sigma=0.01, significant=False)
    assert widen_for_focal(head, 0.8, small, 0.001, FUSION) is head  # the prior dominates


# --------------------------------------------------------------------------- drift


def test_drift_is_found_warned_and_segmented() -> None:
    """Images along a 30 m survey whose scale drifts by 0.03 % per metre: a significant trend,
    three segments whose scales follow it, and a warning naming the drift."""
    rng = np.random.default_rng(9)
    n = 12
    pos = np.linspace(-15.0, 15.0, n)
    ims, centres = [], {}
    for i, x in enumerate(pos):
        s = S * (1 + 0.0003 * x)
        vals = {la: s * (1 + 2e-4 * rng.normal()) for la in ("L1", "L2")}
        ims.append(_image(f"im{i}", vals, S * 2e-4, dict.fromkeys(vals, 0.5)))
        centres[f"im{i}"] = np.array([x / S, 0.1 * rng.normal(), 0.0])
    model_centres = np.array([[x / S, 0.0, 2.0] for x in np.linspace(-16, 16, 30)])
    fused = {"fcm": fuse(ims, "fcm", FUSION)}
    checks = run_model_checks(ims, fused, fused["fcm"], False, centres, model_centres, 0.001,
                              ModelCheckOptions(), FUSION)
    assert checks.drift is not None and checks.drift.significant
    assert abs(checks.drift.slope_pct) == pytest.approx(0.03, abs=3 * checks.drift.sigma_pct)
    segs = checks.segments
    assert len(segs) == 3
    vals = [s.fused.value for s in segs]
    assert (vals[0] < vals[1] < vals[2]) or (vals[0] > vals[1] > vals[2])
    report = _report_for(checks, fused)
    codes = [w["code"] for w in model_warnings(report)]
    assert "scale_drift" in codes
    msg = next(w["message"] for w in model_warnings(report) if w["code"] == "scale_drift")
    assert "drifts" in msg and "segment 1" in msg


def test_no_drift_no_warning() -> None:
    rng = np.random.default_rng(10)
    ims, centres = [], {}
    for i, x in enumerate(np.linspace(-15.0, 15.0, 10)):
        vals = {la: S * (1 + 2e-4 * rng.normal()) for la in ("L1", "L2")}
        ims.append(_image(f"im{i}", vals, S * 2e-4, dict.fromkeys(vals, 0.0)))
        centres[f"im{i}"] = np.array([x / S, 0.0, 0.0])
    fused = {"fcm": fuse(ims, "fcm", FUSION)}
    checks = run_model_checks(ims, fused, fused["fcm"], False, centres,
                              np.array([[x / S, 0.0, 2.0] for x in range(-16, 17)]), 0.001,
                              ModelCheckOptions(), FUSION)
    assert checks.drift is not None and not checks.drift.significant and checks.segments == ()
    assert "scale_drift" not in [w["code"] for w in model_warnings(_report_for(checks, fused))]


def _report_for(checks, fused):  # type: ignore[no-untyped-def]
    """The report.json parts the warnings read, built by the writer's own functions."""
    from sfm_laserscale.report.model_report import budget_dict, model_checks_dict
    from sfm_laserscale.report.writer import fused_to_dict

    methods = {m: fused_to_dict(f) for m, f in fused.items()}
    scale = fused_to_dict(checks.headline)
    scale.update(budget_dict(checks.headline))
    return {"scale": scale, "methods": methods, "rig": {"pair_checks": []},
            "model_checks": model_checks_dict(checks, 0.001)}


def test_focal_error_warning_names_it() -> None:
    rng = np.random.default_rng(12)
    ims = _focal_images(0.006, rng)
    fused = {"fcm": fuse(ims, "fcm", FUSION)}
    centres = {im.image: np.array([0.0, float(i), 0.0]) for i, im in enumerate(ims)}
    checks = run_model_checks(ims, fused, fused["fcm"], False, centres,
                              np.array([[0.0, float(i), 2.0] for i in range(10)]), 0.001,
                              ModelCheckOptions(), FUSION)
    assert checks.focal.significant
    report = _report_for(checks, fused)
    warn = [w for w in model_warnings(report) if w["code"] == "focal_error"]
    assert warn and warn[0]["level"] == "warning" and "focal length" in warn[0]["message"]
    assert checks.headline.std > fused["fcm"].std  # σ widened, value kept
    assert checks.headline.value == fused["fcm"].value


# --------------------------------------------------------------------------- rig pairs


def _rig(pairs: list[dict], lasers: list[dict]) -> object:
    return rig_from_dict({"name": "t", "laser": lasers, "pair": pairs})


def test_configuration_c_non_parallel_pair_is_refused_and_warned() -> None:
    """The demo's ROV rig (configuration C): L1+L2 parallel, L3+L4 declared too (4.8° apart)."""
    from sfm_laserscale.rig import Pair
    from sfm_laserscale.synthetic.dataset import make_rig

    rig = make_rig("rov")
    rig = replace(rig, pairs=(*rig.pairs, Pair(("L3", "L4"), 0.33)))
    geo = {g.pair: g for g in check_pairs(rig)}
    assert geo["L1+L2"].parallel and not geo["L1+L2"].refused
    assert geo["L3+L4"].refused and geo["L3+L4"].angle_deg > 4
    assert "L3+L4" in refused_pairs(rig) and "L1+L2" not in refused_pairs(rig)
    assert "not parallel" in pair_warnings(geo["L3+L4"])[0]


def test_slightly_diverging_and_off_centre_pairs_are_warned() -> None:
    t = math.radians(0.2)
    lasers = [{"name": "A", "origin": [-0.1, 0.0, 0.0], "direction": [0.0, 0.0, 1.0],
               "sigma_direction": 1e-4},
              {"name": "B", "origin": [0.1, 0.0, 0.0], "direction": [math.sin(t), 0.0,
                                                                    math.cos(t)],
               "sigma_direction": 1e-4},
              {"name": "C", "origin": [0.05, 0.2, 0.0], "direction": [0.0, 0.0, 1.0]},
              {"name": "D", "origin": [0.25, 0.2, 0.0], "direction": [0.0, 0.0, 1.0]}]
    rig = _rig([{"lasers": ["A", "B"], "separation": 0.2},
                {"lasers": ["C", "D"], "separation": 0.2}], lasers)
    geo = {g.pair: g for g in check_pairs(rig)}  # type: ignore[arg-type]
    ab, cd = geo["A+B"], geo["C+D"]
    assert ab.parallel is False and not ab.refused
    assert ab.separation_change_pct_per_m == pytest.approx(100 * t / 0.2, rel=1e-6)
    assert cd.parallel and cd.equidistant is False
    assert cd.distance_difference_m == pytest.approx(
        math.hypot(0.25, 0.2) - math.hypot(0.05, 0.2), rel=1e-9)
    assert "equidistant" in " ".join(pair_warnings(cd))
    report = {"rig": {"pair_checks": [{"problems": pair_warnings(g)} for g in geo.values()]},
              "scale": {"value": None}}
    assert [w["code"] for w in model_warnings(report)] == ["rig_pair"] * 2


def test_refused_pair_gives_no_pcm_estimate() -> None:
    """estimate_image rejects PCM and Direct 3D of a refused pair with the reason."""
    from uncertainty_synth import make_scene, observe

    from sfm_laserscale.rig import Pair
    from sfm_laserscale.synthetic.dataset import make_rig
    from sfm_laserscale.uncertainty import EstimationOptions, estimate_image

    rig = make_rig("rov")
    rig = replace(rig, pairs=(*rig.pairs, Pair(("L3", "L4"), 0.33)))
    scene = make_scene(rig, distance_m=2.5, tilt_deg=5.0)
    obs = observe(scene, np.random.default_rng(0), 0.2, None)
    est = estimate_image(obs, rig, EstimationOptions())
    bad = [e for e in est.estimates if e.laser == "L3+L4"]
    assert len(bad) == 2 and all(e.rejected and "not parallel" in (e.reason or "") for e in bad)
    good = [e for e in est.estimates if e.laser == "L1+L2"]
    assert good and not any(e.rejected for e in good)


# --------------------------------------------------------------------------- scatter test


def _scatter_images(rng: np.random.Generator, n_images: int, sigma: float
                    ) -> list[ImageEstimates]:
    lasers = ("L1", "L2", "L3", "L4")
    return [_image(f"i{k}", {la: S + rng.normal(0, sigma) for la in lasers}, sigma,
                   dict.fromkeys(lasers, 0.0)) for k in range(n_images)]


def _scatter(images: list[ImageEstimates]):  # type: ignore[no-untyped-def]
    from sfm_laserscale.model_checks import scatter_test

    fused = fuse(images, "fcm", FUSION)
    return scatter_test(images, fused, "fcm", ModelCheckOptions(), FUSION)


def test_scatter_test_leaves_out_one_gross_error_but_not_an_understated_sigma() -> None:
    """The full demo's case: one wrong spot 12.8 σ off in one image of six made χ²/dof 2.8 and
    a warning that every spot's σ was understated. That spot is a gross error (fusion rejects
    and reports it): left out and named. Spots whose σ is understated 2× everywhere still
    fail, and so do gross errors in more than 10 % of the estimates."""
    sigma = 4e-4
    images = _scatter_images(np.random.default_rng(3), 6, sigma)
    assert _scatter(images).ok
    bad = images[2]
    moved = tuple(replace(e, scale=e.scale + 12.8 * sigma) if e.laser == "L3" else e
                  for e in bad.estimates)
    images[2] = replace(bad, estimates=moved)
    one = _scatter(images)
    assert one.ok and one.gross == ("L3 in i2",)
    assert one.dof == 6 * 3 - 1 + 5  # within the images, one estimate out; between images
    # the same spot taken as evidence gives χ²/dof > 2.5: what the demo showed
    from sfm_laserscale.model_checks import scatter_test

    strict = scatter_test(images, fuse(images, "fcm", FUSION), "fcm",
                          ModelCheckOptions(gross_z=math.inf), FUSION)
    assert strict is not None and not strict.ok and strict.ratio > 2.5
    # σ understated 2× everywhere: no single culprit, the test fails
    wide = _scatter_images(np.random.default_rng(4), 6, 2 * sigma)
    under = [replace(im, covariance={m: c / 4 for m, c in im.covariance.items()}) for im in wide]
    assert not _scatter(under).ok
    # a gross error in every image (6 of 24 estimates, 25 %): not left out
    many = _scatter_images(np.random.default_rng(5), 6, sigma)
    many = [replace(im, estimates=tuple(replace(e, scale=e.scale + 12 * sigma)
                                        if e.laser == "L1" else e for e in im.estimates))
            for im in many]
    worst = _scatter(many)
    assert not worst.ok and worst.gross == ()
