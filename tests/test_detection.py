"""Laser spot detection and assignment on painted images with known spot centres."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from sfm_laserscale.detection import (
    UNCALIBRATED_REASON,
    DetectionOptions,
    DetectionResult,
    beam_polyline_px,
    blob_response,
    clutter_level,
    default_band_px,
    detect_spots,
    distance_to_polyline,
)
from sfm_laserscale.detection.beams import range_along_beam, search_region
from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import Laser, Rig, rig_from_dict
from sfm_laserscale.synthetic.spots import paint_spot, to_uint8

PINHOLE = Camera(1, "PINHOLE", 1024, 768, np.array([900.0, 900.0, 512.0, 384.0]))
CAST = (0.10, 0.32, 0.36)  # blue-green water


def background(rng: np.random.Generator, h: int, w: int, haze: float = 0.12) -> np.ndarray:
    """Smooth multi-octave noise texture with a blue-green cast and haze, linear RGB."""
    tex = np.zeros((h, w), np.float32)
    for sigma, amp in [(40, 0.5), (12, 0.3), (3, 0.2)]:
        n = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
        tex += amp * n / (n.std() + 1e-9)
    tex = np.clip(0.8 + 0.25 * tex, 0.2, 1.6)
    cast = np.asarray(CAST, np.float32)
    return (tex[..., None] * cast * (1 - haze) + haze * 1.2 * cast).astype(np.float32)


def four_laser_rig(rng: np.random.Generator, color: str = "red") -> Rig:
    """Lasers 0.165 m off the camera centre (±x, ±y), directions 1–3° off the optical axis."""
    lasers = []
    for i, origin in enumerate([(0.165, 0, 0), (-0.165, 0, 0), (0, 0.165, 0), (0, -0.165, 0)]):
        tilt, az = math.radians(rng.uniform(1, 3)), rng.uniform(0, 2 * math.pi)
        direction = [math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), math.cos(tilt)]
        lasers.append({"name": f"L{i + 1}", "origin": list(origin), "direction": direction,
                       "color": color})
    return rig_from_dict({"name": "test rig", "laser": lasers})


def spot_positions(rng: np.random.Generator, camera: Camera, rig: Rig,
                   min_sep: float = 60.0) -> dict[str, np.ndarray]:
    """Projections of beam points at ranges 1.5–4 m, at least ``min_sep`` px apart if possible."""
    best: tuple[float, dict[str, np.ndarray]] | None = None
    for _ in range(300):
        ranges = rng.uniform(1.5, 4.0, len(rig.lasers))
        xy = {las.name: camera.project(beam_point(las, r))[0]
              for las, r in zip(rig.lasers, ranges, strict=True)}
        pts = np.array(list(xy.values()))
        sep = min(float(np.linalg.norm(pts[i] - pts[j]))
                  for i in range(len(pts)) for j in range(i))
        if best is None or sep > best[0]:
            best = (sep, xy)
        if sep > min_sep:
            break
    assert best is not None
    return best[1]


def beam_point(las: Laser, range_m: float) -> np.ndarray:
    """Camera-frame point of a calibrated beam at ``range_m`` from its origin (metres)."""
    assert las.origin is not None and las.direction is not None
    return np.asarray(las.origin + range_m * las.direction)


@dataclass
class Scene:
    image: np.ndarray  # (H, W, 3) uint8
    camera: Camera
    rig: Rig
    truth: dict[str, np.ndarray]


Painter = Callable[[np.ndarray, Rig, dict[str, np.ndarray]], None]


def make_scene(seed: int, color: str = "red", camera: Camera = PINHOLE, noise: float = 0.01,
               skip: tuple[str, ...] = (), extra: Painter | None = None) -> Scene:
    """A textured image with one spot painted on each beam (except ``skip``)."""
    rng = np.random.default_rng(seed)
    rig = four_laser_rig(rng, color)
    img = background(rng, camera.height, camera.width)
    truth = spot_positions(rng, camera, rig)
    for name, xy in truth.items():
        if name not in skip:
            paint_spot(img, (float(xy[0]), float(xy[1])), color,
                       sigma_px=rng.uniform(1.2, 3.0), peak=rng.uniform(1.5, 4.0))
    if extra is not None:
        extra(img, rig, truth)
    img += rng.normal(0.0, noise, img.shape).astype(np.float32)
    # gamma-encoded like a camera JPEG (detection decodes with input_gamma = 2.2 by default);
    # the other tests feed linear images, which must work as well
    visible = {k: v for k, v in truth.items() if k not in skip}
    return Scene(to_uint8(img, gamma=2.2), camera, rig, visible)


def errors_px(result: DetectionResult, truth: dict[str, np.ndarray]) -> dict[str, float]:
    """Laser -> distance (px) of its detected spot from the truth."""
    got = {s.laser: np.array([s.x, s.y]) for s in result.spots}
    return {k: float(np.linalg.norm(got[k] - truth[k])) for k in truth if k in got}


# ----------------------------------------------------------------------------- painter


@pytest.mark.parametrize("elongation", [None, (7.0, -3.0)])
def test_painted_spot_centroid_is_exact(elongation: tuple[float, float] | None) -> None:
    img = np.zeros((80, 90, 3), np.float32)
    xy = (41.37, 38.81)
    paint_spot(img, xy, "green", sigma_px=1.8, elongation=elongation)
    w = img.astype(np.float64).sum(axis=2)
    yy, xx = np.mgrid[0:80, 0:90] + 0.5  # COLMAP pixel centres
    assert (w * xx).sum() / w.sum() == pytest.approx(xy[0], abs=1e-3)
    assert (w * yy).sum() / w.sum() == pytest.approx(xy[1], abs=1e-3)


def test_painted_core_saturates_white_with_coloured_halo() -> None:
    img = np.full((60, 60, 3), CAST, np.float32)
    paint_spot(img, (30.0, 30.0), "red", sigma_px=2.0, peak=3.0)
    u8 = to_uint8(img)
    assert u8[29, 29].tolist() == [255, 255, 255]  # clipped white core
    halo = u8[29, 36].astype(int) - u8[0, 0].astype(int)  # 6.5 px out, minus background
    assert halo[0] > 30 and halo[1] < 10 and halo[2] < 10  # red halo


def test_to_uint8_gamma() -> None:
    img = np.array([[[0.25, 1.5, -0.1]]], np.float32)
    assert to_uint8(img).tolist() == [[[64, 255, 0]]]
    assert to_uint8(img, gamma=2.0).tolist() == [[[128, 255, 0]]]


# ----------------------------------------------------------------------------- geometry


def test_distance_to_polyline() -> None:
    line = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    pts = np.array([[5.0, 3.0], [12.0, 5.0], [-3.0, -4.0], [10.0, 10.0]])
    np.testing.assert_allclose(distance_to_polyline(pts, line), [3.0, 2.0, 5.0, 0.0])
    assert np.isinf(distance_to_polyline(pts, np.zeros((0, 2)))).all()


def test_beam_polyline_follows_the_beam() -> None:
    rig = four_laser_rig(np.random.default_rng(0))
    las = rig.lasers[0]
    line = beam_polyline_px(PINHOLE, las, 0.5, 10.0)
    for r in (0.5, 1.7, 9.9):
        xy = PINHOLE.project(beam_point(las, r))
        assert distance_to_polyline(xy, line)[0] < 1e-6  # pinhole: the image of a line
    # the camera-frame origin spacing: at 0.5 m the spot is ~900*0.165/0.5 px off its VP
    assert np.ptp(line[:, 0]) == pytest.approx(900 * 0.165 * (1 / 0.5 - 1 / 10), rel=0.1)


# ----------------------------------------------------------------------------- accuracy


@pytest.mark.parametrize("color", ["red", "green"])
def test_spots_on_beams_found_subpixel_and_assigned(color: str) -> None:
    errs, n_cand = [], 0
    for seed in range(12):
        scene = make_scene(seed, color)
        res = detect_spots(scene.image, scene.camera, scene.rig)
        assert {s.laser for s in res.spots} == set(scene.truth), res.missing
        assert res.missing == {}
        e = errors_px(res, scene.truth)
        errs += list(e.values())
        n_cand += len(res.candidates)
        for s in res.spots:
            assert 0.0 < s.score <= 1.0 and s.source == "detected"
            assert 0.05 <= s.sigma_px < 0.5
    rms = math.sqrt(float(np.mean(np.square(errs))))
    assert rms < 0.15, f"{color}: RMS {rms:.3f} px"  # measured: red ~0.03, green ~0.04 px
    assert max(errs) < 0.4


def test_gaussian_fit_refinement_also_accurate() -> None:
    errs = []
    for seed in range(6):
        scene = make_scene(100 + seed, "red")
        opts = DetectionOptions(refine="gaussian")
        res = detect_spots(scene.image, scene.camera, scene.rig, opts)
        e = errors_px(res, scene.truth)
        assert len(e) == 4
        errs += list(e.values())
    assert math.sqrt(float(np.mean(np.square(errs)))) < 0.15


def test_centroid_is_unbiased_on_clean_spots() -> None:
    """No texture, little noise: mean signed error well below 0.02 px on both axes."""
    rng = np.random.default_rng(7)
    rig = four_laser_rig(rng)
    signed = []
    for _ in range(10):
        img = np.full((PINHOLE.height, PINHOLE.width, 3), CAST, np.float32)
        truth = spot_positions(rng, PINHOLE, rig)
        for xy in truth.values():
            paint_spot(img, (float(xy[0]), float(xy[1])), "red", sigma_px=rng.uniform(1.2, 3.0),
                       peak=rng.uniform(1.5, 4.0))
        img += rng.normal(0, 0.005, img.shape).astype(np.float32)
        res = detect_spots(to_uint8(img), PINHOLE, rig)
        signed += [np.array([s.x, s.y]) - truth[s.laser] for s in res.spots]
    signed_arr = np.array(signed)
    assert len(signed_arr) == 40
    assert np.all(np.abs(signed_arr.mean(axis=0)) < 0.02)
    assert math.sqrt(float(np.mean(np.sum(signed_arr**2, axis=1)))) < 0.1


def test_motion_blurred_spot_keeps_its_centre() -> None:
    rng = np.random.default_rng(3)
    rig = four_laser_rig(rng)
    img = background(rng, PINHOLE.height, PINHOLE.width)
    truth = spot_positions(rng, PINHOLE, rig)
    for xy in truth.values():
        paint_spot(img, (float(xy[0]), float(xy[1])), "red", sigma_px=1.5, peak=3.0,
                   elongation=(6.0, 2.0))
    img += rng.normal(0, 0.01, img.shape).astype(np.float32)
    res = detect_spots(to_uint8(img), PINHOLE, rig)
    e = errors_px(res, truth)
    assert len(e) == 4 and max(e.values()) < 0.3


def test_weaker_spots_get_larger_sigma() -> None:
    def mean_sigma(peak: float, noise: float) -> float:
        rng = np.random.default_rng(11)
        rig = four_laser_rig(rng)
        img = background(rng, PINHOLE.height, PINHOLE.width)
        truth = spot_positions(rng, PINHOLE, rig)
        for xy in truth.values():
            paint_spot(img, (float(xy[0]), float(xy[1])), "red", sigma_px=2.0, peak=peak)
        img += rng.normal(0, noise, img.shape).astype(np.float32)
        res = detect_spots(to_uint8(img), PINHOLE, rig, DetectionOptions(
            sigma_floor_px=0.0, sigma_window_gain=0.0, sigma_asymmetry_gain=0.0,
            sigma_chroma_px=0.0))
        assert len(res.spots) == 4
        return float(np.mean([s.sigma_px for s in res.spots]))

    assert mean_sigma(0.25, 0.04) > 3.0 * mean_sigma(3.0, 0.005)


# ----------------------------------------------------------------------------- distractors


def test_sigma_grows_with_light_that_is_not_point_symmetric() -> None:
    """A clean spot's sigma is the floor; a laser-coloured bar 4-7 px beside each spot pulls
    its centre ~1.5 px and its sigma grows with it (the window's shift, the asymmetry), while
    without those terms it would stay at the floor (the colour term left out: it does not
    depend on the bar, test_a_centre_read_from_colour_holds_the_colour_term). Measured with
    the narrower windows, the crosstalk centre and the brightness peak off (each core's red
    clips, so it is found on the brightness response; with the others off, the sub-pixel
    peak of that response re-centres one of the four: tests/test_detection_wandered.py);
    with the narrower windows, a spot whose
    narrow window states a σ half as large is re-centred on the spot, with the distance moved
    in its σ (tests/test_detection_narrow_window.py). The spots' red channel clips, and the bar
    lies in red alone: read on green and blue (the crosstalk centre, on by default), every
    core is re-centred within 0.35 px (tests/test_detection_crosstalk.py)."""
    def spots(bar: float, **kw: float) -> list[tuple[float, float]]:
        kw = {"sigma_chroma_px": 0.0, **kw}
        rng = np.random.default_rng(5)
        rig = four_laser_rig(rng)
        img = background(rng, PINHOLE.height, PINHOLE.width)
        truth = spot_positions(rng, PINHOLE, rig)
        yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]] + 0.5
        for xy in truth.values():
            paint_spot(img, (float(xy[0]), float(xy[1])), "red", sigma_px=2.0, peak=1.0)
            near = (xx - xy[0] > 4.0) & (xx - xy[0] < 7.0) & (abs(yy - xy[1]) < 6.0)
            img[near, 0] += bar
        img += rng.normal(0, 0.01, img.shape).astype(np.float32)
        res = detect_spots(to_uint8(img), PINHOLE, rig, DetectionOptions(**kw))
        e = errors_px(res, truth)
        return [(e[s.laser], s.sigma_px) for s in res.spots]

    clean = spots(0.0)
    pulled = spots(0.5, narrow_window_ratio=0.0, crosstalk_max_noise_px=0.0, peak_apart_px=0.0)
    flat = spots(0.5, sigma_window_gain=0.0, sigma_asymmetry_gain=0.0, narrow_window_ratio=0.0,
                 crosstalk_max_noise_px=0.0, peak_apart_px=0.0)
    assert len(clean) == len(pulled) == 4
    assert all(e < 0.1 and 0.1 <= s < 0.11 for e, s in clean)
    assert all(e > 1.0 and s > 0.2 for e, s in pulled)
    assert all(s == pytest.approx(0.1, abs=1e-3) for _, s in flat)
    # measured: two of the four re-centred, 0.012 and 0.025 px off
    narrowed = spots(0.5, crosstalk_max_noise_px=0.0, peak_apart_px=0.0)
    assert sum(e < 0.1 for e, _ in narrowed) >= 2
    assert all((e < 0.1 and s > 0.4) or (e > 1.0 and s > 0.2) for e, s in narrowed)
    # measured: 0.02-0.30 px off, σ 0.109-0.119 px
    assert all(e < 0.35 and s < 0.15 for e, s in spots(0.5))


def test_a_centre_read_from_colour_holds_the_colour_term() -> None:
    """A red spot is centred on its texture-free light, a colour difference sampled in 2 × 2
    (Bayer red photosites, 4:2:0 chroma): its σ² gains (0.3 px / half-max radius)², and its
    centre does not move."""
    rng = np.random.default_rng(5)
    rig = four_laser_rig(rng)
    img = background(rng, PINHOLE.height, PINHOLE.width)
    truth = spot_positions(rng, PINHOLE, rig)
    for xy, sigma in zip(truth.values(), (0.7, 1.2, 2.0, 3.0), strict=True):
        paint_spot(img, (float(xy[0]), float(xy[1])), "red", sigma_px=sigma, peak=2.0)
    img += rng.normal(0, 0.01, img.shape).astype(np.float32)
    image = to_uint8(img)
    # the crosstalk centre off: it reads no colour difference (no chroma term) and would take
    # some of these clipped cores
    plain = detect_spots(image, PINHOLE, rig,
                         DetectionOptions(sigma_chroma_px=0.0, crosstalk_max_noise_px=0.0))
    res = detect_spots(image, PINHOLE, rig, DetectionOptions(crosstalk_max_noise_px=0.0))
    assert len(res.spots) == len(plain.spots) == 4
    for s, p in zip(res.spots, plain.spots, strict=True):
        (c,) = [c for c in res.candidates if (c.x, c.y) == (s.x, s.y)]
        assert (s.x, s.y) == (p.x, p.y)
        assert s.sigma_px == pytest.approx(math.hypot(p.sigma_px, 0.3 / max(1.0, c.radius_px)))
    radii = sorted(c.radius_px for c in res.candidates if c.laser)
    assert radii[0] < 1.6 and radii[-1] > 3.0  # the term shrinks as the spot grows
    with pytest.raises(InputError, match="sigma_chroma_px"):
        DetectionOptions(sigma_chroma_px=-0.1)


def _range_of(rig: Rig, name: str, xy: np.ndarray) -> float:
    """Range (m) of the beam's point nearest the image point ``xy``."""
    region = search_region(PINHOLE, rig, DetectionOptions())
    return float(range_along_beam(xy, region.polylines[name], region.ranges[name])[0])


def _glint_px(rig: Rig, truth: dict[str, np.ndarray]) -> np.ndarray:
    """A point of L4's beam whose range is at least 35 % from every other spot's range."""
    las = rig.laser("L4")
    assert las.origin is not None and las.direction is not None
    others = [_range_of(rig, n, xy) for n, xy in truth.items() if n != "L4"]
    r4 = _range_of(rig, "L4", truth["L4"])
    r = next(r4 * k for k in (1.4, 0.7, 1.8, 0.5, 2.5, 0.35)
             if 0.6 < r4 * k < 9.0 and all(abs(math.log(r4 * k / o)) > 0.3 for o in others))
    return PINHOLE.project((las.origin + r * las.direction)[None, :])[0]


def _distractors(img: np.ndarray, rig: Rig, truth: dict[str, np.ndarray]) -> None:
    """White highlight and a huge red blob near L4's band (L4's spot is absent), and a
    compact red blob far off every band."""
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]] + 0.5
    near = truth["L4"]
    # specular highlight: very bright, white, no colour halo, on L4's beam away from the other
    # spots' ranges (a white clipped blob at their range is read as a whitened laser core,
    # docs/DETECTION.md)
    glint = _glint_px(rig, truth)
    r2 = (xx - glint[0]) ** 2 + (yy - glint[1]) ** 2
    img += (2.5 * np.exp(-0.5 * r2 / 2.0**2))[..., None].astype(np.float32)
    # huge red blob (organism) with its edge near L4's beam, 45 px further out on its segment
    line = beam_polyline_px(PINHOLE, rig.laser("L4"), 0.5, 10.0)
    far_end = line[-1] if np.linalg.norm(line[-1] - near) > np.linalg.norm(line[0] - near) \
        else line[0]
    d = (far_end - near) / np.linalg.norm(far_end - near)
    c = near + 70.0 * d
    r2 = (xx - c[0]) ** 2 + (yy - c[1]) ** 2
    blob = np.exp(-0.5 * (r2 / 30.0**2) ** 2)  # flat-topped, radius ~ 35 px
    img += (blob[..., None] * np.array([0.9, 0.02, 0.02])).astype(np.float32)
    # compact red organism off every band (top-left quadrant, far from the centre)
    r2 = (xx - 120.0) ** 2 + (yy - 110.0) ** 2
    img += (np.exp(-0.5 * r2 / 2.5**2)[..., None] * np.array([2.0, 0.1, 0.1])).astype(np.float32)


