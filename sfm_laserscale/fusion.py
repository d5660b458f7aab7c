"""Robust fusion of per-image scale estimates into one scale with a calibrated interval.

Error model: estimate j of image i is s + e_ij + g_ij·δ, where e_i (spots + pose) is random,
correlated within an image (shared pose) and independent between images, and δ (rig
calibration, unit-σ parameters) is COMMON to all images.

Means are taken of u = 1/s (model units per metre) with σ_u = σ_s/s²: a spot's σ grows with
the draw itself (FCM triangulates the range D with σ_D ∝ D², so σ_s ∝ s²), so inverse-variance
weights of s favour the low draws and bias the mean low (−0.03 to −0.05 σ measured). 1/s is
linear in the spot's disparity, its σ does not depend on the draw (FCM: σ_u ∝ σ_D/D² constant;
PCM: u ∝ the model distance of the two hits), and 1/ū is biased by σ_rel² only (1e-6 at 0.1 %).

1. Per image: GLS mean of its non-rejected estimates with their joint covariance (so the shared
   pose error is not averaged away); with >= 3 estimates, an estimate whose leave-one-out
   residual exceeds ``within_image_threshold`` σ is rejected first (iterated).
2. Across images: the worst image is rejected while its normalised residual from the weighted
   median exceeds ``outlier_threshold`` robust sigmas (robust sigma = max(1, 1.4826·MAD) of the
   normalised residuals; needs >= ``min_images_for_rejection`` images), iterated.
3. Inverse-variance mean of the kept images (random σ only). χ² of the images about it with
   their full covariance (random + rig), Birge ratio R = √(χ²/dof). Only when the scatter is
   improbable under the stated σ (P(χ²_dof ≥ χ²) < ``birge_p_value``) is the random σ inflated
   by R and the interval taken from Student's t with dof = n − 1 (for one image: the
   within-image χ²). Inflating whenever R > 1 would widen half of all consistent fusions (the
   σ would be 5–15 % too large and the 95 % interval would hold the truth 97 % of the time).
4. The shared terms (rig calibration and the model's intrinsics, ``rig_params``) are propagated
   through the mean's gradient and added AFTER averaging: σ² = (R⁺σ_rand)² + σ_sys²,
   half-width = √((q σ_rand_eff)² + (z σ_sys)²).

The error budget (``FusedScale.budget``) splits σ² term by term: the random terms (spots, pose,
mesh) through the same weights, the Birge widening as ``scatter``, and the shared terms (rig,
intrinsics) through the mean's gradient.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from sfm_laserscale.model_error import RANDOM_TERMS, SCATTER_TERM, SHARED_TERMS, term_of
from sfm_laserscale.uncertainty import METHODS, Estimate, ImageEstimates

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class FusionOptions:
    """Options of :func:`fuse`."""

    outlier_threshold: float = 3.5  # robust sigmas, across images
    within_image_threshold: float = 3.5  # σ of the leave-one-out residual, within an image
    min_images_for_rejection: int = 3  # fewer images: no cross-image rejection possible
    min_estimates: int = 1  # fewer usable estimates: no scale (value NaN)
    confidence: float = 0.95
    birge_p_value: float = 0.01  # inflate σ only when the scatter is this improbable


@dataclass(frozen=True)
class ImageCombination:
    """GLS combination of one image's estimates of one method."""

    image: str
    value: float  # m per model unit
    sigma_random: float  # spots + pose
    rig_gradient: F64  # (R,) d value / d unit-σ rig parameter (ordered as rig_params)
    rig_params: tuple[str, ...]
    used: tuple[Estimate, ...]
    rejected: tuple[tuple[str, str], ...]  # (laser, reason) rejected here or before
    chi2: float  # within-image χ² of the used estimates about the GLS mean
    dof: int
    random_terms: dict[str, float] = field(default_factory=dict)  # term -> variance (s units)

    @property
    def sigma(self) -> float:
        """Total σ of the image value (random and rig)."""
        return float(np.hypot(self.sigma_random, np.linalg.norm(self.rig_gradient)))

    @property
    def weight_sigma(self) -> float:
        """σ that weights this image across images: the random part (the total if it is 0)."""
        return self.sigma_random if self.sigma_random > 0 else self.sigma


