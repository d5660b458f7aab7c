"""Baselines for comparison only (docs/DESIGN.md §3): Direct 3D and Davis & Tusting image scaling.

Both are wrong on general scenes and are kept to show how much FCM/PCM improve on them:
- Direct 3D is exact only when parallel beams hit the surface perpendicularly (equal depths).
- Davis & Tusting is exact only when the scene is flat (the four spots and every query point lie
  on one plane).
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera

F64 = NDArray[np.float64]


def direct3d_scale_batch(hit1: F64, hit2: F64, separation_m: float | F64) -> F64:
    """Vectorised Direct 3D: separation (m) / ‖X_2 − X_1‖ (model units) for (..., 3) hits."""
    dist = np.linalg.norm(np.asarray(hit2, np.float64) - np.asarray(hit1, np.float64), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(separation_m / dist, dtype=np.float64)


def direct3d_scale(hit1: F64, hit2: F64, separation_m: float) -> float:
    """Direct 3D: separation (m) / hit distance (model units); NaN if the hits coincide."""
    h1 = np.asarray(hit1, dtype=np.float64).reshape(3)
    h2 = np.asarray(hit2, dtype=np.float64).reshape(3)
    dist = float(np.linalg.norm(h2 - h1))
    finite = bool(np.all(np.isfinite(h1)) and np.all(np.isfinite(h2)))
    if not finite or dist <= 0.0 or not separation_m > 0:
        return float("nan")
    return float(separation_m) / dist


def _spot_points_m(spots_px: F64, camera: Camera, origins_m: F64) -> F64:
    """(4, 3) metric camera-frame spot positions for beams parallel to the optical axis.

    A beam through (O_x, O_y) parallel to c_z meets the ray z·(x_n, y_n, 1) where
    z·(x_n, y_n) = (O_x, O_y); z is its least-squares solution, equal to ‖O_xy‖ / ‖(x_n, y_n)‖
    (= f·offset / pixel offset from the principal point) for a consistent spot.
    """
    rays = camera.unproject(spots_px)  # (4, 3), z = 1
    nxy = rays[:, :2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.sum(origins_m[:, :2] * nxy, axis=1) / np.sum(nxy**2, axis=1)
    z[~(z > 0)] = np.nan  # spot at the principal point or on the wrong side: no range
    return np.asarray(rays * z[:, None], dtype=np.float64)


def _fit_plane(points: F64) -> tuple[F64, F64]:
    """Least-squares plane (centroid, unit normal) through (N >= 3, 3) points."""
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid)
    return centroid, vt[2]


def _check_dt_inputs(spots: F64, origins: F64, query_px: F64, query_hits: F64) -> None:
    if spots.shape != (4, 2) or origins.shape != (4, 3):
        raise InputError("Davis & Tusting needs 4 spots (4, 2) and 4 beam origins (4, 3)")
    if query_px.ndim != 2 or query_px.shape[1] != 2 or query_hits.shape != (len(query_px), 3):
        raise InputError("query points must be (K, 2) pixels with (K, 3) model-unit hits")
    if len(query_px) < 2:
        raise InputError("Davis & Tusting needs at least two query points")


def davis_tusting_scale(spots_px: F64, camera: Camera, origins_m: F64, query_px: F64,
                        query_hits_cam: F64) -> float:
    """Davis & Tusting scale (m per model unit); NaN when the spot geometry is degenerate.

    Four beams parallel to the optical axis (origins_m, metres, camera frame): range of each spot
    from its image position, least-squares plane through the four metric spot points, metric
    distances between all query-point pairs on that plane versus their model distances
    (query_hits_cam, camera frame, model units); s = Σ m·d / Σ d² over the pairs. Exact only on
    flat scenes.
    """
    spots = np.asarray(spots_px, dtype=np.float64)
    origins = np.asarray(origins_m, dtype=np.float64)
    qpx = np.asarray(query_px, dtype=np.float64)
    qhits = np.asarray(query_hits_cam, dtype=np.float64)
    _check_dt_inputs(spots, origins, qpx, qhits)
    points = _spot_points_m(spots, camera, origins)
    if not np.all(np.isfinite(points)):
        return float("nan")
    centroid, normal = _fit_plane(points)
    rays = camera.unproject(qpx)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = float(centroid @ normal) / (rays @ normal)
    metric = rays * lam[:, None]  # (K, 3) metres on the spot plane
    pairs = list(combinations(range(len(qpx)), 2))
    i, j = np.array(pairs).T
    m = np.linalg.norm(metric[i] - metric[j], axis=1)
    d = np.linalg.norm(qhits[i] - qhits[j], axis=1)
    ok = np.isfinite(m) & np.isfinite(d) & (lam[i] > 0) & (lam[j] > 0)
    if not np.any(ok) or float(np.sum(d[ok] ** 2)) <= 0.0:
        return float("nan")
    return float(np.sum(m[ok] * d[ok]) / np.sum(d[ok] ** 2))
