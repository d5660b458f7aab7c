"""Laser rig calibration from images of a chessboard or ChArUco target held at several
distances: ``calibrate_images`` gives the calibrated rig, the camera and a report.

Per image: chessboard or ChArUco corners (OpenCV, +0.5 px to COLMAP's convention; ChArUco
corners carry ids, so partial views of the board give a pose too) -> target pose (PnP on
undistorted corners) -> plane; laser-colour spot candidates on the board (the detector's
candidate machinery with a provisional uncalibrated rig) -> rays -> 3D points on the plane.
Then :func:`sfm_laserscale.calibration.fit.calibrate_rig` tracks and fits the beams.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.calibration.fit import (
    CalibrationOptions,
    CalibrationResult,
    SpotPoint,
    board_object_points,
    calibrate_rig,
    plane_from_pose,
    point_line_distance,
    ray_plane_points,
    target_pose,
)
from sfm_laserscale.detection import DetectionOptions, detect_spots
from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.rig import COLORS, Laser, Rig

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class CalibrateOptions:
    """Target geometry, laser colours/names and the maths' settings."""

    board: tuple[int, int] = (9, 6)  # chessboard: inner corners; charuco: squares (cols, rows)
    square_m: float = 0.05
    target: str = "chessboard"  # chessboard | charuco
    marker_m: float | None = None  # ChArUco marker side (m); None = 0.7 square
    dictionary: str = "DICT_5X5_100"  # ChArUco markers: a cv2.aruco predefined dictionary
    min_corners: int = 6  # fewest ChArUco corners for a pose (partial views are fine)
    colors: tuple[str, ...] = ("red",)
    names: tuple[str, ...] | None = None  # None: L1..Ln, n = most spots seen in one image
    rig_name: str = "calibrated laser rig"
    min_images: int = 3
    min_candidate_score: float = 0.25
    # a neutral target: its black/white edges through a spot would read as target-coloured light
    detection: DetectionOptions = field(
        default_factory=lambda: DetectionOptions(colour_evidence=False))
    calibration: CalibrationOptions = field(default_factory=CalibrationOptions)

    def __post_init__(self) -> None:
        if min(self.board) < 2 or self.square_m <= 0:
            raise InputError(f"bad target: board {self.board}, square size {self.square_m} m")
        bad = [c for c in self.colors if c not in COLORS or c == "any"]
        if bad or not self.colors:
            raise InputError(f"laser colours must be red, green or blue, got {self.colors}")
        if self.target not in ("chessboard", "charuco"):
            raise InputError(f"target must be chessboard or charuco, got {self.target!r}")
        if self.target == "charuco":
            if not self.dictionary.startswith("DICT_") or not hasattr(cv2.aruco,
                                                                      self.dictionary):
                raise InputError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. "
                                 "DICT_5X5_100, DICT_4X4_50, DICT_6X6_250)")
            if self.marker_m is not None and not 0 < self.marker_m < self.square_m:
                raise InputError(f"marker size must be between 0 and the square size, got "
                                 f"{self.marker_m} m")
        if self.names is not None and (not self.names or len(set(self.names)) != len(self.names)):
            raise InputError(f"laser names must be distinct and non-empty, got {self.names}")


@dataclass(frozen=True)
class ImageObservation:
    """What one target image gave: board pose and spot candidates, or why it was skipped."""

    name: str
    cam_from_board: Pose | None
    spots: tuple[SpotPoint, ...] = ()
    corners_px: F64 | None = None  # (cols*rows, 2) COLMAP pixels
    skipped: str | None = None


@dataclass(frozen=True)
class CalibrateResult:
    """The calibration, the camera used, per-image observations, report and summary."""

    calibration: CalibrationResult
    camera: Camera
    observations: tuple[ImageObservation, ...]
    report: dict[str, Any]
    summary: str


# ----------------------------------------------------------------------------- per image


def find_board(image_rgb: NDArray[np.uint8], board: tuple[int, int]) -> F64 | None:
    """(cols*rows, 2) chessboard inner corners in COLMAP pixels, or None when not found."""
    gray = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2GRAY)
    ok, corners = cv2.findChessboardCornersSB(gray, board, flags=cv2.CALIB_CB_ACCURACY)
    if not ok or corners is None:
        return None
    # OpenCV pixel centres are integers; COLMAP's are at +0.5
    return np.asarray(corners, dtype=np.float64).reshape(-1, 2) + 0.5


