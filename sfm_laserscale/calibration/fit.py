"""Laser rig calibration maths (pure): target plane, ray–plane points, beam tracks, line fits.

Camera frame, metres (x right, y down, z forward); pixels in COLMAP convention. A beam is fitted
as a 3D line (total least squares) through the points where it hit a planar target seen at
several distances; its origin is the line's intersection with the laser plane z = 0.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.rig import Laser, Pair, Rig

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class CalibrationOptions:
    """Settings of :func:`calibrate_rig`.

    - ``inlier_tol_m``: max distance of a spot's 3D point from its beam line while tracking.
    - ``min_spots``: fewest spots (images) per laser.
    - ``min_distance_ratio``/``min_distance_spread_m``: each laser's spots must span at least
      this ratio of max/min distance from the camera and this spread (metres).
    - ``parallel_sigmas``/``parallel_floor_deg``: two beams are a pair when their angle is below
      ``max(parallel_sigmas * sigma_combined, parallel_floor_deg)``.
    """

    inlier_tol_m: float = 0.01
    min_spots: int = 3
    min_distance_ratio: float = 1.5
    min_distance_spread_m: float = 0.5
    parallel_sigmas: float = 3.0
    parallel_floor_deg: float = 0.1

    def __post_init__(self) -> None:
        if self.inlier_tol_m <= 0 or self.min_spots < 3:
            raise InputError("inlier_tol_m must be positive and min_spots at least 3")


@dataclass(frozen=True)
class Plane:
    """Plane n·X = d in the camera frame (n unit, metres)."""

    normal: F64  # (3,)
    d: float


@dataclass(frozen=True)
class LineFit:
    """A fitted beam: origin on z = 0, unit direction (+z), uncertainties and residuals."""

    origin: F64  # (3,) metres, origin[2] == 0
    direction: F64  # (3,) unit, direction[2] > 0
    sigma_origin_m: float  # per axis
    sigma_direction_rad: float
    residuals_m: F64  # (N,) distance of each point from the line


@dataclass(frozen=True)
class SpotPoint:
    """One spot: image index, pixel (COLMAP), 3D point on the target (camera frame, m)."""

    image: int
    xy_px: F64  # (2,)
    xyz_m: F64  # (3,)
    color: str


@dataclass(frozen=True)
class CalibratedLaser:
    """One calibrated beam with its spots."""

    name: str
    color: str
    fit: LineFit
    spots: tuple[SpotPoint, ...]


@dataclass(frozen=True)
class CalibrationResult:
    """The calibrated rig and per-laser fits (same order as ``rig.lasers``)."""

    rig: Rig
    lasers: tuple[CalibratedLaser, ...]
    pair_angles_deg: dict[tuple[str, str], float]


# ----------------------------------------------------------------------------- target


def board_object_points(cols: int, rows: int, square_m: float) -> F64:
    """(cols*rows, 3) inner-corner positions on the board (z = 0), OpenCV's row-major order."""
    jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
    pts = np.column_stack([jj.ravel(), ii.ravel(), np.zeros(jj.size)]) * square_m
    return np.asarray(pts, dtype=np.float64)


def target_pose(corners_px: F64, object_m: F64, camera: Camera) -> Pose:
    """cam_from_board from (N, 2) COLMAP-pixel corners and (N, 3) board points.

    Corners are undistorted to normalised coordinates with the camera model, so the PnP solve
    uses an identity K and no distortion (any COLMAP model works).
    """
    norm = camera.unproject(np.asarray(corners_px, dtype=np.float64))[:, :2]
    if not np.all(np.isfinite(norm)):
        raise InputError("target corners cannot be undistorted with this camera model")
    k, dist = np.eye(3), np.zeros(5)
    obj = np.ascontiguousarray(object_m, dtype=np.float64)
    img = np.ascontiguousarray(norm, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise InputError("the target's pose could not be solved (PnP failed)")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, dist, rvec, tvec)
    r, _ = cv2.Rodrigues(rvec)
    return Pose(R=np.asarray(r, dtype=np.float64), t=np.asarray(tvec, dtype=np.float64).ravel())


