"""The floor search: where the spots found in one image put a missing laser's spot (closed form
on planes), and the search there (a spot the band's blobs hide is found, a reason otherwise)."""

from __future__ import annotations

import functools
import math
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, DetectionResult, detect_spots
from sfm_laserscale.detection.assign import RESCUED_PAIR
from sfm_laserscale.detection.beams import search_region
from sfm_laserscale.detection.candidates import Measure
from sfm_laserscale.detection.floor import (
    PLACE,
    beam_range_on_plane,
    default_floor_radius_px,
    floor_plane,
    floor_predictions,
)
from sfm_laserscale.detection.guided import GuidedOptions, search_near
from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import Rig, rig_from_dict
from sfm_laserscale.synthetic.spots import paint_spot, to_uint8
from sfm_laserscale.synthetic.underwater import CONDITIONS, Frame, render_frame
from tests.test_detection_second_look import CAMERA, WATER

RANGES = (0.5, 10.0)


def _rig() -> Rig:
    """Four green beams 0.15 m from the camera, parallel to its axis; no two of their image lines
    coincide (opposite beams on one line would share a band)."""
    direction = [0.0, 0.0, 1.0]
    return rig_from_dict({"laser": [
        {"name": f"L{i + 1}", "origin": [0.15 * math.cos(a), 0.15 * math.sin(a), 0.0],
         "direction": direction, "color": "green"}
        for i, a in enumerate(np.radians([10.0, 100.0, 225.0, 300.0]))]})


def _spot(rig: Rig, name: str, normal: np.ndarray, point: np.ndarray) -> tuple[float, float]:
    """Closed form: the beam meets the plane (normal, point), projected."""
    las = rig.laser(name)
    assert las.origin is not None and las.direction is not None
    r = float(normal @ (point - las.origin)) / float(normal @ las.direction)
    xy = CAMERA.project((las.origin + r * las.direction)[None, :])[0]
    return float(xy[0]), float(xy[1])


def _spots(normal: tuple[float, float, float], depth_m: float) -> dict[str, tuple[float, float]]:
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    rig = _rig()
    return {name: _spot(rig, name, n, np.array([0.0, 0.0, depth_m])) for name in rig.names}


def _predict(found: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
    rig = _rig()
    return floor_predictions(CAMERA, rig, search_region(CAMERA, rig, DetectionOptions()), found,
                             2, RANGES)


@pytest.mark.parametrize(("normal", "depth"), [((0.2, -0.3, 1.0), 2.5), ((-0.5, 0.4, 1.0), 4.0)])
def test_three_spots_put_the_fourth_where_its_beam_meets_their_plane(
        normal: tuple[float, float, float], depth: float) -> None:
    truth = _spots(normal, depth)
    got = _predict({k: truth[k] for k in ("L1", "L2", "L3")})
    assert set(got) == {"L4"} and math.dist(got["L4"], truth["L4"]) < 1e-3


def test_two_spots_take_the_least_tilted_plane_through_their_chord() -> None:
    rig = _rig()
    o1, o3 = (rig.laser(n).origin for n in ("L1", "L3"))
    assert o1 is not None and o3 is not None
    chord = o3 - o1  # the spots' chord is this plus a multiple of the beams' direction z
    across = np.cross([0.0, 0.0, 1.0], chord)
    tilted_along_chord = _spots(tuple(np.cross(chord + [0, 0, 0.3], across)), 3.0)
    got = _predict({k: tilted_along_chord[k] for k in ("L1", "L3")})
    assert set(got) == {"L2", "L4"}
    for name in ("L2", "L4"):
        assert math.dist(got[name], tilted_along_chord[name]) < 1e-3
    # a tilt across the chord is invisible to two spots: they give the level plane through them
    unit_across = across / np.linalg.norm(across)
    tilted_across = _spots(tuple(0.4 * unit_across + [0, 0, 1.0]), 3.0)
    got = _predict({k: tilted_across[k] for k in ("L1", "L3")})
    level = _spots((0.0, 0.0, 1.0), 3.0 - 0.4 * float(unit_across @ o1))
    for name in ("L2", "L4"):
        assert math.dist(got[name], level[name]) < 1e-3
        assert math.dist(got[name], tilted_across[name]) > 0.5


def test_planes_and_ranges_that_do_not_exist() -> None:
    assert floor_plane(np.zeros((1, 3))) is None
    assert floor_plane(np.array([[0, 0, 1.0], [1, 0, 1.0], [2, 0, 1.0]])) is None  # collinear
    assert floor_plane(np.array([[0, 0, 1.0], [0, 0, 2.0]])) is None  # chord on the axis
    z = np.array([0.0, 0.0, 1.0])
    assert beam_range_on_plane(np.zeros(3), z, np.array([0, 0, 2.0]), z) == pytest.approx(2.0)
    assert beam_range_on_plane(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 0, 2.0]),
                               z) is None  # parallel
    assert beam_range_on_plane(np.zeros(3), z, np.array([0, 0, -2.0]), z) is None  # behind
    assert _predict({"L1": (500.0, 384.0)}) == {}  # one spot gives no plane
    with pytest.raises(InputError, match="floor_min_spots"):
        DetectionOptions(floor_min_spots=1)


