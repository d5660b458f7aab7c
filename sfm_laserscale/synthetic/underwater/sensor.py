"""The camera: optics, Bayer sensor, in-camera processing and JPEG.

Input: linear raw-channel radiance of the scene already multiplied by the exposure (1.0 =
the sensor's white, i.e. a full photosite). Steps (:func:`capture`):

1. lens: the optical PSF (Gaussian, sigma 0.4-0.8 px; laser spots are rendered with it
   before pixel integration and added after it), optional whole-frame defocus (a uniform
   disc) and motion blur (a uniform segment), and veiling glare (a small fraction of the
   light spread over a kernel of ~2 % of the image width). Residual lateral chromatic
   aberration (R and B magnified by 1 + ε_R, 1 + ε_B about the principal point; G is the
   reference the camera model describes) is applied to the laser light only, as a local
   translation of its R and B channels (:func:`chromatic_shift_px`);
2. sensor: RGGB Bayer mosaic (R at pixel (0, 0)), shot noise (Poisson, Gaussian approximation,
   from the full-well capacity in electrons) and read noise, clipping of every photosite at
   the white (1.0), 12-bit quantisation;
3. processing: demosaicing (OpenCV edge-aware, 16-bit; note OpenCV calls an RGGB sensor
   "BayerBG"; the sensor is SENSOR_MARGIN_PX wider on each side than the recorded frame, so
   the frame's outer pixels are demosaiced and sharpened with real neighbours), white-balance
   gains, highlight clipping, a colour-correction matrix (rows sum to 1, negative
   off-diagonals: it removes part of the filters' crosstalk and clips to 0), sRGB transfer
   curve, an optional mild tone S-curve and unsharp-mask sharpening, 8 bits;
4. JPEG at the given quality with 4:2:0 chroma subsampling (``IMWRITE_JPEG_SAMPLING_FACTOR``),
   decoded back to uint8 RGB.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]
#: a typical camera-RGB -> sRGB matrix (rows sum to 1)
BASE_CCM = ((1.62, -0.47, -0.15), (-0.22, 1.58, -0.36), (0.03, -0.55, 1.52))
#: highlight protection of the central quarter (where the laser spots are) in auto-exposure
CENTRE_QUANTILE = 99.0
#: OpenCV's code for an RGGB mosaic (R at (0, 0)) -> RGB, edge-aware, 8 or 16 bit
DEMOSAIC_RGGB = cv2.COLOR_BayerBG2RGB_EA
#: (x0, y0, light (h, w, 3)): a crop of light whose top-left pixel is (x0, y0)
Crop = tuple[int, int, NDArray[np.float32]]
#: photosites beyond the recorded frame on each side (even: keeps the Bayer phase). A camera
#: demosaics and sharpens the pixels it records with the sensor's margin around them; OpenCV
#: demosaicing a frame by itself fills its outer pixels from their inner neighbours instead,
#: which moves a spot near the edge outwards (docs/DETECTION.md, "How honest the σ is")
SENSOR_MARGIN_PX = 8


def mirrored_margin(img: NDArray[np.float32], margin_px: int) -> NDArray[np.float32]:
    """``img`` with ``margin_px`` pixels mirrored onto each side (:data:`cv2.BORDER_REFLECT_101`:
    an even margin keeps the Bayer phase); ``img`` itself when the margin is 0."""
    if not margin_px:
        return img
    m = margin_px
    return np.asarray(cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_REFLECT_101), np.float32)


@dataclass(frozen=True)
class SensorSettings:
    """Everything the camera does to the light (see the module docstring)."""

    psf_sigma_px: float = 0.6
    full_well_e: float = 8000.0
    read_noise_e: float = 3.0
    adc_bits: int = 12
    wb_gains: tuple[float, float, float] = (1.5, 1.0, 2.3)
    ccm: tuple[tuple[float, float, float], ...] = BASE_CCM  # rows sum to 1
    jpeg_quality: int = 90
    chroma_420: bool = True
    motion_px: float = 0.0
    motion_angle_rad: float = 0.0
    defocus_radius_px: float = 0.0
    glare_fraction: float = 0.01
    ca_red: float = 0.0
    ca_blue: float = 0.0
    tone: float = 0.0
    sharpen: float = 0.0
    noise: bool = True
    jpeg: bool = True


def _odd(n: float) -> int:
    k = int(math.ceil(n))
    return k + 1 if k % 2 == 0 else k


def disc_kernel(radius_px: float) -> F32:
    """Normalised uniform disc (defocus) with anti-aliased edge, odd size, centred."""
    size = _odd(2 * radius_px + 3)
    c = size // 2
    ss = 8
    g = (np.arange(size * ss) + 0.5) / ss - 0.5 - c
    gx, gy = np.meshgrid(g, g)
    inside = (gx * gx + gy * gy <= radius_px ** 2).astype(np.float64)
    k = inside.reshape(size, ss, size, ss).mean(axis=(1, 3))
    return (k / k.sum()).astype(np.float32)


def line_kernel(length_px: float, angle_rad: float) -> F32:
    """Normalised uniform segment (motion blur) of this length, centred, anti-aliased."""
    half = 0.5 * length_px
    size = _odd(length_px + 3)
    c = size // 2
    ker = np.zeros((size, size))
    n = max(int(length_px * 16), 2)
    u = np.linspace(-half, half, n)
    xs, ys = c + u * math.cos(angle_rad), c + u * math.sin(angle_rad)
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - x0, ys - y0
    for dy, dx, w in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)),
                      (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(ker, (y0 + dy, x0 + dx), w)
    ker = 0.5 * (ker + ker[::-1, ::-1])  # exactly centro-symmetric: no shift
    return (ker / ker.sum()).astype(np.float32)


def lens(rgb: F32, s: SensorSettings, post_psf: Sequence[Crop] = (), margin_px: int = 0
         ) -> F32:
    """Optical PSF, then (after adding ``post_psf`` light crops that were rendered with the
    PSF already: the laser spots) whole-frame defocus, motion blur and veiling glare (linear).
    Lateral chromatic aberration is applied to the laser light only (see
    :func:`chromatic_shift_px`): on the seabed texture a 0.1-0.4 px shift of R and B is
    invisible. ``margin_px``: the sensor's margin around the recorded frame; the glare is
    that of the recorded frame's light (a kernel of 2 % of its width; the margin's few pixels
    add nothing to it), mirrored into the margin."""
    out = rgb
    if s.psf_sigma_px > 0.0:
        out = cv2.GaussianBlur(out, (0, 0), s.psf_sigma_px, borderType=cv2.BORDER_REFLECT)
    for x0, y0, light in post_psf:
        add_crop(out, x0, y0, light)
    if s.defocus_radius_px > 0.0:
        out = cv2.filter2D(out, -1, disc_kernel(s.defocus_radius_px),
                           borderType=cv2.BORDER_REFLECT)
    if s.motion_px > 0.0:
        out = cv2.filter2D(out, -1, line_kernel(s.motion_px, s.motion_angle_rad),
                           borderType=cv2.BORDER_REFLECT)
    if s.glare_fraction > 0.0:
        m = margin_px
        frame = out[m:out.shape[0] - m, m:out.shape[1] - m]
        glare = mirrored_margin(wide_blur(frame, 0.02 * frame.shape[1]), m)
        out = cv2.scaleAdd(glare, s.glare_fraction, out)
    return np.asarray(out, np.float32)


def add_crop(img: F32, x0: int, y0: int, light: F32) -> None:
    """In place: add a crop of light whose top-left pixel is (x0, y0), clipped to the image."""
    h, w = light.shape[:2]
    ya, xa = max(y0, 0), max(x0, 0)
    yb, xb = min(y0 + h, img.shape[0]), min(x0 + w, img.shape[1])
    if yb > ya and xb > xa:
        img[ya:yb, xa:xb] += light[ya - y0: yb - y0, xa - x0: xb - x0]


def chromatic_shift_px(x_px: float, y_px: float, s: SensorSettings, cx: float, cy: float
                       ) -> tuple[tuple[float, float], tuple[float, float]]:
    """Lateral chromatic aberration at a point: displacement (px) of the R and of the B
    channel relative to G (radial magnification 1 + ε about the principal point)."""
    dx, dy = x_px - cx, y_px - cy
    return (s.ca_red * dx, s.ca_red * dy), (s.ca_blue * dx, s.ca_blue * dy)


def shift_channels(light: F32, shifts: tuple[tuple[float, float], ...]) -> F32:
    """A copy of a (h, w, 3) crop with channels 0 and 2 translated by sub-pixel shifts
    (bilinear; used for the chromatic aberration of laser spots)."""
    out = light.copy()
    h, w = light.shape[:2]
    for ch, (dx, dy) in zip((0, 2), shifts, strict=True):
        if dx == 0.0 and dy == 0.0:
            continue
        mat = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], np.float64)
        out[..., ch] = cv2.warpAffine(np.ascontiguousarray(light[..., ch]), mat, (w, h),
                                      flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return out


def wide_blur(img: F32, sigma_px: float, mix: tuple[tuple[float, float], ...] = ((1.0, 1.0),)
              ) -> F32:
    """Blur by a mixture of wide Gaussians (``mix`` = (weight, sigma factor) pairs, sigma =
    factor x ``sigma_px``), computed at 1/8 resolution (cheap; the result is smooth)."""
    h, w = img.shape[:2]
    f = 8
    small = cv2.resize(img, (max(w // f, 1), max(h // f, 1)), interpolation=cv2.INTER_AREA)
    acc = np.zeros_like(small)
    for weight, factor in mix:
        acc += np.float32(weight) * cv2.GaussianBlur(
            small, (0, 0), max(factor * sigma_px / f, 0.5), borderType=cv2.BORDER_REFLECT)
    return np.asarray(cv2.resize(acc, (w, h), interpolation=cv2.INTER_LINEAR), np.float32)


def bayer_mosaic(rgb: F32) -> F32:
    """(H, W) RGGB mosaic: R at even rows/even columns, B at odd/odd, G elsewhere."""
    raw = np.empty(rgb.shape[:2], np.float32)
    raw[0::2, 0::2] = rgb[0::2, 0::2, 0]
    raw[0::2, 1::2] = rgb[0::2, 1::2, 1]
    raw[1::2, 0::2] = rgb[1::2, 0::2, 1]
    raw[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return raw


def expose_raw(raw: F32, s: SensorSettings, rng: np.random.Generator, margin_px: int = 0
               ) -> NDArray[np.uint16]:
    """Shot and read noise, clipping at the white, ADC quantisation -> 16-bit raw.

    ``margin_px``: the sensor's margin around the recorded frame (even). The noise is drawn
    for the recorded frame only (the same draws with or without a margin) and mirrored into
    the margin (:func:`mirrored_margin`)."""
    if s.noise:
        electrons = np.maximum(raw, 0.0) * np.float32(s.full_well_e)
        sigma = np.sqrt(electrons + np.float32(s.read_noise_e ** 2))
        m = margin_px
        draws = rng.standard_normal((raw.shape[0] - 2 * m, raw.shape[1] - 2 * m),
                                    dtype=np.float32)
        noise = mirrored_margin(draws, m) * sigma
        raw = (electrons + noise) * np.float32(1.0 / s.full_well_e)
    levels = (1 << s.adc_bits) - 1
    code = np.rint(np.clip(raw, 0.0, 1.0) * np.float32(levels))
    return (code * (65535.0 / levels)).astype(np.uint16)


def srgb_encode(lin: F32) -> F32:
    """sRGB transfer curve (linear [0, 1] -> encoded [0, 1])."""
    lin = np.clip(lin, 0.0, 1.0)
    return np.where(lin <= 0.0031308, 12.92 * lin,
                    1.055 * np.power(lin, 1.0 / 2.4) - 0.055).astype(np.float32)


def srgb_decode(enc: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse of :func:`srgb_encode` (encoded [0, 1] -> linear [0, 1]), in float64."""
    enc = np.clip(np.asarray(enc, np.float64), 0.0, 1.0)
    return np.asarray(np.where(enc <= 0.04045, enc / 12.92, ((enc + 0.055) / 1.055) ** 2.4))


