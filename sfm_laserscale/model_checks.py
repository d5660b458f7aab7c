"""Checks that catch the reconstruction's own error, run on the fused scales and the per-image
estimates of a ``scale`` run (docs/DESIGN.md §4, "Checks of the model"):

- methods against each other: FCM against PCM, PCM-joint against FCM, each difference against
  their combined σ (random parts independent; shared rig and intrinsics terms through the
  difference of their gradients);
- per-laser consistency: each laser's FCM scale over the images against the other lasers';
- scale against camera–scene distance: a slope points to a focal error of the model, a
  refraction error (camera or rig calibrated in air, a flat port) or a rig error;
- the model's focal error fitted from the data (:mod:`sfm_laserscale.focal_fit`) and the
  focal-corrected scale (a separate method);
- scale drift: the per-image scale against the position along the model (the principal axis of
  its camera centres), a weighted trend test; when significant, per-segment scales.

Every test uses Student's t or χ² against the stated σ, and widens by the observed scatter (the
Birge ratio) so that a σ that is too small overall does not turn into a trend. Each failed check
becomes a plain-word warning in the report (:mod:`sfm_laserscale.report.model_warnings`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from sfm_laserscale.focal_fit import (
    FocalEstimate,
    FocalFitOptions,
    fit_focal_error,
    fused_focal_sensitivity,
    widen_for_focal,
)
from sfm_laserscale.fusion import (
    FusedScale,
    FusionOptions,
    combine_image,
    fuse,
    leave_one_out_z,
)
from sfm_laserscale.uncertainty import ImageEstimates

F64 = NDArray[np.float64]
#: A laser's image beyond this many σ of its other images: a wrong spot, left out of its check.
OUTLIER_SIGMA = 4.0


@dataclass(frozen=True)
class ModelCheckOptions:
    """Thresholds of the model checks."""

    enabled: bool = True
    z_limit: float = 3.0  # |difference| / combined σ above this: the check fails
    p_value: float = 0.01  # trend tests (distance, drift): significant below this
    min_images_trend: int = 4  # fewer images: no trend test
    min_distance_spread: float = 0.1  # distance range / mean below this: no distance test
    max_segments: int = 3
    min_images_per_segment: int = 2
    # scatter test: an image's one estimate beyond this leave-one-out |z| is a gross error (a
    # wrong spot, reported as fusion's rejection), not a σ understated across the board; left
    # out of the χ² while such estimates are at most ``max_gross_share`` of those tested
    gross_z: float = 8.0
    max_gross_share: float = 0.1
    focal: FocalFitOptions = field(default_factory=FocalFitOptions)


@dataclass(frozen=True)
class Comparison:
    """One method against another: relative difference and its σ (%)."""

    a: str
    b: str
    difference_pct: float  # 100 (a / b − 1)
    sigma_pct: float  # combined σ of the difference, % of b
    z: float
    ok: bool


@dataclass(frozen=True)
class LaserCheck:
    """One laser's FCM scale over the images against the other lasers'."""

    laser: str
    n_images: int
    value: float
    sigma: float
    vs_others_pct: float
    sigma_pct: float
    z: float
    ok: bool


@dataclass(frozen=True)
class Trend:
    """Weighted straight-line fit of per-image relative scale (%) against a coordinate."""

    variable: str  # "distance_m" or "position_m"
    slope_pct: float  # % per metre
    sigma_pct: float  # its σ (widened by the scatter)
    change_pct: float  # slope × the coordinate's range
    p: float
    significant: bool
    n: int
    x: tuple[float, ...]  # per image: coordinate
    y_pct: tuple[float, ...]  # per image: 100 (s_i / s̄ − 1)
    sigma_y_pct: tuple[float, ...]
    images: tuple[str, ...]
    used: tuple[bool, ...]  # kept by fusion


@dataclass(frozen=True)
class ScatterTest:
    """χ² of the checked method's estimates about their image values and of the images about
    the fused value, against their stated σ: the σ of spots, pose or mesh understated."""

    chi2: float
    dof: int
    ratio: float  # √(χ² / dof)
    p: float
    ok: bool
    gross: tuple[str, ...] = ()  # "laser in image" of the gross errors left out of the χ²


@dataclass(frozen=True)
class Segment:
    """The headline method fused over one stretch of the survey."""

    index: int
    position_m: tuple[float, float]
    images: tuple[str, ...]
    fused: FusedScale


@dataclass(frozen=True)
class ModelChecks:
    """Every model check of a run; ``headline`` is the headline after :func:`widen_for_focal`."""

    comparisons: tuple[Comparison, ...]
    lasers: tuple[LaserCheck, ...]
    distance: Trend | None
    focal: FocalEstimate
    headline_gamma: float  # the headline's relative focal sensitivity
    drift: Trend | None
    segments: tuple[Segment, ...]
    drift_outliers: tuple[str, ...]  # images fusion left out that lie in the drift's range
    headline: FusedScale
    method: str  # the method the per-image checks use
    scatter: ScatterTest | None = None
    notes: tuple[str, ...] = ()


# --------------------------------------------------------------------------- comparisons


def _shared_sigma(a: FusedScale, b: FusedScale) -> float:
    """σ of a − b from their shared terms (the difference of their gradients)."""
    names = set(a.systematic_gradient) | set(b.systematic_gradient)
    return math.sqrt(sum((a.systematic_gradient.get(k, 0.0) - b.systematic_gradient.get(k, 0.0))
                         ** 2 for k in names))


def compare(a: FusedScale, b: FusedScale, z_limit: float) -> Comparison | None:
    """a against b (None unless both have a value and a σ)."""
    if not all(math.isfinite(x) for x in (a.value, b.value, a.std, b.std)):
        return None
    ra = a.std_random if math.isfinite(a.std_random) else a.std
    rb = b.std_random if math.isfinite(b.std_random) else b.std
    sigma = math.sqrt(ra**2 + rb**2 + _shared_sigma(a, b) ** 2)
    z = (a.value - b.value) / sigma if sigma > 0 else float("inf")
    return Comparison(a.method, b.method, 100.0 * (a.value / b.value - 1.0),
                      100.0 * sigma / b.value, z, abs(z) <= z_limit)


def comparisons(methods: dict[str, FusedScale], joint: bool, z_limit: float
                ) -> tuple[Comparison, ...]:
    """FCM against PCM, and PCM-joint (when its joint fit ran) against FCM."""
    out = []
    if "fcm" in methods and "pcm" in methods:
        out.append(compare(methods["fcm"], methods["pcm"], z_limit))
    if joint and "fcm" in methods and "pcm_joint" in methods:
        out.append(compare(methods["pcm_joint"], methods["fcm"], z_limit))
    return tuple(c for c in out if c is not None)


# --------------------------------------------------------------------------- lasers


def _laser_values(estimates: Sequence[ImageEstimates], fcm: FusedScale
                  ) -> dict[str, tuple[list[float], list[float], list[dict[str, float]]]]:
    """Per laser: FCM values, random σ and shared gradients of the images fusion kept: every
    estimate the estimators accepted, also those fusion left out within their image (a laser
    that is off in every image is what this check looks for)."""
    used = set(fcm.images_used)
    rejected: set[tuple[str, str]] = set()
    out: dict[str, tuple[list[float], list[float], list[dict[str, float]]]] = {}
    for est in estimates:
        if est.image not in used:
            continue
        cov = np.asarray(est.covariance_random["fcm"])
        jac = np.asarray(est.rig_jacobian["fcm"])
        for i, e in enumerate(est.of("fcm")):
            if e.rejected or (est.image, e.laser) in rejected or not np.isfinite(e.scale):
                continue
            vals, sig, grads = out.setdefault(e.laser, ([], [], []))
            vals.append(e.scale)
            sig.append(float(np.sqrt(cov[i, i])))
            grads.append({p: float(jac[i, k]) for k, p in enumerate(est.rig_params)})
    return out


def _without_outliers(vals: list[float], sig: list[float], grads: list[dict[str, float]],
                      limit: float) -> tuple[list[float], list[float], list[dict[str, float]]]:
    """One laser's values without those beyond ``limit`` σ of the laser's other images (a wrong
    spot in one image is not a laser that is off), worst first, at least two kept."""
    keep = list(range(len(vals)))
    while len(keep) > 2:
        z = []
        for k in keep:
            o = [i for i in keep if i != k]
            m, sm, _ = _mean([vals[i] for i in o], [sig[i] for i in o], [{} for _ in o])
            z.append(abs(vals[k] - m) / math.hypot(sig[k], sm))
        worst = int(np.argmax(z))
        if z[worst] <= limit:
            break
        keep.pop(worst)
    return [vals[i] for i in keep], [sig[i] for i in keep], [grads[i] for i in keep]


def _mean(vals: list[float], sig: list[float], grads: list[dict[str, float]]
          ) -> tuple[float, float, dict[str, float]]:
    """Inverse-variance mean of 1/s, its random σ and its shared gradient (s units)."""
    v, s = np.array(vals), np.array(sig)
    w = (v**2 / s) ** 2  # 1 / σ_u², σ_u = σ_s / s²
    w = w / w.sum()
    value = 1.0 / float(w @ (1.0 / v))
    d = w * value**2 / v**2
    sigma = float(np.sqrt(np.sum((d * s) ** 2)))
    g: dict[str, float] = {}
    for di, gi in zip(d, grads, strict=True):
        for k, x in gi.items():
            g[k] = g.get(k, 0.0) + di * x
    return value, sigma, g


def _vs(laser: str, pool: list[str], means: dict[str, tuple[float, float, dict[str, float]]],
        per: dict[str, tuple[list[float], list[float], list[dict[str, float]]]]
        ) -> tuple[float, float, float]:
    """A laser against the others of ``pool`` together: (difference %, its σ %, z)."""
    v, s, g = means[laser]
    rest = [(x, y, z) for other in pool if other != laser
            for x, y, z in zip(*per[other], strict=True)]
    vo, so, go = _mean([r[0] for r in rest], [r[1] for r in rest], [r[2] for r in rest])
    shared = math.sqrt(sum((g.get(k, 0.0) - go.get(k, 0.0)) ** 2 for k in set(g) | set(go)))
    sigma = math.sqrt(s**2 + so**2 + shared**2)
    z = (v - vo) / sigma if sigma > 0 else float("inf")
    return 100 * (v / vo - 1), 100 * sigma / vo, z


def laser_checks(estimates: Sequence[ImageEstimates], fcm: FusedScale | None, z_limit: float
                 ) -> tuple[LaserCheck, ...]:
    """Each laser's FCM scale over the images against the other lasers' together. The worst
    laser beyond ``z_limit`` is flagged and leaves the reference, iterated (one laser off must
    not make the others look off); the others are compared with the final reference."""
    if fcm is None or not math.isfinite(fcm.value):
        return ()
    per = {la: _without_outliers(*v, limit=OUTLIER_SIGMA)
           for la, v in _laser_values(estimates, fcm).items()}
    if len(per) < 2:
        return ()
    means = {la: _mean(*per[la]) for la in per}
    pool = sorted(per)
    flagged: dict[str, tuple[float, float, float]] = {}
    while len(pool) > 2:
        res = {la: _vs(la, pool, means, per) for la in pool}
        worst = max(pool, key=lambda la: abs(res[la][2]))
        if abs(res[worst][2]) <= z_limit:
            break
        flagged[worst] = res[worst]
        pool.remove(worst)
    out = []
    for la in sorted(per):
        d, sig, z = flagged[la] if la in flagged else _vs(la, pool if la in pool else pool + [la],
                                                          means, per)
        out.append(LaserCheck(la, len(per[la][0]), means[la][0], means[la][1], d, sig, z,
                              abs(z) <= z_limit))
    return tuple(out)


# --------------------------------------------------------------------------- trends


@dataclass(frozen=True)
class ImagePoint:
    """One image's combined value of the checked method and where it was taken."""

    image: str
    value: float
    sigma_random: float
    distance_m: float  # median camera–hit distance
    centre: F64  # (3,) camera centre, model frame
    used: bool  # kept by fusion