def _image(spots: dict[str, tuple[float, float]], peaks: dict[str, float],
           rng: np.random.Generator) -> np.ndarray:
    """The lasers' spots at peak 1.6 unless ``peaks`` says otherwise (0: no spot), and 400 green
    specks of peak 0.1-0.3 all over the image."""
    img = np.empty((CAMERA.height, CAMERA.width, 3), np.float32)
    img[:] = WATER
    img += rng.normal(0.0, 0.004, img.shape).astype(np.float32)
    for _ in range(400):
        x, y = rng.uniform(0, CAMERA.width), rng.uniform(0, CAMERA.height)
        if min(math.dist((x, y), xy) for xy in spots.values()) > 30:
            paint_spot(img, (x, y), "green", sigma_px=1.5, peak=float(rng.uniform(0.1, 0.3)))
    for name, xy in spots.items():
        if (peak := peaks.get(name, 1.6)) > 0:
            paint_spot(img, xy, "green", sigma_px=1.5, peak=peak)
    return to_uint8(img, 2.2)


def test_a_spot_the_band_hides_is_found_where_the_other_spots_floor_puts_it() -> None:
    truth = _spots((0.25, -0.2, 1.0), 2.8)
    image = _image(truth, {"L4": 0.08}, np.random.default_rng(5))  # a 20th of the others
    rig = _rig()
    band_only = detect_spots(image, CAMERA, rig, DetectionOptions(floor_search=False))
    assert {s.laser for s in band_only.spots} == {"L1", "L2", "L3"}  # the specks hide L4
    res = detect_spots(image, CAMERA, rig)
    got = {s.laser: s for s in res.spots}
    assert set(got) == {"L1", "L2", "L3", "L4"} and "L4" not in res.missing
    assert math.dist((got["L4"].x, got["L4"].y), truth["L4"]) < 0.3
    taken = [c for c in res.candidates if c.laser == "L4"]
    assert len(taken) == 1 and PLACE in taken[0].reason and "L4" not in res.near_misses
    # no spot of L4 at all: nothing taken, and its reason says what the floor search saw
    empty = detect_spots(_image(truth, {"L4": 0.0}, np.random.default_rng(5)), CAMERA, rig)
    assert "L4" not in {s.laser for s in empty.spots}
    assert PLACE in empty.missing["L4"]