def test_distractors_rejected_and_missing_laser_reported() -> None:
    for seed in range(4):
        scene = make_scene(200 + seed, "red", skip=("L4",), extra=_distractors)
        res = detect_spots(scene.image, scene.camera, scene.rig)
        assert {s.laser for s in res.spots} == {"L1", "L2", "L3"}
        assert "L4" in res.missing and res.missing["L4"]
        e = errors_px(res, scene.truth)
        assert max(e.values()) < 0.4
        assert any(c.reason.startswith("too large") for c in res.candidates)  # the big blob
        # nothing is assigned to the red organism off the bands
        for s in res.spots:
            assert math.hypot(s.x - 120.0, s.y - 110.0) > 10


def test_off_band_red_blob_is_reported_as_candidate_not_spot() -> None:
    rng = np.random.default_rng(301)
    rig = four_laser_rig(rng)
    lines = [beam_polyline_px(PINHOLE, las, 0.5, 10.0) for las in rig.lasers]
    # a place between the beam bands, inside the searched region: >= 40 px from every band
    angles = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    ring = np.column_stack([512 + 150 * np.cos(angles), 384 + 150 * np.sin(angles)])
    clearance = np.min([distance_to_polyline(ring, ln) for ln in lines], axis=0)
    blob_xy = ring[int(np.argmax(clearance))]
    assert clearance.max() > 40

    img = background(rng, PINHOLE.height, PINHOLE.width)
    truth = spot_positions(rng, PINHOLE, rig)
    for xy in [*truth.values(), blob_xy]:
        paint_spot(img, (float(xy[0]), float(xy[1])), "red", sigma_px=2.0, peak=3.0)
    img += rng.normal(0, 0.01, img.shape).astype(np.float32)
    res = detect_spots(to_uint8(img), PINHOLE, rig)
    assert len(res.spots) == 4 and max(errors_px(res, truth).values()) < 0.3
    blob = [c for c in res.candidates if math.dist((c.x, c.y), blob_xy) < 2.0]
    assert len(blob) == 1 and blob[0].laser is None and "beam band" in blob[0].reason


