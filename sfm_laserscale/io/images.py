"""Laser image discovery and reading (sizes checked against the model's cameras)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from PIL import Image as PILImage
from PIL import UnidentifiedImageError

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera, SparseModel

logger = logging.getLogger(__name__)
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".webp"}


@dataclass(frozen=True)
class LaserImage:
    """A laser image file and the model camera it was taken with."""

    name: str  # file name, the key in spots CSVs and reports
    path: Path
    camera: Camera | None  # None when the file is not a readable image (reported, not used)


def expand_image_paths(paths: Sequence[Path]) -> list[Path]:
    """Image files from files and folders (folders: their images, sorted by name)."""
    files: list[Path] = []
    for p in paths:
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                raise InputError("folder holds no images (.jpg, .png, .tif, ...)", p)
            files += found
        elif p.exists():
            files.append(p)
        else:
            raise InputError("laser image not found", p)
    return files


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header; InputError when it is not a readable image."""
    try:
        with PILImage.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except (UnidentifiedImageError, OSError, ValueError):
        raise InputError("not a readable image", path) from None


def camera_for_size(model: SparseModel, width: int, height: int) -> Camera | None:
    """The model camera of this size used by the most images (None when no camera matches)."""
    matching = [c for c in model.cameras.values() if (c.width, c.height) == (width, height)]
    if not matching:
        return None
    uses = {
        c.camera_id: sum(im.camera_id == c.camera_id for im in model.images.values())
        for c in matching
    }
    return max(matching, key=lambda c: uses[c.camera_id])


def find_laser_images(paths: Sequence[Path], model: SparseModel) -> tuple[LaserImage, ...]:
    """Expand files/folders, check each image's size against the model's cameras."""
    if not paths:
        raise InputError("no laser images given")
    found: list[LaserImage] = []
    unreadable: list[Path] = []
    for f in expand_image_paths(paths):
        try:
            w, h = image_size(f)
        except InputError:
            unreadable.append(f)
            continue
        cam = camera_for_size(model, w, h)
        if cam is None:
            sizes = ", ".join(sorted({f"{c.width}x{c.height}" for c in model.cameras.values()}))
            raise InputError(f"image size {w}x{h} does not match the model's camera ({sizes})", f)
        found.append(LaserImage(name=f.name, path=f, camera=cam))
    if not found:  # every file unreadable
        raise InputError("no readable laser image", unreadable[0] if unreadable else paths[0])
    for f in unreadable:
        logger.warning("%s: not a readable image; reported and skipped", f)
        found.append(LaserImage(name=f.name, path=f, camera=None))
    names = [li.name for li in found]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise InputError(f"several laser images share the file name {dupes[0]!r}")
    return tuple(found)


# Pixels as stored: an EXIF orientation tag is not applied. COLMAP and OpenMVG ignore it (their
# cameras and keypoints are in the stored frame), and so does ``image_size``; OpenCV would
# otherwise turn a tagged JPEG by 90° and its pixels would no longer fit the camera.
_STORED_COLOR = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
_STORED_GRAY = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION


def damage(path: Path) -> str | None:
    """Why the image data of ``path`` is damaged, or None. A JPEG cut short (an interrupted
    copy or download) still decodes in OpenCV, its missing part grey, with only a libjpeg
    warning on stderr; the whole entropy-coded stream is read here (Pillow, at 1/8 scale: a
    third of a full decode) and its end checked. Other formats: OpenCV refuses them whole."""
    try:
        im = PILImage.open(path)
    except (UnidentifiedImageError, OSError, ValueError):
        return None  # not an image Pillow knows: OpenCV decides (not readable at all)
    with im:
        if im.format != "JPEG":
            return None
        try:
            im.draft("RGB", (max(1, im.size[0] // 8), max(1, im.size[1] // 8)))
            im.load()
        except (OSError, ValueError, SyntaxError) as exc:
            why = str(exc) or type(exc).__name__
            if "truncated" in why:
                return f"damaged image: the JPEG data is cut short, the file is truncated ({why})"
            return f"damaged image: the JPEG data does not decode ({why})"
    return None


def read_rgb(path: Path, check: bool = True) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 RGB, in the stored pixel frame; InputError when unreadable, or
    (``check``) damaged (:func:`damage`: a truncated JPEG)."""
    if check:
        why = damage(path)
        if why is not None:
            raise InputError(why, path)
    bgr = cv2.imread(str(path), _STORED_COLOR)
    if bgr is None:
        raise InputError("not a readable image", path)
    # in place: one image in memory, not two (36 MB less at 4000 × 3000)
    return np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB, dst=bgr), dtype=np.uint8)


def read_scene_reference(path: Path) -> NDArray[np.float32]:
    """A scene reference (H, W, 3) float32 RGB in 8-bit levels, NaN where unknown: an 8- or
    16-bit RGB image (16-bit scaled by 1/257), or RGBA whose alpha 0 marks pixels the
    reference does not cover (the mesh did not reach them); InputError when unreadable."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if raw is None or raw.ndim != 3 or raw.shape[2] not in (3, 4):
        raise InputError("not a readable RGB or RGBA image", path)
    if raw.dtype not in (np.uint8, np.uint16):
        raise InputError(f"a scene reference must be 8- or 16-bit, got {raw.dtype}", path)
    levels = np.float32(1.0 if raw.dtype == np.uint8 else 1.0 / 257.0)
    rgb = cv2.cvtColor(np.ascontiguousarray(raw[..., :3]), cv2.COLOR_BGR2RGB).astype(np.float32)
    rgb *= levels
    if raw.shape[2] == 4:
        rgb[raw[..., 3] == 0] = np.nan
    return rgb


def read_gray(path: Path) -> NDArray[np.uint8]:
    """(H, W) uint8 grey, in the stored pixel frame; InputError when unreadable."""
    gray = cv2.imread(str(path), _STORED_GRAY)
    if gray is None:
        raise InputError("not a readable image", path)
    return gray