def charuco_board(options: CalibrateOptions) -> cv2.aruco.CharucoBoard:
    """The OpenCV ChArUco board of the options (squares, sizes, dictionary)."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, options.dictionary))
    marker = options.marker_m if options.marker_m is not None else 0.7 * options.square_m
    return cv2.aruco.CharucoBoard(options.board, options.square_m, marker, dictionary)


def find_charuco(image_rgb: NDArray[np.uint8], options: CalibrateOptions
                 ) -> tuple[F64, F64] | None:
    """ChArUco corners seen (partial views included): ((N, 2) COLMAP px, (N, 3) board m).

    None when fewer than ``options.min_corners`` corners, or only collinear ones, are found.
    """
    board = charuco_board(options)
    gray = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2GRAY)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
    if corners is None or ids is None or len(ids) < options.min_corners:
        return None
    obj = np.asarray(board.getChessboardCorners(), dtype=np.float64)[ids.ravel()]
    if np.linalg.matrix_rank(obj[:, :2] - obj[:, :2].mean(axis=0), tol=1e-9) < 2:
        return None  # one row of corners: no plane
    # OpenCV pixel centres are integers; COLMAP's are at +0.5
    return np.asarray(corners, dtype=np.float64).reshape(-1, 2) + 0.5, obj


def find_target(image_rgb: NDArray[np.uint8], options: CalibrateOptions
                ) -> tuple[F64, F64] | None:
    """The target's corners (COLMAP px) and their board points (m), or None when not found."""
    if options.target == "charuco":
        return find_charuco(image_rgb, options)
    corners = find_board(image_rgb, options.board)
    if corners is None:
        return None
    return corners, board_object_points(options.board[0], options.board[1], options.square_m)


def board_polygon_px(camera: Camera, cam_from_board: Pose, board: tuple[int, int],
                     square_m: float, target: str = "chessboard") -> F64:
    """(4, 2) image outline of the board's squares plus half a square (COLMAP pixels)."""
    cols, rows = board
    lo, hi_x, hi_y = -1.5 * square_m, (cols + 0.5) * square_m, (rows + 0.5) * square_m
    if target == "charuco":  # object points start at the board's outer corner
        lo, hi_x, hi_y = -0.5 * square_m, (cols + 0.5) * square_m, (rows + 0.5) * square_m
    corners = np.array([[lo, lo, 0], [hi_x, lo, 0], [hi_x, hi_y, 0], [lo, hi_y, 0]])
    return camera.project(cam_from_board.transform(corners))


def colour_signal(image_rgb: NDArray[np.uint8], color: str, gamma: float) -> NDArray[np.float32]:
    """(H, W) linear max(laser - max(others), 0): texture-free on a neutral grey target."""
    lut = ((np.arange(256) / 255.0) ** gamma).astype(np.float32)
    lin = lut[image_rgb]
    c = {"red": 0, "green": 1, "blue": 2}[color]
    others = np.max(np.delete(lin, c, axis=2), axis=2)
    return np.asarray(np.maximum(lin[:, :, c] - others, 0.0), dtype=np.float32)


def refine_centre(signal: NDArray[np.float32], xy_px: F64, window_px: float = 3.0,
                  iterations: int = 20) -> F64:
    """Gaussian-windowed centroid of ``signal`` iterated to its fixed point (COLMAP pixels).

    Unbiased for any point-symmetric, unclipped spot. Used instead of the detector's centre
    because on a high-contrast chessboard its texture model leaves ~0.5 px biases, while the
    plain colour difference of a grey target carries no texture at all.
    """
    h, w = signal.shape
    r = int(np.ceil(4 * window_px))
    xy = np.asarray(xy_px, dtype=np.float64).copy()
    for _ in range(iterations):
        cx, cy = int(np.floor(xy[0])), int(np.floor(xy[1]))
        x0, x1, y0, y1 = max(0, cx - r), min(w, cx + r + 1), max(0, cy - r), min(h, cy + r + 1)
        patch = signal[y0:y1, x0:x1].astype(np.float64)
        gx = np.arange(x0, x1) + 0.5  # pixel centres, COLMAP convention
        gy = np.arange(y0, y1) + 0.5
        wgt = np.exp(-0.5 * ((gy[:, None] - xy[1]) ** 2 + (gx[None, :] - xy[0]) ** 2)
                     / window_px**2) * patch
        total = float(wgt.sum())
        if total <= 0:
            return xy
        new = np.array([float((wgt * gx[None, :]).sum()), float((wgt * gy[:, None]).sum())])
        new /= total
        if np.linalg.norm(new - xy) < 1e-4:
            return new
        xy = new
    return xy


