"""Rotation and similarity helpers against closed-form answers."""

from __future__ import annotations

import numpy as np

from sfm_laserscale.geometry import (
    qvec_from_rotmat,
    rotation_angle_deg,
    rotmat_from_qvec,
    umeyama_sim3,
)


def test_quaternion_round_trip() -> None:
    rng = np.random.default_rng(1)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        np.testing.assert_allclose(qvec_from_rotmat(rotmat_from_qvec(q)), q, atol=1e-12)


def test_quaternion_convention_is_hamilton_wxyz() -> None:
    # 90° about z: x axis -> y axis.
    q = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(rotmat_from_qvec(q) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(qvec_from_rotmat(rotmat_from_qvec(q)), q, atol=1e-12)
    assert abs(rotation_angle_deg(rotmat_from_qvec(q), np.eye(3)) - 90.0) < 1e-9


def test_umeyama_recovers_similarity() -> None:
    rng = np.random.default_rng(2)
    src = rng.normal(size=(30, 3))
    R = rotmat_from_qvec(np.array([0.9, 0.1, -0.3, 0.2]))
    dst = 2.5 * src @ R.T + [1.0, -2.0, 3.0]
    s, R_est, t = umeyama_sim3(src, dst)
    assert abs(s - 2.5) < 1e-12
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 3.0], atol=1e-12)
