"""PCM-joint — parallel-pair scale with the beam direction estimated jointly over the images.

The paper's PCM (``pcm.py``) approximates the unknown beam direction in each image by the
direction camera centre -> midpoint of the two hits, which overestimates the beams' separation
whenever the hits differ in depth. A rigid rig keeps the beams fixed in the camera frame and every
registered image shares the model's scale, so with three or more images ``estimate_pcm_joint``
fits the two beams as two parallel lines (camera frame, model units) and takes their separation;
with fewer, or when the hits leave the direction undetermined, the midpoint PCM is returned under
this method's name with a note saying so.

The formulation (a linear fit iteratively reweighted with each image's hit covariance, i.e. the
Gauss–Helmert estimate), its first-order uncertainty (random part and the rig's systematic part)
and the leave-one-out outlier rule are in docs/DESIGN.md §3.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from sfm_laserscale.errors import InputError
from sfm_laserscale.fusion import FusedScale, FusionOptions, error_budget, fuse, interval
from sfm_laserscale.rig import Pair, Rig
from sfm_laserscale.rig_checks import refused_pairs
from sfm_laserscale.uncertainty import (
    RIG_PARAM_SUFFIXES,
    EstimationOptions,
    ImageObservation,
    estimate_image,
    mesh_sqrt,
    perturb_poses,
    perturbed_observation,
    pose_sqrt,
    tilt_basis,
)

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
METHOD = "pcm_joint"
#: H's reciprocal condition number below this: the beam direction is not determined.
_MIN_RCOND = 1e-12


@dataclass(frozen=True)
class PcmJointOptions:
    """Options of :func:`estimate_pcm_joint`."""

    min_images: int = 3  # usable images of a pair needed for the joint fit
    outlier_p_value: float = 1e-4  # leave-one-out χ² (4 dof) test per image
    max_iterations: int = 20  # reweighting iterations of the linear fit
    birge_inflation: bool = True  # inflate the random σ when χ²/dof > 1
    estimation: EstimationOptions = field(default_factory=EstimationOptions)
    fusion: FusionOptions = field(default_factory=FusionOptions)  # fallback and confidence


@dataclass(frozen=True)
class PairImageFit:
    """One image of a pair in the joint fit."""

    image: str
    implied_scale: float  # d_L / ‖(X2 − X1) ⟂ v̂‖: this image's scale with the joint direction
    implied_sigma: float  # its σ from this image's spots and pose (direction held fixed)
    chi2: float  # residual χ² (4 dof) in the final fit; leave-one-out χ² when rejected
    rejected: bool
    reason: str | None


@dataclass(frozen=True)
class PairJointFit:
    """The joint fit of one parallel pair (``joint`` False: not fitted, see ``reason``)."""

    pair: str  # "L1+L2"
    joint: bool
    scale: float  # metres per model unit
    sigma_random: float  # spots + pose of every image (before Birge inflation)
    sigma_rig: float  # common calibration term (calibrated pair lasers with σ only)
    direction_cam: F64  # (3,) unit beam direction, camera frame
    direction_sigma_deg: float  # 1-σ of the direction (largest axis)
    origins_m: F64  # (2, 3) the beams' points on z = 0 in metres (s · o_k)
    chi2: float
    dof: int
    images: tuple[PairImageFit, ...]
    reason: str | None = None


@dataclass(frozen=True)
class PcmJointResult:
    """PCM-joint over all pairs: the fused scale and each pair's fit."""

    fused: FusedScale  # method "pcm_joint"
    joint: bool  # False: the midpoint approximation was returned
    pairs: tuple[PairJointFit, ...]


# --------------------------------------------------------------------------- per-image data


@dataclass(frozen=True)
class _ImageData:
    """Camera-frame hits of one image and their sensitivity to its noisy inputs."""

    image: str
    names: tuple[str, ...]  # laser of each hit
    x: F64  # (K, 3) camera-frame hits, model units
    normal: F64  # (K, 3) unit normals, camera frame
    cos_inc: F64  # (K,) |cos| of the ray–normal angle
    sens: F64  # (3K, m) d hits / d unit-σ input (spot pixels, pose directions, mesh depths)
    terms: NDArray[np.str_]  # (m,) the error budget's term of each input: spots, pose, mesh

    def rows(self, k: int) -> slice:
        return slice(3 * k, 3 * k + 3)


