"""Overlay images: detected spots, predicted beam lines, the model points used for registration
(reprojected with the estimated pose), per-laser scale.

Everything is drawn AFTER resizing the photograph to the output size (longer side between
``min_side`` and ``max_side``), so lines and text have the same legible size for a 640×480 and
a 4K image. Spot labels are short (the laser's name) and placed where they overlap nothing
already drawn; the numbers go into a legend strip below the photograph, one box per laser,
so they never hide the image.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection import (
    DetectionOptions,
    DetectionResult,
    beam_polyline_px,
    default_band_px,
)
from sfm_laserscale.model import Camera, Pose, Spot
from sfm_laserscale.report.style import INLIER_HEX, WARNING_HEX, hex_to_bgr, laser_color_bgr
from sfm_laserscale.rig import Rig

_FONT = cv2.FONT_HERSHEY_DUPLEX
_SHIFT = 4  # fixed-point bits for sub-pixel drawing
_BLACK = (0, 0, 0)
_WHITE = (255, 255, 255)
_RED = hex_to_bgr(WARNING_HEX)
_INLIER = hex_to_bgr(INLIER_HEX)
_TEXT = (238, 238, 238)
_LIGHT_RED = (110, 110, 255)  # the warning red, lightened for text on the dark legend strip
Box = tuple[float, float, float, float]  # x0, y0, x1, y1 (output pixels)


@dataclass(frozen=True)
class _Style:
    """Sizes in output pixels, derived from the output's longer side."""

    line: int
    circle: float
    font: float
    text_thick: int
    dot: float

    @staticmethod
    def for_size(long_side: int) -> _Style:
        # The report shows overlays about 600 CSS pixels wide: a 1200-pixel overlay is drawn
        # at 0.5x, so spot labels of scale 1.5 (caps ~33 px) read as ~16 CSS pixels and the
        # legend (x 0.75) as ~12.
        u = long_side / 1200.0
        return _Style(
            line=max(2, round(3 * u)),
            circle=20.0 * u,
            font=1.5 * u,
            text_thick=max(2, round(3 * u)),
            dot=2.4 * u,
        )


def _fp(xy: NDArray[np.float64] | Sequence[float], f: float) -> tuple[int, int]:
    """COLMAP pixel (centre of top-left pixel is (0.5, 0.5)) of the INPUT image -> OpenCV
    drawing coordinates of the resized output (subtract 0.5, scale), fixed point."""
    x = (float(xy[0]) * f - 0.5) * (1 << _SHIFT)
    y = (float(xy[1]) * f - 0.5) * (1 << _SHIFT)
    return int(round(x)), int(round(y))


def _resize(
    img: NDArray[np.uint8], min_side: int, max_side: int
) -> tuple[NDArray[np.uint8], float]:
    long_side = max(img.shape[:2])
    target = min(max(long_side, min_side), max_side)
    f = target / long_side
    if abs(f - 1.0) < 1e-9:
        return img.copy(), 1.0
    interp = cv2.INTER_AREA if f < 1.0 else cv2.INTER_CUBIC
    return cv2.resize(img, None, fx=f, fy=f, interpolation=interp), f


def _label(
    img: NDArray[np.uint8],
    text: str,
    box: Box,
    scale: float,
    color: tuple[int, int, int],
    thick: int,
) -> None:
    """Text on a translucent dark box (legible on any background; OpenCV 5's putText draws
    filled glyphs, so a thicker dark copy does not make an outline)."""
    h, w = img.shape[:2]
    x0, y0 = max(int(box[0]), 0), max(int(box[1]), 0)
    x1, y1 = min(int(np.ceil(box[2])), w), min(int(np.ceil(box[3])), h)
    if x1 > x0 and y1 > y0:
        img[y0:y1, x0:x1] = (img[y0:y1, x0:x1] * 0.35).astype(np.uint8)
    (tw, th), base = cv2.getTextSize(text, _FONT, scale, thick)
    org = (int(round((box[0] + box[2] - tw) / 2)), int(round((box[1] + box[3] + th) / 2)))
    cv2.putText(img, text, org, _FONT, scale, color, thick, cv2.LINE_AA)


