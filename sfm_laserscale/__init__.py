"""sfm-laserscale: metric scale for monocular SfM models from laser scaler images."""

__version__ = "0.1.0"