def _check_hits(obs: ImageObservation, rig: Rig) -> None:
    names = [h.laser for h in obs.hits]
    for name in names:
        if name not in rig.names:
            raise InputError(f"image {obs.image}: spot for unknown laser {name!r}")
        if names.count(name) > 1:
            raise InputError(f"image {obs.image}: two spots assigned to laser {name!r}")
    for h in obs.hits:
        if not (np.isfinite(h.sigma_px) and h.sigma_px >= 0):
            raise InputError(f"image {obs.image}: spot sigma must be finite and >= 0")


def _image_data(obs: ImageObservation, rig: Rig, h: float) -> _ImageData | None:
    """Hits of the pair lasers in the camera frame and their unit-σ sensitivity (None: none)."""
    _check_hits(obs, rig)
    in_pairs = {n for p in rig.pairs for n in p.lasers}
    hits = [x for x in obs.hits if x.laser in in_pairs]
    if not hits:
        return None
    k = len(hits)
    xy = np.array([np.asarray(x.xy_px, np.float64).reshape(2) for x in hits])
    hw = np.array([np.asarray(x.hit_world, np.float64).reshape(3) for x in hits])
    nw = np.array([np.asarray(x.normal_world, np.float64).reshape(3) for x in hits])
    with np.errstate(divide="ignore", invalid="ignore"):
        nw = nw / np.linalg.norm(nw, axis=1, keepdims=True)
    px_sigma = np.repeat([float(x.sigma_px) for x in hits], 2)
    root = pose_sqrt(obs)
    _, mesh = mesh_sqrt(obs, [obs.hits.index(h) for h in hits])  # (k, q), correlated
    m, q = root.shape[1], mesh.shape[1]
    d = np.zeros((3 * k + 6, 2 * k + m + q))
    d[np.arange(2 * k), np.arange(2 * k)] = px_sigma
    d[2 * k:2 * k + 6, 2 * k:2 * k + m] = root
    d[2 * k + 6:, 2 * k + m:] = mesh
    terms = np.array(["spots"] * (2 * k) + ["pose"] * m + ["mesh"] * q)
    keep = np.any(d != 0, axis=0)
    d, terms = d[:, keep], terms[keep]
    deltas = np.vstack([np.zeros(3 * k + 6), h * d.T, -h * d.T])  # row 0 nominal
    R, t = perturb_poses(obs.cam_from_world, deltas[:, 2 * k:2 * k + 6])
    rays = obs.camera.unproject((xy[None] + deltas[:, :2 * k].reshape(-1, k, 2)).reshape(-1, 2))
    rays = rays.reshape(len(deltas), k, 3)
    n_c = np.einsum("bij,kj->bki", R, nw)
    ray_w = hw - obs.cam_from_world.center
    ray_w /= np.linalg.norm(ray_w, axis=1, keepdims=True)
    hw_b = hw[None] + deltas[:, 2 * k + 6:, None] * ray_w[None]  # mesh depth along the rays
    h_c = np.einsum("bij,bkj->bki", R, hw_b) + t[:, None, :]
    denom = np.sum(n_c * rays, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = rays * (np.sum(n_c * h_c, axis=2) / denom)[..., None]  # ray ∩ tangent plane
        cos_inc = np.abs(denom[0]) / np.linalg.norm(rays[0], axis=1)
    n = d.shape[1]
    sens = (x[1:1 + n] - x[1 + n:]).reshape(n, 3 * k).T / (2 * h)
    return _ImageData(obs.image, tuple(x.laser for x in hits), x[0], n_c[0], cos_inc, sens,
                      terms)


def _hits_cam(obs: ImageObservation, rig: Rig) -> tuple[tuple[str, ...], F64]:
    """The pair lasers' names and (K, 3) camera-frame hits of an observation."""
    in_pairs = {n for p in rig.pairs for n in p.lasers}
    hits = [x for x in obs.hits if x.laser in in_pairs]
    hw = np.array([np.asarray(x.hit_world, np.float64).reshape(3) for x in hits]).reshape(-1, 3)
    return tuple(x.laser for x in hits), obs.cam_from_world.transform(hw)


def _unusable(data: _ImageData, k1: int, k2: int, min_cos: float) -> str | None:
    """Why an image's two hits of a pair cannot enter the fit, or None."""
    x = data.x[[k1, k2]]
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(data.sens))):
        return "non-finite hit or hit sensitivity"
    if np.any(x[:, 2] <= 0):
        return "hit behind the camera (z ≤ 0)"
    for k in (k1, k2):
        if not data.cos_inc[k] >= min_cos:
            angle = float(np.degrees(np.arccos(min(float(data.cos_inc[k]), 1.0))))
            return f"ray of laser {data.names[k]} grazes the mesh (incidence {angle:.1f}°)"
    return None