def test_the_floor_is_searched_again_with_the_spots_the_second_look_took() -> None:
    """L3 below the clutter gate (taken on the second look, at the other spots' range), L4 a
    20th of the bright spots (found only on the floor). With ``floor_min_spots`` 3 the floor of
    L1 and L2 is not searched; the one through L1, L2 and L3 is, after the second look."""
    truth = _spots((0.25, -0.2, 1.0), 2.8)
    image = _image(truth, {"L3": 0.3, "L4": 0.08}, np.random.default_rng(5))
    rig = _rig()
    res = detect_spots(image, CAMERA, rig, DetectionOptions(floor_min_spots=3))
    got = {s.laser: s for s in res.spots}
    assert set(got) == {"L1", "L2", "L3", "L4"}, res.missing
    reasons = {c.laser: c.reason for c in res.candidates if c.laser}
    assert "below the clutter gate" in reasons["L3"] and PLACE in reasons["L4"]
    assert math.dist((got["L4"].x, got["L4"].y), truth["L4"]) < 0.3
    # without the second look neither is found, and L4's floor (two spots) is not searched
    off = detect_spots(image, CAMERA, rig,
                       DetectionOptions(floor_min_spots=3, second_look_clutter_ratio=1.5))
    assert {s.laser for s in off.spots} == {"L1", "L2"} and PLACE not in off.missing["L4"]


@functools.lru_cache(maxsize=2)  # a test reads its frame more than once
def _physical(seed: int, condition: str, index: int, name: str
              ) -> tuple[Frame, Camera, Rig, tuple[float, float]]:
    """A 1920 × 1080 frame of the physical benchmark (as its ``seed``), its camera and rig, and
    laser ``name``'s true spot (COLMAP px)."""
    ci = list(CONDITIONS).index(condition)
    frame = render_frame(condition, 1920, 1080, np.random.default_rng([seed, ci, 0, index]))
    camera, rig = parse_camera(frame.camera_spec), rig_from_dict(tomllib.loads(frame.rig_toml))
    truth = frame.truth[name]
    assert truth is not None
    return frame, camera, rig, truth


def _searched_with_the_other_spots_radius(seed: int, condition: str, index: int, name: str,
                                          failed: str) -> tuple[DetectionResult, Measure, float]:
    """A physical frame's ``name`` spot: found by ``detect_spots`` within 1.5 px; searched near
    its truth without the other spots' radius (and without centring a maximum whose refinement
    failed at its peak), the maximum there fails with ``failed``; with it, the candidate taken
    (returned with its evidence and that radius)."""
    frame, camera, rig, truth = _physical(seed, condition, index, name)
    res = detect_spots(frame.image_rgb, camera, rig)
    got = {s.laser: s for s in res.spots}
    assert name in got, res.missing.get(name)
    assert math.dist((got[name].x, got[name].y), truth) < 1.5
    others = float(np.median([c.radius_px for c in res.candidates
                              if c.laser is not None and c.laser != name]))
    guided = GuidedOptions(radius_px=default_floor_radius_px(camera.width, camera.height))
    alone = search_near(frame.image_rgb, camera, rig, name, truth,
                        DetectionOptions(peak_when_refinement_fails=False), guided)
    assert alone[0] is None and failed in alone[2]
    helped, score, _ = search_near(frame.image_rgb, camera, rig, name, truth,
                                   DetectionOptions(), guided, PLACE, others)
    assert helped is not None and score >= guided.min_score
    assert math.dist((helped.x, helped.y), truth) < 1.5
    return res, helped, others


