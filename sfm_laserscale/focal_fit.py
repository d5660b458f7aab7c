"""The SfM model's focal-length error estimated from the laser data, and the scale corrected for it.

A relative focal error ε of the model moves estimate j by s_j ≈ s (1 + γ_j ε), with γ_j its
focal sensitivity (``ImageEstimates.focal_sensitivity`` / s_j, from the model's response to its
intrinsics, :mod:`sfm_laserscale.registration.covariance`). FCM's γ grows with the range and
depends on the beam's tilt relative to its origin; PCM's is close to 0 for a camera between
parallel beams. Where the γ of the data differ (calibrated beams at several ranges or of several
tilts, or FCM beside PCM), ε is identifiable: with u_j = 1 / s_j = a + b γ_j (a = 1/s, b = −ε/s
to first order), GLS over

- every FCM estimate the estimators accepted, of the images FCM fusion kept (also those it
  left out as inconsistent within their image: beams of different γ disagree under a focal
  error), with their joint covariance (random per image; the rig's shared part), estimates
  beyond ``outlier_sigma`` of the fit of the others left out worst first, and
- the PCM-type value (PCM-joint when its joint fit ran, else the fused PCM) as one more datum,
  independent of the FCM estimates (they share spots; ignoring it overstates σ(ε̂) a little),

gives ε̂ = −b/a with its σ (Birge-widened when the scatter about the fit is improbable), and
the corrected scale 1/a: method ``focal_corrected``, offered beside the others; it never
replaces the headline. The model's own σ(δf / f) is a prior on ε; where the data's ε̂ makes
the focal error's RMS larger than it (:func:`focal_rms`), the headline's σ gets the excess
(:func:`widen_for_focal`, with a note): the model's focal error as the data measured it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from sfm_laserscale.fusion import FusedScale, FusionOptions, interval
from sfm_laserscale.model_error import term_of
from sfm_laserscale.uncertainty import ImageEstimates

F64 = NDArray[np.float64]
METHOD = "focal_corrected"


@dataclass(frozen=True)
class FocalFitOptions:
    """Options of :func:`fit_focal_error`."""

    min_estimates: int = 3
    max_sigma: float = 0.01  # σ(ε̂) above this: the data do not determine the focal error
    significance: float = 3.0  # |ε̂| / σ(ε̂) above this: a significant focal error
    outlier_sigma: float = 4.0  # leave-one-out residual beyond this: the estimate is left out


@dataclass(frozen=True)
class FocalEstimate:
    """The model's focal error estimated from the laser data (NaN: not determined)."""

    focal_error: float  # ε̂ = δf / f
    sigma: float  # σ(ε̂), Birge-widened when needed
    z: float  # ε̂ / σ
    significant: bool
    n_estimates: int
    sources: tuple[str, ...]  # "fcm" (several beams or ranges), "pcm", "pcm_joint"
    gamma_range: tuple[float, float]  # min, max of the data's focal sensitivity γ
    chi2: float
    dof: int
    corrected: FusedScale | None  # method "focal_corrected" (None when not determined)
    reason: str | None = None  # why it was not determined


@dataclass(frozen=True)
class _Data:
    values: F64  # (n,) scales
    gamma: F64  # (n,) relative focal sensitivities
    cov: F64  # (n, n) covariance (random + shared rig), s units
    images: tuple[str, ...]
    sources: tuple[str, ...]