def spot_candidates(image_rgb: NDArray[np.uint8], camera: Camera, polygon_px: F64,
                    options: CalibrateOptions) -> list[tuple[F64, str]]:
    """Laser-colour spot candidates (pixel, colour) inside the board outline."""
    prov = Rig("provisional", tuple(Laser(f"_{c}", None, None, c) for c in options.colors))
    res = detect_spots(image_rgb, camera, prov, options.detection)
    poly = np.asarray(polygon_px - 0.5, dtype=np.float32).reshape(-1, 1, 2)  # OpenCV coords
    out: list[tuple[F64, str]] = []
    signals: dict[str, NDArray[np.float32]] = {}
    for c in res.candidates:
        if c.score < options.min_candidate_score:
            continue
        if cv2.pointPolygonTest(poly, (c.x - 0.5, c.y - 0.5), False) >= 0:
            if c.color not in signals:
                signals[c.color] = colour_signal(image_rgb, c.color,
                                                 options.detection.input_gamma)
            out.append((refine_centre(signals[c.color], np.array([c.x, c.y])), c.color))
    return out


def observe_image(index: int, name: str, image_rgb: NDArray[np.uint8], camera: Camera,
                  options: CalibrateOptions, found: tuple[F64, F64] | None) -> ImageObservation:
    """Board pose and the spots' 3D points for one image (skipped when no board).

    ``found``: the target's corners (COLMAP px) and board points (m), see :func:`find_target`.
    """
    if found is None:
        return ImageObservation(name, None, skipped=f"{options.target} target not found")
    corners_px, obj = found
    pose = target_pose(corners_px, obj, camera)
    plane = plane_from_pose(pose)
    cands = spot_candidates(image_rgb, camera, board_polygon_px(
        camera, pose, options.board, options.square_m, options.target), options)
    spots: list[SpotPoint] = []
    for xy, color in cands:
        xyz = ray_plane_points(camera.unproject(xy[None, :]), plane)[0]
        if np.all(np.isfinite(xyz)) and xyz[2] > 0:
            spots.append(SpotPoint(image=index, xy_px=xy, xyz_m=xyz, color=color))
    return ImageObservation(name, pose, spots=tuple(spots), corners_px=corners_px)


# ----------------------------------------------------------------------------- intrinsics


def self_calibrate(corners: list[F64], size: tuple[int, int], options: CalibrateOptions,
                   objects: list[F64] | None = None) -> Camera:
    """OPENCV camera (COLMAP convention) from the target's corners (cv2.calibrateCamera).

    ``objects``: each image's (N, 3) board points; None = the full chessboard of ``options``.
    """
    if len(corners) < 3:
        raise InputError(f"self-calibration needs the target in >= 3 images, got {len(corners)}")
    if objects is None:
        obj = board_object_points(options.board[0], options.board[1], options.square_m)
        objects = [obj] * len(corners)
    objs = [o.astype(np.float32) for o in objects]
    # COLMAP -> OpenCV pixel convention (-0.5) for calibrateCamera
    imgs = [(c - 0.5).astype(np.float32).reshape(-1, 1, 2) for c in corners]
    rms, k, dist, _, _ = cv2.calibrateCamera(objs, imgs, size, None, None,
                                             flags=cv2.CALIB_FIX_K3)
    logger.info("self-calibration: reprojection RMS %.3f px", rms)
    d = np.asarray(dist, dtype=np.float64).ravel()
    # OpenCV principal point -> COLMAP convention: +0.5
    params = np.array([k[0, 0], k[1, 1], k[0, 2] + 0.5, k[1, 2] + 0.5, d[0], d[1], d[2], d[3]])
    return Camera(camera_id=1, model="OPENCV", width=size[0], height=size[1], params=params)


# ----------------------------------------------------------------------------- all images


