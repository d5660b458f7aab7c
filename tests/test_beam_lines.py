"""Learned beam lines (uncalibrated lasers) on closed-form points and rendered images."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from sfm_laserscale.commands.detect import DetectRunOptions, Frame, detect_many
from sfm_laserscale.detection import beam_polyline_px, distance_to_polyline
from sfm_laserscale.detection.beam_lines import (
    BeamLineOptions,
    ImageCandidates,
    learn_beam_lines,
    pseudo_beam,
    rig_with_learned_lines,
)
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.spots import paint_spot, to_uint8

PINHOLE = Camera(1, "PINHOLE", 1024, 768, np.array([900.0, 900.0, 512.0, 384.0]))
RADIAL = Camera(2, "SIMPLE_RADIAL", 1024, 768, np.array([900.0, 512.0, 384.0, -0.15]))
BARE = rig_from_dict({"laser": [{"name": "A", "color": "red"}, {"name": "B", "color": "red"}],
                      "pair": [{"lasers": ["A", "B"], "separation": 0.24}]})


def _beams(dy: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Two parallel beams 0.24 m apart (A left, B right in the image), 2 degrees off axis."""
    t, az = math.radians(2.0), math.radians(200.0)
    d = np.array([math.sin(t) * math.cos(az), math.sin(t) * math.sin(az), math.cos(t)])
    return [(np.array([-0.12, dy, 0.0]), d), (np.array([0.12, dy, 0.0]), d)]


def _candidates(camera: Camera, dy: float, n: int, seed: int, clutter: int = 3
                ) -> tuple[list[ImageCandidates], list[list[np.ndarray]]]:
    """Exact spot positions (normalised) of both beams in n images plus random clutter."""
    rng = np.random.default_rng(seed)
    cands, truth = [], []
    for _ in range(n):
        pts = [o + rng.uniform(1.5, 5.0) * d for o, d in _beams(dy)]
        px = [camera.project(p)[0] for p in pts]
        junk = rng.uniform([0, 0], [camera.width, camera.height], (clutter, 2))
        xy = np.vstack([np.array(px), junk])
        cands.append(ImageCandidates(camera.unproject(xy)[:, :2], ("red",) * len(xy)))
        truth.append(px)
    return cands, truth


@pytest.mark.parametrize("camera", [PINHOLE, RADIAL])
@pytest.mark.parametrize("dy", [0.04, 0.0])  # 0.0: camera in the beams' plane (one shared line)
def test_lines_learned_from_points_and_clutter(camera: Camera, dy: float) -> None:
    cands, truth = _candidates(camera, dy, 12, seed=1)
    res = learn_beam_lines(cands, BARE, camera.focal_px)
    assert set(res.lines) == {"A", "B"} and res.missing == {}
    assert (res.lines["A"].shared_with == "B") == (dy == 0.0)
    rig = rig_with_learned_lines(BARE, res, 0.5, 10.0)
    for k, name in enumerate(("A", "B")):  # A is the left beam: the rule orders by mean x
        line = beam_polyline_px(camera, rig.laser(name), 0.5, 10.0)
        d = distance_to_polyline(np.array([t[k] for t in truth]), line)
        assert d.max() < 0.05, name  # every true spot lies on its learned segment
        other = distance_to_polyline(np.array([t[1 - k] for t in truth]), line)
        assert other.min() > 10.0  # and the other laser's spots are off it


def test_pseudo_beam_spans_the_learned_segment() -> None:
    cands, _ = _candidates(PINHOLE, 0.04, 8, seed=2, clutter=0)
    line = learn_beam_lines(cands, BARE, PINHOLE.focal_px).lines["A"]
    origin, direction = pseudo_beam(line, 0.5, 10.0)
    assert origin[2] == 0.0 and direction[2] > 0 and np.linalg.norm(direction) == \
        pytest.approx(1.0)
    ends = [origin + r * direction for r in (10.0, 0.5)]
    s = [float((e[:2] / e[2] - line.point) @ line.direction) for e in ends]
    np.testing.assert_allclose(s, line.s_range, atol=1e-9)


def test_too_few_images_or_wrong_line_count_is_reported() -> None:
    cands, _ = _candidates(PINHOLE, 0.04, 2, seed=3)
    res = learn_beam_lines(cands, BARE, PINHOLE.focal_px)
    assert res.lines == {} and "needs >= 3" in res.missing["A"]
    # only clutter: no line holds spots of 3 images
    rng = np.random.default_rng(4)
    junk = [ImageCandidates(rng.uniform(-0.5, 0.5, (3, 2)), ("red",) * 3) for _ in range(6)]
    res = learn_beam_lines(junk, BARE, PINHOLE.focal_px, BeamLineOptions(inlier_px=0.5))
    assert res.lines == {} and "ambiguous" in res.missing["B"]


def test_rendered_images_uncalibrated_pair_found_by_learned_lines() -> None:
    rng = np.random.default_rng(5)
    frames, truth = [], []
    for k in range(8):
        img = np.full((PINHOLE.height, PINHOLE.width, 3), (0.1, 0.32, 0.36), np.float32)
        img *= rng.uniform(0.7, 1.3, (PINHOLE.height, 1, 1)).astype(np.float32)  # banding
        pts = [PINHOLE.project(o + rng.uniform(1.5, 4.0) * d)[0] for o, d in _beams(0.04)]
        for p in pts:
            paint_spot(img, (float(p[0]), float(p[1])), "red", sigma_px=2.0, peak=3.0)
        # a red distractor somewhere else
        paint_spot(img, tuple(rng.uniform([100, 100], [900, 300])), "red", sigma_px=2.0)
        img += rng.normal(0, 0.01, img.shape).astype(np.float32)
        u8 = to_uint8(img, gamma=2.2)
        frames.append(Frame(f"{k}.png", PINHOLE, functools.partial(np.asarray, u8)))
        truth.append(pts)
    many = detect_many(frames, BARE, DetectRunOptions())
    assert many.learned is not None and set(many.learned.lines) == {"A", "B"}
    for f, pts in zip(frames, truth, strict=True):
        got = {s.laser: (s.x, s.y) for s in many.results[f.name].spots}
        assert math.dist(got["A"], pts[0]) < 0.3 and math.dist(got["B"], pts[1]) < 0.3