def plane_from_pose(cam_from_board: Pose) -> Plane:
    """The board plane z_board = 0 in the camera frame."""
    n = cam_from_board.R[:, 2].copy()
    return Plane(normal=n, d=float(n @ cam_from_board.t))


def ray_plane_points(rays: F64, plane: Plane) -> F64:
    """(N, 3) points where rays (N, 3) from the camera centre meet the plane (NaN if parallel)."""
    rays = np.atleast_2d(rays)
    denom = rays @ plane.normal
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(np.abs(denom) > 1e-12, plane.d / denom, np.nan)
    return np.asarray(rays * lam[:, None], dtype=np.float64)


# ----------------------------------------------------------------------------- line fit


def fit_line(points_m: F64) -> LineFit:
    """Total-least-squares 3D line through (N >= 3, 3) points, with fit uncertainties.

    The direction is the principal axis (oriented +z); the origin is where the line meets
    z = 0. The residual sigma (2 perpendicular axes, N-2 dof each) gives the direction sigma
    sigma / sqrt(sum s_i^2) (s: positions along the line about the centroid) and the origin
    sigma sqrt(sigma^2/N + (L sigma_dir)^2) / d_z with L the lever arm from the centroid to z=0.
    """
    pts = np.asarray(points_m, dtype=np.float64)
    if len(pts) < 3:
        raise InputError(f"a beam needs at least 3 points, got {len(pts)}")
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    d = vt[0] if vt[0, 2] >= 0 else -vt[0]
    if abs(d[2]) < 1e-6:
        raise InputError("a beam is parallel to the laser plane z = 0")
    s = (pts - c) @ d
    perp = (pts - c) - s[:, None] * d[None, :]
    res = np.linalg.norm(perp, axis=1)
    n = len(pts)
    sigma = math.sqrt(float(np.sum(res**2)) / (2.0 * max(n - 2, 1)))
    sigma_dir = sigma / math.sqrt(max(float(np.sum(s**2)), 1e-18))
    lever = abs(c[2] / d[2])
    sigma_origin = math.sqrt(sigma**2 / n + (lever * sigma_dir) ** 2) / abs(d[2])
    origin = c - (c[2] / d[2]) * d
    origin[2] = 0.0
    return LineFit(origin=origin, direction=d, sigma_origin_m=sigma_origin,
                   sigma_direction_rad=sigma_dir, residuals_m=res)


def point_line_distance(points_m: F64, origin: F64, direction: F64) -> F64:
    """(N,) distances of (N, 3) points from the line origin + s * direction (unit)."""
    v = np.atleast_2d(points_m) - origin[None, :]
    return np.asarray(np.linalg.norm(np.cross(v, direction[None, :]), axis=1), dtype=np.float64)


# ----------------------------------------------------------------------------- tracks


def _best_line(pts: F64, images: NDArray[np.intp], free: NDArray[np.bool_], tol: float
               ) -> list[int]:
    """Indices of the largest one-point-per-image set within ``tol`` of a two-point line.

    Exhaustive over all pairs of free points from different images (deterministic; the
    candidate count is small), ties broken by the smaller RMS distance.
    """
    idx = np.flatnonzero(free)
    best: list[int] = []
    best_rms = np.inf
    for a, b in itertools.combinations(idx.tolist(), 2):
        if images[a] == images[b]:
            continue
        d = pts[b] - pts[a]
        norm = float(np.linalg.norm(d))
        if norm < 1e-6:
            continue
        dist = point_line_distance(pts[idx], pts[a], d / norm)
        chosen: dict[int, tuple[float, int]] = {}
        for k, dk in zip(idx.tolist(), dist.tolist(), strict=True):
            im = int(images[k])
            if dk <= tol and (im not in chosen or dk < chosen[im][0]):
                chosen[im] = (dk, k)
        members = [k for _, k in chosen.values()]
        rms = math.sqrt(sum(v * v for v, _ in chosen.values()) / max(len(members), 1))
        if len(members) > len(best) or (len(members) == len(best) and rms < best_rms):
            best, best_rms = members, rms
    return sorted(best, key=lambda k: int(images[k]))