def test_low_score_spot_goes_to_missing_with_reason() -> None:
    scene = make_scene(5, "red")
    res = detect_spots(scene.image, scene.camera, scene.rig, DetectionOptions(min_score=0.999))
    assert res.spots == ()
    assert all("min_score" in res.missing[n] for n in scene.rig.names)


# ----------------------------------------------------------------------------- cameras, border


def _single_laser_through(camera: Camera, xy_px: tuple[float, float], range_m: float,
                          color: str = "red") -> Rig:
    """A one-laser rig whose beam hits the pixel ``xy_px`` at ``range_m`` from its origin."""
    origin = np.array([0.165, 0.0, 0.0])
    ray = camera.unproject(np.array([xy_px]))[0]
    # point on the pixel's ray at distance range_m from origin: solve |t·ray - O| = range
    a, b, c = ray @ ray, -2 * ray @ origin, origin @ origin - range_m**2
    t = (-b + math.sqrt(b * b - 4 * a * c)) / (2 * a)
    direction = t * ray - origin
    return rig_from_dict({"laser": [{"name": "L1", "origin": origin.tolist(),
                                     "direction": direction.tolist(), "color": color}]})


@pytest.mark.parametrize("xy", [(4.3, 300.7), (700.2, 764.1), (1021.6, 2.4)])
def test_spot_at_image_border(xy: tuple[float, float]) -> None:
    rng = np.random.default_rng(9)
    rig = _single_laser_through(PINHOLE, xy, 2.0)
    img = background(rng, PINHOLE.height, PINHOLE.width)
    paint_spot(img, xy, "red", sigma_px=1.5, peak=3.0)
    img += rng.normal(0, 0.01, img.shape).astype(np.float32)
    res = detect_spots(to_uint8(img), PINHOLE, rig)
    assert len(res.spots) == 1, res.missing
    # the spot is cut by the border: refined by a model fit to its visible part
    assert math.hypot(res.spots[0].x - xy[0], res.spots[0].y - xy[1]) < 0.5


