"""Learned beam lines for uncalibrated lasers (PCM-only rigs), from many laser images.

A fixed beam is a 3D line in the camera frame; its spot moves along the image of that line as
the range changes. For a pinhole camera that image is a straight line; for a distorted camera
it is straight in undistorted normalised coordinates (``camera.unproject``), where all the
work here is done.

1. ``image_candidates``: the valid spot candidates of each image (pass 1 of ``detect``: the
   detector run without beam geometry), in normalised coordinates, with their colour.
2. ``learn_beam_lines``: per colour group of uncalibrated lasers, sequential RANSAC finds the
   lines supported by the most *images* (a laser's spots lie on its line, one per image;
   distractors are scattered). Each line is refitted by total least squares on its inliers.
   If both spots of most images lie on one line (the camera centre lies in the plane of two
   parallel beams: their images coincide, on either side of the common vanishing point), the
   line is split into two half-lines at the gap between the two spot clusters.
3. Lasers are assigned to lines by a fixed rule: the group's lasers in rig-file order get the
   (half-)lines ordered left to right by the mean x of their inlier spots. This is a
   convention, not an observation: list uncalibrated lasers of one colour left to right as
   they appear in the images. A swap within a PCM pair changes nothing (PCM is symmetric in
   its two lasers); a swap across pairs would be wrong, so check the overlays. When the number
   of lines found differs from the number of lasers, no line is assigned (reported).
4. ``rig_with_learned_lines``: each learned line becomes a pseudo-calibrated 3D beam whose
   image between ``min_range_m`` and ``max_range_m`` is exactly the learned (padded) segment,
   so pass 2 searches its band exactly like a calibrated beam's. The pseudo beam is a search
   aid only: its origin and direction are not the laser's and must never feed FCM.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection import DetectionResult
from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import Laser, Rig

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
#: spots of another line closer than this (px) to a line limit how far its segment is padded
NEAR_LINE_PX = 30.0


@dataclass(frozen=True)
class ImageCandidates:
    """Valid spot candidates of one image: (N, 2) normalised (z = 1) coordinates, colours."""

    xy_n: F64
    colors: tuple[str, ...]


@dataclass(frozen=True)
class BeamLineOptions:
    """Settings of :func:`learn_beam_lines` (pixels are converted with ``focal_px``).

    - ``inlier_px``: max distance of a spot from its line.
    - ``min_images``: a line needs spots on it in at least this many images.
    - ``hypotheses``: random two-point line hypotheses per line search.
    - ``pad_fraction``/``min_pad_px``: the learned segment (extent of its spots) is extended by
      this fraction of its length, at least ``min_pad_px``, at both ends.
    - ``seed``: of the RANSAC sampler.
    """

    inlier_px: float = 2.0
    min_images: int = 3
    hypotheses: int = 3000
    pad_fraction: float = 0.3
    min_pad_px: float = 20.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.inlier_px <= 0 or self.min_images < 2 or self.hypotheses < 1:
            raise InputError("beam line options: inlier_px > 0, min_images >= 2, hypotheses >= 1")


@dataclass(frozen=True)
class LearnedLine:
    """One laser's learned image line in normalised coordinates.

    ``point`` (2,) and unit ``direction`` (2,) define the line; ``s_range`` is the searched
    segment (padded) as signed distances along ``direction`` from ``point``.
    """

    laser: str
    point: F64
    direction: F64
    s_range: tuple[float, float]
    n_images: int
    rms_px: float
    shared_with: str | None = None


@dataclass(frozen=True)
class BeamLinesResult:
    """Learned lines per laser and, for uncalibrated lasers without one, why."""

    lines: dict[str, LearnedLine]
    missing: dict[str, str]


@dataclass
class _Found:
    """A (half-)line found by RANSAC (internal)."""

    point: F64
    direction: F64
    s: F64  # along-line coordinates of the inliers
    images: NDArray[np.intp]  # image index of each inlier
    rms: float  # normalised units
    mean_x: float
    cut: float | None = None  # split point of a shared line (along-line coordinate)


def image_candidates(result: DetectionResult, camera: Camera) -> ImageCandidates:
    """The valid (measured, not rejected) candidates of a detection, normalised."""
    valid = [c for c in result.candidates if c.score > 0.0]
    if not valid:
        return ImageCandidates(np.zeros((0, 2)), ())
    xy = np.array([[c.x, c.y] for c in valid], dtype=np.float64)
    return ImageCandidates(camera.unproject(xy)[:, :2], tuple(c.color for c in valid))


def _tls_line(pts: F64) -> tuple[F64, F64]:
    """Total least squares line (centroid, unit direction) of (N, 2) points."""
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    d = vt[0]
    if d[0] < 0 or (d[0] == 0 and d[1] < 0):
        d = -d
    return c, d


def _support(pts: F64, img: NDArray[np.intp], n_img: int, p0: F64, d: F64, tol: float
             ) -> tuple[NDArray[np.bool_], int]:
    """Inlier mask of a line and the number of distinct images with an inlier."""
    normal = np.array([-d[1], d[0]])
    inl = np.abs((pts - p0) @ normal) <= tol
    return inl, int(np.unique(img[inl]).size)


def _ransac_line(pts: F64, img: NDArray[np.intp], tol: float, options: BeamLineOptions,
                 rng: np.random.Generator) -> tuple[F64, F64] | None:
    """Best two-point line hypothesis by MSAC over images: each image costs the truncated
    squared distance of its closest point (so support counts images, and among lines seen in
    as many images the more exact one wins); None if no hypothesis can be drawn."""
    n = len(pts)
    if n < 2:
        return None
    order = np.argsort(img, kind="stable")
    pts, img = pts[order], img[order]
    starts = np.flatnonzero(np.r_[True, img[1:] != img[:-1]])
    i = rng.integers(0, n, options.hypotheses)
    j = rng.integers(0, n, options.hypotheses)
    keep = (img[i] != img[j]) & (np.linalg.norm(pts[i] - pts[j], axis=1) > 2 * tol)
    i, j = i[keep], j[keep]
    if len(i) == 0:
        return None
    d = pts[j] - pts[i]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    normal = np.column_stack([-d[:, 1], d[:, 0]])  # (H, 2)
    dist = np.einsum("hk,nk->hn", normal, pts) - np.sum(normal * pts[i], axis=1)[:, None]
    cost = np.minimum(dist**2, tol**2)  # (H, N)
    per_image = np.minimum.reduceat(cost, starts, axis=1)  # (H, images)
    best = int(np.argmin(per_image.sum(axis=1)))
    return pts[i[best]], d[best]


def _refit(pts: F64, img: NDArray[np.intp], p0: F64, d: F64, tol: float
           ) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Two rounds of total least squares on the inliers."""
    n_img = int(img.max()) + 1
    inl, _ = _support(pts, img, n_img, p0, d, tol)
    for _ in range(2):
        if inl.sum() < 2:
            break
        p0, d = _tls_line(pts[inl])
        inl, _ = _support(pts, img, n_img, p0, d, tol)
    return p0, d, inl