@pytest.mark.parametrize(("index", "name"), [(15, "L4"), (17, "L3")])
def test_a_spot_on_bright_water_is_refined_at_the_other_spots_radius(index: int,
                                                                      name: str) -> None:
    """Green water near full scale (physical generator): the spot's half-maximum region runs
    into its bright surroundings (a radius of 8.5 px for frame 15's 3 × 2 px clipped core), and
    a centroid window that wide wanders off it. Near the floor's prediction it is refined again
    at the found spots' median radius, and taken (both were missed before)."""
    res, helped, others = _searched_with_the_other_spots_radius(
        0, "green_water", index, name, "sub-pixel refinement failed")
    assert PLACE in next(c.reason for c in res.candidates if c.laser == name)
    assert helped.radius_px == others
    # frame 15's maximum, centred at its peak, is taken alone too (0.28 px off); 17's is not
    frame, camera, rig, truth = _physical(0, "green_water", index, name)
    guided = GuidedOptions(radius_px=default_floor_radius_px(camera.width, camera.height))
    at_peak = search_near(frame.image_rgb, camera, rig, name, truth, DetectionOptions(), guided)
    if index == 15:
        assert at_peak[0] is not None and at_peak[0].at_peak
        assert math.dist((at_peak[0].x, at_peak[0].y), truth) < 0.5
    else:
        assert at_peak[0] is None


@pytest.mark.parametrize(("seed", "condition", "index", "name", "failed"), [
    (0, "turbid_brown", 10, "L4", "not compact"),  # a clipped core on a lit patch
    (1, "green_all", 4, "L2", "weak"),
])
def test_a_spot_near_the_floors_prediction_is_measured_against_its_own_surroundings(
        seed: int, condition: str, index: int, name: str, failed: str) -> None:
    """Physical frames: measured against the far background, the maximum at the spot fails a
    shape test; near the floor's prediction, with the other spots' radius to expect, it is
    measured against its own surroundings and taken (both were missed before)."""
    _, helped, _ = _searched_with_the_other_spots_radius(seed, condition, index, name, failed)
    assert helped.snr >= 5.0


@pytest.mark.parametrize(("seed", "condition", "index", "name"), [
    (0, "red_blue_water", 4, "L3"),  # a red spot on a textured floor in blue water
    (1, "faint_far", 1, "L3"),  # a far green spot 0.8 × white at the end of its beam's glow
])
def test_a_weak_spot_near_the_floors_point_is_taken_on_its_evidence(
        seed: int, condition: str, index: int, name: str) -> None:
    """Physical frames: near where the floor through the other spots puts it, the maximum at the
    spot fails the weak-spot test (SNR < 5), and the spot was missed. Searched again there with
    SNR 2.5 allowed, its evidence (laser-coloured, round) reaches ``min_score``: it is taken."""
    frame, camera, rig, truth = _physical(seed, condition, index, name)
    before = detect_spots(frame.image_rgb, camera, rig, DetectionOptions(floor_weak_min_snr=None))
    assert name not in {s.laser for s in before.spots}
    assert PLACE in before.missing[name]
    res = detect_spots(frame.image_rgb, camera, rig)
    got = {s.laser: s for s in res.spots}
    assert name in got, res.missing.get(name)
    assert math.dist((got[name].x, got[name].y), truth) < 0.5
    assert PLACE in next(c.reason for c in res.candidates if c.laser == name)
    # the others are as before
    assert {s.laser: (s.x, s.y) for s in res.spots if s.laser != name} == {
        s.laser: (s.x, s.y) for s in before.spots}


def test_the_weak_spot_search_says_what_it_saw_and_checks_its_option() -> None:
    """Physical frame (seed 0, ``camera_output`` 0, L1: a clipped core in a pale scene): the
    maximum at the spot is weak (SNR 3.0 < 5); with SNR 2.5 allowed it scores just below
    ``min_score``, and the reason says both. Where the second search saw nothing the first did
    not, the reason is the first's."""
    ci = list(CONDITIONS).index("camera_output")
    frame = render_frame("camera_output", 1920, 1080, np.random.default_rng([0, ci, 0, 0]))
    camera, rig = parse_camera(frame.camera_spec), rig_from_dict(tomllib.loads(frame.rig_toml))
    res = detect_spots(frame.image_rgb, camera, rig)
    assert "L1" not in {s.laser for s in res.spots}
    why = res.missing["L1"][res.missing["L1"].index(PLACE):]
    assert ("is weak (SNR 3.0 < 5); with SNR 2.5 allowed, the best candidate near the same "
            "point, at") in why
    assert why.endswith("< 0.25") and why.count(PLACE) == 2
    # no spot and no maximum near the point: the second search adds nothing to say
    truth = _spots((0.25, -0.2, 1.0), 2.8)
    empty = detect_spots(_image(truth, {"L4": 0.0}, np.random.default_rng(5)), CAMERA, _rig())
    assert "no local maximum" in empty.missing["L4"] and "allowed" not in empty.missing["L4"]
    with pytest.raises(InputError, match="floor_weak_min_snr"):
        DetectionOptions(floor_weak_min_snr=0.0)