def _fcm_data(estimates: Sequence[ImageEstimates], fcm: FusedScale) -> _Data:
    """FCM estimates of the images FCM fusion kept, their γ and joint covariance: every estimate
    the estimators accepted, also those fusion left out as inconsistent within their image (a
    focal error makes beams of different γ disagree: those carry the information)."""
    used = set(fcm.images_used)
    rejected: set[tuple[str, str]] = set()
    vals: list[float] = []
    gam: list[float] = []
    blocks: list[F64] = []
    rig_rows: list[dict[str, float]] = []
    names: list[str] = []
    for est in estimates:
        sens = est.focal_sensitivity.get("fcm") if est.focal_sensitivity else None
        if est.image not in used or sens is None:
            continue
        ests = est.of("fcm")
        keep = [i for i, e in enumerate(ests) if not e.rejected and np.isfinite(e.scale)
                and np.isfinite(sens[i]) and (est.image, e.laser) not in rejected]
        if not keep:
            continue
        vals += [ests[i].scale for i in keep]
        gam += [float(sens[i]) / ests[i].scale for i in keep]
        blocks.append(np.asarray(est.covariance_random["fcm"])[np.ix_(keep, keep)])
        jac = np.asarray(est.rig_jacobian["fcm"])
        for i in keep:
            rig_rows.append({p: float(jac[i, k]) for k, p in enumerate(est.rig_params)
                             if term_of(p) == "rig"})
        names += [est.image] * len(keep)
    n = len(vals)
    cov = np.zeros((n, n))
    at = 0
    for b in blocks:
        cov[at:at + len(b), at:at + len(b)] = b
        at += len(b)
    params = sorted({p for row in rig_rows for p in row})
    g = np.array([[row.get(p, 0.0) for p in params] for row in rig_rows]).reshape(
        n, len(params))
    return _Data(np.array(vals), np.array(gam), cov + g @ g.T, tuple(names),
                 ("fcm",) if n else ())


def _pair_datum(methods: dict[str, FusedScale], estimates: Sequence[ImageEstimates],
                joint: bool) -> tuple[str, float, float, float] | None:
    """(method, value, σ, γ) of the PCM-type value, or None: PCM-joint when its joint fit ran
    (``joint``), else PCM; γ from the per-image PCM sensitivities (weighted by their σ⁻²)."""
    name = "pcm_joint" if joint and "pcm_joint" in methods else "pcm"
    f = methods.get(name)
    if f is None or not (np.isfinite(f.value) and np.isfinite(f.std) and f.std > 0):
        return None
    num = den = 0.0
    for est in estimates:
        sens = est.focal_sensitivity.get("pcm") if est.focal_sensitivity else None
        if sens is None:
            continue
        for e, g in zip(est.of("pcm"), sens, strict=True):
            if not e.rejected and np.isfinite(g) and np.isfinite(e.sigma) and e.sigma > 0:
                num += g / e.scale / e.sigma**2
                den += 1.0 / e.sigma**2
    if den == 0:
        return None
    return name, f.value, f.std, num / den


def _with_pair(data: _Data, pair: tuple[str, float, float, float] | None) -> _Data:
    if pair is None:
        return data
    name, value, sigma, gamma = pair
    n = len(data.values)
    cov = np.zeros((n + 1, n + 1))
    cov[:n, :n] = data.cov
    cov[n, n] = sigma**2
    return _Data(np.append(data.values, value), np.append(data.gamma, gamma), cov,
                 (*data.images, name), (*data.sources, name))


def _not_determined(data: _Data, reason: str) -> FocalEstimate:
    nan = float("nan")
    rng = (float(data.gamma.min()), float(data.gamma.max())) if len(data.gamma) else (nan, nan)
    return FocalEstimate(nan, nan, nan, False, len(data.values), data.sources, rng, nan, 0, None,
                         reason)


def _gls(u: F64, x: F64, cov: F64) -> tuple[F64, F64, float]:
    """GLS of u = x θ: θ (2,), its covariance (2, 2) and the χ² of the residuals."""
    w = np.linalg.pinv(cov, hermitian=True)
    h = x.T @ w @ x
    h_inv = np.asarray(np.linalg.inv(h), dtype=np.float64)
    theta = np.asarray(h_inv @ x.T @ w @ u, dtype=np.float64)
    r = u - x @ theta
    return theta, h_inv, float(r @ w @ r)