# --------------------------------------------------------------------------- the linear fit


@dataclass(frozen=True)
class _Solution:
    """Weighted fit r = y + A θ of n images (θ = w_x, w_y, o_1 (2), o_2 (2))."""

    theta: F64  # (6,)
    h: F64  # (6, 6) Σ Aᵀ W A
    g: F64  # (6,) Σ Aᵀ W y
    y: F64  # (n, 4)
    a: F64  # (n, 4, 6)
    cov_r: F64  # (n, 4, 4) residual covariance B C Bᵀ (+ floor)
    weight: F64  # (n, 4, 4) its inverse
    chi2: F64  # (n,) per-image residual χ²

    @property
    def w(self) -> F64:
        return self.theta[:2]


def _design(x: F64) -> tuple[F64, F64]:
    """y (n, 4) and A (n, 4, 6) of the residuals r = y + A θ of hits x (n, 2, 3)."""
    n = len(x)
    eye = np.eye(2)
    a = np.zeros((n, 4, 6))
    a[:, 0:2, 0:2] = -x[:, 0, 2, None, None] * eye
    a[:, 2:4, 0:2] = -x[:, 1, 2, None, None] * eye
    a[:, 0:2, 2:4] = -eye
    a[:, 2:4, 4:6] = -eye
    return x[:, :, :2].reshape(n, 4), a


def _b_matrix(w: F64) -> F64:
    """(4, 6) ∂r/∂(X1, X2): r_k = X_k,xy − X_k,z w − o_k."""
    b = np.zeros((4, 6))
    b[[0, 1, 2, 3], [0, 1, 3, 4]] = 1.0
    b[[0, 2], [2, 5]] = -w[0]
    b[[1, 3], [2, 5]] = -w[1]
    return b


def _rcond(h: F64) -> float:
    """Reciprocal condition number of H after Jacobi scaling (unit-free)."""
    d = np.sqrt(np.abs(np.diag(h)))
    if not np.all(d > 0):
        return 0.0
    return float(1.0 / np.linalg.cond(h / np.outer(d, d)))


def _solve(x: F64, c: F64, iterations: int) -> _Solution | None:
    """Iteratively reweighted fit of hits x (n, 2, 3), hit covariances c (n, 6, 6); None when
    the beam direction is not determined."""
    y, a = _design(x)
    floor = (1e-9 * float(np.mean(np.linalg.norm(x, axis=2)))) ** 2 * np.eye(4)
    mid = 0.5 * (x[:, 0] + x[:, 1])
    w = np.mean(mid[:, :2] / mid[:, 2:3], axis=0)  # start: the midpoint directions
    for _ in range(max(iterations, 1)):
        b = _b_matrix(w)
        cov_r = b @ c @ b.T + floor
        weight = np.asarray(np.linalg.inv(cov_r), dtype=np.float64)
        at_w = np.einsum("nji,njk->nik", a, weight)
        h = np.einsum("nij,njk->ik", at_w, a)
        g = np.einsum("nij,nj->i", at_w, y)
        if _rcond(h) < _MIN_RCOND:
            return None
        theta = -np.linalg.solve(h, g)
        done = np.linalg.norm(theta[:2] - w) <= 1e-12 * (1.0 + np.linalg.norm(w))
        w = theta[:2]
        if done:
            break
    r = y + np.einsum("nij,j->ni", a, theta)
    chi2 = np.einsum("ni,nij,nj->n", r, weight, r)
    return _Solution(theta, h, g, y, a, cov_r, weight, chi2)


