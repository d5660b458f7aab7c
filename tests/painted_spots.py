"""A painted green spot's grid and planes, shared by the tests that paint one on a 41 × 41 px
patch (COLMAP pixel centres at index + 0.5)."""

from __future__ import annotations

import numpy as np

from sfm_laserscale.detection import DetectionOptions
from sfm_laserscale.detection.response import Planes, crop_channels, make_planes
from sfm_laserscale.laser_color import DEFAULT_RGB

SIZE = 41
TRUE_XY = (20.3, 19.8)  # COLMAP px
GREEN = DEFAULT_RGB["green"]


def gaussian(xy: tuple[float, float], sigma: float) -> np.ndarray:
    """(SIZE, SIZE) unit-peak Gaussian at a COLMAP point (pixel centres at index + 0.5)."""
    c = np.arange(SIZE) + 0.5
    gx, gy = np.meshgrid(c, c)
    return np.exp(-0.5 * ((gx - xy[0]) ** 2 + (gy - xy[1]) ** 2) / sigma**2)


def green_planes(image: np.ndarray) -> Planes:
    """The green laser's detection planes of a (SIZE, SIZE, 3) gamma-2.2 patch."""
    options = DetectionOptions()
    return make_planes(crop_channels(image, (0, 0, SIZE, SIZE), options.input_gamma), "green",
                       options, 10.0, GREEN)
