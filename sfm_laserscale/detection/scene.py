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

The texture is the seafloor's reflectance times its light, so where the laser image is lit
otherwise than the reference (a lamp's hot spot, a vehicle nearer the floor, the reference's
views lit from elsewhere) it is stronger or weaker there by the ratio of the two lights. With
``gain_sigma_px`` the reference's texture is scaled, per channel and pixel, by the local
least-squares gain of the image's texture on it, ``g = G_w(t_i t_r) / (G_w(t_r^2) + v)``
(``G_w`` a Gaussian of ``gain_sigma_px`` over pixels where the reference is known and the
image's channel is not clipped, ``v`` a floor of ``GAIN_VARIANCE_FLOOR`` level^2), limited to
[0, ``MAX_GAIN``], and blended towards 1 where under ``MIN_GAIN_SHARE`` of the window is
usable (inside a clipped hot spot). That gain leaves the least residual texture in each
window; where the reference's texture is mostly its own noise it falls towards 0, so its noise
is not added. A laser spot adds to ``t_i`` but not in proportion to ``t_r``, and a window
holds thousands of pixels, so a spot barely moves the gain. The blurs (the texture's low
pass and the gain's window) are computed on planes shrunk ``SHRINK_STEP`` times and grown
back: they hold nothing as fine as that.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError

#: a channel at or above this 8-bit value is clipped: kept as the image has it ...
CLIPPED_LEVEL = 254
#: ... unless the reference is this bright there: then the scene clips the image, not a laser
SCENE_BRIGHT = 240.0
#: level^2 added to the reference texture's local variance: a flat reference gets a gain near 0
GAIN_VARIANCE_FLOOR = 1.0
#: the most the image's texture is taken to be stronger than the reference's
MAX_GAIN = 8.0
#: below this share of usable pixels in its window a gain is blended towards 1 (unscaled)
MIN_GAIN_SHARE = 0.5
#: blurs of 8 px or more (the texture's low pass, the gain's window) are computed on planes
#: shrunk this many times and grown back
SHRINK_STEP = 4


def check_scene(scene_rgb: NDArray[np.floating], image_shape: tuple[int, ...]) -> None:
    """Validate a scene reference against its laser image (shape, float values)."""
    if scene_rgb.shape != image_shape:
        raise InputError(f"the scene reference is {scene_rgb.shape} but its laser image is "
                         f"{image_shape} (H, W, 3): it must be aligned pixel for pixel")
    if not np.issubdtype(scene_rgb.dtype, np.floating):
        raise InputError(f"the scene reference must be float (8-bit levels, NaN where "
                         f"unknown), got {scene_rgb.dtype}")


def _step(sigma_px: float) -> int:
    """The shrink factor for a blur of ``sigma_px``: at most SHRINK_STEP, at least 2 px of the
    blur's sigma per shrunk pixel (1: no shrinking)."""
    return min(SHRINK_STEP, max(1, int(sigma_px // 2)))


def _shrunk(planes: NDArray[np.float32], step: int) -> NDArray[np.float32]:
    """``planes`` (H, W, C) as means over ``step`` × ``step`` blocks (h, w, C)."""
    height, width = planes.shape[:2]
    size = (max(1, -(-width // step)), max(1, -(-height // step)))
    small = cv2.resize(planes, size, interpolation=cv2.INTER_AREA)
    return small.reshape(size[1], size[0], -1).astype(np.float32)


def _grown(small: NDArray[np.float32], shape: tuple[int, int]) -> NDArray[np.float32]:
    """Shrunk planes (h, w, C) brought back to ``shape`` (H, W) by bilinear interpolation."""
    big = cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return big.reshape(shape[0], shape[1], -1).astype(np.float32)


def _blurred_small(small: NDArray[np.float32], sigma_px: float, step: int) -> NDArray[np.float32]:
    """Planes shrunk ``step`` times, blurred so that with the block means and the bilinear
    growth back (variances (step² − 1)/12 and step²/6 px²) the whole is a Gaussian of
    ``sigma_px`` full-size pixels."""
    rest = max(sigma_px**2 - (step**2 - 1) / 12.0 - step**2 / 6.0, 0.25 * sigma_px**2)
    out = cv2.GaussianBlur(small, (0, 0), math.sqrt(rest) / step, borderType=cv2.BORDER_REFLECT)
    return out.reshape(small.shape).astype(np.float32)


def low_pass(planes: NDArray[np.float32], sigma_px: float) -> NDArray[np.float32]:
    """``planes`` (H, W, C) blurred by a Gaussian of ``sigma_px``, computed on them shrunk
    (:func:`_step`) and grown back: a blur of 8 px holds nothing finer than 4 px."""
    step = _step(sigma_px)
    if step == 1:
        out = cv2.GaussianBlur(planes, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
        return out.reshape(planes.shape).astype(np.float32)
    return _grown(_blurred_small(_shrunk(planes, step), sigma_px, step), planes.shape[:2])


def scene_texture(scene_rgb: NDArray[np.floating], sigma_px: float) -> NDArray[np.float32]:
    """The reference's texture finer than ``sigma_px`` (H, W, 3; 8-bit levels; 0 where the
    reference is unknown): the reference minus its blur normalised over known pixels."""
    return _texture(scene_rgb, np.isfinite(scene_rgb).all(axis=2), sigma_px)


def _texture(scene_rgb: NDArray[np.floating], known: NDArray[np.bool_],
             sigma_px: float) -> NDArray[np.float32]:
    """:func:`scene_texture` with the reference's ``known`` (H, W) pixels given."""
    filled = np.where(known[..., None], scene_rgb, np.float32(0.0)).astype(np.float32)
    planes = np.concatenate([filled, known[..., None].astype(np.float32)], axis=2)
    step = _step(sigma_px)
    if step == 1:
        sums = low_pass(planes, sigma_px)
    else:  # the normalised blur formed while shrunk, then grown: one full-size pass fewer
        sums = _blurred_small(_shrunk(planes, step), sigma_px, step)
    ratio = (sums[..., :3] / np.maximum(sums[..., 3:], np.float32(1e-3))).astype(np.float32)
    filled -= ratio if step == 1 else _grown(ratio, filled.shape[:2])
    filled[~known] = 0.0
    return filled


def texture_gain(image_rgb: NDArray[np.uint8] | NDArray[np.float32],
                 reference_texture: NDArray[np.float32], known: NDArray[np.bool_],
                 sigma_px: float, gain_sigma_px: float) -> NDArray[np.float32]:
    """The local least-squares gain (H, W, 3) of the image's texture finer than ``sigma_px``
    on the reference's (``reference_texture``), per channel over a Gaussian window of
    ``gain_sigma_px`` and the ``known`` (H, W) pixels where that channel is not clipped; 1
    where under ``MIN_GAIN_SHARE`` of the window is usable (module docstring). The image is
    uint8 or float 8-bit levels. The window's sums are kept shrunk until the gain is formed:
    it is smooth."""
    shape = image_rgb.shape[:2]
    image = np.asarray(image_rgb, dtype=np.float32)  # no copy when float32 already
    image_texture = image - low_pass(image, sigma_px)
    usable = (known[..., None] & (image < CLIPPED_LEVEL)).astype(np.float32)
    weighted = reference_texture * usable
    step = _step(gain_sigma_px)
    covariance, variance, share = (
        _blurred_small(_shrunk(planes, step), gain_sigma_px, step)
        for planes in (weighted * image_texture, weighted * reference_texture, usable))
    gain = covariance / (variance + np.float32(GAIN_VARIANCE_FLOOR) * share + np.float32(1e-6))
    trust = np.clip(share / np.float32(MIN_GAIN_SHARE), 0.0, 1.0)
    small = trust * np.clip(gain, 0.0, MAX_GAIN) + (1.0 - trust)
    return _grown(small.astype(np.float32), shape)


def remove_scene(image_rgb: NDArray[np.uint8], scene_rgb: NDArray[np.floating],
                 sigma_px: float, gain_sigma_px: float | None = None) -> NDArray[np.uint8]:
    """The laser image (H, W, 3, uint8) with the reference's texture subtracted, scaled by
    :func:`texture_gain` when ``gain_sigma_px`` is given; pixels of unknown reference, and
    clipped channels the scene does not explain, kept as they are (module docstring)."""
    check_scene(scene_rgb, image_rgb.shape)
    if not sigma_px > 0:
        raise InputError(f"the scene texture's sigma must be positive, got {sigma_px}")
    if gain_sigma_px is not None and not gain_sigma_px > 0:
        raise InputError(f"the scene gain's sigma must be positive, got {gain_sigma_px}")
    out = image_rgb.astype(np.float32)
    known = np.isfinite(scene_rgb).all(axis=2)
    texture = _texture(scene_rgb, known, sigma_px)
    if gain_sigma_px is not None:
        texture *= texture_gain(out, texture, known, sigma_px, gain_sigma_px)
    out -= texture
    with np.errstate(invalid="ignore"):  # NaN (unknown) is not bright: its texture is 0
        kept = (image_rgb >= CLIPPED_LEVEL) & ~(scene_rgb >= SCENE_BRIGHT)
    out[kept] = image_rgb[kept]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