def reprojected_points(
    camera: Camera, cam_from_world: Pose, xyz_world: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(K, 2) COLMAP pixels of the (K', 3) model points in front of the camera (K <= K')."""
    xyz_cam = cam_from_world.transform(np.asarray(xyz_world, dtype=np.float64).reshape(-1, 3))
    front = xyz_cam[:, 2] > 1e-12
    if not np.any(front):
        return np.empty((0, 2), dtype=np.float64)
    return camera.project(xyz_cam[front]).reshape(-1, 2)


def _draw_inliers(
    img: NDArray[np.uint8],
    xy: NDArray[np.float64],
    f: float,
    st: _Style,
    color: tuple[int, int, int] = _INLIER,
) -> None:
    r = int(round(st.dot * (1 << _SHIFT)))
    layer = img.copy()
    for p in np.asarray(xy, dtype=np.float64).reshape(-1, 2)[:3000]:
        cv2.circle(layer, _fp(p, f), r, color, -1, cv2.LINE_AA, _SHIFT)
    cv2.addWeighted(layer, 0.65, img, 0.35, 0.0, dst=img)


def _draw_beams(
    img: NDArray[np.uint8],
    camera: Camera,
    rig: Rig,
    f: float,
    st: _Style,
    min_range_m: float,
    max_range_m: float,
) -> list[NDArray[np.float64]]:
    """Predicted beam lines (calibrated lasers); returns their output-pixel polylines."""
    lines = []
    for i, las in enumerate(rig.lasers):
        line = beam_polyline_px(camera, las, min_range_m, max_range_m)
        if len(line) < 2:
            continue
        pts = np.array([_fp(p, f) for p in line], dtype=np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], False, _BLACK, st.line + 2, cv2.LINE_AA, _SHIFT)
        cv2.polylines(img, [pts], False, laser_color_bgr(i), st.line, cv2.LINE_AA, _SHIFT)
        lines.append(line * f)
    return lines


def _overlap_sum(boxes: NDArray[np.float64], others: NDArray[np.float64]) -> NDArray[np.float64]:
    """(C,) total overlap area of each of (C, 4) boxes with (M, 4) other boxes."""
    if len(others) == 0:
        return np.zeros(len(boxes))
    w = np.minimum(boxes[:, None, 2], others[None, :, 2]) - np.maximum(boxes[:, None, 0],
                                                                       others[None, :, 0])
    h = np.minimum(boxes[:, None, 3], others[None, :, 3]) - np.maximum(boxes[:, None, 1],
                                                                       others[None, :, 1])
    return np.sum(np.maximum(w, 0.0) * np.maximum(h, 0.0), axis=1)


def _box_distances(boxes: NDArray[np.float64], xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """(C, K) distance from each of (C, 4) boxes to each of (K, 2) points (0 inside)."""
    dx = np.maximum.reduce([boxes[:, None, 0] - xy[None, :, 0], np.zeros((len(boxes), len(xy))),
                            xy[None, :, 0] - boxes[:, None, 2]])
    dy = np.maximum.reduce([boxes[:, None, 1] - xy[None, :, 1], np.zeros((len(boxes), len(xy))),
                            xy[None, :, 1] - boxes[:, None, 3]])
    return np.hypot(dx, dy)


_RINGS = np.array([1.25, 2.0, 3.0, 4.5, 6.5, 9.0])
_ANGLES = np.deg2rad([-30, 30, -150, 150, -90, 90, 0, 180, -60, 60, -120, 120])


def _candidates(x: float, y: float, w: float, h: float, radius: float) -> NDArray[np.float64]:
    """(rings × angles, 4) label boxes around an anchor, ring by ring: each box is attached
    by its nearest side or corner to a point on the ring."""
    d = radius * _RINGS + 0.5 * min(w, h) * (_RINGS > 2)
    c, s = np.cos(_ANGLES)[None, :], np.sin(_ANGLES)[None, :]
    cx, cy = x + d[:, None] * c, y + d[:, None] * s
    bx = np.where(c > 0.3, cx, np.where(c < -0.3, cx - w, cx - w / 2))
    by = np.where(s < -0.3, cy - h, np.where(s > 0.3, cy, cy - h / 2))
    return np.stack([bx, by, bx + w, by + h], axis=-1).reshape(-1, 4)


def place_labels(
    anchors: Sequence[tuple[float, float]],
    sizes: Sequence[tuple[float, float]],
    radius: float,
    width: int,
    height: int,
    obstacles: Sequence[Box] | NDArray[np.float64] = (),
) -> list[Box]:
    """Label boxes near their anchors (pixels): greedy, candidates on growing rings; a box
    overlapping another label, a spot circle or the image border costs most, one crossing an
    ``obstacle`` (beam line) less, and farther rings a little."""
    xy = np.asarray(anchors, dtype=np.float64).reshape(-1, 2)
    circles = np.column_stack([xy - radius, xy + radius])
    soft_boxes = np.asarray(obstacles, dtype=np.float64).reshape(-1, 4)
    frame = np.array([[0.0, 0.0, float(width), float(height)]])
    placed: list[Box] = []
    ring_of = np.repeat(_RINGS, len(_ANGLES))
    for i, ((x, y), (w, h)) in enumerate(zip(anchors, sizes, strict=True)):
        boxes = _candidates(x, y, w, h, radius)
        hard = _overlap_sum(boxes, np.vstack([np.asarray(placed).reshape(-1, 4), circles]))
        area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
        hard += area - _overlap_sum(boxes, frame)  # the part outside the image
        # ambiguous: the box is nearer to another spot than to its own
        dist = _box_distances(boxes, xy)
        others = np.any(xy != xy[i], axis=1)
        hard += 0.5 * w * h * np.any(dist[:, others] < dist[:, [i]], axis=1)
        cost = 10.0 * hard + _overlap_sum(boxes, soft_boxes) + 0.02 * ring_of * w * h
        for r, ring in enumerate(_RINGS):  # stop at the first ring where nothing hard is hit
            best = int(np.argmin(cost[: (r + 1) * len(_ANGLES)]))
            if cost[best] < 0.02 * (ring + 1) * w * h:
                break
        placed.append(tuple(float(v) for v in boxes[best]))  # type: ignore[arg-type]
    return placed


def _line_obstacles(lines: Sequence[NDArray[np.float64]], half: float) -> NDArray[np.float64]:
    """(M, 4) small boxes along polylines (output pixels), so labels keep off the beam lines:
    each segment sampled at both ends and at most ``half`` apart."""
    centres = [np.zeros((0, 2))]
    for line in lines:
        seg = np.diff(line, axis=0)
        n = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / half)).astype(int)
        first = np.repeat(np.arange(len(seg)), n + 1)
        t = np.concatenate([np.linspace(0.0, 1.0, k + 1) for k in n]) if len(n) else np.zeros(0)
        centres.append(line[first] + t[:, None] * seg[first])
    xy = np.concatenate(centres)
    return np.column_stack([xy - half, xy + half])


def _draw_spots(
    img: NDArray[np.uint8],
    rig: Rig,
    spots: Sequence[Spot],
    f: float,
    st: _Style,
    rejected: Mapping[str, str],
    lines: Sequence[NDArray[np.float64]],
) -> None:
    if not spots:
        return
    h, w = img.shape[:2]
    r_circle = st.circle
    anchors = [(s.x * f - 0.5, s.y * f - 0.5) for s in spots]
    sizes = []
    for s in spots:
        (tw, th), _ = cv2.getTextSize(s.laser, _FONT, st.font, st.text_thick)
        sizes.append((tw + 0.5 * th, 1.5 * th))
    boxes = place_labels(anchors, sizes, r_circle, w, h, _line_obstacles(lines, 2.0 * st.line))
    for s, (ax, ay), box in zip(spots, anchors, boxes, strict=True):
        idx = rig.names.index(s.laser) if s.laser in rig.names else 0
        color = _RED if s.laser in rejected else laser_color_bgr(idx)
        c = _fp((s.x, s.y), f)
        rr = int(round(r_circle * (1 << _SHIFT)))
        cv2.circle(img, c, rr, _BLACK, st.line + 2, cv2.LINE_AA, _SHIFT)
        cv2.circle(img, c, rr, color, st.line, cv2.LINE_AA, _SHIFT)
        bx = min(max(ax, box[0]), box[2])
        by = min(max(ay, box[1]), box[3])
        dist = float(np.hypot(bx - ax, by - ay))
        if dist > r_circle * 1.15:  # leader line from the circle to a label not touching it
            ux, uy = (bx - ax) / dist, (by - ay) / dist
            p0 = _fp(((ax + ux * r_circle + 0.5) / f, (ay + uy * r_circle + 0.5) / f), f)
            p1 = _fp(((bx + 0.5) / f, (by + 0.5) / f), f)
            cv2.line(img, p0, p1, color, max(1, st.line - 1), cv2.LINE_AA, _SHIFT)
        _label(img, s.laser, box, st.font, color, st.text_thick)


#: a near miss: position (COLMAP px) and score (0 when a test rejected it)
NearMiss = tuple[float, float, float]


def _draw_near_misses(img: NDArray[np.uint8], rig: Rig, near: Mapping[str, Sequence[NearMiss]],
                      f: float, st: _Style) -> None:
    """The best candidates in the band of each laser without a spot: an open square in the
    laser's colour and the candidate's score (×: a test rejected it)."""
    half = 0.6 * st.circle
    for name, cands in near.items():
        color = laser_color_bgr(rig.names.index(name)) if name in rig.names else _WHITE
        for x, y, score in cands:
            cx, cy = x * f - 0.5, y * f - 0.5
            p0 = (int(round(cx - half)), int(round(cy - half)))
            p1 = (int(round(cx + half)), int(round(cy + half)))
            cv2.rectangle(img, p0, p1, _BLACK, st.line + 2, cv2.LINE_AA)
            cv2.rectangle(img, p0, p1, color, max(1, st.line - 1), cv2.LINE_AA)
            text = f"{name}? {score:.2f}" if score > 0 else f"{name}? x"
            org = (int(round(cx + half + 4)), int(round(cy - half)))
            for c, thick in ((_BLACK, st.text_thick + 2), (color, st.text_thick)):
                cv2.putText(img, text, org, _FONT, 0.6 * st.font, c, thick, cv2.LINE_AA)


def _legend_entries(
    rig: Rig,
    spots: Sequence[Spot],
    scales: Mapping[str, float],
    rejected: Mapping[str, str],
    n_inliers: int | None,
    pose_rejected: bool = False,
    near: Mapping[str, Sequence[NearMiss]] | None = None,
) -> list[tuple[str, tuple[int, int, int], str]]:
    """(kind, colour, text) per legend box: one per laser, then inliers and beams."""
    seen = {s.laser for s in spots}
    guided = {s.laser: " (where the model puts it)" for s in spots if s.source == "guided"}
    out: list[tuple[str, tuple[int, int, int], str]] = []
    for i, name in enumerate(rig.names):
        how = guided.get(name, "")
        if name in rejected:
            out.append(("spot", _RED, f"{name} rejected{how}"))
        elif name in scales and np.isfinite(scales[name]):
            out.append(("spot", laser_color_bgr(i), f"{name} s={scales[name]:.6g}{how}"))
        elif name in seen:
            out.append(("spot", laser_color_bgr(i), f"{name} no FCM{how}"))
        elif near and near.get(name):
            out.append(("square", laser_color_bgr(i), f"{name} not found: best candidates"))
        else:
            out.append(("spot", laser_color_bgr(i), f"{name} not found"))
    if n_inliers is not None and pose_rejected:
        out.append(("dot", _RED, f"keypoints of the rejected pose ({n_inliers})"))
    elif n_inliers is not None:
        out.append(("dot", _INLIER, f"model points used, reprojected ({n_inliers})"))
    if any(las.calibrated for las in rig.lasers):
        out.append(("line", _WHITE, "predicted beams"))
    return out


def _legend_strip(
    entries: Sequence[tuple[str, tuple[int, int, int], str]], width: int, st: _Style
) -> NDArray[np.uint8]:
    """A dark strip of legend boxes (flow layout, as many rows as needed)."""
    scale = st.font * 0.75
    (_, th), base = cv2.getTextSize("Ag", _FONT, scale, st.text_thick)
    row_h = int(th + base + 2 * st.circle * 0.6 + 6)
    pad = int(st.circle)
    items, x, y = [], pad, 0
    for kind, color, text in entries:
        tw = cv2.getTextSize(text, _FONT, scale, st.text_thick)[0][0]
        w = int(2.4 * st.circle + tw + pad)
        if x + w > width and x > pad:
            x, y = pad, y + row_h
        items.append((x, y, kind, color, text))
        x += w + pad
    strip = np.full((y + row_h + pad // 2, width, 3), 28, dtype=np.uint8)
    for x0, y0, kind, color, text in items:
        cy = y0 + row_h // 2 + pad // 4
        cx = int(x0 + st.circle)
        if kind == "spot":
            cv2.circle(strip, (cx, cy), int(st.circle * 0.75), color, -1, cv2.LINE_AA)
        elif kind == "dot":
            cv2.circle(strip, (cx, cy), max(2, int(st.dot * 1.5)), color, -1, cv2.LINE_AA)
        elif kind == "square":
            r = int(st.circle * 0.6)
            cv2.rectangle(strip, (cx - r, cy - r), (cx + r, cy + r), color, max(1, st.line - 1),
                          cv2.LINE_AA)
        else:
            cv2.line(
                strip, (int(x0), cy), (int(x0 + 1.6 * st.circle), cy), color, st.line, cv2.LINE_AA
            )
        org = (int(x0 + 2.4 * st.circle), cy + th // 2)
        text_color = _LIGHT_RED if color == _RED else _TEXT
        cv2.putText(strip, text, org, _FONT, scale, text_color, st.text_thick, cv2.LINE_AA)
    return strip


def near_misses(result: DetectionResult | None) -> dict[str, list[NearMiss]]:
    """Laser without a spot -> its best candidates (x, y, score) from a detection result."""
    if result is None:
        return {}
    return {name: [(c.x, c.y, c.score) for c in cands]
            for name, cands in result.near_misses.items() if cands}


def draw_bands(rgb: NDArray[np.uint8], camera: Camera, rig: Rig, options: DetectionOptions
               ) -> NDArray[np.uint8]:
    """Copy of ``rgb`` with each searched beam band (segment ± band_px) shaded and outlined."""
    band = options.band_px or default_band_px(camera.width, camera.height)
    out = rgb.copy()
    mask = np.zeros(rgb.shape[:2], np.uint8)
    for las in rig.lasers:
        line = beam_polyline_px(camera, las, options.min_range_m, options.max_range_m)
        if len(line) < 2:
            continue
        # COLMAP px -> OpenCV drawing coordinates: subtract 0.5 (4 fractional bits)
        pts = np.round((line - 0.5) * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(mask, [pts], False, 255, 2 * int(math.ceil(band)), cv2.LINE_8, 4)
    shade = mask > 0
    out[shade] = (0.7 * out[shade] + 0.3 * 255).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, (255, 255, 0), 1, cv2.LINE_AA)
    return out


def draw_overlay(
    rgb: NDArray[np.uint8],
    camera: Camera,
    rig: Rig,
    spots: Sequence[Spot],
    scales: Mapping[str, float],
    inliers_xy: NDArray[np.float64] | None,
    min_range_m: float,
    max_range_m: float,
    max_side: int = 1600,
    *,
    min_side: int = 1200,
    rejected: Mapping[str, str] | None = None,
    pose_rejected: bool = False,
    near_misses: Mapping[str, Sequence[NearMiss]] | None = None,
) -> NDArray[np.uint8]:
    """(H', W' + legend, 3) BGR overlay: the photo resized so its longer side lies in
    [``min_side``, ``max_side``], annotated, with a legend strip below it.

    ``inliers_xy``: (K, 2) COLMAP pixels of the registration's points (green): the model points
    used, reprojected (:func:`reprojected_points`); with ``pose_rejected`` the keypoints of a
    rejected pose (red). ``scales``: FCM scale per laser for the legend; ``rejected``: laser ->
    reason (drawn red); ``near_misses``: laser without a spot -> its best candidates (x, y,
    score), drawn as open squares with their score.
    """
    rejected = rejected or {}
    found = {s.laser for s in spots}  # a spot found later (guided search) has no near misses
    near_misses = {k: v for k, v in (near_misses or {}).items() if k not in found}
    img, f = _resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), min_side, max_side)
    st = _Style.for_size(max(img.shape[:2]))
    if inliers_xy is not None:
        _draw_inliers(img, inliers_xy, f, st, _RED if pose_rejected else _INLIER)
    lines = _draw_beams(img, camera, rig, f, st, min_range_m, max_range_m)
    _draw_spots(img, rig, spots, f, st, rejected, lines)
    if near_misses:
        _draw_near_misses(img, rig, near_misses, f, st)
    n_in = None if inliers_xy is None else int(np.asarray(inliers_xy).reshape(-1, 2).shape[0])
    entries = _legend_entries(rig, spots, scales, rejected, n_in, pose_rejected, near_misses)
    strip = _legend_strip(entries, img.shape[1], st)
    return np.vstack([img, strip])