def test_simple_radial_camera_uses_the_distortion_model() -> None:
    cam = Camera(2, "SIMPLE_RADIAL", 1024, 768, np.array([900.0, 512.0, 384.0, -0.2]))
    pinhole = Camera(3, "PINHOLE", 1024, 768, np.array([900.0, 900.0, 512.0, 384.0]))
    rng = np.random.default_rng(21)
    band = default_band_px(cam.width, cam.height)
    truth = {}
    # beams ~20° off axis whose image segments run tangentially, where barrel distortion moves
    # them sideways (across the band) rather than along themselves
    beams = [((0.165, 0.0), (0.0, -0.38)), ((-0.165, 0.0), (0.0, 0.38)),
             ((0.0, 0.165), (0.45, 0.0))]
    rig = rig_from_dict({"laser": [
        {"name": f"L{i + 1}", "origin": [o[0], o[1], 0.0], "direction": [d[0], d[1], 1.0],
         "color": "red"} for i, (o, d) in enumerate(beams)]})
    img = background(rng, cam.height, cam.width)
    for las in rig.lasers:
        xy = cam.project(beam_point(las, 2.5))[0]
        truth[las.name] = xy
        # precondition: the undistorted (pinhole) beam line would miss this spot
        assert distance_to_polyline(xy[None], beam_polyline_px(pinhole, las, 0.5, 10.0))[0] > band
        paint_spot(img, (float(xy[0]), float(xy[1])), "red", sigma_px=2.0, peak=3.0)
    img += rng.normal(0, 0.01, img.shape).astype(np.float32)
    res = detect_spots(to_uint8(img), cam, rig)
    e = errors_px(res, truth)
    assert set(e) == {"L1", "L2", "L3"} and max(e.values()) < 0.3


