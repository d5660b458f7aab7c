"""PCM-joint: the pair's beam direction fitted over the images, against exact synthetic truth.

Rough-terrain scene (metres): a heightfield of four sinusoids (0.3 m at 3 m wavelength down to
18 mm at 15 cm, local slopes up to ~60°), evaluated analytically; every ray–surface
intersection is exact (first sign change along the ray, then bisection to machine precision).
A PINHOLE camera (1024×768, f 900 px) looks at it from 2–4 m with pitch up to ±40° and roll
30–40° either way. The rig: two parallel beams 10 cm apart, mounted 0.5 m beside the camera
(camera equidistant from both, the paper's PCM assumption), tilted 4° off the optical axis; the
estimator knows only the separation. Model units: metres / K. Noise (Monte Carlo): spot pixels
0.25 px and a correlated pose covariance (0.017°, 2 mm) drawn per image, noisy rays
re-intersected exactly with the true terrain.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from uncertainty_synth import (
    K_TRUE,
    make_camera,
    make_scene,
    pose_covariance,
    rodrigues,
)
from uncertainty_synth import make_rig as make_rig4
from uncertainty_synth import observe as observe_plane

from sfm_laserscale.fusion import FusionOptions, fuse
from sfm_laserscale.methods.pcm_joint import (
    METHOD,
    PcmJointOptions,
    estimate_pcm_joint,
    fuse_pcm_joint,
)
from sfm_laserscale.model import Pose
from sfm_laserscale.rig import Rig, rig_from_dict
from sfm_laserscale.uncertainty import (
    EstimationOptions,
    ImageObservation,
    SpotHit,
    estimate_image,
)

K = K_TRUE  # metres per model unit
SEP = 0.10
TILT = np.radians(4.0)
V_TRUE = np.array([0.0, -np.sin(TILT), np.cos(TILT)])
O_TRUE = np.array([[-SEP / 2, 0.5, 0.0], [SEP / 2, 0.5, 0.0]])  # metres on z = 0
CAM = make_camera()
SIGMA_PX = 0.25
N_VIEWS = 10
N_MC = 200
OPTS = PcmJointOptions()


# ---------------------------------------------------------------- synthetic rough terrain


class Terrain:
    """z = Σ a sin(k·xy + φ) (metres); exact first hits of rays."""

    def __init__(self, rng: np.random.Generator) -> None:
        comps = [(0.3, 3.0), (0.15, 0.9), (0.045, 0.35), (0.018, 0.15)]  # (amplitude, wavelength)
        self.a = np.array([c[0] for c in comps])
        ang = rng.uniform(0, 2 * np.pi, len(comps))
        self.k = (2 * np.pi / np.array([c[1] for c in comps]))[:, None] * np.c_[np.cos(ang),
                                                                                np.sin(ang)]
        self.phi = rng.uniform(0, 2 * np.pi, len(comps))

    def f(self, p: np.ndarray) -> np.ndarray:
        """Height above the surface (> 0 above)."""
        return p[..., 2] - np.sin(p[..., :2] @ self.k.T + self.phi) @ self.a

    def normal(self, p: np.ndarray) -> np.ndarray:
        g = (np.cos(p[..., :2] @ self.k.T + self.phi) * self.a) @ self.k
        n = np.concatenate([-g, np.ones(g.shape[:-1] + (1,))], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def first_hit(self, c: np.ndarray, d: np.ndarray, lo: Any = 0.05, hi: Any = 10.0,
                  n: int = 2500) -> np.ndarray:
        """(N,) first t in [lo, hi] with c + t d on the surface (NaN if none)."""
        t = np.broadcast_to(lo, len(c))[:, None] + np.linspace(0, 1, n)[None] * (
            np.broadcast_to(hi, len(c)) - np.broadcast_to(lo, len(c)))[:, None]
        below = self.f(c[:, None] + t[..., None] * d[:, None]) < 0
        idx = np.argmax(below, axis=1)
        rows = np.arange(len(c))
        ok = below[rows, idx] & (idx > 0)
        a, b = t[rows, np.maximum(idx - 1, 0)], t[rows, idx]
        for _ in range(60):
            mid = 0.5 * (a + b)
            above = self.f(c + mid[:, None] * d) > 0
            a, b = np.where(above, mid, a), np.where(above, b, mid)
        return np.where(ok, 0.5 * (a + b), np.nan)


def _rot(axis: int, deg: float) -> np.ndarray:
    w = np.zeros(3)
    w[axis] = np.radians(deg)
    return rodrigues(w)


@dataclass(frozen=True)
class View:
    R_wc: np.ndarray  # world_from_cam rotation
    C: np.ndarray  # camera centre, world metres
    hits: np.ndarray  # (2, 3) true hits, world metres
    px: np.ndarray  # (2, 2) true spot pixels


def _well_posed(ter: Terrain, C: np.ndarray, hw: np.ndarray) -> bool:
    """Spots visible with clearance, not grazing, away from silhouettes, inside the image."""
    ray = hw - C
    dist = np.linalg.norm(ray, axis=1)
    ray = ray / dist[:, None]
    if np.any(np.abs(np.sum(ray * ter.normal(hw), axis=1)) < 0.2):
        return False
    s = np.linspace(0.0, 1.0, 2000)[None, :, None] * (dist[:, None, None] - 0.1)
    if np.any(ter.f(C + s * ray[:, None, :]) < 0.03):
        return False  # (nearly) hidden from the camera
    for h in hw:  # rays aimed 2 cm around the hit must land near it (no silhouette jump)
        d = h + 0.02 * np.vstack([np.eye(3), -np.eye(3)]) - C
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        if np.any(~(np.abs(ter.first_hit(np.tile(C, (6, 1)), d) - np.linalg.norm(h - C)) < 0.06)):
            return False
    return True


def make_views(ter: Terrain, rng: np.random.Generator, n: int) -> list[View]:
    """n random well-posed views: 2–4 m, pitch ±40°, roll ±(30–40)°."""
    down = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]]).T
    views: list[View] = []
    while len(views) < n:
        R_wc = (down @ _rot(0, rng.uniform(-40, 40))
                @ _rot(1, rng.choice([-1, 1]) * rng.uniform(30, 40)))
        target = np.r_[rng.uniform(-5, 5, 2), 0.0]
        target[2] = -ter.f(target)
        C = target - rng.uniform(2, 4) * R_wc[:, 2]
        starts, dirs = C + O_TRUE @ R_wc.T, np.tile(R_wc @ V_TRUE, (2, 1))
        hw = starts + ter.first_hit(starts, dirs)[:, None] * dirs
        if np.any(np.isnan(hw)) or not _well_posed(ter, C, hw):
            continue
        px = CAM.project((hw - C) @ R_wc)
        if np.all((px > 20) & (px < [CAM.width - 20, CAM.height - 20])):
            views.append(View(R_wc, C, hw, px))
    return views


def pcm_rig(calibrated: bool = False, sigma_origin: float = 0.0, sigma_direction: float = 0.0
            ) -> Rig:
    lasers = []
    for name, o in zip(("L1", "L2"), O_TRUE, strict=True):
        las: dict[str, Any] = {"name": name}
        if calibrated:
            las.update(origin=list(o), direction=list(V_TRUE), sigma_origin=sigma_origin,
                       sigma_direction=sigma_direction)
        lasers.append(las)
    return rig_from_dict({"laser": lasers, "pair": [{"lasers": ["L1", "L2"], "separation": SEP}]})


def observe(ter: Terrain, views: list[View], rng: np.random.Generator, sigma_px: float,
            pose_cov: np.ndarray | None, px_offset: dict[int, np.ndarray] | None = None
            ) -> list[ImageObservation]:
    """Noisy pixels and poses; each noisy ray re-intersected exactly with the true terrain."""
    out = []
    for i, vw in enumerate(views):
        R, t = vw.R_wc.T, -vw.R_wc.T @ vw.C / K
        if pose_cov is not None:
            d = np.linalg.cholesky(pose_cov) @ rng.normal(size=6)
            R, t = rodrigues(d[:3]) @ R, t + d[3:]
        pose = Pose(R, t)
        px = vw.px + rng.normal(scale=sigma_px, size=(2, 2))
        if px_offset and i in px_offset:
            px = px + px_offset[i]
        c = pose.center * K
        dirs = CAM.unproject(px) @ R  # world directions, |d| ≈ 1
        dist = np.linalg.norm(vw.hits - c, axis=1)  # clearance is checked up to dist − 0.1 m
        lam = ter.first_hit(np.tile(c, (2, 1)), dirs, dist - 0.1, dist + 0.2, 600)
        hw = c + lam[:, None] * dirs
        hits = tuple(SpotHit(n, px[j], SIGMA_PX, hw[j] / K, ter.normal(hw[j]))
                     for j, n in enumerate(("L1", "L2")))
        out.append(ImageObservation(f"im{i:02d}", CAM, pose, pose_cov, hits))
    return out


def midpoint_pcm(obs: list[ImageObservation], rig: Rig) -> float:
    """What the tool's 'pcm' gives: the paper's midpoint PCM per image, fused."""
    est = [estimate_image(o, rig, EstimationOptions()) for o in obs]
    return fuse(est, "pcm", FusionOptions()).value


@pytest.fixture(scope="module")
def scene() -> tuple[Terrain, list[View], np.ndarray]:
    rng = np.random.default_rng(0)
    ter = Terrain(rng)
    return ter, make_views(ter, rng, N_VIEWS), pose_covariance(rng, k=K)


@pytest.fixture(scope="module")
def monte_carlo(scene) -> dict[str, np.ndarray]:
    ter, views, pose_cov = scene
    rng = np.random.default_rng(1)
    rig = pcm_rig()
    joint, std, std_rand, mid, rejected = [], [], [], [], 0
    for trial in range(N_MC):
        obs = observe(ter, views, rng, SIGMA_PX, pose_cov)
        res = estimate_pcm_joint(obs, rig, OPTS)
        assert res.joint
        joint.append(res.fused.value)
        std.append(res.fused.std)
        std_rand.append(res.pairs[0].sigma_random)
        rejected += res.fused.n_rejected
        if trial < 60:
            mid.append(midpoint_pcm(obs, rig))
    return {"joint": np.array(joint), "std": np.array(std), "std_rand": np.array(std_rand),
            "mid": np.array(mid), "rejected": np.array(rejected)}


# ---------------------------------------------------------------- exactness


def clean_obs(scene) -> list[ImageObservation]:
    ter, views, _ = scene
    return observe(ter, views, np.random.default_rng(2), 0.0, None)


def test_noise_free_recovers_scale_direction_and_origins(scene):
    res = estimate_pcm_joint(clean_obs(scene), pcm_rig(), OPTS)
    assert res.joint and res.fused.method == METHOD == "pcm_joint"
    assert res.fused.value == pytest.approx(K, rel=1e-9)
    assert res.fused.inverse == pytest.approx(1 / K, rel=1e-9)
    fit = res.pairs[0]
    np.testing.assert_allclose(fit.direction_cam, V_TRUE, atol=1e-9)
    np.testing.assert_allclose(fit.origins_m, O_TRUE, atol=1e-9)
    assert fit.dof == 4 * N_VIEWS - 6 and fit.chi2 < 1e-12
    assert res.fused.n_estimates == N_VIEWS and res.fused.n_rejected == 0
    assert res.fused.notes[0] == f"joint beam direction from {N_VIEWS} images"
    assert len(res.fused.per_image) == N_VIEWS
    for value, sigma in res.fused.per_image.values():  # exact direction: every image exact
        assert value == pytest.approx(K, rel=1e-9) and sigma > 0
    lo, hi = res.fused.ci95
    assert lo < K < hi


# ---------------------------------------------------------------- Monte Carlo


def test_mc_joint_is_unbiased_where_the_midpoint_approximation_is_not(monte_carlo):
    mid_bias = monte_carlo["mid"].mean() / K - 1
    assert abs(mid_bias) >= 0.01, mid_bias  # the scenario: the paper's PCM is ≥ 1 % off
    joint = monte_carlo["joint"]
    bias = joint.mean() / K - 1
    assert abs(bias) < 0.002, bias
    assert abs(bias) < 4 * joint.std(ddof=1) / K / np.sqrt(len(joint))  # no detectable bias
    assert monte_carlo["rejected"] <= 2  # good images are (almost) never rejected


def test_mc_reported_sigma_matches_the_spread(monte_carlo):
    spread = monte_carlo["joint"].std(ddof=1)
    ratio = spread / np.sqrt(np.mean(monte_carlo["std"] ** 2))  # as reported (Birge included)
    assert 0.85 <= ratio <= 1.2, ratio
    ratio_rand = spread / np.sqrt(np.mean(monte_carlo["std_rand"] ** 2))  # propagation alone
    assert 0.85 <= ratio_rand <= 1.15, ratio_rand


def test_mc_rig_calibration_term_is_calibrated(scene):
    """Calibrated pair lasers with σ: true beams drawn from that σ (no longer parallel), exact
    hits, no spot noise; the spread of the estimates is the reported systematic term."""
    ter, views, _ = scene
    so, sd, n = 0.0005, 0.0005, 60
    rig = pcm_rig(True, so, sd)
    rng = np.random.default_rng(3)

    def exact_obs(origins: np.ndarray, dirs: np.ndarray) -> list[ImageObservation]:
        out = []
        for i, vw in enumerate(views):
            starts, d = vw.C + origins @ vw.R_wc.T, dirs @ vw.R_wc.T
            r = np.linalg.norm(vw.hits - starts, axis=1)
            hw = starts + ter.first_hit(starts, d, r - 0.1, r + 0.1, 400)[:, None] * d
            px = CAM.project((hw - vw.C) @ vw.R_wc)
            hits = tuple(SpotHit(nm, px[j], SIGMA_PX, hw[j] / K, ter.normal(hw[j]))
                         for j, nm in enumerate(("L1", "L2")))
            out.append(ImageObservation(f"im{i}", CAM, Pose(vw.R_wc.T, -vw.R_wc.T @ vw.C / K),
                                        None, hits))
        return out

    nominal = fuse_pcm_joint(exact_obs(O_TRUE, np.tile(V_TRUE, (2, 1))), rig, OPTS)
    assert nominal.value == pytest.approx(K, rel=1e-9) and nominal.std_systematic > 0
    draws = []
    for _ in range(n):
        o = O_TRUE + np.c_[rng.normal(scale=so, size=(2, 2)), np.zeros(2)]
        v = V_TRUE + rng.normal(scale=sd, size=(2, 3)) @ (np.eye(3) - np.outer(V_TRUE, V_TRUE))
        draws.append(fuse_pcm_joint(exact_obs(o, v / np.linalg.norm(v, axis=1)[:, None]), rig,
                                    replace(OPTS, birge_inflation=False)).value)
    ratio = np.std(draws, ddof=1) / nominal.std_systematic
    assert 0.8 <= ratio <= 1.25, ratio


# ---------------------------------------------------------------- fallback and rejection


def test_fewer_than_three_images_falls_back_to_the_midpoint_approximation(scene):
    ter, views, pose_cov = scene
    rig = pcm_rig()
    obs = observe(ter, views[:2], np.random.default_rng(4), SIGMA_PX, pose_cov)
    res = estimate_pcm_joint(obs, rig, OPTS)
    assert not res.joint and not res.pairs[0].joint
    assert res.fused.method == "pcm_joint"
    assert res.fused.notes[0] == "fewer than 3 images: midpoint approximation"
    assert "only 2 usable image(s)" in res.fused.notes[1]
    assert res.fused.value == pytest.approx(midpoint_pcm(obs, rig), rel=1e-12)


@pytest.mark.parametrize("fault", ["20px", "swapped"])
def test_an_image_with_a_wrong_spot_is_rejected_with_a_reason(scene, fault):
    ter, views, pose_cov = scene
    rng = np.random.default_rng(5)
    offset = {3: np.array([[0.0, 0.0], [20.0, 0.0]])} if fault == "20px" else None
    obs = observe(ter, views, rng, SIGMA_PX, pose_cov, offset)
    if fault == "swapped":
        h1, h2 = obs[3].hits
        obs[3] = replace(obs[3], hits=(replace(h1, laser="L2"), replace(h2, laser="L1")))
    res = estimate_pcm_joint(obs, pcm_rig(), OPTS)
    f = res.fused
    assert res.joint and f.n_rejected == 1 and f.n_estimates == N_VIEWS - 1
    (image, pair, reason), = f.rejected
    assert (image, pair) == ("im03", "L1+L2")
    assert reason.startswith("inconsistent with the beams fitted to the other images")
    assert "im03" not in f.per_image and "im03" not in f.images_used
    assert abs(f.value - K) < 4 * f.std


def test_rejection_leaving_two_images_falls_back(scene):
    ter, views, pose_cov = scene
    obs = observe(ter, views[:3], np.random.default_rng(6), SIGMA_PX, pose_cov,
                  {1: np.array([[0.0, 0.0], [20.0, 0.0]])})
    res = estimate_pcm_joint(obs, pcm_rig(), OPTS)
    assert not res.joint
    assert res.fused.notes[0] == "fewer than 3 images: midpoint approximation"
    dropped = [im for im in res.pairs[0].images if im.rejected]
    assert [im.image for im in dropped] == ["im01"]


def test_same_depth_in_every_image_leaves_the_direction_undetermined():
    rig = make_rig4()
    scene = make_scene(rig)
    obs = [observe_plane(scene, np.random.default_rng(7), 0.0, None, name=f"im{i}",
                         sigma_claimed=0.3) for i in range(4)]
    res = estimate_pcm_joint(obs, rig, OPTS)
    assert not res.joint
    assert res.fused.notes[0] == "no joint beam direction: midpoint approximation"
    assert all("beam direction not determined" in (p.reason or "") for p in res.pairs)


def test_grazing_image_is_rejected_and_options_are_checked(scene):
    obs = clean_obs(scene)
    h1, h2 = obs[0].hits
    ray = h1.hit_world - obs[0].cam_from_world.center
    graze = np.cross(ray / np.linalg.norm(ray), [0.0, 0.0, 1.0])
    obs[0] = replace(obs[0], hits=(replace(h1, normal_world=graze), h2))
    f = fuse_pcm_joint(obs, pcm_rig())
    assert f.n_rejected == 1 and "grazes the mesh" in f.rejected[0][2]
    assert f.value == pytest.approx(K, rel=1e-9)
    with pytest.raises(ValueError, match="min_images"):
        fuse_pcm_joint(obs, pcm_rig(), replace(OPTS, min_images=1))


# ---------------------------------------------------------------- invariance, several pairs


def scaled(obs: ImageObservation, c: float) -> ImageObservation:
    """The same observation in a world scaled by c about its origin (pose covariance too)."""
    pose = obs.cam_from_world
    cov = obs.pose_covariance
    if cov is not None:
        t = np.diag([1.0, 1, 1, c, c, c])
        cov = t @ cov @ t
    return ImageObservation(obs.image, obs.camera, Pose(pose.R, c * pose.t), cov,
                            tuple(replace(h, hit_world=c * h.hit_world) for h in obs.hits))


@pytest.mark.parametrize("c", [0.05, 7.0])
def test_scaling_the_world_by_k_scales_the_estimate_by_its_inverse(scene, c):
    ter, views, pose_cov = scene
    obs = observe(ter, views, np.random.default_rng(8), SIGMA_PX, pose_cov)
    a = fuse_pcm_joint(obs, pcm_rig())
    b = fuse_pcm_joint([scaled(o, c) for o in obs], pcm_rig())
    assert b.value == pytest.approx(a.value / c, rel=1e-9)
    assert b.std == pytest.approx(a.std / c, rel=1e-6)
    assert b.birge_ratio == pytest.approx(a.birge_ratio, rel=1e-6)


def test_two_pairs_are_combined_with_their_shared_noise():
    """4-laser rig of the planar fixtures (two pairs, different directions); five views."""
    rig = make_rig4()
    rng = np.random.default_rng(9)
    pose_cov = pose_covariance(rng)
    geometry = [(2.0, 30.0), (3.0, -20.0), (4.0, 35.0), (2.5, 10.0), (3.5, -35.0)]
    scenes = [make_scene(rig, distance_m=d, tilt_deg=a, tilt_axis=(1.0, 0.3, 0.0))
              for d, a in geometry]

    def draw(sigma: float, cov: np.ndarray | None) -> list[ImageObservation]:
        return [observe_plane(s, rng, sigma, cov, name=f"im{i}", sigma_claimed=0.3)
                for i, s in enumerate(scenes)]

    clean = estimate_pcm_joint(draw(0.0, None), rig, OPTS)
    assert clean.joint and clean.fused.value == pytest.approx(K_TRUE, rel=1e-9)
    for fit, pair in zip(clean.pairs, rig.pairs, strict=True):
        truth = np.asarray(rig.laser(pair.lasers[0]).direction, dtype=np.float64)
        assert np.allclose(fit.direction_cam, truth, atol=1e-9)
    assert clean.fused.n_estimates == 10 and len(clean.fused.images_used) == 5
    runs = [estimate_pcm_joint(draw(0.3, pose_cov), rig, replace(OPTS, birge_inflation=False))
            for _ in range(150)]
    values = np.array([r.fused.value for r in runs])
    sigma = np.sqrt(np.mean([r.fused.std_random**2 for r in runs]))
    assert 0.85 <= values.std(ddof=1) / sigma <= 1.2
    assert sigma < min(np.sqrt(np.mean([p.sigma_random**2 for r in runs for p in r.pairs])),
                       1.0)
    assert abs(values.mean() / K_TRUE - 1) < 4 * values.std(ddof=1) / K_TRUE / np.sqrt(150)


# ---------------------------------------------------------------- pipeline headline


def _runs(obs: list[ImageObservation], rig: Rig) -> list[Any]:
    from sfm_laserscale.run_types import ImageRun

    return [ImageRun(name=o.image, path=None, camera=o.camera,  # type: ignore[arg-type]
                     registration=SimpleNamespace(cam_from_world=o.cam_from_world,  # type: ignore[arg-type]
                                                  covariance=o.pose_covariance),
                     detection=None, spots=(), hits=o.hits, spot_reasons={},
                     estimates=estimate_image(o, rig, EstimationOptions()), reason=None)
            for o in obs]


@pytest.mark.parametrize("n_images, headline", [(N_VIEWS, "pcm_joint"), (2, "pcm")])
def test_pipeline_headline_is_pcm_joint_when_available(scene, n_images, headline):
    from sfm_laserscale.commands.scale import fuse_all
    from sfm_laserscale.run_types import ScaleOptions

    ter, views, pose_cov = scene
    rig = pcm_rig()
    obs = observe(ter, views[:n_images], np.random.default_rng(10), SIGMA_PX, pose_cov)
    res = fuse_all(_runs(obs, rig), rig, ScaleOptions())
    head, fused = res.headline, res.methods
    assert set(fused) == {"fcm", "pcm", "direct3d", "pcm_joint"}
    assert head.method == headline
    assert fused["pcm_joint"].value == pytest.approx(fuse_pcm_joint(obs, rig).value, rel=1e-12)