def _found(pts: F64, img: NDArray[np.intp], p0: F64, d: F64, mask: NDArray[np.bool_],
           cut: float | None, camera_x: F64) -> _Found:
    """A _Found record for the inliers ``mask`` of the line (p0, d)."""
    normal = np.array([-d[1], d[0]])
    resid = (pts[mask] - p0) @ normal
    return _Found(point=p0, direction=d, s=(pts[mask] - p0) @ d, images=img[mask],
                  rms=float(np.sqrt(np.mean(resid**2))) if mask.any() else 0.0,
                  mean_x=float(np.mean(camera_x[mask])), cut=cut)


def _split_shared(pts: F64, img: NDArray[np.intp], p0: F64, d: F64, inl: NDArray[np.bool_],
                  camera_x: F64) -> list[_Found] | None:
    """Two half-lines when most images have two well separated spots on the line, else None."""
    s = (pts - p0) @ d
    idx = np.flatnonzero(inl)
    per_image: dict[int, list[float]] = {}
    for k in idx:
        per_image.setdefault(int(img[k]), []).append(float(s[k]))
    doubles = [v for v in per_image.values() if len(v) >= 2]
    if len(doubles) < max(2, len(per_image) // 2):
        return None
    lows, highs = max(min(v) for v in doubles), min(max(v) for v in doubles)
    if not lows < highs:
        return None
    cut = 0.5 * (lows + highs)
    low = inl & (s < cut)
    # each half refitted on its own spots: two distinct but nearly collinear beam images
    # (lines meeting at the vanishing point at a small angle) are separated here
    return [_found(pts, img, *_tls_line(pts[m]), m, cut, camera_x) for m in (low, inl & ~low)]


def _find_lines(pts: F64, img: NDArray[np.intp], camera_x: F64, wanted: int, tol: float,
                options: BeamLineOptions, rng: np.random.Generator) -> list[_Found]:
    """Up to ``wanted`` (half-)lines, each supported by >= min_images images."""
    out: list[_Found] = []
    free = np.ones(len(pts), dtype=bool)
    while len(out) < wanted and free.sum() >= 2:
        sub = np.flatnonzero(free)
        hyp = _ransac_line(pts[sub], img[sub], tol, options, rng)
        if hyp is None:
            break
        p0, d, inl_sub = _refit(pts[sub], img[sub], hyp[0], hyp[1], tol)
        if np.unique(img[sub][inl_sub]).size < options.min_images:
            break
        inl = np.zeros(len(pts), dtype=bool)
        inl[sub[inl_sub]] = True
        halves = _split_shared(pts, img, p0, d, inl, camera_x) if wanted - len(out) >= 2 else None
        out += halves if halves is not None else [_found(pts, img, p0, d, inl, None, camera_x)]
        free &= ~inl
    return out


def _segment(f: _Found, others: Sequence[_Found], options: BeamLineOptions,
             focal_px: float) -> tuple[float, float]:
    """Padded along-line extent of a line's spots, never reaching past the midpoint of the gap
    to the spots of another line of the group that lie near this line (both beams' images
    then meet at their vanishing point, between the two spot clusters)."""
    lo, hi = float(f.s.min()), float(f.s.max())
    pad = max(options.pad_fraction * (hi - lo), options.min_pad_px / focal_px)
    lo_pad, hi_pad = lo - pad, hi + pad
    normal = np.array([-f.direction[1], f.direction[0]])
    for g in others:
        spots = g.point + g.s[:, None] * g.direction[None, :]
        near = np.abs((spots - f.point) @ normal) * focal_px < NEAR_LINE_PX
        if not near.any():
            continue
        proj = (spots[near] - f.point) @ f.direction
        if proj.min() > hi:
            hi_pad = min(hi_pad, 0.5 * (hi + float(proj.min())))
        elif proj.max() < lo:
            lo_pad = max(lo_pad, 0.5 * (lo + float(proj.max())))
    return lo_pad, hi_pad


def _group_lasers(rig: Rig) -> dict[str, list[Laser]]:
    """Uncalibrated lasers grouped by the colours they can take ("any" searches all)."""
    groups: dict[str, list[Laser]] = {}
    for las in rig.lasers:
        if not las.calibrated:
            groups.setdefault(las.color, []).append(las)
    return groups


def _group_points(cands: Sequence[ImageCandidates], color: str
                  ) -> tuple[F64, NDArray[np.intp]]:
    """(N, 2) normalised points of one colour group and their image indices."""
    pts, img = [], []
    for k, c in enumerate(cands):
        for xy, col in zip(c.xy_n, c.colors, strict=True):
            if color == "any" or col == color:
                pts.append(xy)
                img.append(k)
    return np.array(pts, dtype=np.float64).reshape(-1, 2), np.array(img, dtype=np.intp)


def learn_beam_lines(
    cands: Sequence[ImageCandidates], rig: Rig, focal_px: float,
    options: BeamLineOptions = BeamLineOptions(),  # noqa: B008 (frozen dataclass)
) -> BeamLinesResult:
    """Learn one image line per uncalibrated laser from candidates of many images."""
    rng = np.random.default_rng(options.seed)
    tol = options.inlier_px / focal_px
    lines: dict[str, LearnedLine] = {}
    missing: dict[str, str] = {}
    for color, lasers in _group_lasers(rig).items():
        pts, img = _group_points(cands, color)
        if len(np.unique(img)) < options.min_images:
            for las in lasers:
                missing[las.name] = (f"{color} candidates in {len(np.unique(img))} images: "
                                     f"a beam line needs >= {options.min_images}")
            continue
        found = _find_lines(pts, img, pts[:, 0], len(lasers), tol, options, rng)
        if len(found) != len(lasers):
            for las in lasers:
                missing[las.name] = (f"found {len(found)} {color} beam line(s) for "
                                     f"{len(lasers)} uncalibrated {color} laser(s): ambiguous")
            continue
        found.sort(key=lambda f: f.mean_x)
        names = [las.name for las in lasers]
        for las, f in zip(lasers, found, strict=True):
            partner = next((names[k] for k, o in enumerate(found) if o is not f
                            and f.cut is not None and o.cut == f.cut), None)
            lines[las.name] = LearnedLine(
                laser=las.name, point=f.point, direction=f.direction,
                s_range=_segment(f, [o for o in found if o is not f], options, focal_px),
                n_images=int(np.unique(f.images).size), rms_px=f.rms * focal_px,
                shared_with=partner)
            logger.info("learned beam line for %s: %d images, rms %.2f px", las.name,
                        lines[las.name].n_images, lines[las.name].rms_px)
    return BeamLinesResult(lines=lines, missing=missing)


def pseudo_beam(line: LearnedLine, min_range_m: float, max_range_m: float) -> tuple[F64, F64]:
    """(origin (3,), unit direction (3,)) of a 3D beam whose image between the two ranges is
    the learned segment: vanishing point at its far end, origin offset along the line."""
    a, b = line.s_range
    inv_span = 1.0 / min_range_m - 1.0 / max_range_m
    s_vp = a
    for _ in range(20):  # u_z depends (weakly) on the vanishing point: fixed point
        vp = line.point + s_vp * line.direction
        uz = 1.0 / math.sqrt(1.0 + float(vp @ vp))
        k = uz * (b - a) / inv_span
        s_vp = a - k / (max_range_m * uz)
    vp = line.point + s_vp * line.direction
    direction = np.array([vp[0], vp[1], 1.0])
    origin = np.array([k * line.direction[0], k * line.direction[1], 0.0])
    return origin, direction / np.linalg.norm(direction)


def rig_with_learned_lines(rig: Rig, learned: BeamLinesResult, min_range_m: float,
                           max_range_m: float) -> Rig:
    """The rig with each learned laser given its pseudo beam (a detection search aid only)."""
    lasers = []
    for las in rig.lasers:
        line = learned.lines.get(las.name)
        if las.calibrated or line is None:
            lasers.append(las)
            continue
        origin, direction = pseudo_beam(line, min_range_m, max_range_m)
        lasers.append(replace(las, origin=origin, direction=direction))
    return replace(rig, lasers=tuple(lasers))


__all__ = ["BeamLineOptions", "BeamLinesResult", "ImageCandidates", "LearnedLine",
           "image_candidates", "learn_beam_lines", "pseudo_beam", "rig_with_learned_lines"]
