"""Closed-form tests of the scale methods (FCM, PCM, Direct 3D, Davis & Tusting).

Scenes are built analytically: camera at the origin of its frame, a plane, beams O + r v
(metres), hits in model units = metric hit / k for a known scale k (metres per model unit).
"""

from __future__ import annotations

import numpy as np
import pytest

from sfm_laserscale.errors import InputError
from sfm_laserscale.methods import (
    davis_tusting_scale,
    direct3d_scale,
    fcm_scale,
    pcm_scale,
    pcm_scale_known_direction,
)
from sfm_laserscale.model import Camera

K = 0.0437  # metres per model unit


def unit(v: list[float] | np.ndarray) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a)


def plane(distance: float, tilt_deg: float, axis: str = "y") -> tuple[np.ndarray, np.ndarray]:
    """Point on the optical axis at `distance` m and unit normal tilted about x or y."""
    t = np.radians(tilt_deg)
    normal = np.array([np.sin(t), 0, -np.cos(t)]) if axis == "y" else \
        np.array([0, np.sin(t), -np.cos(t)])
    return np.array([0.0, 0.0, distance]), normal


def beam_hit_m(origin: np.ndarray, direction: np.ndarray, point: np.ndarray,
               normal: np.ndarray) -> tuple[np.ndarray, float]:
    """Metric hit of the beam on the plane and its range r along the beam."""
    r = float(normal @ (point - origin) / (normal @ direction))
    return origin + r * direction, r


def model_hit(origin, direction, point, normal, k=K) -> np.ndarray:
    return beam_hit_m(origin, direction, point, normal)[0] / k


# ---------------------------------------------------------------- FCM

@pytest.mark.parametrize("tilt,axis", [(0.0, "y"), (30.0, "y"), (30.0, "x"), (-40.0, "y")])
@pytest.mark.parametrize("origin,direction", [
    ([0.165, 0.0, 0.0], [0.0, 0.0, 1.0]),
    ([-0.12, 0.08, 0.0], [np.tan(np.radians(3)), -np.tan(np.radians(2)), 1.0]),
    ([0.0, 0.2, 0.0], [-0.2, 0.1, 1.0]),  # strongly non-parallel to the axis
])
def test_fcm_exact(tilt, axis, origin, direction):
    o, v = np.array(origin), unit(direction)
    p, n = plane(2.7, tilt, axis)
    res = fcm_scale(model_hit(o, v, p, n), o, v)
    assert res.valid and res.reason is None
    assert res.scale == pytest.approx(K, rel=1e-12)
    assert res.direction_residual_deg < 1e-9
    np.testing.assert_allclose(res.origin_hat * K, o, atol=1e-12)


def test_fcm_origin_given_off_the_laser_plane_is_moved_along_the_beam():
    o, v = np.array([0.1, -0.05, 0.0]), unit([0.05, 0.02, 1.0])
    p, n = plane(3.0, 20.0)
    hit = model_hit(o, v, p, n)
    res = fcm_scale(hit, o + 0.37 * v, v)
    assert res.scale == pytest.approx(K, rel=1e-12)


def test_fcm_residual_flags_wrong_assignment_and_calibration():
    v = unit([0.0, 0.0, 1.0])
    o1, o2 = np.array([0.165, 0.0, 0.0]), np.array([0.0, 0.165, 0.0])
    p, n = plane(3.0, 20.0)
    swapped = fcm_scale(model_hit(o2, v, p, n), o1, v)  # L2's spot given to L1
    assert swapped.valid and swapped.direction_residual_deg == pytest.approx(90.0, abs=1e-9)
    # 1° calibration error of the direction at 3 m: residual of the order of 3·0.0175/0.165 rad
    wrong_v = unit([np.tan(np.radians(1.0)), 0.0, 1.0])
    off = fcm_scale(model_hit(o2, v, p, n), o2, wrong_v)
    assert 10.0 < off.direction_residual_deg < 25.0


@pytest.mark.parametrize("hit,origin,direction,word", [
    ([0.1, 0.1, 10.0], [0.1, 0.0, 0.0], [1.0, 0.0, 0.001], "parallel"),
    ([0.1, 0.1, 10.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], "camera centre"),
    ([0.1, 0.1, -10.0], [0.1, 0.0, 0.0], [0.0, 0.0, 1.0], "behind"),
    ([np.nan, 0.1, 10.0], [0.1, 0.0, 0.0], [0.0, 0.0, 1.0], "non-finite"),
    ([0.0, 0.0, 10.0], [0.1, 0.0, 0.0], [0.0, 0.0, 1.0], "‖Ô_L‖"),
])
def test_fcm_rejects_degenerate_inputs(hit, origin, direction, word):
    res = fcm_scale(np.array(hit), np.array(origin), np.array(direction))
    assert not res.valid and np.isnan(res.scale)
    assert res.reason is not None and word in res.reason


# ---------------------------------------------------------------- PCM and Direct 3D

def pair_hits(o1, o2, v, p, n, k=K):
    (x1, r1), (x2, r2) = beam_hit_m(o1, v, p, n), beam_hit_m(o2, v, p, n)
    return x1 / k, x2 / k, r1, r2


