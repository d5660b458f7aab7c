"""What detection reads: the image checked against its camera, and the colours the rig's lasers
need (which channels to search, and the light each channel's lasers are expected to add)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection.response import CHANNELS
from sfm_laserscale.errors import InputError
from sfm_laserscale.laser_color import DEFAULT_RGB
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import Rig


def check_image(image_rgb: NDArray[np.uint8], camera: Camera) -> None:
    """Validate the image against its camera (shape, size, dtype)."""
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
        raise InputError(f"laser image must be RGB (H, W, 3), got shape {image_rgb.shape}")
    if image_rgb.shape[:2] != (camera.height, camera.width):
        raise InputError(
            f"laser image is {image_rgb.shape[1]}x{image_rgb.shape[0]} px but its camera is "
            f"{camera.width}x{camera.height} px")
    if image_rgb.dtype != np.uint8:
        raise InputError(f"laser image must be 8-bit (uint8), got {image_rgb.dtype}")


def colours_needed(rig: Rig) -> list[str]:
    """Laser channels to search, in channel order ("any" needs all three)."""
    wanted = {las.color for las in rig.lasers}
    if "any" in wanted:
        return list(CHANNELS)
    return [c for c in CHANNELS if c in wanted]


def group_rgb(rig: Rig, color: str) -> tuple[float, float, float]:
    """Expected colour of a channel's lasers: the mean of theirs, or the channel's default."""
    rgbs = [las.expected_rgb for las in rig.lasers if las.color == color and las.expected_rgb]
    if not rgbs:
        return DEFAULT_RGB[color]
    mean = np.mean(np.asarray(rgbs), axis=0)
    return (float(mean[0]), float(mean[1]), float(mean[2]))