@functools.lru_cache(maxsize=16)
def _transfer_lut(tone: float) -> F32:
    """(65536,) sRGB curve then tone S-curve, on linear values i / 65535 (read-only: one table
    per tone curve, made once and shared by every developed patch)."""
    enc = srgb_encode(np.linspace(0.0, 1.0, 65536, dtype=np.float32))
    if tone > 0.0:
        enc = (1.0 - tone) * enc + tone * enc * enc * (3.0 - 2.0 * enc)
    lut = np.array(enc, np.float32)
    lut.flags.writeable = False
    return lut


def develop(lin_rgb: F32, s: SensorSettings) -> F32:
    """White balance, highlight clip, colour matrix, sRGB curve and tone curve -> [0, 1]
    (the curves through a 16-bit look-up table)."""
    shape = lin_rgb.shape
    img = np.ascontiguousarray(lin_rgb.reshape(-1, 1, 3) if lin_rgb.ndim == 2 else lin_rgb,
                               np.float32)
    img = cv2.multiply(img, (*s.wb_gains, 0.0))  # per-channel scalar (4-tuple)
    np.minimum(img, np.float32(1.0), out=img)
    img = cv2.transform(img, np.asarray(s.ccm, np.float32))
    np.clip(img, np.float32(0.0), np.float32(1.0), out=img)
    idx16 = cv2.multiply(img, (65535.0, 65535.0, 65535.0, 0.0), dtype=cv2.CV_16U)  # rounds
    return np.asarray(_transfer_lut(s.tone)[idx16], np.float32).reshape(shape)