def _names(observations: list[ImageObservation], options: CalibrateOptions) -> list[str]:
    if options.names is not None:
        return list(options.names)
    n = max((len(o.spots) for o in observations), default=0)
    if n == 0:
        raise InputError("no laser spot of the given colour(s) was found on the target")
    return [f"L{i + 1}" for i in range(n)]


def calibrate_images(images: Mapping[str, NDArray[np.uint8]], camera: Camera | None,
                     options: CalibrateOptions) -> CalibrateResult:
    """Calibrate from in-memory RGB images (name -> (H, W, 3) uint8); camera None = self-cal."""
    names = list(images)
    corners = {n: find_target(images[n], options) for n in names}
    for n in names:
        if corners[n] is None:
            logger.warning("%s: %s target not found; image skipped", n, options.target)
    found = [n for n in names if corners[n] is not None]
    if len(found) < options.min_images:
        raise InputError(f"the target was found in only {len(found)} image(s) (need "
                         f">= {options.min_images}); not found in: "
                         f"{', '.join(n for n in names if corners[n] is None) or '-'}")
    if camera is None:
        h, w = images[found[0]].shape[:2]
        seen = [c for c in corners.values() if c is not None]
        camera = self_calibrate([c[0] for c in seen], (w, h), options, [c[1] for c in seen])
    obs = [observe_image(i, n, images[n], camera, options, corners[n])
           for i, n in enumerate(names)]
    spots = [s for o in obs for s in o.spots]
    result = calibrate_rig(spots, _names(obs, options), options.rig_name, options.calibration)
    report = build_report(result, camera, obs)
    lines = [f"calibrated {len(result.rig.lasers)} laser(s) from {len(found)} image(s)"]
    for cl in result.lasers:
        lines.append(f"  {cl.name}: origin {np.round(cl.fit.origin, 4).tolist()} m, direction "
                     f"{np.round(cl.fit.direction, 5).tolist()}, {len(cl.spots)} spots, "
                     f"rms {1e3 * np.sqrt(np.mean(cl.fit.residuals_m ** 2)):.2f} mm")
    lines += [f"  pair {p.lasers[0]}-{p.lasers[1]}: separation {p.separation:.4f} m"
              for p in result.rig.pairs]
    return CalibrateResult(result, camera, tuple(obs), report, "\n".join(lines))


def build_report(result: CalibrationResult, camera: Camera,
                 observations: list[ImageObservation]) -> dict[str, Any]:
    """JSON-ready report: camera, lasers, pairs, per-image residuals (mm)."""
    per_image: list[dict[str, Any]] = []
    for i, o in enumerate(observations):
        entry: dict[str, Any] = {"image": o.name, "skipped": o.skipped, "spots": {}}
        if o.cam_from_board is not None:
            entry["target_distance_m"] = float(np.linalg.norm(o.cam_from_board.t))
        for cl in result.lasers:
            for s in cl.spots:
                if s.image == i:
                    res = point_line_distance(s.xyz_m[None, :], cl.fit.origin, cl.fit.direction)
                    entry["spots"][cl.name] = {"x": float(s.xy_px[0]), "y": float(s.xy_px[1]),
                                               "xyz_m": s.xyz_m.tolist(),
                                               "residual_mm": float(1e3 * res[0])}
        per_image.append(entry)
    lasers = [{"name": cl.name, "color": cl.color, "origin": cl.fit.origin.tolist(),
               "direction": cl.fit.direction.tolist(), "sigma_origin_m": cl.fit.sigma_origin_m,
               "sigma_direction_rad": cl.fit.sigma_direction_rad, "n_spots": len(cl.spots),
               "rms_residual_mm": float(1e3 * np.sqrt(np.mean(cl.fit.residuals_m ** 2)))}
              for cl in result.lasers]
    return {
        "camera": {"model": camera.model, "width": camera.width, "height": camera.height,
                   "params": np.asarray(camera.params).tolist()},
        "lasers": lasers,
        "pairs": [{"lasers": list(p.lasers), "separation_m": p.separation,
                   "angle_deg": result.pair_angles_deg.get(p.lasers)}
                  for p in result.rig.pairs],
        "pair_angles_deg": {f"{a}-{b}": v for (a, b), v in result.pair_angles_deg.items()},
        "images": per_image,
    }