def _loo_chi2(sol: _Solution) -> F64:
    """(n,) χ² (4 dof) of each image's residuals predicted by the fit of the others."""
    out = np.zeros(len(sol.y))
    for i in range(len(sol.y)):
        at_w = sol.a[i].T @ sol.weight[i]
        h = sol.h - at_w @ sol.a[i]
        if _rcond(h) < _MIN_RCOND:
            continue  # the others alone do not determine the beams: no test
        h_inv = np.linalg.inv(h)
        r = sol.y[i] + sol.a[i] @ (-h_inv @ (sol.g - at_w @ sol.y[i]))
        cov = sol.cov_r[i] + sol.a[i] @ h_inv @ sol.a[i].T
        out[i] = float(r @ np.linalg.solve(cov, r))
    return out


def _scale_and_gradient(theta: F64, separation: float) -> tuple[float, F64]:
    """s = d_L / ‖(o_2 − o_1) ⟂ v‖ and ∂s/∂θ (6,)."""
    w, dxy = theta[:2], theta[4:6] - theta[2:4]
    n2 = 1.0 + float(w @ w)  # ‖(w_x, w_y, 1)‖²
    along = float(dxy @ w)  # (o_2 − o_1)·(w, 1), o on z = 0
    q = float(dxy @ dxy) - along**2 / n2
    s = separation / np.sqrt(q)
    dq_dd = 2.0 * dxy - 2.0 * along * w / n2
    dq_dw = -2.0 * along * dxy / n2 + 2.0 * along**2 * w / n2**2
    return float(s), (-s / (2.0 * q)) * np.concatenate([dq_dw, -dq_dd, dq_dd])


def _hit_gradients(sol: _Solution, grad_theta: F64) -> F64:
    """(n, 6) ∂s/∂(X1, X2) of every image: −∇sᵀ H⁻¹ Aᵢᵀ Wᵢ B."""
    left = -np.linalg.solve(sol.h, grad_theta)  # (6,)
    aw = np.einsum("j,nkj,nkl->nl", left, sol.a, sol.weight)  # (n, 4)
    return np.asarray(aw @ _b_matrix(sol.w), dtype=np.float64)


def _unit_direction(w: F64) -> F64:
    v = np.array([w[0], w[1], 1.0])
    return np.asarray(v / np.linalg.norm(v), dtype=np.float64)


def _direction_sigma_deg(sol: _Solution) -> float:
    """Largest-axis 1-σ of the unit beam direction, degrees."""
    v = _unit_direction(sol.w)
    jac = (np.eye(3) - np.outer(v, v))[:, :2] / np.sqrt(1.0 + float(sol.w @ sol.w))
    cov = jac @ np.linalg.inv(sol.h)[:2, :2] @ jac.T
    return float(np.degrees(np.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))))


def _implied(x: F64, v: F64, separation: float) -> tuple[float, F64]:
    """One image's scale with the joint direction, d_L / ‖(X2 − X1) ⟂ v‖, and ∂/∂(X1, X2)."""
    d = x[1] - x[0]
    perp = d - (d @ v) * v
    d_hat = float(np.linalg.norm(perp))
    s = separation / d_hat
    u = perp / d_hat
    return s, (-s / d_hat) * np.concatenate([-u, u])


def _implied_terms(names: Sequence[str], x: F64, sens: Sequence[F64], v: F64, separation: float
                   ) -> dict[str, tuple[float, F64]]:
    """image -> (implied scale, (m,) its gradient over the image's unit-σ inputs)."""
    out = {}
    for name, xi, si in zip(names, x, sens, strict=True):
        s_i, g_i = _implied(xi, v, separation)
        out[name] = (s_i, g_i @ si)
    return out