@pytest.mark.parametrize("v", [[0.0, 0.0, 1.0], [np.tan(np.radians(4)), 0.0, 1.0]])
def test_pcm_exact_when_the_plane_is_perpendicular_to_parallel_beams(v):
    """Frontal plane and beams along the optical axis, or a plane perpendicular to tilted
    beams: both hits lie at the same position along the beams (Δ = 0)."""
    v = unit(v)
    o1, o2 = np.array([-0.06, 0.11, 0.0]), np.array([0.06, 0.11, 0.0])
    d = float(np.linalg.norm((o2 - o1) - ((o2 - o1) @ v) * v))
    h1, h2, _, _ = pair_hits(o1, o2, v, np.array([0.0, 0.0, 2.5]), -v)
    res = pcm_scale(h1, h2, d)
    assert res.valid and res.scale == pytest.approx(K, rel=1e-12)
    assert res.depth_difference == pytest.approx(0.0, abs=1e-9)
    assert res.alpha_deg == pytest.approx(90.0, abs=1e-6)


@pytest.mark.parametrize("tilt", [10.0, 30.0, -30.0, 45.0])
@pytest.mark.parametrize("h", [0.1, 0.3])
def test_pcm_bias_on_tilted_plane_matches_closed_form(tilt, h):
    """Beams along z at (∓d/2, h): v_CM is tilted by β = atan(h / r̄) out of the beams' plane,
    the hits are Δ = r2 − r1 apart along the beams, so d̂ = √(d² + Δ² sin²β)."""
    d, v = 0.1, np.array([0.0, 0.0, 1.0])
    o1, o2 = np.array([-d / 2, h, 0.0]), np.array([d / 2, h, 0.0])
    h1, h2, r1, r2 = pair_hits(o1, o2, v, *plane(3.0, tilt))
    beta = np.arctan2(h, 0.5 * (r1 + r2))
    expected = K * d / np.sqrt(d**2 + (r2 - r1) ** 2 * np.sin(beta) ** 2)
    res = pcm_scale(h1, h2, d)
    assert res.scale == pytest.approx(expected, rel=1e-12)
    assert res.scale < K  # the approximation always overestimates d̂
    assert res.depth_difference * K == pytest.approx(
        (r2 - r1) * np.cos(beta), rel=1e-9)
    # with the true beam direction, the known-direction variant is exact
    exact = pcm_scale_known_direction(h1, h2, d, v)
    assert exact.scale == pytest.approx(K, rel=1e-12)


def test_pcm_exact_when_camera_half_way_between_the_beams():
    v = unit([0.05, -0.03, 1.0])
    o1, o2 = np.array([-0.08, 0.02, 0.0]), np.array([0.08, -0.02, 0.0])  # symmetric about C
    d = float(np.linalg.norm((o2 - o1) - ((o2 - o1) @ v) * v))
    h1, h2, _, _ = pair_hits(o1, o2, v, *plane(3.0, 35.0, "x"))
    assert pcm_scale(h1, h2, d).scale == pytest.approx(K, rel=1e-12)


def test_pcm_overestimates_d_hat_for_any_tilt_when_equidistant():
    rng = np.random.default_rng(3)
    v = np.array([0.0, 0.0, 1.0])
    o1, o2 = np.array([-0.05, 0.12, 0.0]), np.array([0.05, 0.12, 0.0])
    for _ in range(50):
        n = unit(np.r_[rng.uniform(-0.6, 0.6, 2), -1.0])
        h1, h2, _, _ = pair_hits(o1, o2, v, np.array([0, 0, rng.uniform(1, 5)]), n)
        assert pcm_scale(h1, h2, 0.1).scale <= K * (1 + 1e-12)


def test_direct3d_exact_only_when_beams_perpendicular_to_plane():
    d = 0.1
    o1, o2 = np.array([-d / 2, 0.0, 0.0]), np.array([d / 2, 0.0, 0.0])
    axis = np.array([0.0, 0.0, 1.0])
    h1, h2, _, _ = pair_hits(o1, o2, axis, *plane(3.0, 0.0))
    assert direct3d_scale(h1, h2, d) == pytest.approx(K, rel=1e-12)
    # tilted 30° about y: the hits are d / cos 30° apart
    h1, h2, _, _ = pair_hits(o1, o2, axis, *plane(3.0, 30.0))
    assert direct3d_scale(h1, h2, d) == pytest.approx(K * np.cos(np.radians(30)), rel=1e-12)
    # beams along the plane normal (perpendicular to the tilted plane): exact again
    p, n = plane(3.0, 30.0)
    d_perp = d * np.cos(np.radians(30))  # perpendicular distance of beams along −n
    h1, h2, _, _ = pair_hits(o1, o2, -n, p, n)
    assert direct3d_scale(h1, h2, d_perp) == pytest.approx(K, rel=1e-12)