@dataclass(frozen=True)
class FusedScale:
    """The fused scale of one method, its uncertainty and what was rejected."""

    value: float  # metres per model unit (NaN when nothing is left)
    std: float  # total 1-σ: inflated random part and common rig part
    ci95: tuple[float, float]
    inverse: float  # model units per metre
    method: str
    n_estimates: int  # estimates used
    n_rejected: int  # estimates rejected (before or during fusion)
    per_image: dict[str, tuple[float, float]]  # every combined image: (value, total σ)
    rejected: list[tuple[str, str, str]]  # (image, laser, reason)
    notes: list[str] = field(default_factory=list)
    std_random: float = float("nan")  # after Birge inflation
    std_systematic: float = float("nan")  # common rig calibration part
    birge_ratio: float = float("nan")
    birge_p: float = float("nan")  # P(χ² >= observed) of the images' scatter
    inflated: bool = False  # random σ inflated by the Birge ratio
    images_used: tuple[str, ...] = ()
    reason: str | None = None  # why there is no value
    budget: dict[str, float] = field(default_factory=dict)  # term -> variance (s units)
    systematic_gradient: dict[str, float] = field(default_factory=dict)  # shared param -> ds

    def budget_shares(self) -> dict[str, float]:
        """Each term's share of std² (they sum to 1; empty without a budget)."""
        total = sum(self.budget.values())
        return {k: v / total for k, v in self.budget.items()} if total > 0 else {}


def error_budget(random_terms: dict[str, float], sigma_random: float, inflated_sigma: float,
                 gradient: dict[str, float]) -> dict[str, float]:
    """Variance per term: the random terms scaled to ``sigma_random``² (their sum), the Birge
    widening (``inflated_sigma``² − ``sigma_random``²) and the shared terms from the gradient."""
    out = dict.fromkeys((*RANDOM_TERMS, SCATTER_TERM, *SHARED_TERMS), 0.0)
    total = sum(random_terms.values())
    for term, var in random_terms.items():
        out[term] = var / total * sigma_random**2 if total > 0 else 0.0
    if total <= 0 and sigma_random > 0:  # estimates without a term-by-term covariance
        out["random"] = sigma_random**2
    out[SCATTER_TERM] = max(inflated_sigma**2 - sigma_random**2, 0.0)
    for param, g in gradient.items():
        out[term_of(param)] += g * g
    return out


def _gls(values: F64, cov: F64) -> tuple[F64, float]:
    """GLS weights (n,) (summing to 1) and the χ² of values about the weighted mean."""
    rhs = np.column_stack([np.ones(len(values)), values])
    try:
        sol = np.linalg.solve(cov, rhs)
    except np.linalg.LinAlgError:
        sol = np.linalg.pinv(cov) @ rhs
    cinv_1, cinv_v = sol[:, 0], sol[:, 1]
    w = cinv_1 / cinv_1.sum()
    chi2 = float(values @ cinv_v - cinv_v.sum() ** 2 / cinv_1.sum())
    return w, (max(chi2, 0.0) if np.isfinite(chi2) else 0.0)


def leave_one_out_z(values: F64, cov: F64) -> F64:
    """|s_k − GLS mean of the others| / σ of that difference, for each k."""
    z = np.zeros(len(values))
    for k in range(len(values)):
        o = np.delete(np.arange(len(values)), k)
        w, _ = _gls(values[o], cov[np.ix_(o, o)])
        a = np.zeros(len(values))
        a[k], a[o] = 1.0, -w
        var = float(a @ cov @ a)
        z[k] = abs(a @ values) / np.sqrt(var) if var > 0 else np.inf
    return z


def _usable(ests: tuple[Estimate, ...]) -> tuple[list[int], list[tuple[str, str]]]:
    """Indices of usable estimates and (laser, reason) of the others."""
    keep, rej = [], []
    for i, e in enumerate(ests):
        if e.rejected:
            rej.append((e.laser, e.reason or "rejected"))
        elif not (np.isfinite(e.scale) and np.isfinite(e.sigma) and e.sigma > 0):
            rej.append((e.laser, "no finite estimate with positive sigma"))
        elif e.scale <= 0:
            rej.append((e.laser, f"non-positive scale {e.scale:.4g}"))
        else:
            keep.append(i)
    return keep, rej


def _inverse(values: F64, cov: F64, jac: F64) -> tuple[F64, F64, F64]:
    """u = 1/s (n,), its covariance (n, n) and rig Jacobian (n, R): du = −ds / s²."""
    with np.errstate(invalid="ignore", divide="ignore"):
        u = 1.0 / values
    d = -(u**2)
    return u, cov * np.outer(d, d), jac * d[:, None]