def _robust(u: F64, x: F64, cov: F64, options: FocalFitOptions) -> NDArray[np.intp]:
    """Indices kept after dropping, worst first, estimates whose residual from the fit of the
    others exceeds ``outlier_sigma`` (a wrong spot is no focal error), at most a quarter."""
    keep = list(range(len(u)))
    while len(keep) > max(options.min_estimates, 3) and len(keep) > 0.75 * len(u):
        z = np.zeros(len(keep))
        for j in range(len(keep)):
            o = [k for i, k in enumerate(keep) if i != j]
            theta, cov_t, _ = _gls(u[o], x[o], cov[np.ix_(o, o)])
            var = cov[keep[j], keep[j]] + float(x[keep[j]] @ cov_t @ x[keep[j]])
            z[j] = abs(u[keep[j]] - float(x[keep[j]] @ theta)) / np.sqrt(var)
        worst = int(np.argmax(z))
        if z[worst] <= options.outlier_sigma:
            break
        keep.pop(worst)
    return np.array(keep, dtype=np.intp)


def fit_focal_error(estimates: Sequence[ImageEstimates], methods: dict[str, FusedScale],
                    options: FocalFitOptions, fusion: FusionOptions, joint: bool = False
                    ) -> FocalEstimate:
    """ε̂ and the focal-corrected scale from the FCM estimates and the PCM-type value
    (``joint``: PCM-joint's joint fit ran, so it is the PCM-type value)."""
    fcm = methods.get("fcm")
    data = _fcm_data(estimates, fcm) if fcm is not None else _Data(
        np.zeros(0), np.zeros(0), np.zeros((0, 0)), (), ())
    data = _with_pair(data, _pair_datum(methods, estimates, joint))
    if len(data.values) < options.min_estimates:
        return _not_determined(data, f"only {len(data.values)} estimate(s) with a focal "
                                     f"sensitivity (need {options.min_estimates})")
    d = 1.0 / data.values**2
    u, cov_u = 1.0 / data.values, data.cov * np.outer(d, d)
    x = np.column_stack([np.ones(len(u)), data.gamma])
    if float(np.ptp(data.gamma)) < 1e-6:
        return _not_determined(data, "every estimate responds alike to the focal length")
    keep = _robust(u, x, cov_u, options)
    data = _Data(data.values[keep], data.gamma[keep], data.cov[np.ix_(keep, keep)],
                 tuple(data.images[i] for i in keep), data.sources)
    u, cov_u, x = u[keep], cov_u[np.ix_(keep, keep)], x[keep]
    theta, cov_t, chi2 = _gls(u, x, cov_u)
    a, b = float(theta[0]), float(theta[1])
    grad = np.array([b / a**2, -1.0 / a])
    dof = len(u) - 2
    iv = interval(float(np.sqrt(max(grad @ cov_t @ grad, 0.0))), 0.0, chi2, dof, fusion)
    eps, sigma = -b / a, iv.sigma_random
    if not sigma <= options.max_sigma:
        return _not_determined(data, f"the data determine the focal error only to "
                                     f"±{100 * sigma:.2g} %")
    return FocalEstimate(eps, sigma, eps / sigma, abs(eps) > options.significance * sigma,
                         len(u), tuple(dict.fromkeys(data.sources)),
                         (float(data.gamma.min()), float(data.gamma.max())), chi2, dof,
                         _corrected(a, cov_t, chi2, dof, data, fusion))


