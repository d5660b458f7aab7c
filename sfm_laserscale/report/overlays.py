"""Overlay images: detected spots, predicted beam lines, registration inliers, per-laser scale."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection import beam_polyline_px
from sfm_laserscale.model import Camera, Spot
from sfm_laserscale.rig import Rig

_COLORS_BGR = [(0, 255, 255), (255, 0, 255), (255, 255, 0), (0, 165, 255), (0, 255, 0)]


def _pt(xy: NDArray[np.float64], shift: int = 4) -> tuple[int, int]:
    # COLMAP pixel convention -> OpenCV drawing coordinates: subtract 0.5, fixed-point shift.
    return (int(round((xy[0] - 0.5) * (1 << shift))), int(round((xy[1] - 0.5) * (1 << shift))))


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
) -> NDArray[np.uint8]:
    """(H', W', 3) BGR overlay, shrunk so its longer side is at most ``max_side`` pixels."""
    img = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    thick = max(1, int(round(max(img.shape[:2]) / 800)))
    if inliers_xy is not None:
        for xy in np.asarray(inliers_xy)[:2000]:
            cv2.circle(img, _pt(xy), 2 << 4, (0, 200, 0), -1, cv2.LINE_AA, 4)
    for i, las in enumerate(rig.lasers):
        color = _COLORS_BGR[i % len(_COLORS_BGR)]
        line = beam_polyline_px(camera, las, min_range_m, max_range_m)
        if len(line) >= 2:
            pts = np.array([_pt(p) for p in line], dtype=np.int32).reshape(-1, 1, 2)
            cv2.polylines(img, [pts], False, color, thick, cv2.LINE_AA, 4)
    for spot in spots:
        idx = rig.names.index(spot.laser) if spot.laser in rig.names else 0
        color = _COLORS_BGR[idx % len(_COLORS_BGR)]
        c = _pt(np.array([spot.x, spot.y]))
        cv2.circle(img, c, (12 * thick) << 4, color, thick, cv2.LINE_AA, 4)
        label = spot.laser
        if spot.laser in scales and np.isfinite(scales[spot.laser]):
            label += f" s={scales[spot.laser]:.5g}"
        org = (int(spot.x) + 14 * thick, int(spot.y) - 6 * thick)
        cv2.putText(
            img,
            label,
            org,
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5 * thick,
            (0, 0, 0),
            3 * thick,
            cv2.LINE_AA,
        )
        cv2.putText(
            img, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5 * thick, color, thick, cv2.LINE_AA
        )
    f = min(1.0, max_side / max(img.shape[:2]))
    if f < 1.0:
        img = cv2.resize(img, None, fx=f, fy=f, interpolation=cv2.INTER_AREA)
    return img