def _rig_gradient(pair: Pair, rig: Rig, x: F64, normal: F64, grads: F64, v: F64, s: float
                  ) -> dict[str, float]:
    """∂s/∂(unit-σ calibration parameter) of the pair's calibrated lasers (common to all images).

    A beam error (origin offset on z = 0, tilt about the origin) displaces beam k at the hit by
    δO + ρ δv (metres, ρ = range along the beam); the hit slides on its tangent plane.
    """
    out: dict[str, float] = {}
    for j, name in enumerate(pair.lasers):
        las = rig.laser(name)
        if las.origin is None or las.direction is None:
            continue
        so, sd = las.sigma_origin, las.sigma_direction
        if so == 0 and sd == 0:
            continue
        tilt = tilt_basis(np.asarray(las.direction, dtype=np.float64))
        rho = s * x[:, j, 2] / v[2]  # (n,) metres along the beam
        disp = np.zeros((len(x), 4, 3))  # (n, parameter, xyz) metres
        disp[:, 0, 0] = so
        disp[:, 1, 1] = so
        disp[:, 2] = rho[:, None] * sd * tilt[0]
        disp[:, 3] = rho[:, None] * sd * tilt[1]
        nk = normal[:, j]
        slide = np.einsum("npk,nk->np", disp, nk) / (nk @ v)[:, None]
        dx = (disp - slide[..., None] * v) / s  # (n, 4, 3) model units
        ds = np.einsum("npk,nk->p", dx, grads[:, 3 * j:3 * j + 3])
        out.update({f"{name}.{suf}": float(g) for suf, g in zip(RIG_PARAM_SUFFIXES, ds,
                                                                strict=True)})
    return out


# --------------------------------------------------------------------------- one pair


@dataclass(frozen=True)
class _PairState:
    """A fitted pair: public summary and what combining pairs needs."""

    fit: PairJointFit
    inputs: dict[str, F64]  # image -> (m,) ∂s/∂(unit-σ inputs of that image)
    implied: dict[str, tuple[float, F64]]  # image -> (implied scale, (m,) its input gradient)
    rig: dict[str, float]  # shared parameter (rig, model intrinsics) -> ∂s/∂(unit-σ parameter)
    terms: dict[str, NDArray[np.str_]] = field(default_factory=dict)  # image -> (m,) terms


#: Hits of the perturbed observations: direction -> (h, per image (names, (K, 3) camera hits) at
#: +h, the same at −h).
Shifted = dict[str, tuple[float, dict[str, tuple[tuple[str, ...], F64]],
                          dict[str, tuple[tuple[str, ...], F64]]]]


def _shifted_hits(observations: Sequence[ImageObservation], rig: Rig, h: float) -> Shifted:
    """The pair lasers' camera-frame hits of every observation moved ±h along each of its
    model intrinsics directions of unit σ (:mod:`sfm_laserscale.model_error`)."""
    out: Shifted = {}
    for obs in observations:
        for d in obs.model_directions:
            if not d.in_sigma:
                continue
            entry = out.setdefault(d.name, (h, {}, {}))
            entry[1][obs.image] = _hits_cam(perturbed_observation(obs, d, h), rig)
            entry[2][obs.image] = _hits_cam(perturbed_observation(obs, d, -h), rig)
    return out


def _model_gradient(pair: Pair, entries: Sequence[tuple[_ImageData, int, int]], kept: list[int],
                    c: F64, shifted: Shifted, options: PcmJointOptions) -> dict[str, float]:
    """∂s/∂(unit-σ model intrinsics direction): the joint fit of the kept images re-solved with
    their hits moved ± along the direction (central difference; weights held)."""
    out: dict[str, float] = {}
    for name, (h, plus, minus) in shifted.items():
        s_pm = []
        for side in (plus, minus):
            rows = []
            for i in kept:
                dat = entries[i][0]
                if dat.image not in side:
                    break
                names, x = side[dat.image]
                rows.append(x[[names.index(pair.lasers[0]), names.index(pair.lasers[1])]])
            sol = None if len(rows) != len(kept) else _solve(np.array(rows), c[kept],
                                                               options.max_iterations)
            if sol is None:
                break
            s_pm.append(_scale_and_gradient(sol.theta, pair.separation)[0])
        if len(s_pm) == 2:
            out[name] = (s_pm[0] - s_pm[1]) / (2 * h)
    return out


