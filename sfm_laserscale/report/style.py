"""One colour per laser, shared by the overlays (BGR) and the plots (hex), so a laser looks the
same everywhere in the report. Red is kept out: in the report red means rejected or warning.
"""

from __future__ import annotations

# Okabe–Ito colour-blind-safe palette without its vermillion (red is reserved for warnings).
LASER_COLORS_HEX = ("#E69F00", "#56B4E9", "#009E73", "#CC79A7", "#0072B2", "#F0E442")
WARNING_HEX = "#C0392B"
INLIER_HEX = "#7CFC00"


def hex_to_bgr(color: str) -> tuple[int, int, int]:
    """'#RRGGBB' -> (B, G, R) for OpenCV drawing."""
    c = color.lstrip("#")
    r, g, b = (int(c[i : i + 2], 16) for i in (0, 2, 4))
    return (b, g, r)


def laser_color_hex(index: int) -> str:
    """The colour of the rig's laser number ``index`` (rig order)."""
    return LASER_COLORS_HEX[index % len(LASER_COLORS_HEX)]


def laser_color_bgr(index: int) -> tuple[int, int, int]:
    """The colour of the rig's laser number ``index`` (rig order), OpenCV BGR."""
    return hex_to_bgr(laser_color_hex(index))