@pytest.mark.parametrize(("condition", "index", "name"), [
    ("strobe_hotspots", 4, "L2"),  # a clipped core on a lamp's hot spot
    ("blue_beams", 7, "L2"),  # a blue spot among the floor's own blobs
])
def test_near_the_floors_point_maxima_are_listed_from_the_crops_texture_not_its_noise(
        condition: str, index: int, name: str) -> None:
    """Physical frames (seed 0): near the spot, the search's crop holds a hot spot or clutter,
    so 4 robust σ of its DoG list no maximum of the spot's light that passes; from 2 σ (the
    search's default) the spot's maximum is listed and, with the weak-spot test's SNR, taken.
    Both spots were missed before. Measured with the brightness's DoG (on its ridge-free
    response, which lists the spots from 4 σ, they are found by the same search)."""
    frame, camera, rig, truth = _physical(0, condition, index, name)
    on_dog = DetectionOptions(ridge_free_brightness=False)
    weak = GuidedOptions(radius_px=default_floor_radius_px(camera.width, camera.height),
                         min_snr=DetectionOptions().floor_weak_min_snr)
    four = search_near(frame.image_rgb, camera, rig, name, truth, on_dog,
                       replace(weak, maxima_sigmas=4.0))
    assert four[0] is None  # strobe_hotspots 4: "no local maximum of its light within …"
    two, score, _ = search_near(frame.image_rgb, camera, rig, name, truth, on_dog, weak)
    assert two is not None and score >= weak.min_score  # centred when chosen (below)
    for options in (on_dog, DetectionOptions()):
        res = detect_spots(frame.image_rgb, camera, rig, options)
        got = {s.laser: s for s in res.spots}
        assert name in got, res.missing.get(name)
        assert math.dist((got[name].x, got[name].y), truth) < 1.0
        assert PLACE in next(c.reason for c in res.candidates if c.laser == name)


def test_two_whitened_cores_are_taken_where_the_floor_through_them_holds_the_other_spots(
        ) -> None:
    """Seed 1's `green_all` 5: every spot is a whitened clipped core, and only two lie within
    0.1 band_px of their beams' lines (the third 0.16), too few to be taken alone. The floor
    through a pair of them (within PAIR_BEAM of their lines) puts the other two spots where the
    floor search finds them: all four are found (all four were missed before). Seed 0's
    `green_all` 9 has such a pair too, but the floor through it holds one other spot at most:
    nothing is taken, and its cores' reasons say what the floor held."""
    frame, camera, rig, _ = _physical(1, "green_all", 5, "L1")
    res = detect_spots(frame.image_rgb, camera, rig)
    assert len(res.spots) == 4
    for spot in res.spots:
        truth = frame.truth[spot.laser]
        assert truth is not None and math.dist((spot.x, spot.y), truth) < 1.0
    reasons = sorted(c.reason for c in res.candidates if c.laser)
    assert sum(r.endswith(f": {RESCUED_PAIR}") for r in reasons) == 2
    assert sum(PLACE in r for r in reasons) == 2
    frame, camera, rig, _ = _physical(0, "green_all", 9, "L1")
    res = detect_spots(frame.image_rgb, camera, rig)
    assert res.spots == ()
    for name in ("L1", "L4"):
        assert "at one range, the floor through the two holds" in res.missing[name]