def _robust_fit(x: F64, c: F64, options: PcmJointOptions
                ) -> tuple[_Solution | None, list[int], list[tuple[int, float, str]], str | None]:
    """Fit, then drop the worst leave-one-out image while it fails the χ² test (iterated).

    Returns the solution (None: no joint fit), kept indices, (index, χ², reason) of the dropped
    images, and why there is no fit.
    """
    idx = list(range(len(x)))
    dropped: list[tuple[int, float, str]] = []
    crit = float(stats.chi2.isf(options.outlier_p_value, 4))
    while True:
        if len(idx) < options.min_images:
            return None, idx, dropped, (f"only {len(idx)} usable image(s), the joint fit needs "
                                        f"{options.min_images}")
        sol = _solve(x[idx], c[idx], options.max_iterations)
        if sol is None:
            return None, idx, dropped, ("beam direction not determined (the hits lie at nearly "
                                        "one depth along the beams in every image)")
        if len(idx) < 3:
            return sol, idx, dropped, None  # the others alone cannot be fitted: no test
        z = _loo_chi2(sol)
        worst = int(np.argmax(z))
        # χ² of the others' own fit (= total − leave-one-out χ², linear GLS): its χ²/dof scales
        # the threshold when every image scatters more than its σ says (σ underestimated)
        rest = max(float(sol.chi2.sum()) - float(z[worst]), 0.0) / (4 * len(idx) - 10)
        limit = crit * max(1.0, rest)
        if z[worst] <= limit:
            return sol, idx, dropped, None
        dropped.append((idx.pop(worst), float(z[worst]),
                        f"inconsistent with the beams fitted to the other images (leave-one-out "
                        f"chi2 {z[worst]:.1f} > {limit:.1f}, 4 dof): wrong spot or laser "
                        f"assignment"))


def _pair_entries(pair: Pair, data: Sequence[_ImageData], min_cos: float
                  ) -> tuple[list[tuple[_ImageData, int, int]], list[PairImageFit]]:
    """Images seeing both lasers of the pair: usable ones, and the others with their reason."""
    usable, rejected = [], []
    nan = float("nan")
    for dat in data:
        if pair.lasers[0] not in dat.names or pair.lasers[1] not in dat.names:
            continue
        k1, k2 = dat.names.index(pair.lasers[0]), dat.names.index(pair.lasers[1])
        why = _unusable(dat, k1, k2, min_cos)
        if why is None:
            usable.append((dat, k1, k2))
        else:
            rejected.append(PairImageFit(dat.image, nan, nan, nan, True, why))
    return usable, rejected


def _not_fitted(name: str, images: list[PairImageFit], reason: str) -> _PairState:
    nan = float("nan")
    fit = PairJointFit(name, False, nan, nan, nan, np.full(3, nan), nan, np.full((2, 3), nan),
                       nan, 0, tuple(images), reason)
    return _PairState(fit, {}, {}, {})


def _fit_pair(pair: Pair, data: Sequence[_ImageData], rig: Rig, options: PcmJointOptions,
              shifted: Shifted | None = None) -> _PairState:
    """Joint fit of one parallel pair over the images that see both its lasers."""
    name = "+".join(pair.lasers)
    refused = refused_pairs(rig).get(name)
    if refused is not None:
        return _not_fitted(name, [], refused)
    entries, unusable = _pair_entries(pair, data, options.estimation.min_incidence_cos)
    sens = [dat.sens[np.r_[dat.rows(k1), dat.rows(k2)]] for dat, k1, k2 in entries]  # (6, m)
    x = np.array([dat.x[[k1, k2]] for dat, k1, k2 in entries]).reshape(-1, 2, 3)
    c = np.array([s_ @ s_.T for s_ in sens]).reshape(-1, 6, 6)
    sol, kept, dropped, reason = _robust_fit(x, c, options)
    nan = float("nan")
    images = unusable + [PairImageFit(entries[i][0].image, nan, nan, z, True, why)
                         for i, z, why in dropped]
    if sol is None:
        return _not_fitted(name, images, reason or "no joint fit")
    s, grad = _scale_and_gradient(sol.theta, pair.separation)
    v = _unit_direction(sol.w)
    grads = _hit_gradients(sol, grad)  # (n, 6)
    names = [entries[i][0].image for i in kept]
    inputs = {im: grads[row] @ sens[i] for row, (im, i) in enumerate(zip(names, kept, strict=True))}
    implied = _implied_terms(names, x[kept], [sens[i] for i in kept], v, pair.separation)
    images += [PairImageFit(im, implied[im][0], float(np.linalg.norm(implied[im][1])),
                            float(sol.chi2[row]), False, None) for row, im in enumerate(names)]
    normal = np.array([dat.normal[[k1, k2]] for dat, k1, k2 in entries])[kept]
    rig_grad = (_rig_gradient(pair, rig, x[kept], normal, grads, v, s)
                if options.estimation.include_rig_uncertainty else {})
    rig_grad.update(_model_gradient(pair, entries, kept, c, shifted or {}, options))
    sigma_rand = float(np.sqrt(sum(float(u @ u) for u in inputs.values())))
    fit = PairJointFit(name, True, s, sigma_rand,
                       float(np.linalg.norm(list(rig_grad.values()))) if rig_grad else 0.0,
                       v, _direction_sigma_deg(sol),
                       s * np.column_stack([sol.theta[2:].reshape(2, 2), np.zeros(2)]),
                       float(sol.chi2.sum()), 4 * len(kept) - 6, tuple(images))
    terms = {entries[i][0].image: entries[i][0].terms for i in kept}
    return _PairState(fit, inputs, implied, rig_grad, terms)


