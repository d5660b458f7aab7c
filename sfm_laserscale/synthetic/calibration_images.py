"""Render rig-calibration images of a known rig: a chessboard or ChArUco board on a plane,
laser spots on it.

The board texture is projected exactly through a pinhole camera and anti-aliased by
supersampling every pixel on an ``ss x ss`` grid (COLMAP convention: pixel (i, j) covers
[j, j+1) x [i, i+1)). Each beam is intersected with the board plane and its spot painted with
:func:`paint_spot` at the exact projection of that point.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.model import Camera, Pose
from sfm_laserscale.rig import Rig
from sfm_laserscale.synthetic.spots import paint_spot, to_uint8

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class BoardSpec:
    """A target: chessboard (``cols`` x ``rows`` inner corners) or ChArUco (``cols`` x ``rows``
    squares, OpenCV's layout, ArUco markers of ``marker_fraction`` of a square from
    ``dictionary``); square size (m), white margin (squares)."""

    cols: int = 9
    rows: int = 6
    square_m: float = 0.06
    margin_squares: float = 1.0
    white: float = 0.45  # linear intensity of white squares and margin
    black: float = 0.04
    background: float = 0.2
    kind: str = "chessboard"  # chessboard | charuco
    marker_fraction: float = 0.7
    dictionary: str = "DICT_5X5_100"


@dataclass(frozen=True)
class CalibrationShot:
    """One rendered image: uint8 RGB (gamma-encoded), the board pose, true spot pixels."""

    image: NDArray[np.uint8]  # (H, W, 3)
    cam_from_board: Pose
    spots_px: dict[str, tuple[float, float]]  # laser name -> COLMAP pixel, lasers on the board
    spots_cam: dict[str, F64]  # laser name -> (3,) metres, camera frame


def board_pose(distance_m: float, tilt_x_deg: float, tilt_y_deg: float,
               offset_xy_m: tuple[float, float] = (0.0, 0.0)) -> Pose:
    """cam_from_board: board centre at (offset, distance), facing the camera, tilted."""
    ax, ay = np.radians(tilt_x_deg), np.radians(tilt_y_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    r = rx @ ry
    t = np.array([offset_xy_m[0], offset_xy_m[1], distance_m], dtype=np.float64)
    return Pose(R=r, t=t)


def board_extent_m(board: BoardSpec) -> tuple[float, float]:
    """Half width and half height (m) of the whole board including its margin."""
    sq = board.square_m
    extra = 0 if board.kind == "charuco" else 1  # chessboard: squares = inner corners + 1
    return ((board.cols + extra) / 2 + board.margin_squares) * sq, \
        ((board.rows + extra) / 2 + board.margin_squares) * sq


#: pixels per square of the ChArUco texture sampled by :func:`render_board`
CHARUCO_PX_PER_SQUARE = 60


def charuco_texture(board: BoardSpec) -> NDArray[np.float32]:
    """(rows*P, cols*P) ChArUco pattern (1 = white, 0 = black), P = CHARUCO_PX_PER_SQUARE.

    Texel (i, j) covers board coordinates [j, j+1) x [i, i+1) / P squares from the top-left
    outer corner, which is where OpenCV's ChArUco object points start (x right, y down).
    """
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    cb = cv2.aruco.CharucoBoard((board.cols, board.rows), board.square_m,
                                board.marker_fraction * board.square_m, dictionary)
    px = CHARUCO_PX_PER_SQUARE
    img = cb.generateImage((board.cols * px, board.rows * px), marginSize=0, borderBits=1)
    return np.asarray(img, dtype=np.float32) / 255.0


def _charuco_intensity(u: NDArray[np.float32], v: NDArray[np.float32], board: BoardSpec,
                       texture: NDArray[np.float32]) -> NDArray[np.float32]:
    """Linear intensity of a ChArUco board at board coordinates (m, origin at its centre)."""
    sq, px = board.square_m, CHARUCO_PX_PER_SQUARE
    hw, hh = board_extent_m(board)
    ju = np.floor((u / sq + board.cols / 2) * px).astype(np.int64)
    iv = np.floor((v / sq + board.rows / 2) * px).astype(np.int64)
    inside = (ju >= 0) & (ju < texture.shape[1]) & (iv >= 0) & (iv < texture.shape[0])
    t = texture[np.clip(iv, 0, texture.shape[0] - 1), np.clip(ju, 0, texture.shape[1] - 1)]
    pattern = board.black + (board.white - board.black) * t
    on_board = (np.abs(u) <= hw) & (np.abs(v) <= hh)
    out = np.where(on_board, np.float32(board.white), np.float32(board.background))
    return np.where(inside, pattern, out).astype(np.float32)


def _board_intensity(u: NDArray[np.float32], v: NDArray[np.float32], board: BoardSpec
                     ) -> NDArray[np.float32]:
    """Linear intensity at board coordinates (m, origin at the board centre)."""
    sq = board.square_m
    hw, hh = board_extent_m(board)
    iu = np.floor(u / sq + (board.cols + 1) / 2)  # square indices, 0 .. cols
    iv = np.floor(v / sq + (board.rows + 1) / 2)
    squares = (iu >= 0) & (iu <= board.cols) & (iv >= 0) & (iv <= board.rows)
    black = squares & ((iu + iv) % 2 == 0)
    on_board = (np.abs(u) <= hw) & (np.abs(v) <= hh)
    out = np.where(on_board, np.float32(board.white), np.float32(board.background))
    return np.where(black, np.float32(board.black), out).astype(np.float32)


def render_board(camera: Camera, cam_from_board: Pose, board: BoardSpec, ss: int = 3
                 ) -> NDArray[np.float32]:
    """(H, W, 3) linear float32 grey image of the board (pinhole camera, supersampled)."""
    fx, fy, cx, cy = (float(p) for p in camera.params[:4])
    w, h = camera.width, camera.height
    sub = (np.arange(ss, dtype=np.float64) + 0.5) / ss
    xs = ((np.arange(w)[:, None] + sub[None, :]).ravel() - cx) / fx  # (W*ss,)
    r, t = cam_from_board.R, cam_from_board.t
    n = r[:, 2]
    d = float(n @ t)
    out = np.empty((h, w), dtype=np.float32)
    texture = charuco_texture(board) if board.kind == "charuco" else None
    chunk = 64
    for y0 in range(0, h, chunk):
        y1 = min(h, y0 + chunk)
        ys = ((np.arange(y0, y1)[:, None] + sub[None, :]).ravel() - cy) / fy
        rx, ry = np.meshgrid(xs, ys)
        denom = n[0] * rx + n[1] * ry + n[2]
        lam = np.where(denom > 1e-9, d / np.where(denom > 1e-9, denom, 1.0), -1.0)
        px, py, pz = lam * rx - t[0], lam * ry - t[1], lam - t[2]  # X_cam - t
        u = (r[0, 0] * px + r[1, 0] * py + r[2, 0] * pz).astype(np.float32)  # R^T (X - t)
        v = (r[0, 1] * px + r[1, 1] * py + r[2, 1] * pz).astype(np.float32)
        inten = (_board_intensity(u, v, board) if texture is None
                 else _charuco_intensity(u, v, board, texture))
        val = np.where(lam > 0, inten, np.float32(board.background))
        out[y0:y1] = val.reshape(y1 - y0, ss, w, ss).mean(axis=(1, 3))
    return np.repeat(out[:, :, None], 3, axis=2)


def beam_hits(rig: Rig, cam_from_board: Pose, board: BoardSpec) -> dict[str, F64]:
    """Laser name -> (3,) camera-frame point where its beam meets the board (on the board only)."""
    n = cam_from_board.R[:, 2]
    d = float(n @ cam_from_board.t)
    hw, hh = board_extent_m(board)
    hits: dict[str, F64] = {}
    for las in rig.lasers:
        if las.origin is None or las.direction is None:
            continue
        lam = (d - float(n @ las.origin)) / float(n @ las.direction)
        p = las.origin + lam * las.direction
        uv = cam_from_board.R.T @ (p - cam_from_board.t)
        if lam > 0 and abs(uv[0]) < hw and abs(uv[1]) < hh:
            hits[las.name] = p
    return hits


def render_calibration_shot(
    camera: Camera, rig: Rig, cam_from_board: Pose, board: BoardSpec = BoardSpec(),  # noqa: B008
    ss: int = 3, spot_sigma_px: float = 2.0, spot_peak: float = 0.3, spot_halo: float = 0.5,
    rng: np.random.Generator | None = None, noise: float = 0.0,
) -> CalibrationShot:
    """Render the board at ``cam_from_board`` with the rig's spots; gamma 2.2 uint8 output.

    The defaults keep the spots unclipped on the white squares (a grey target, as advised
    for calibration), so the colour difference is free of the board texture.
    """
    img = render_board(camera, cam_from_board, board, ss)
    hits = beam_hits(rig, cam_from_board, board)
    spots: dict[str, tuple[float, float]] = {}
    for name, p in hits.items():
        xy = camera.project(p[None, :])[0]
        spots[name] = (float(xy[0]), float(xy[1]))
        color = rig.laser(name).color
        paint_spot(img, spots[name], color="red" if color == "any" else color,
                   sigma_px=spot_sigma_px, peak=spot_peak, halo=spot_halo)
    if rng is not None and noise > 0:
        img += rng.normal(0.0, noise, img.shape).astype(np.float32)
    return CalibrationShot(image=to_uint8(img, gamma=2.2), cam_from_board=cam_from_board,
                           spots_px=spots, spots_cam=hits)
