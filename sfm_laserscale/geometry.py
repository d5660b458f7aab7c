"""Small geometry helpers: quaternions (w, x, y, z), rigid and similarity transforms."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

F64 = NDArray[np.float64]


def rotmat_from_qvec(qvec_wxyz: F64) -> F64:
    """3×3 rotation matrix from a (normalised here) quaternion (w, x, y, z)."""
    q = np.asarray(qvec_wxyz, dtype=np.float64)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def qvec_from_rotmat(R: F64) -> F64:
    """Quaternion (w, x, y, z) with w >= 0 from a 3×3 rotation matrix."""
    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def rotation_angle_deg(R_a: F64, R_b: F64) -> float:
    """Angle in degrees of the relative rotation R_a R_bᵀ."""
    c = (np.trace(R_a @ R_b.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def umeyama_sim3(src_xyz: F64, dst_xyz: F64) -> tuple[float, F64, F64]:
    """Similarity (s, R, t) minimising ‖dst − (s R src + t)‖² over (N, 3) point pairs."""
    src = np.asarray(src_xyz, dtype=np.float64)
    dst = np.asarray(dst_xyz, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError("umeyama_sim3 needs two (N>=3, 3) arrays of the same shape")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var_s = (a**2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s)
    t = mu_d - s * R @ mu_s
    return s, R, t