def encode_jpeg(rgb8: U8, quality: int, chroma_420: bool = True) -> bytes:
    """The JPEG file (4:2:0 or 4:4:4 chroma) of an RGB uint8 image, as bytes."""
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality), cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
              cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420 if chroma_420
              else cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return bytes(buf.tobytes())


def decode_jpeg(data: bytes) -> U8:
    """RGB uint8 pixels of a JPEG file's bytes."""
    buf = np.frombuffer(data, np.uint8)
    return np.asarray(cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB),
                      np.uint8)


def jpeg_roundtrip(rgb8: U8, quality: int, chroma_420: bool = True) -> U8:
    """Encode as JPEG (4:2:0 or 4:4:4 chroma) and decode back, RGB uint8."""
    return decode_jpeg(encode_jpeg(rgb8, quality, chroma_420))


def capture(radiance: F32, s: SensorSettings, rng: np.random.Generator,
            post_psf: Sequence[Crop] = ()) -> U8:
    """The whole camera: exposed linear radiance (H, W, 3) -> decoded JPEG (H, W, 3) uint8.
    ``post_psf``: (x0, y0, light) crops already blurred by the PSF (laser spots), added after
    the PSF (see :func:`lens`). The sensor is SENSOR_MARGIN_PX wider on each side than the
    frame it records (the scene mirrored there, the crops' own light where they reach it);
    the margin is cut off after sharpening."""
    m = SENSOR_MARGIN_PX
    sensor_radiance = mirrored_margin(radiance, m)
    lit = lens(sensor_radiance, s, [(x0 + m, y0 + m, light) for x0, y0, light in post_psf], m)
    del sensor_radiance
    raw16 = expose_raw(bayer_mosaic(lit), s, rng, margin_px=m)
    del lit
    lin = cv2.cvtColor(raw16, DEMOSAIC_RGGB).astype(np.float32) * np.float32(1.0 / 65535.0)
    enc = develop(lin, s)
    if s.sharpen > 0.0:
        blur = cv2.GaussianBlur(enc, (0, 0), 1.0)
        enc = cv2.addWeighted(enc, 1.0 + s.sharpen, blur, -s.sharpen, 0.0)
    enc = enc[m:enc.shape[0] - m, m:enc.shape[1] - m]
    rgb8 = np.clip(np.rint(enc * 255.0), 0, 255).astype(np.uint8)
    return jpeg_roundtrip(rgb8, s.jpeg_quality, s.chroma_420) if s.jpeg else rgb8


