"""The scene removed from a laser image: its texture taken out with a laser-free reference.

A laser image's spots must be told from the seafloor's texture under and beside them (pale
specks, shell hash, mineral speckle). When the same scene is known without the lasers (a
*scene reference*: a model image warped into the laser image's pose through the mesh, or a
render of the textured mesh there), its fine texture can be subtracted before detection.

The reference is aligned to the laser image pixel for pixel but not matched in light: it was
lit from elsewhere, exposed otherwise, and its own noise and compression differ. So only its
texture is used: ``texture = scene - G_s(scene)``, the reference minus its Gaussian blur of
``sigma_px`` (normalised over the reference's known pixels), and the detector reads
``image - texture``. The laser image keeps its own light, lamps and glow (everything coarser
than ``sigma_px``), and the spots keep their shape. Two things are kept from the image as it
is: a pixel where the reference is unknown (NaN: the mesh does not cover it), and a channel
at 254 or more that the scene does not explain (a clipped value is what the detector's
clipped-core tests read). The scene explains it where the reference itself is bright there
(``SCENE_BRIGHT``, 240): a bright speck of the seafloor in a bright place clips in the image
too, and kept at 255 among neighbours with their texture removed it would stand out as a
spot. (The image's own light cannot tell: a laser's halo brightens it around its core.)
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError

#: a channel at or above this 8-bit value is clipped: kept as the image has it ...
CLIPPED_LEVEL = 254
#: ... unless the reference is this bright there: then the scene clips the image, not a laser
SCENE_BRIGHT = 240.0


def check_scene(scene_rgb: NDArray[np.floating], image_shape: tuple[int, ...]) -> None:
    """Validate a scene reference against its laser image (shape, float values)."""
    if scene_rgb.shape != image_shape:
        raise InputError(f"the scene reference is {scene_rgb.shape} but its laser image is "
                         f"{image_shape} (H, W, 3): it must be aligned pixel for pixel")
    if not np.issubdtype(scene_rgb.dtype, np.floating):
        raise InputError(f"the scene reference must be float (8-bit levels, NaN where "
                         f"unknown), got {scene_rgb.dtype}")


def scene_texture(scene_rgb: NDArray[np.floating], sigma_px: float) -> NDArray[np.float32]:
    """The reference's texture finer than ``sigma_px`` (H, W, 3; 8-bit levels; 0 where the
    reference is unknown): the reference minus its blur normalised over known pixels."""
    known = np.isfinite(scene_rgb).all(axis=2)
    filled = np.where(known[..., None], scene_rgb, 0.0).astype(np.float32)
    weight = cv2.GaussianBlur(known.astype(np.float32), (0, 0), sigma_px,
                              borderType=cv2.BORDER_REFLECT)
    blurred = cv2.GaussianBlur(filled, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
    low = blurred / np.maximum(weight, np.float32(1e-3))[..., None]
    return np.where(known[..., None], filled - low, np.float32(0.0)).astype(np.float32)


def remove_scene(image_rgb: NDArray[np.uint8], scene_rgb: NDArray[np.floating],
                 sigma_px: float) -> NDArray[np.uint8]:
    """The laser image (H, W, 3, uint8) with the reference's texture subtracted; pixels of
    unknown reference, and clipped channels the scene does not explain, kept as they are
    (module docstring)."""
    check_scene(scene_rgb, image_rgb.shape)
    if not sigma_px > 0:
        raise InputError(f"the scene texture's sigma must be positive, got {sigma_px}")
    image = image_rgb.astype(np.float32)
    texture = scene_texture(scene_rgb, sigma_px)
    out = image - texture
    with np.errstate(invalid="ignore"):  # NaN (unknown) is not bright: its texture is 0
        kept = (image_rgb >= CLIPPED_LEVEL) & ~(scene_rgb >= SCENE_BRIGHT)
    out[kept] = image[kept]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