def track_beams(spots: list[SpotPoint], n_lasers: int, options: CalibrationOptions
                ) -> list[list[SpotPoint]]:
    """Group spots into ``n_lasers`` beams (3D lines, one spot per image); InputError if short."""
    if not spots:
        raise InputError("no laser spot was found on the target in any image")
    pts = np.array([s.xyz_m for s in spots])
    images = np.array([s.image for s in spots], dtype=np.intp)
    free = np.ones(len(spots), dtype=bool)
    tracks: list[list[SpotPoint]] = []
    for k in range(n_lasers):
        members = _best_line(pts, images, free, options.inlier_tol_m)
        if len(members) < options.min_spots:
            raise InputError(
                f"laser #{k + 1} of {n_lasers} has fewer than {options.min_spots} spots on a "
                f"common beam line (best: {len(members)}); add target images where every spot "
                "is on the board")
        free[members] = False
        tracks.append([spots[m] for m in members])
    if free.any():
        logger.info("%d spot candidate(s) left on no beam", int(free.sum()))
    return tracks


def check_range(distances_m: F64, name: str, options: CalibrationOptions) -> None:
    """InputError when a laser's spot distances span too little range."""
    lo, hi = float(np.min(distances_m)), float(np.max(distances_m))
    if lo <= 0 or hi / lo < options.min_distance_ratio or hi - lo < options.min_distance_spread_m:
        raise InputError(
            f"laser {name}: target distances span {lo:.2f}–{hi:.2f} m, too little range "
            f"(need max/min >= {options.min_distance_ratio:g} and a spread >= "
            f"{options.min_distance_spread_m:g} m)")


# ----------------------------------------------------------------------------- pairs, rig


def find_pairs(lasers: list[CalibratedLaser], options: CalibrationOptions
               ) -> tuple[list[Pair], dict[tuple[str, str], float]]:
    """Parallel beam pairs (angle within uncertainty) with their perpendicular separation."""
    pairs: list[Pair] = []
    angles: dict[tuple[str, str], float] = {}
    for a, b in itertools.combinations(lasers, 2):
        cosang = float(np.clip(a.fit.direction @ b.fit.direction, -1.0, 1.0))
        ang = math.acos(cosang)
        angles[(a.name, b.name)] = math.degrees(ang)
        sig = math.hypot(a.fit.sigma_direction_rad, b.fit.sigma_direction_rad)
        limit = max(options.parallel_sigmas * sig, math.radians(options.parallel_floor_deg))
        if ang > limit:
            continue
        d = a.fit.direction + b.fit.direction
        d /= np.linalg.norm(d)
        v = b.fit.origin - a.fit.origin
        sep = float(np.linalg.norm(v - (v @ d) * d))
        pairs.append(Pair(lasers=(a.name, b.name), separation=sep))
    return pairs, angles


def calibrate_rig(spots: list[SpotPoint], names: list[str], rig_name: str = "calibrated rig",
                  options: CalibrationOptions = CalibrationOptions(),  # noqa: B008
                  ) -> CalibrationResult:
    """Track beams through the spots, fit each, detect pairs; lasers named left to right."""
    tracks = track_beams(spots, len(names), options)
    fits = [fit_line(np.array([s.xyz_m for s in tr])) for tr in tracks]
    order = sorted(range(len(tracks)), key=lambda i: (fits[i].origin[0], fits[i].origin[1]))
    lasers: list[CalibratedLaser] = []
    for name, i in zip(names, order, strict=True):
        check_range(np.array([float(np.linalg.norm(s.xyz_m)) for s in tracks[i]]), name,
                    options)
        colors = sorted({s.color for s in tracks[i]})
        lasers.append(CalibratedLaser(name=name, color=colors[0] if len(colors) == 1 else "any",
                                      fit=fits[i], spots=tuple(tracks[i])))
    pairs, angles = find_pairs(lasers, options)
    rig = Rig(name=rig_name, pairs=tuple(pairs), lasers=tuple(
        Laser(name=cl.name, origin=cl.fit.origin, direction=cl.fit.direction, color=cl.color,
              sigma_origin=cl.fit.sigma_origin_m, sigma_direction=cl.fit.sigma_direction_rad)
        for cl in lasers))
    return CalibrationResult(rig=rig, lasers=tuple(lasers), pair_angles_deg=angles)