def combine_image(est: ImageEstimates, method: str, options: FusionOptions
                  ) -> ImageCombination | None:
    """GLS combination of one image's estimates of one method (None if none is usable)."""
    ests = est.of(method)
    keep, rej = _usable(ests)
    if not ests:
        return None
    values = np.array([e.scale for e in ests])
    u, c_rand, g_all = _inverse(values, np.asarray(est.covariance_random[method]),
                                np.asarray(est.rig_jacobian[method]))
    c_tot = c_rand + g_all @ g_all.T
    while len(keep) >= 3:
        z = leave_one_out_z(u[keep], c_tot[np.ix_(keep, keep)])
        worst = int(np.argmax(z))
        if z[worst] <= options.within_image_threshold:
            break
        e = ests[keep.pop(worst)]
        rej.append((e.laser, f"inconsistent with the image's other {method} estimates "
                             f"({z[worst]:.1f} sigma)"))
    if not keep:
        return ImageCombination(est.image, np.nan, np.nan, np.zeros(len(est.rig_params)),
                                est.rig_params, (), tuple(rej), 0.0, 0) if rej else None
    w, chi2 = _gls(u[keep], c_tot[np.ix_(keep, keep)])
    value = 1.0 / float(w @ u[keep])
    sigma_u = float(np.sqrt(max(float(w @ c_rand[np.ix_(keep, keep)] @ w), 0.0)))
    return ImageCombination(est.image, value, sigma_u * value**2,
                            -(value**2) * (w @ g_all[keep]), est.rig_params,
                            tuple(ests[i] for i in keep), tuple(rej), chi2, len(keep) - 1,
                            _image_terms(est, method, values, keep, w, value))


def _image_terms(est: ImageEstimates, method: str, values: F64, keep: list[int], w: F64,
                 value: float) -> dict[str, float]:
    """Variance of the image's value (s units) per random term, through the GLS weights."""
    terms = est.covariance_terms.get(method, {}) if est.covariance_terms else {}
    d = value**2 / values[keep] ** 2  # ds = value² Σ w_j du_j, du_j = −ds_j / s_j²
    out = {}
    for term, cov in terms.items():
        c = np.asarray(cov)[np.ix_(keep, keep)]
        out[term] = max(float((w * d) @ c @ (w * d)), 0.0)
    return out


def _align_rig(combos: list[ImageCombination]) -> tuple[F64, tuple[str, ...]]:
    """(n, R) rig gradients of all images on the union of their rig parameter names."""
    names: list[str] = []
    for c in combos:
        names += [p for p in c.rig_params if p not in names]
    g = np.zeros((len(combos), len(names)))
    for i, c in enumerate(combos):
        for j, p in enumerate(c.rig_params):
            g[i, names.index(p)] = c.rig_gradient[j]
    return g, tuple(names)


def _weighted_median(values: F64, weights: F64) -> float:
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])


def _reject_images(combos: list[ImageCombination], options: FusionOptions
                   ) -> tuple[list[ImageCombination], list[tuple[ImageCombination, str]]]:
    """Iteratively drop the worst image beyond the robust threshold."""
    kept = list(combos)
    dropped: list[tuple[ImageCombination, str]] = []
    while len(kept) >= max(3, options.min_images_for_rejection):
        v = np.array([c.value for c in kept])
        s = np.array([c.weight_sigma for c in kept])
        centre = _weighted_median(v, 1.0 / s**2)
        z = (v - centre) / s
        spread = max(1.0, 1.4826 * float(np.median(np.abs(z))))
        worst = int(np.argmax(np.abs(z)))
        if abs(z[worst]) <= options.outlier_threshold * spread:
            break
        c = kept.pop(worst)
        dropped.append((c, f"image scale {c.value:.6g} deviates from the consensus "
                           f"{centre:.6g} by {abs(z[worst]) / spread:.1f} robust sigmas"))
    return kept, dropped


def _chi2(combos: list[ImageCombination], u: F64, w: F64, c_u: F64) -> tuple[float, int]:
    """χ² and dof of the kept images' u = 1/s (n,) about their weighted mean, with their full
    (n, n) covariance c_u (random + rig); for one image, its within-image χ²."""
    n = len(combos)
    if n == 1:
        c = combos[0]
        return (c.chi2, c.dof) if c.dof > 0 else (float("nan"), 0)
    p = np.eye(n) - np.outer(np.ones(n), w)
    r = p @ u
    chi2 = float(r @ np.linalg.pinv(p @ c_u @ p.T, rcond=1e-10, hermitian=True) @ r)
    return max(chi2, 0.0), n - 1


def _nothing(method: str, reason: str, n_rej: int, rejected: list[tuple[str, str, str]],
             per_image: dict[str, tuple[float, float]]) -> FusedScale:
    nan = float("nan")
    return FusedScale(nan, nan, (nan, nan), nan, method, 0, n_rej, per_image, rejected,
                      [reason], reason=reason)