# ----------------------------------------------------------------------------- rig variants


def _two_spot_image(colors: tuple[str, str]) -> tuple[np.ndarray, list[tuple[float, float]]]:
    rng = np.random.default_rng(31)
    img = background(rng, PINHOLE.height, PINHOLE.width)
    pts = [(400.4, 380.2), (640.7, 390.9)]
    for xy, col in zip(pts, colors, strict=True):
        paint_spot(img, xy, col, sigma_px=2.0, peak=3.0)
    img += rng.normal(0, 0.01, img.shape).astype(np.float32)
    return to_uint8(img), pts


def test_uncalibrated_lasers_same_colour_left_unassigned() -> None:
    img, _ = _two_spot_image(("red", "red"))
    rig = rig_from_dict({"laser": [{"name": "A", "color": "red"}, {"name": "B", "color": "red"}],
                         "pair": [{"lasers": ["A", "B"], "separation": 0.1}]})
    res = detect_spots(img, PINHOLE, rig)
    assert res.spots == ()
    assert res.missing == {"A": UNCALIBRATED_REASON, "B": UNCALIBRATED_REASON}
    seen = [c for c in res.candidates if c.reason.startswith("no calibrated laser")]
    assert len(seen) == 2  # both spots were found, neither could be assigned


def test_uncalibrated_lasers_unique_colours_assigned_by_colour() -> None:
    img, pts = _two_spot_image(("red", "green"))
    rig = rig_from_dict({"laser": [{"name": "A", "color": "green"}, {"name": "B", "color": "red"}],
                         "pair": [{"lasers": ["A", "B"], "separation": 0.1}]})
    res = detect_spots(img, PINHOLE, rig)
    got = {s.laser: (s.x, s.y) for s in res.spots}
    assert math.dist(got["B"], pts[0]) < 0.3 and math.dist(got["A"], pts[1]) < 0.3