def _corrected(a: float, cov_t: F64, chi2: float, dof: int, data: _Data, fusion: FusionOptions
               ) -> FusedScale:
    """The scale 1/a of the fit as a method of its own (random and rig parts together)."""
    value = 1.0 / a
    iv = interval(float(np.sqrt(cov_t[0, 0])) * value**2, 0.0, chi2, dof, fusion)
    half = iv.half_width
    images = tuple(dict.fromkeys(i for i in data.images if i not in ("pcm", "pcm_joint")))
    notes = [f"scale with the model's focal error fitted ({len(data.values)} estimates: "
             f"{', '.join(dict.fromkeys(data.sources))}); offered beside the headline, never "
             "replacing it", *iv.notes]
    return FusedScale(value, iv.std, (value - half, value + half), 1.0 / value, METHOD,
                      len(data.values), 0, {}, [], notes, iv.sigma_random, 0.0, iv.birge_ratio,
                      iv.p_value, iv.inflated, images, None,
                      {"random": iv.sigma_random**2}, {})


def fused_focal_sensitivity(estimates: Sequence[ImageEstimates], fused: FusedScale,
                            method: str) -> float:
    """γ of a fused value: its images' estimates' relative focal sensitivities, weighted by
    σ⁻² (NaN without sensitivities)."""
    used = set(fused.images_used)
    num = den = 0.0
    for est in estimates:
        sens = est.focal_sensitivity.get(method) if est.focal_sensitivity else None
        if sens is None or est.image not in used:
            continue
        for e, g in zip(est.of(method), sens, strict=True):
            if not e.rejected and np.isfinite(g) and np.isfinite(e.sigma) and e.sigma > 0:
                num += g / e.scale / e.sigma**2
                den += 1.0 / e.sigma**2
    return num / den if den > 0 else float("nan")


def focal_rms(focal: FocalEstimate, prior: float) -> float:
    """RMS of the focal error given the data's ε̂ ± σ(ε̂) and the model's own σ (the prior):
    √(ε̂² + σ²) when ε̂ is significant (the data contradict the prior), else the posterior
    √(μ² + v), v = (prior⁻² + σ⁻²)⁻¹, μ = v ε̂ / σ² (normal prior N(0, prior²); 0 without a
    prior). NaN when ε̂ is not determined."""
    eps, sig = focal.focal_error, focal.sigma
    if not (math.isfinite(eps) and math.isfinite(sig) and sig > 0):
        return float("nan")
    if focal.significant:  # the data contradict the prior: no shrinking towards it
        return math.hypot(eps, sig)
    if not prior > 0:
        return 0.0
    v = 1.0 / (1.0 / prior**2 + 1.0 / sig**2)
    return math.sqrt((v * eps / sig**2) ** 2 + v)


def widen_for_focal(headline: FusedScale, gamma: float, focal: FocalEstimate,
                    model_sigma: float, fusion: FusionOptions) -> FusedScale:
    """The headline with σ widened where the laser data show a larger focal error than the
    model's own σ(δf / f) (``model_sigma``, already in σ): variance (γ s)² (r² − model_sigma²)
    added to the intrinsics term, r = :func:`focal_rms`. The value never changes."""
    rms = focal_rms(focal, model_sigma)
    if not (math.isfinite(rms) and math.isfinite(gamma) and math.isfinite(headline.value)):
        return headline
    excess = (gamma * headline.value) ** 2 * max(rms**2 - model_sigma**2, 0.0)
    if excess <= 0:
        return headline
    z = float(stats.norm.ppf(0.5 + fusion.confidence / 2))
    half = math.hypot(headline.ci95[1] - headline.value, z * math.sqrt(excess))
    budget = dict(headline.budget)
    budget["intrinsics"] = budget.get("intrinsics", 0.0) + excess
    note = (f"sigma widened by the model's focal error the laser data show "
            f"({100 * focal.focal_error:+.3g} % ± {100 * focal.sigma:.2g} %: RMS "
            f"{100 * rms:.2g} % against the model's own {100 * model_sigma:.2g} %)")
    return replace(headline, std=math.hypot(headline.std, math.sqrt(excess)),
                   ci95=(headline.value - half, headline.value + half),
                   std_systematic=math.hypot(headline.std_systematic, math.sqrt(excess)),
                   notes=[*headline.notes, note], budget=budget)
