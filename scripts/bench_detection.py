"""Laser spot detection benchmark on rendered images with known spot centres.

Usage: python scripts/bench_detection.py [--per-condition 20] [--seed 0]

Every image: 1024x768 PINHOLE (f = 900 px), a textured seafloor-like background (multi-octave
noise, blue-green cast, haze), camera noise, gamma-encoded uint8 like a camera JPEG, and spots
painted with :func:`sfm_laserscale.synthetic.spots.paint_spot` (saturated white core, coloured
halo, exact centroid). Conditions are listed in ``CONDITIONS``. Per condition it prints RMS
error (px) of the correctly assigned spots, detection rate (truth spots found within 1.5 px
and assigned to the right laser) and false spots (reported spots that are not, over all
reported spots) and false spots per image. The two "textured seafloor" conditions use the demo
scene's texture (synthetic.scene.make_texture: pebbles, brown patches, speckles) with red
organisms, lit through water as the demo renderer does; one paints no laser at all (every
reported spot is false). ``run_benchmark`` is also used by tests/test_detect_command.py.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.commands.detect import DetectRunOptions, Frame, detect_many
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import Rig, rig_from_dict
from sfm_laserscale.synthetic.scene import SceneOptions, make_texture
from sfm_laserscale.synthetic.spots import paint_spot, to_uint8

CAMERA = Camera(1, "PINHOLE", 1024, 768, np.array([900.0, 900.0, 512.0, 384.0]))
MATCH_PX = 1.5
MIN_SEP_PX = 40.0
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class Condition:
    """How the images of one benchmark condition are made."""

    name: str
    color: str = "red"
    sigma: tuple[float, float] = (1.2, 3.0)
    peak: tuple[float, float] = (1.5, 4.0)
    halo: float = 1.0
    ranges_m: tuple[float, float] = (1.5, 4.0)
    blur_px: tuple[float, float] | None = None
    haze: float = 0.12
    cast: tuple[float, float, float] = (0.10, 0.32, 0.36)
    noise: float = 0.01
    distractors: bool = False
    border: bool = False
    n_missing: int = 0
    uncalibrated: str | None = None  # None | "distinct" | "shared" (learned beam lines)
    blurred: bool = False  # target class: < 0.5 px instead of < 0.2 px
    gap_px: tuple[float, float] = (MIN_SEP_PX, math.inf)  # wanted nearest-spot distance
    seafloor: bool = False  # the demo's seafloor texture, lit through water, red organisms
    lasers_on: bool = True  # False: no spot painted (every reported spot is false)


CONDITIONS = (
    Condition("clean red (saturated core, red halo)"),
    Condition("clean green", color="green"),
    Condition("motion blur 4-12 px", blur_px=(4.0, 12.0), blurred=True),
    Condition("defocus sigma 3.5-6 px", sigma=(3.5, 6.0), peak=(0.8, 2.0), blurred=True),
    Condition("defocus, overlapping halos (spots 40-50 px apart)", sigma=(3.5, 6.0),
              peak=(0.8, 2.0), ranges_m=(4.0, 5.5), gap_px=(40.0, 50.0), blurred=True),
    Condition("faint far spots 5-9 m (peak 0.5-1.0)", sigma=(1.0, 1.6), peak=(0.5, 1.0),
              halo=0.3, ranges_m=(5.0, 9.0)),
    Condition("very faint far spots (peak 0.15-0.5)", sigma=(1.0, 1.6), peak=(0.15, 0.5),
              halo=0.3, ranges_m=(5.0, 9.0)),
    Condition("strong cast + haze", cast=(0.04, 0.30, 0.40), haze=0.45, noise=0.015),
    Condition("green in strong cast + haze", color="green", cast=(0.04, 0.30, 0.40),
              haze=0.45, noise=0.015),
    Condition("distractors: highlights, red objects", distractors=True),
    Condition("spots near the border (1.5-12 px)", border=True),
    Condition("missing spots (1-2 occluded)", n_missing=2),
    Condition("uncalibrated pair, learned lines", uncalibrated="distinct"),
    Condition("uncalibrated pair, camera in beam plane", uncalibrated="shared"),
    Condition("no lasers: textured seafloor, red organisms", seafloor=True, lasers_on=False),
    Condition("faint spots on textured seafloor, red organisms", sigma=(1.0, 1.6),
              peak=(0.5, 1.0), halo=0.3, ranges_m=(2.0, 6.0), seafloor=True),
)
#: the demo scene's texture (7 m at 2048 texels: ~1 texel per pixel at 2 m with f = 900 px)
SEAFLOOR = SceneOptions(size_m=(7.0, 7.0), texture_px=2048)
#: the demo renderer's water (synthetic.render.RenderOptions): veiling light, attenuation 1/m
WATER_RGB = np.array([0.015, 0.09, 0.11], np.float32)
ATTENUATION = np.array([0.30, 0.07, 0.06], np.float32)


def background(rng: np.random.Generator, cond: Condition) -> F32:
    """Multi-octave noise texture with a colour cast and haze, linear RGB (H, W, 3)."""
    h, w = CAMERA.height, CAMERA.width
    tex = np.zeros((h, w), np.float32)
    for sigma, amp in [(40, 0.5), (12, 0.3), (3, 0.2)]:
        n = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
        tex += amp * n / (n.std() + 1e-9)
    tex = np.clip(0.8 + 0.25 * tex, 0.2, 1.6)
    cast = np.asarray(cond.cast, np.float32)
    return (tex[..., None] * cast * (1 - cond.haze) + cond.haze * 1.2 * cast).astype(np.float32)


def _red_organisms(tex: F32, rng: np.random.Generator) -> None:
    """In place: 6-14 red to brown organisms (filled ellipses, radius 1.5-25 texels) on a
    texture; reflectance, so lit and attenuated like the floor (no glow)."""
    h, w = tex.shape[:2]
    for _ in range(int(rng.integers(6, 15))):
        r = float(np.exp(rng.uniform(math.log(1.5), math.log(25.0))))
        colour = (rng.uniform(0.5, 0.9), rng.uniform(0.05, 0.3), rng.uniform(0.05, 0.25))
        centre = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        axes = (max(1, round(r)), max(1, round(r * rng.uniform(0.5, 1.0))))
        cv2.ellipse(tex, centre, axes, float(rng.uniform(0, 180)), 0, 360, colour, -1)


def seafloor_background(rng: np.random.Generator) -> F32:
    """A crop of the demo's seafloor texture (pebbles, speckles, brown and red patches) plus
    red organisms, lit as the demo renderer does (two-way attenuation over 1.5-3 m, veiling
    light), linear RGB (H, W, 3)."""
    tex = make_texture(rng, replace(SEAFLOOR, seed=int(rng.integers(1 << 30))), [])
    h, w = CAMERA.height, CAMERA.width
    y0 = int(rng.integers(0, tex.shape[0] - h))
    x0 = int(rng.integers(0, tex.shape[1] - w))
    crop = np.ascontiguousarray(tex[y0 : y0 + h, x0 : x0 + w])
    _red_organisms(crop, rng)
    trans = np.exp(-rng.uniform(1.5, 3.0) * ATTENUATION)
    lamp = rng.uniform(0.8, 1.5)
    return (crop * (lamp * trans * trans) + WATER_RGB * (1.0 - trans)).astype(np.float32)


def _beam(origin: tuple[float, float], tilt_deg: float, az: float) -> dict[str, list[float]]:
    t = math.radians(tilt_deg)
    return {"origin": [origin[0], origin[1], 0.0],
            "direction": [math.sin(t) * math.cos(az), math.sin(t) * math.sin(az), math.cos(t)]}


def calibrated_rig(rng: np.random.Generator, color: str) -> Rig:
    """Four lasers 0.165 m off the camera centre, 1-3 degrees off the optical axis."""
    lasers = [{"name": f"L{i + 1}", "color": color,
               **_beam(o, rng.uniform(1, 3), rng.uniform(0, 2 * math.pi))}
              for i, o in enumerate([(0.165, 0), (-0.165, 0), (0, 0.165), (0, -0.165)])]
    return rig_from_dict({"name": "bench", "laser": lasers})


def border_rig(rng: np.random.Generator, color: str) -> Rig:
    """Four lasers whose spots at 2 m lie 1.5-12 px from each image edge."""
    lasers = []
    w, h = CAMERA.width, CAMERA.height
    for i, side in enumerate(["left", "right", "top", "bottom"]):
        m = rng.uniform(1.5, 12.0)
        xy = {"left": (m, rng.uniform(100, h - 100)), "right": (w - m, rng.uniform(100, h - 100)),
              "top": (rng.uniform(100, w - 100), m), "bottom": (rng.uniform(100, w - 100), h - m)}
        ray = CAMERA.unproject(np.array([xy[side]]))[0]
        origin = np.array([0.165, 0.0, 0.0]) if i % 2 == 0 else np.array([-0.165, 0.0, 0.0])
        direction = 2.0 * ray / np.linalg.norm(ray) - origin
        lasers.append({"name": f"L{i + 1}", "color": color, "origin": origin.tolist(),
                       "direction": direction.tolist()})
    return rig_from_dict({"name": "border", "laser": lasers})


def pcm_rigs(kind: str, color: str) -> tuple[Rig, Rig]:
    """(render rig with known beams, detection rig without them): one parallel pair, lasers
    listed left to right in the image as the learned-line rule wants."""
    dy = 0.0 if kind == "shared" else 0.04
    az = math.radians(200.0)
    beams = [_beam((-0.12, dy), 2.0, az), _beam((0.12, dy), 2.0, az)]
    render = rig_from_dict({"laser": [{"name": f"L{i + 1}", "color": color, **b}
                                      for i, b in enumerate(beams)]})
    bare = rig_from_dict({"laser": [{"name": "L1", "color": color},
                                    {"name": "L2", "color": color}],
                          "pair": [{"lasers": ["L1", "L2"], "separation": 0.24}]})
    return render, bare


def _distractors(img: F32, rng: np.random.Generator, truth: dict[str, NDArray[np.float64]]
                 ) -> None:
    """White specular highlights and compact/large red objects away from the true spots."""
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]] + 0.5
    pts = list(truth.values())
    for k in range(6):
        while True:
            c = rng.uniform([60, 60], [CAMERA.width - 60, CAMERA.height - 60])
            if all(np.linalg.norm(c - p) > 30 for p in pts):
                break
        r2 = (xx - c[0]) ** 2 + (yy - c[1]) ** 2
        if k < 3:  # specular highlight: very bright, white, no coloured halo
            img += (2.5 * np.exp(-0.5 * r2 / rng.uniform(1.5, 3.0) ** 2))[..., None]
        elif k < 5:  # red organism, large and flat-topped
            blob = np.exp(-0.5 * (r2 / rng.uniform(20, 35) ** 2) ** 2)
            img += (blob[..., None] * np.array([0.9, 0.02, 0.02])).astype(np.float32)
        else:  # compact red organism
            img += (np.exp(-0.5 * r2 / 2.5**2)[..., None]
                    * np.array([2.0, 0.1, 0.1])).astype(np.float32)


def _spot_positions(cond: Condition, render: Rig, rng: np.random.Generator
                    ) -> dict[str, NDArray[np.float64]]:
    """True spot centres; ranges redrawn (up to 300 times) until the nearest two spots are
    ``cond.gap_px`` apart (by default >= MIN_SEP_PX: closer spots merge into one blob)."""
    truth: dict[str, NDArray[np.float64]] = {}
    for _ in range(300):
        for las in render.lasers:
            assert las.origin is not None and las.direction is not None
            r = 2.0 if cond.border else rng.uniform(*cond.ranges_m)
            truth[las.name] = CAMERA.project(las.origin + r * las.direction)[0]
        if _gap_ok(cond, truth):
            break
    return truth


def _gap_ok(cond: Condition, truth: dict[str, NDArray[np.float64]]) -> bool:
    """The nearest two spots are ``cond.gap_px`` apart."""
    pts = np.array(list(truth.values()))
    gaps = [np.linalg.norm(pts[i] - pts[j]) for i in range(len(pts)) for j in range(i)]
    return bool(cond.gap_px[0] <= min(gaps, default=np.inf) <= cond.gap_px[1])


def _rig_for(cond: Condition, rng: np.random.Generator) -> Rig:
    """A random calibrated rig (redrawn until its spots can meet ``cond.gap_px``)."""
    make = border_rig if cond.border else calibrated_rig
    rig = make(rng, cond.color)
    if not math.isfinite(cond.gap_px[1]):
        return rig
    for _ in range(100):
        if _gap_ok(cond, _spot_positions(cond, rig, rng)):
            break
        rig = make(rng, cond.color)
    return rig


def make_image(cond: Condition, render: Rig, rng: np.random.Generator
               ) -> tuple[NDArray[np.uint8], dict[str, NDArray[np.float64]]]:
    """One rendered image and the true centres (COLMAP px) of the spots painted in it."""
    img = seafloor_background(rng) if cond.seafloor else background(rng, cond)
    truth = _spot_positions(cond, render, rng) if cond.lasers_on else {}
    hidden = set(rng.choice(render.names, size=int(rng.integers(1, cond.n_missing + 1)),
                            replace=False)) if cond.n_missing else set()
    truth = {k: v for k, v in truth.items() if k not in hidden}
    for xy in truth.values():
        blur = None
        if cond.blur_px is not None:
            a, length = rng.uniform(0, 2 * math.pi), rng.uniform(*cond.blur_px)
            blur = (length * math.cos(a), length * math.sin(a))
        paint_spot(img, (float(xy[0]), float(xy[1])), cond.color,
                   sigma_px=rng.uniform(*cond.sigma), peak=rng.uniform(*cond.peak),
                   elongation=blur, halo=cond.halo)
    if cond.distractors:
        _distractors(img, rng, truth)
    img += rng.normal(0.0, cond.noise, img.shape).astype(np.float32)
    return to_uint8(img, gamma=2.2), truth


@dataclass
class Tally:
    """Counts and errors of one condition."""

    errors: list[float]
    expected: int = 0
    found: int = 0
    reported: int = 0
    false: int = 0
    images: int = 0
    seconds: float = 0.0

    def row(self) -> dict[str, float]:
        rms = math.sqrt(float(np.mean(np.square(self.errors)))) if self.errors else math.nan
        return {"rms_px": rms, "max_px": max(self.errors, default=math.nan),
                "detection_rate": self.found / max(self.expected, 1),
                "false_rate": self.false / max(self.reported, 1),
                "expected": self.expected, "reported": self.reported, "false": self.false,
                "images": self.images, "false_per_image": self.false / max(self.images, 1),
                "seconds": self.seconds}


def run_condition(cond: Condition, n_images: int, seed: int) -> Tally:
    """Render ``n_images`` images of one condition, detect, score against the truth."""
    rng = np.random.default_rng(seed)
    tally = Tally(errors=[])
    images, truths = [], []
    det_rig: Rig | None = None
    render: Rig | None = None
    if cond.uncalibrated is not None:
        render, det_rig = pcm_rigs(cond.uncalibrated, cond.color)
    for _ in range(n_images):
        if cond.uncalibrated is None:
            render = _rig_for(cond, rng)
            det_rig = render
        assert render is not None and det_rig is not None
        img, truth = make_image(cond, render, rng)
        images.append((img, det_rig))
        truths.append(truth)
    t0 = time.perf_counter()
    results = []
    if cond.uncalibrated is not None:
        assert det_rig is not None
        frames = [Frame(f"{k}", CAMERA, _const(img)) for k, (img, _) in enumerate(images)]
        many = detect_many(frames, det_rig, DetectRunOptions())
        results = [many.results[f"{k}"] for k in range(n_images)]
    else:
        for img, rig in images:
            many = detect_many([Frame("x", CAMERA, _const(img))], rig, DetectRunOptions())
            results.append(many.results["x"])
    tally.seconds = time.perf_counter() - t0
    for res, truth in zip(results, truths, strict=True):
        _score(res.spots, truth, tally)
    return tally


def _const(img: NDArray[np.uint8]) -> Callable[[], NDArray[np.uint8]]:
    return lambda: img


def _score(spots: tuple, truth: dict[str, NDArray[np.float64]], tally: Tally) -> None:  # type: ignore[type-arg]
    tally.images += 1
    tally.expected += len(truth)
    tally.reported += len(spots)
    for s in spots:
        t = truth.get(s.laser)
        err = math.inf if t is None else math.hypot(s.x - t[0], s.y - t[1])
        if err <= MATCH_PX:
            tally.found += 1
            tally.errors.append(err)
        else:
            tally.false += 1


def run_benchmark(per_condition: int, seed: int = 0,
                  conditions: tuple[Condition, ...] = CONDITIONS) -> dict[str, dict[str, float]]:
    """Condition name -> metrics (see :meth:`Tally.row`)."""
    return {c.name: run_condition(c, per_condition, seed + 1000 * i).row()
            for i, c in enumerate(conditions)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-condition", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    t0 = time.perf_counter()
    rows = run_benchmark(args.per_condition, args.seed)
    n = args.per_condition * len(CONDITIONS)
    print("| condition | RMS px | max px | detected | false | false/img | spots | detect s |")
    print("|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        print(f"| {name} | {r['rms_px']:.3f} | {r['max_px']:.3f} | "
              f"{100 * r['detection_rate']:.1f} % | {100 * r['false_rate']:.1f} % | "
              f"{r['false_per_image']:.2f} | {r['expected']:.0f} | {r['seconds']:.1f} |")
    tot = {k: sum(r[k] for r in rows.values()) for k in ("expected", "reported", "false")}
    found = sum(r["detection_rate"] * r["expected"] for r in rows.values())
    print(f"\npooled: {found:.0f} of {tot['expected']:.0f} spots found "
          f"({100 * found / max(tot['expected'], 1):.1f} %), {tot['false']:.0f} false of "
          f"{tot['reported']:.0f} reported ({100 * tot['false'] / max(tot['reported'], 1):.1f} %)")
    print(f"\n{n} images, total {time.perf_counter() - t0:.1f} s (rendering included)")


if __name__ == "__main__":
    main()