def test_any_colour_laser_picks_the_spot_channel() -> None:
    for color in ("green", "blue"):
        scene = make_scene(41, color)
        rig = rig_from_dict({"laser": [
            {"name": las.name, "origin": beam_point(las, 0.0).tolist(),
             "direction": (beam_point(las, 1.0) - beam_point(las, 0.0)).tolist(),
             "color": "any"} for las in scene.rig.lasers]})
        res = detect_spots(scene.image, scene.camera, rig)
        e = errors_px(res, scene.truth)
        assert len(e) == 4 and max(e.values()) < 0.3


def test_beam_outside_image_is_reported() -> None:
    rig = rig_from_dict({"laser": [{"name": "L1", "origin": [0.165, 0, 0],
                                    "direction": [0.9, 0.0, 0.3], "color": "red"}]})
    img = to_uint8(background(np.random.default_rng(1), PINHOLE.height, PINHOLE.width))
    res = detect_spots(img, PINHOLE, rig)
    assert res.spots == () and "outside the image" in res.missing["L1"]


def test_bad_image_raises_input_error() -> None:
    rig = four_laser_rig(np.random.default_rng(0))
    with pytest.raises(InputError, match="1024x768"):
        detect_spots(np.zeros((100, 100, 3), np.uint8), PINHOLE, rig)
    with pytest.raises(InputError, match="RGB"):
        detect_spots(np.zeros((768, 1024), np.uint8), PINHOLE, rig)