# --------------------------------------------------------------------------- all pairs


def _gls(values: F64, cov: F64) -> tuple[F64, float]:
    """GLS weights (summing to 1) and the χ² of the values about their GLS mean."""
    cinv = np.linalg.pinv(cov, hermitian=True)
    ones = np.ones(len(values))
    w = cinv @ ones / float(ones @ cinv @ ones)
    r = values - float(w @ values)
    return w, float(r @ cinv @ r)


def _cross_cov(grads: Sequence[dict[str, F64]],
               masks: Sequence[dict[str, NDArray[np.bool_]]] | None = None) -> F64:
    """Covariance of estimates from their per-image input gradients (images independent);
    ``masks``: only these inputs of each image (one term of the budget)."""
    n = len(grads)
    cov = np.zeros((n, n))
    for p in range(n):
        for q in range(p, n):
            total = 0.0
            for im, u in grads[p].items():
                if im not in grads[q]:
                    continue
                keep = np.ones(len(u), bool) if masks is None else masks[p][im]
                total += float(u[keep] @ grads[q][im][keep])
            cov[p, q] = cov[q, p] = total
    return cov


def _term_variances(states: Sequence[_PairState], w: F64) -> dict[str, float]:
    """Variance of the GLS mean per random term (spots, pose, mesh)."""
    names = {str(t) for st in states for ts in st.terms.values() for t in ts}
    out = {}
    for term in sorted(names):
        masks = [{im: ts == term for im, ts in st.terms.items()} for st in states]
        out[term] = max(float(w @ _cross_cov([st.inputs for st in states], masks) @ w), 0.0)
    return out


def _per_image(states: Sequence[_PairState]) -> dict[str, tuple[float, float]]:
    """Each image's implied scale (GLS over its pairs) and σ from its own spots and pose."""
    out: dict[str, tuple[float, float]] = {}
    images = [im for st in states for im in st.implied]
    for image in dict.fromkeys(images):
        own = [st.implied[image] for st in states if image in st.implied]
        values = np.array([v for v, _ in own])
        cov = _cross_cov([{image: g} for _, g in own])
        w, _ = _gls(values, cov)
        out[image] = (float(w @ values), float(np.sqrt(max(float(w @ cov @ w), 0.0))))
    return out


def _notes(states: Sequence[_PairState], others: Sequence[PairJointFit], sigma_sys: float,
           n_images: int) -> list[str]:
    notes = [f"joint beam direction from {n_images} images"]
    for st in states:
        f = st.fit
        angle = float(np.degrees(np.arccos(np.clip(f.direction_cam[2], -1.0, 1.0))))
        n_rej = sum(im.rejected for im in f.images)
        notes.append(f"{f.pair}: {len(st.inputs)} image(s) used, {n_rej} rejected; beam "
                     f"{angle:.3f}° ± {f.direction_sigma_deg:.3f}° off the optical axis; "
                     f"chi2 {f.chi2:.1f} / {f.dof} dof")
    notes += [f"{f.pair}: not used ({f.reason})" for f in others]
    notes.append(f"shared term (rig calibration, model intrinsics) {sigma_sys:.3g} "
                 "(does not average down)")
    return notes