def auto_exposure(radiance: F32, s: SensorSettings, target_green: float,
                  highlight_quantile: float = 99.0, highlight_max: float = 0.98) -> float:
    """Exposure factor that puts the median output green (no noise, no blur, 0-1) of this
    radiance at ``target_green``, unless that would push the ``highlight_quantile`` of the
    output green, in the whole frame or in its central quarter (centre-weighted metering),
    above ``highlight_max`` (highlight protection, as camera auto-exposure does); bisection
    on log exposure, on regular subsamples of ~10 000 pixels."""
    h, w = radiance.shape[:2]

    def subsample(img: F32) -> F32:
        step = max(1, int(math.sqrt(img.shape[0] * img.shape[1] / 10000.0)))
        return np.ascontiguousarray(img[::step, ::step].reshape(-1, 3))

    def solve(sample: F32, quantile: float, target: float) -> float:
        lo, hi = -30.0, 30.0
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            g = float(np.percentile(develop(sample * np.float32(math.exp(mid)), s)[:, 1],
                                    quantile))
            lo, hi = (mid, hi) if g < target else (lo, mid)
        return math.exp(0.5 * (lo + hi))

    whole = subsample(radiance)
    centre = subsample(radiance[h // 4: 3 * h // 4, w // 4: 3 * w // 4])
    return min(solve(whole, 50.0, target_green),
               solve(whole, highlight_quantile, highlight_max),
               solve(centre, CENTRE_QUANTILE, highlight_max))