def test_full_hd_image_is_fast() -> None:
    cam = Camera(4, "PINHOLE", 1920, 1080, np.array([1600.0, 1600.0, 960.0, 540.0]))
    scene = make_scene(51, "red", camera=cam)
    detect_spots(scene.image, cam, scene.rig)  # warm-up (imports, OpenCV threads)
    t0 = time.perf_counter()
    res = detect_spots(scene.image, cam, scene.rig)
    elapsed = time.perf_counter() - t0
    assert len(res.spots) == 4 and max(errors_px(res, scene.truth).values()) < 0.3
    assert elapsed < 1.0, f"{elapsed:.2f} s"  # measured ~0.15 s (2 slow cores)


def test_clutter_level_measures_texture_not_spots() -> None:
    """A few strong spots hardly move the clutter level of a noisy image; a coarse texture of
    blobs raises it; too few maxima give 0; a negative ratio is refused."""
    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 0.01, (300, 400)).astype(np.float32).clip(0, None)
    base = clutter_level(blob_response(noise, (1.0, 2.0, 4.0)))
    spotted = noise.copy()
    for x, y in [(50, 50), (200, 150), (350, 250), (100, 250)]:
        yy, xx = np.mgrid[0:300, 0:400]
        spotted += 0.5 * np.exp(-0.5 * ((xx - x) ** 2 + (yy - y) ** 2) / 2.0**2).astype(np.float32)
    with_spots = clutter_level(blob_response(spotted, (1.0, 2.0, 4.0)))
    assert base > 0 and abs(with_spots / base - 1.0) < 0.05
    blobs = noise + 0.05 * cv2.GaussianBlur(rng.random((300, 400)).astype(np.float32) ** 8,
                                            (0, 0), 2.0) / 0.01
    assert clutter_level(blob_response(blobs, (1.0, 2.0, 4.0))) > 3.0 * base
    assert clutter_level(np.zeros((20, 20), np.float32)) == 0.0
    with pytest.raises(InputError):
        DetectionOptions(min_clutter_ratio=-1.0)


@pytest.mark.parametrize("gamma", [1.0, 2.2, 0.45])
def test_laser_and_other_planes_decode_then_max_exactly(gamma: float) -> None:
    """Planes made from the uint8 crop (max of the other two channels taken before decoding)
    equal decoding the three channels first, then taking the max: bit for bit."""
    from sfm_laserscale.detection.response import CHANNELS, crop_channels, laser_and_other

    rng = np.random.default_rng(4)
    rgb = rng.integers(0, 256, (40, 50, 3)).astype(np.uint8)
    channels = crop_channels(rgb, (3, 5, 47, 38), gamma)
    decoded = ((rgb[5:38, 3:47].astype(np.float64) / 255.0) ** gamma).astype(np.float32)
    for color, c in CHANNELS.items():
        laser, other = laser_and_other(channels, color)
        o1, o2 = (decoded[..., i] for i in range(3) if i != c)
        assert laser.dtype == other.dtype == np.float32 and laser.shape == (33, 44)
        np.testing.assert_array_equal(laser, decoded[..., c])
        np.testing.assert_array_equal(other, np.maximum(o1, o2))