def image_points(estimates: Sequence[ImageEstimates], fused: FusedScale, method: str,
                 centres: dict[str, F64], fusion: FusionOptions) -> list[ImagePoint]:
    """Per image: its combined value (random σ) of ``method``, distance and camera centre."""
    used = set(fused.images_used)
    out = []
    for est in estimates:
        c = combine_image(est, method, fusion)
        if c is None or not c.used or not math.isfinite(c.value) or est.image not in centres:
            continue
        depths = [e.depth_m for e in c.used if math.isfinite(e.depth_m)]
        out.append(ImagePoint(est.image, c.value, c.weight_sigma,
                              float(np.median(depths)) if depths else float("nan"),
                              np.asarray(centres[est.image], np.float64), est.image in used))
    return out


def trend(points: Sequence[ImagePoint], x: F64, variable: str, options: ModelCheckOptions,
          reference: float, include_rejected: bool = False) -> Trend | None:
    """Weighted line through 100 (s_i / reference − 1) against x (the points fusion kept, or
    every point with ``include_rejected``)."""
    y = np.array([100 * (p.value / reference - 1) for p in points])
    sy = np.array([100 * p.sigma_random / reference for p in points])
    used = np.array([p.used for p in points])
    ok = (used | include_rejected) & np.isfinite(x) & np.isfinite(y) & (sy > 0)
    n = int(ok.sum())
    if n < options.min_images_trend:
        return None
    w = 1.0 / sy[ok] ** 2
    xm = float(np.sum(w * x[ok]) / w.sum())
    sxx = float(np.sum(w * (x[ok] - xm) ** 2))
    if sxx <= 0:
        return None
    ym = float(np.sum(w * y[ok]) / w.sum())
    slope = float(np.sum(w * (x[ok] - xm) * (y[ok] - ym)) / sxx)
    chi2 = float(np.sum(w * (y[ok] - ym - slope * (x[ok] - xm)) ** 2))
    birge = chi2 / (n - 2) if n > 2 else 1.0
    # the stated σ (normal) unless the scatter exceeds it: then widened, Student's t
    sigma = math.sqrt(max(birge, 1.0) / sxx)
    t_ = abs(slope) / sigma
    p = (float(2 * stats.t.sf(t_, n - 2)) if birge > 1.0 else float(2 * stats.norm.sf(t_))
         ) if n > 2 else float("nan")
    span = float(np.ptp(x[ok]))
    return Trend(variable, slope, sigma, slope * span, p, bool(p < options.p_value), n,
                 tuple(float(v) for v in x), tuple(float(v) for v in y),
                 tuple(float(v) for v in sy), tuple(p_.image for p_ in points),
                 tuple(bool(u) for u in used))