def test_non_parallel_beams_fcm_exact_pcm_and_direct3d_wrong():
    o1, o2 = np.array([-0.08, 0.1, 0.0]), np.array([0.08, 0.1, 0.0])
    v1, v2 = unit([-0.03, 0.0, 1.0]), unit([0.03, 0.0, 1.0])  # diverging by ~3.4°
    d = 0.16  # separation at the origins
    p, n = plane(3.0, 30.0)
    h1, h2 = model_hit(o1, v1, p, n), model_hit(o2, v2, p, n)
    assert fcm_scale(h1, o1, v1).scale == pytest.approx(K, rel=1e-12)
    assert fcm_scale(h2, o2, v2).scale == pytest.approx(K, rel=1e-12)
    assert abs(direct3d_scale(h1, h2, d) / K - 1) > 0.2
    assert abs(pcm_scale(h1, h2, d).scale / K - 1) > 0.2


def test_pair_rejections():
    a = np.array([0.1, 0.0, 10.0])
    assert not pcm_scale(a, a, 0.1).valid
    assert "coincide" in (pcm_scale(a, a, 0.1).reason or "")
    assert not pcm_scale(a, a * np.array([1, 1, -1]), 0.1).valid
    assert not pcm_scale(a, a + 1, -0.1).valid
    assert not pcm_scale_known_direction(a, a + 1, 0.1, np.zeros(3)).valid
    assert np.isnan(direct3d_scale(a, a, 0.1))


# ---------------------------------------------------------------- scaling

@pytest.mark.parametrize("c", [0.01, 3.7, 250.0])
def test_scaling_the_world_scales_every_method_by_its_inverse(c):
    v = unit([0.03, 0.02, 1.0])
    o1, o2 = np.array([0.0, 0.15, 0.0]), np.array([0.1, 0.15, 0.0])
    p, n = plane(3.0, 25.0)
    h1, h2 = model_hit(o1, v, p, n), model_hit(o2, v, p, n)
    for f in (lambda a, b: fcm_scale(a, o1, v).scale, lambda a, b: pcm_scale(a, b, 0.1).scale,
              lambda a, b: pcm_scale_known_direction(a, b, 0.1, v).scale,
              lambda a, b: direct3d_scale(a, b, 0.1)):
        assert f(c * h1, c * h2) == pytest.approx(f(h1, h2) / c, rel=1e-12)


# ---------------------------------------------------------------- Davis & Tusting

CAM = Camera(1, "PINHOLE", 1024, 768, np.array([900.0, 880.0, 515.0, 380.0]))
DT_ORIGINS = np.array([[0.15, 0.15, 0.0], [-0.15, 0.15, 0.0], [-0.15, -0.15, 0.0],
                       [0.15, -0.15, 0.0]])


def dt_setup(point, normal, query_depth_offsets=None):
    axis = np.array([0.0, 0.0, 1.0])
    spots_m = np.array([beam_hit_m(o, axis, point, normal)[0] for o in DT_ORIGINS])
    spots_px = CAM.project(spots_m)
    query_px = np.array([[200.0, 150.0], [800.0, 190.0], [500.0, 600.0], [300.0, 500.0]])
    rays = CAM.unproject(query_px)
    lam = (point @ normal) / (rays @ normal)
    query_m = rays * lam[:, None]
    if query_depth_offsets is not None:  # a non-flat scene: the points move along their rays
        query_m *= (1 + np.asarray(query_depth_offsets))[:, None]
    return spots_px, query_px, query_m / K


@pytest.mark.parametrize("tilt,axis", [(0.0, "y"), (25.0, "x"), (-35.0, "y")])
def test_davis_tusting_exact_on_flat_scene(tilt, axis):
    spots_px, qpx, qhits = dt_setup(*plane(2.5, tilt, axis))
    assert davis_tusting_scale(spots_px, CAM, DT_ORIGINS, qpx, qhits) == pytest.approx(
        K, rel=1e-9)


def test_davis_tusting_wrong_on_non_flat_scene():
    spots_px, qpx, qhits = dt_setup(*plane(2.5, 20.0), [0.0, 0.3, -0.2, 0.1])
    s = davis_tusting_scale(spots_px, CAM, DT_ORIGINS, qpx, qhits)
    assert abs(s / K - 1) > 0.05


def test_davis_tusting_scaling_and_input_checks():
    spots_px, qpx, qhits = dt_setup(*plane(2.5, 10.0))
    s = davis_tusting_scale(spots_px, CAM, DT_ORIGINS, qpx, qhits)
    assert davis_tusting_scale(spots_px, CAM, DT_ORIGINS, qpx, 4 * qhits) == pytest.approx(
        s / 4, rel=1e-12)
    with pytest.raises(InputError):
        davis_tusting_scale(spots_px[:3], CAM, DT_ORIGINS, qpx, qhits)
    with pytest.raises(InputError):
        davis_tusting_scale(spots_px, CAM, DT_ORIGINS, qpx[:1], qhits[:1])
    centre = np.tile([[515.0, 380.0]], (4, 1))  # spots at the principal point: no range
    assert np.isnan(davis_tusting_scale(centre, CAM, DT_ORIGINS, qpx, qhits))