def _combine(states: Sequence[_PairState], others: Sequence[PairJointFit],
             options: PcmJointOptions) -> FusedScale:
    """GLS over the fitted pairs, Birge inflation, common rig term and interval."""
    values = np.array([st.fit.scale for st in states])
    c_rand = _cross_cov([st.inputs for st in states])
    names = list(dict.fromkeys(k for st in states for k in st.rig))
    g = np.array([[st.rig.get(k, 0.0) for k in names] for st in states]).reshape(len(states), -1)
    w, chi2_between = _gls(values, c_rand + g @ g.T)
    value = float(w @ values)
    sigma_rand = float(np.sqrt(max(float(w @ c_rand @ w), 0.0)))
    sigma_sys = float(np.linalg.norm(w @ g))
    chi2 = sum(st.fit.chi2 for st in states) + chi2_between
    dof = sum(st.fit.dof for st in states) + len(states) - 1
    n_images = len({im for st in states for im in st.inputs})
    iv = interval(sigma_rand, sigma_sys, chi2, dof, options.fusion, options.birge_inflation)
    notes = [*_notes(states, others, sigma_sys, n_images), *iv.notes]
    rejected = [(im.image, f.pair, im.reason or "rejected")
                for f in [st.fit for st in states] for im in f.images if im.rejected]
    used = tuple(dict.fromkeys(im for st in states for im in st.inputs))
    half = iv.half_width
    gradient = dict(zip(names, (w @ g).tolist(), strict=True))
    budget = error_budget(_term_variances(states, w), sigma_rand, iv.sigma_random, gradient)
    return FusedScale(value, iv.std, (value - half, value + half),
                      1.0 / value, METHOD, sum(len(st.inputs) for st in states), len(rejected),
                      _per_image(states), rejected, notes, iv.sigma_random, sigma_sys,
                      iv.birge_ratio, iv.p_value, iv.inflated, used, None, budget, gradient)


def _fallback(observations: Sequence[ImageObservation], rig: Rig, fits: Sequence[PairJointFit],
              options: PcmJointOptions) -> FusedScale:
    """The paper's midpoint PCM, fused as usual, under this method's name and saying so."""
    fused = fuse([estimate_image(o, rig, options.estimation) for o in observations], "pcm",
                 options.fusion)
    if not fits:
        head = "no parallel pair in the rig: midpoint approximation"
    elif all(f.reason is not None and f.reason.startswith("only ") for f in fits):
        head = f"fewer than {options.min_images} images: midpoint approximation"
    else:
        head = "no joint beam direction: midpoint approximation"
    notes = [head] + [f"{f.pair}: {f.reason}" for f in fits] + list(fused.notes)
    return replace(fused, method=METHOD, notes=notes)


def _check_options(options: PcmJointOptions) -> None:
    if options.min_images < 2:
        raise ValueError("min_images must be >= 2 (two images give 8 equations for 6 unknowns)")
    if not 0.0 < options.outlier_p_value < 1.0:
        raise ValueError("outlier_p_value must lie in (0, 1)")


def estimate_pcm_joint(observations: Sequence[ImageObservation], rig: Rig,
                       options: PcmJointOptions) -> PcmJointResult:
    """PCM with each pair's beam direction fitted jointly over the images (midpoint fallback)."""
    _check_options(options)
    data = [d for d in (_image_data(o, rig, options.estimation.fd_step_sigma)
                        for o in observations) if d is not None]
    shifted = _shifted_hits(observations, rig, options.estimation.fd_step_sigma)
    states = [_fit_pair(pair, data, rig, options, shifted) for pair in rig.pairs]
    fitted = [st for st in states if st.fit.joint]
    fits = tuple(st.fit for st in states)
    if not fitted:
        logger.info("pcm_joint: no pair fitted jointly, midpoint approximation")
        return PcmJointResult(_fallback(observations, rig, fits, options), False, fits)
    others = [st.fit for st in states if not st.fit.joint]
    fused = _combine(fitted, others, options)
    logger.debug("pcm_joint: %.6g ± %.3g from %d pair(s)", fused.value, fused.std, len(fitted))
    return PcmJointResult(fused, True, fits)


def fuse_pcm_joint(observations: Sequence[ImageObservation], rig: Rig,
                   options: PcmJointOptions | None = None) -> FusedScale:
    """The ``pcm_joint`` fused scale (FusedScale, method "pcm_joint") of the observations."""
    return estimate_pcm_joint(observations, rig, options or PcmJointOptions()).fused