def fuse(estimates: Sequence[ImageEstimates], method: str, options: FusionOptions) -> FusedScale:
    """Fuse all images' estimates of one method into one scale with a calibrated interval."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r} (known: {', '.join(METHODS)})")
    combos, rejected = [], []
    for est in estimates:
        c = combine_image(est, method, options)
        if c is None:
            continue
        rejected += [(est.image, laser, reason) for laser, reason in c.rejected]
        if c.used:
            combos.append(c)
    kept, dropped = _reject_images(combos, options)
    for c, reason in dropped:
        rejected += [(c.image, e.laser, reason) for e in c.used]
    per_image = {c.image: (c.value, c.sigma) for c in combos}
    n_used = sum(len(c.used) for c in kept)
    if not kept or n_used < options.min_estimates:
        why = (f"no usable {method} estimate" if not kept else
               f"only {n_used} usable {method} estimate(s), need {options.min_estimates}")
        return _nothing(method, why, len(rejected), rejected, per_image)
    return _combine_images(kept, method, options, n_used, rejected, per_image)


@dataclass(frozen=True)
class Interval:
    """σ and confidence half-width of a fused value after the scatter test."""

    sigma_random: float  # inflated by the Birge ratio when the scatter is improbable
    std: float  # total: random and common rig parts
    half_width: float  # of the ``confidence`` interval
    birge_ratio: float  # √(χ²/dof), NaN without dof
    p_value: float  # P(χ²_dof ≥ χ²), NaN without dof
    inflated: bool
    notes: tuple[str, ...]


def interval(sigma_random: float, sigma_systematic: float, chi2: float, dof: int,
             options: FusionOptions, allow_inflation: bool = True) -> Interval:
    """Scatter test and interval: the random σ is inflated by the Birge ratio (and Student's t
    used) only when P(χ²_dof ≥ χ²) < ``birge_p_value``; the rig part is added after."""
    birge = float(np.sqrt(chi2 / dof)) if dof > 0 else float("nan")
    p_value = float(stats.chi2.sf(chi2, dof)) if dof > 0 else float("nan")
    alpha = 1.0 - options.confidence
    z = float(stats.norm.ppf(1.0 - alpha / 2))
    inflated = bool(allow_inflation and np.isfinite(p_value) and p_value < options.birge_p_value
                    and birge > 1.0)
    q, sigma_eff = z, sigma_random
    notes: tuple[str, ...] = ()
    if inflated:
        q, sigma_eff = float(stats.t.ppf(1.0 - alpha / 2, dof)), sigma_random * birge
        notes = (f"scatter beyond the stated sigmas (Birge ratio {birge:.2f}, dof {dof}, "
                 f"p = {p_value:.2g}): random sigma inflated, Student t interval",)
    return Interval(sigma_eff, float(np.hypot(sigma_eff, sigma_systematic)),
                    float(np.hypot(q * sigma_eff, z * sigma_systematic)), birge, p_value,
                    inflated, notes)


def _combine_images(kept: list[ImageCombination], method: str, options: FusionOptions,
                    n_used: int, rejected: list[tuple[str, str, str]],
                    per_image: dict[str, tuple[float, float]]) -> FusedScale:
    """Inverse-variance mean of u = 1/s, Birge inflation, systematic rig term and interval."""
    v = np.array([c.value for c in kept])
    u, c_u, g_u = _inverse(v, np.diag([c.weight_sigma**2 for c in kept]), _align_rig(kept)[0])
    w = (1.0 / np.diag(c_u)) / np.sum(1.0 / np.diag(c_u))
    value = 1.0 / float(w @ u)
    rand_u = np.array([c.sigma_random for c in kept]) / v**2  # (n,) random σ of u
    sigma_rand = value**2 * float(np.sqrt(w**2 @ rand_u**2))
    sigma_sys = value**2 * float(np.linalg.norm(w @ g_u))
    chi2, dof = _chi2(kept, u, w, c_u + g_u @ g_u.T)
    iv = interval(sigma_rand, sigma_sys, chi2, dof, options)
    names = _align_rig(kept)[1]
    gradient = dict(zip(names, (value**2 * (w @ g_u)).tolist(), strict=True))
    terms: dict[str, float] = {}
    for wi, c in zip(w, kept, strict=True):
        scale = (value**2 / c.value**2) ** 2 * wi**2
        for term, var in c.random_terms.items():
            terms[term] = terms.get(term, 0.0) + scale * var
    notes = [f"{len(kept)} image(s), {n_used} estimate(s); shared term (rig calibration, "
             f"model intrinsics) {sigma_sys:.3g} (does not average down)", *iv.notes]
    std, half, birge, p_value = iv.std, iv.half_width, iv.birge_ratio, iv.p_value
    logger.debug("fused %s: %.6g ± %.3g (birge %.2f, p %.3g)", method, value, std, birge,
                 p_value)
    return FusedScale(value, std, (value - half, value + half), 1.0 / value, method, n_used,
                      len(rejected), per_image, rejected, notes, iv.sigma_random, sigma_sys,
                      birge, p_value, iv.inflated, tuple(c.image for c in kept), None,
                      error_budget(terms, sigma_rand, iv.sigma_random, gradient), gradient)