def survey_axis(model_centres: F64) -> tuple[F64, F64]:
    """The model's long axis: the mean of its camera centres and the unit first principal axis."""
    c = np.asarray(model_centres, dtype=np.float64).reshape(-1, 3)
    mean = c.mean(axis=0)
    if len(c) < 2:
        return mean, np.array([1.0, 0.0, 0.0])
    _, _, vt = np.linalg.svd(c - mean, full_matrices=False)
    return mean, np.asarray(vt[0], dtype=np.float64)


def segments(estimates: Sequence[ImageEstimates], points: Sequence[ImagePoint], position: F64,
             method: str, options: ModelCheckOptions, fusion: FusionOptions
             ) -> tuple[Segment, ...]:
    """The headline method fused over equal-count stretches along the survey axis."""
    k = min(options.max_segments, len(points) // options.min_images_per_segment)
    if k < 2:
        return ()
    order = np.argsort(position, kind="stable")
    by_name = {e.image: e for e in estimates}
    out = []
    for i, part in enumerate(np.array_split(order, k)):
        names = tuple(points[j].image for j in part)
        fused = fuse([by_name[n] for n in names], method, fusion)
        out.append(Segment(i + 1, (float(position[part].min()), float(position[part].max())),
                           names, fused))
    return tuple(out)


@dataclass(frozen=True)
class _WithinImage:
    """One image's χ² about its GLS mean, with and without its gross error (if any)."""

    chi2: float
    dof: int
    chi2_trimmed: float
    dof_trimmed: int
    gross: str | None  # "laser in image" of the estimate left out of the trimmed χ²
    n: int  # estimates tested


def _gls_chi2(u: F64, cov: F64) -> float:
    w = np.linalg.pinv(cov, hermitian=True)
    ones = np.ones(len(u))
    r = u - float(ones @ w @ u) / float(ones @ w @ ones)
    return max(float(r @ w @ r), 0.0)


def _within_chi2(est: ImageEstimates, method: str, gross_z: float) -> _WithinImage:
    """χ² (and dof) of an image's estimates that the estimators accepted (also those fusion
    left out as inconsistent) about their GLS mean, in 1/s with their full covariance; and the
    same without its worst estimate when that one lies beyond ``gross_z`` (leave-one-out, with
    at least 3 estimates: with 2 the culprit is unknown)."""
    ests = est.of(method)
    keep = [i for i, e in enumerate(ests) if not e.rejected and math.isfinite(e.scale)
            and math.isfinite(e.sigma) and e.sigma > 0 and e.scale > 0]
    if len(keep) < 2:
        return _WithinImage(0.0, 0, 0.0, 0, None, len(keep))
    v = np.array([ests[i].scale for i in keep])
    d = 1.0 / v**2
    cov = np.asarray(est.covariance[method])[np.ix_(keep, keep)] * np.outer(d, d)
    u = 1.0 / v
    chi2 = _gls_chi2(u, cov)
    if len(keep) >= 3:
        z = leave_one_out_z(u, cov)
        k = int(np.argmax(z))
        if z[k] > gross_z:
            o = np.delete(np.arange(len(keep)), k)
            return _WithinImage(chi2, len(keep) - 1, _gls_chi2(u[o], cov[np.ix_(o, o)]),
                                len(keep) - 2, f"{ests[keep[k]].laser} in {est.image}",
                                len(keep))
    return _WithinImage(chi2, len(keep) - 1, chi2, len(keep) - 1, None, len(keep))


def scatter_test(estimates: Sequence[ImageEstimates], fused: FusedScale, method: str,
                 options: ModelCheckOptions, fusion: FusionOptions) -> ScatterTest | None:
    """Within-image χ² of the images fusion kept (every accepted estimate: a spot fusion left
    out is evidence too) plus the between-image χ², one test. An image's single gross error
    (beyond ``gross_z``) is left out while such errors are at most ``max_gross_share`` of the
    estimates: one wrong spot is not a σ understated across the board (fusion reports it)."""
    used = set(fused.images_used)
    parts = [_within_chi2(est, method, options.gross_z) for est in estimates
             if est.image in used]
    gross = tuple(w.gross for w in parts if w.gross is not None)
    trim = bool(gross) and len(gross) <= options.max_gross_share * sum(w.n for w in parts)
    chi2 = sum(w.chi2_trimmed if trim else w.chi2 for w in parts)
    dof = sum(w.dof_trimmed if trim else w.dof for w in parts)
    n = len(used)
    if n > 1 and math.isfinite(fused.birge_ratio):
        chi2 += fused.birge_ratio**2 * (n - 1)
        dof += n - 1
    if dof == 0:
        return None
    p = float(stats.chi2.sf(chi2, dof))
    return ScatterTest(chi2, dof, math.sqrt(chi2 / dof), p, p >= options.p_value,
                       gross if trim else ())


# --------------------------------------------------------------------------- all checks


def _method(methods: dict[str, FusedScale], headline: FusedScale) -> str:
    """The method of the per-image checks: the headline's, or FCM/PCM for PCM-joint."""
    if headline.method in ("fcm", "pcm", "direct3d"):
        return headline.method
    return "fcm" if "fcm" in methods and math.isfinite(methods["fcm"].value) else "pcm"


def run_model_checks(estimates: Sequence[ImageEstimates], methods: dict[str, FusedScale],
                     headline: FusedScale, joint: bool, centres: dict[str, F64],
                     model_centres: F64, model_focal_sigma: float, options: ModelCheckOptions,
                     fusion: FusionOptions) -> ModelChecks:
    """Every model check; ``centres``: laser image -> camera centre (model frame)."""
    focal = fit_focal_error(estimates, methods, options.focal, fusion, joint)
    gamma = fused_focal_sensitivity(estimates, headline, headline.method) if (
        headline.method in ("fcm", "pcm", "direct3d")) else float("nan")
    widened = widen_for_focal(headline, gamma, focal, model_focal_sigma if math.isfinite(
        model_focal_sigma) else 0.0, fusion)
    method = _method(methods, headline)
    fused = methods[method]
    points = image_points(estimates, fused, method, centres, fusion)
    ref = fused.value if math.isfinite(fused.value) else float("nan")
    dist = None
    if points and math.isfinite(ref):
        d = np.array([p.distance_m for p in points])
        spread = float(np.ptp(d[np.isfinite(d)])) / float(np.nanmean(d)) if np.isfinite(
            d).any() else 0.0
        dist = trend(points, d, "distance_m", options, ref) if (
            spread >= options.min_distance_spread) else None
    drift, segs, outliers = _drift(estimates, points, model_centres, method, ref, options,
                                   fusion)
    return ModelChecks(comparisons(methods, joint, options.z_limit),
                       laser_checks(estimates, methods.get("fcm"), options.z_limit), dist,
                       focal, gamma, drift, segs, outliers, widened, method,
                       scatter_test(estimates, fused, method, options, fusion))


def _drift(estimates: Sequence[ImageEstimates], points: Sequence[ImagePoint],
           model_centres: F64, method: str, ref: float, options: ModelCheckOptions,
           fusion: FusionOptions) -> tuple[Trend | None, tuple[Segment, ...], tuple[str, ...]]:
    """Trend along the survey axis (metres at the reference scale), segments when significant,
    and the images fusion left out that lie within the drifting stretch."""
    if not points or not math.isfinite(ref):
        return None, (), ()
    mean, axis = survey_axis(model_centres)
    pos = np.array([float((p.centre - mean) @ axis) * ref for p in points])
    drift = trend(points, pos, "position_m", options, ref, include_rejected=True)
    if drift is None or not drift.significant:
        return drift, (), ()
    segs = segments(estimates, points, pos, method, options, fusion)
    outliers = tuple(p.image for p in points if not p.used)
    return drift, segs, outliers
