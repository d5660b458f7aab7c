"""io/images.py: laser and model images read as RGB."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.images import read_gray, read_rgb


def test_read_rgb_gives_the_written_pixels_in_rgb_order(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, (37, 53, 3)).astype(np.uint8)
    path = tmp_path / "a.png"
    assert cv2.imwrite(str(path), rgb[:, :, ::-1])  # OpenCV writes BGR
    got = read_rgb(path)
    assert got.dtype == np.uint8 and got.flags.c_contiguous and got.flags.writeable
    np.testing.assert_array_equal(got, rgb)
    grey = read_gray(path).astype(int)  # the PNG decoder's own conversion: ±1 of OpenCV's
    assert grey.shape == (37, 53)
    assert np.abs(grey - cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(int)).max() <= 1


def test_unreadable_image_is_an_input_error(tmp_path: Path) -> None:
    path = tmp_path / "broken.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    with pytest.raises(InputError, match="not a readable image"):
        read_rgb(path)
    with pytest.raises(InputError, match="not a readable image"):
        read_gray(path)


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_exif_orientation_is_not_applied(tmp_path: Path, orientation: int) -> None:
    """A JPEG tagged as rotated is read in its stored frame, as COLMAP and OpenMVG read it and
    as ``image_size`` measures it (OpenCV's default would turn it)."""
    from PIL import Image

    from sfm_laserscale.io.images import image_size

    stored = np.zeros((40, 64, 3), np.uint8)
    stored[:, :16] = (255, 255, 255)  # a white band on the left of the stored pixels
    exif = Image.Exif()
    exif[0x0112] = orientation
    path = tmp_path / "tagged.jpg"
    Image.fromarray(stored).save(path, exif=exif.tobytes(), quality=95)
    assert image_size(path) == (64, 40)
    rgb, gray = read_rgb(path), read_gray(path)
    assert rgb.shape == (40, 64, 3) and gray.shape == (40, 64)
    assert rgb[:, :12].min() > 200 and rgb[:, 20:].max() < 60
    assert gray[:, :12].min() > 200 and gray[:, 20:].max() < 60
