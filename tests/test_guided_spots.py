"""The model-guided search: where the model puts a spot (closed form on a plane) and the search
around that point (a spot too faint for the band's competition is found there)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sfm_laserscale.detection import DetectionOptions, detect_spots
from sfm_laserscale.detection.guided import GuidedOptions, detect_near
from sfm_laserscale.guided_spots import laser_offsets, predict_spots
from sfm_laserscale.model import Pose
from sfm_laserscale.raycast import MeshRaycaster
from sfm_laserscale.rig import Rig
from sfm_laserscale.synthetic.spots import paint_spot, to_uint8
from tests.test_detection_second_look import CAMERA, WATER
from tests.test_detection_second_look import _rig as _two_green_lasers


def _looking_down(centre: np.ndarray, tilt_deg: float) -> Pose:
    """cam_from_world of a camera at ``centre`` looking down (−z world), tilted about x."""
    a = math.radians(tilt_deg)
    tilt = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    rot = tilt @ np.diag([1.0, -1.0, -1.0])
    return Pose(rot, -rot @ centre)


def _floor() -> MeshRaycaster:
    """The plane z = 0 (model units), 40 units square."""
    v = np.array([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0]], dtype=np.float64)
    return MeshRaycaster(v, np.array([[0, 1, 2], [0, 2, 3]]))


def _true_spot(rig: Rig, name: str, pose: Pose, scale: float) -> tuple[float, float]:
    """Closed form: the beam (metres, camera frame) / scale meets z_world = 0."""
    las = rig.laser(name)
    assert las.origin is not None and las.direction is not None
    rt = pose.R.T
    # z of R^T((o + r d) / s - t) = 0, linear in r
    z0 = (rt @ (las.origin / scale - pose.t))[2]
    dz = (rt @ (las.direction / scale))[2]
    xy = CAMERA.project((las.origin + (-z0 / dz) * las.direction)[None, :])[0]
    return float(xy[0]), float(xy[1])


@pytest.mark.parametrize(("scale", "tilt"), [(0.25, 0.0), (0.8, 12.0)])
def test_the_predicted_spot_is_where_the_beam_meets_the_mesh(scale: float, tilt: float) -> None:
    rig = _two_green_lasers()
    pose = _looking_down(np.array([0.7, -0.4, 9.0]), tilt)  # 9 model units up
    pred, why = predict_spots(CAMERA, pose, rig, ["L1", "L2"], _floor(), scale)
    assert not why
    for name in ("L1", "L2"):
        assert math.dist(pred[name], _true_spot(rig, name, pose, scale)) < 1e-6
    # the rig's offset is added; a beam that never reaches the floor has none, with its reason
    moved, _ = predict_spots(CAMERA, pose, rig, ["L1"], _floor(), scale,
                             offsets={"L1": (1.5, -0.5)})
    assert math.dist(moved["L1"], (pred["L1"][0] + 1.5, pred["L1"][1] - 0.5)) < 1e-9
    far, why = predict_spots(CAMERA, pose, rig, ["L1"], _floor(), 0.001)  # beside the floor
    assert far == {} and "does not meet the mesh" in why["L1"]


def test_laser_offsets_are_medians_of_enough_spots() -> None:
    rows = [("L1", 10.0, 20.0, 9.0, 20.5), ("L1", 30.0, 40.0, 29.2, 40.4),
            ("L1", 50.0, 60.0, 40.0, 60.0), ("L2", 1.0, 1.0, 0.0, 0.0)]
    got = laser_offsets(rows, min_spots=2)
    assert set(got) == {"L1"}  # one L2 spot is not enough
    assert got["L1"] == pytest.approx((1.0, -0.4))  # the median: the 10 px outlier does not pull


def _cluttered_image(l2_xy: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """L2's spot faint, L1's hidden (behind a rock), and green specks stronger than L2 all over
    the image (the band's competition that holds L2 back in detect_spots)."""
    img = np.empty((CAMERA.height, CAMERA.width, 3), np.float32)
    img[:] = WATER
    img += rng.normal(0.0, 0.004, img.shape).astype(np.float32)
    for _ in range(400):  # laser-green specks (algae, a lit organism) brighter than L2's spot
        x, y = rng.uniform(0, CAMERA.width), rng.uniform(0, CAMERA.height)
        if math.dist((x, y), l2_xy) > 30 and math.dist((x, y), (l2_xy[0], l2_xy[1] + 40)) > 12:
            paint_spot(img, (x, y), "green", sigma_px=1.5, peak=float(rng.uniform(0.1, 0.3)))
    paint_spot(img, l2_xy, "green", sigma_px=1.5, peak=0.08)
    return to_uint8(img, 2.2)


def test_a_spot_lost_among_scene_blobs_is_found_where_the_model_puts_it() -> None:
    rig = _two_green_lasers()
    las = rig.laser("L2")
    assert las.origin is not None and las.direction is not None
    xy = CAMERA.project((las.origin + 2.5 * las.direction)[None, :])[0]
    l2 = (float(xy[0]), float(xy[1]))
    image = _cluttered_image(l2, np.random.default_rng(3))
    alone = detect_spots(image, CAMERA, rig)
    assert "L2" not in {s.laser for s in alone.spots}  # the band's blobs hide it
    near = detect_near(image, CAMERA, rig, {"L2": (l2[0] + 0.8, l2[1] - 0.6)})
    assert [s.laser for s in near.spots] == ["L2"] and near.spots[0].source == "guided"
    assert math.dist((near.spots[0].x, near.spots[0].y), l2) < 0.3
    # 40 px along its band there is nothing: no spot, and the reason says what was there
    off = detect_near(image, CAMERA, rig, {"L2": (l2[0], l2[1] + 40.0)})
    assert off.spots == () and "where the model puts its spot" in off.missing["L2"]
    out = detect_near(image, CAMERA, rig, {"L2": (-50.0, 10.0)})
    assert "outside the image" in out.missing["L2"]
    with pytest.raises(Exception, match="radius_px"):
        GuidedOptions(radius_px=0.0)
    with pytest.raises(Exception, match="maxima_sigmas"):
        GuidedOptions(maxima_sigmas=0.0)
    assert DetectionOptions().min_snr > 0  # the weak-spot test still applies near a prediction


def test_the_overlay_names_a_guided_spot_and_drops_its_laser_near_misses() -> None:
    from sfm_laserscale.model import Spot
    from sfm_laserscale.report.overlays import _legend_entries, draw_overlay

    rig = _two_green_lasers()
    spots = [Spot("L2", 512.0, 412.0, source="guided")]
    texts = [t for _, _, t in _legend_entries(rig, spots, {"L2": 0.3}, {}, None)]
    assert texts[:2] == ["L1 not found", "L2 s=0.3 (where the model puts it)"]
    rgb = np.full((CAMERA.height, CAMERA.width, 3), 60, np.uint8)
    args = (rgb, CAMERA, rig, spots, {"L2": 0.3}, None, 0.3, 20.0)
    plain = draw_overlay(*args)
    assert np.array_equal(draw_overlay(*args, near_misses={"L2": [(300.0, 300.0, 0.2)]}), plain)
    assert not np.array_equal(draw_overlay(*args, near_misses={"L1": [(300.0, 300.0, 0.2)]}),
                              plain)


def test_near_a_prediction_colour_counts_at_least_the_floor() -> None:
    from sfm_laserscale.detection.candidates import Measure
    from sfm_laserscale.detection.guided import evidence
    from sfm_laserscale.detection.score import ColourEvidence

    m = Measure(x=0.0, y=0.0, color="green", source="bright", response=1.0)
    m.terms = {"contrast": 0.6, "roundness": 0.9, "clutter": 0.1}  # clutter does not count
    m.colour = ColourEvidence(0.05, 0.0, True)  # a green spot in green water: the scene's colour
    assert evidence(m, 0.5) == pytest.approx(0.6 * 0.9 * 0.5)
    assert evidence(m, 0.0) == pytest.approx(0.6 * 0.9 * 0.05)
    m.whitened = True  # a clipped core whose rim reads white
    assert evidence(m, 0.0) == pytest.approx(0.6 * 0.9)


@pytest.mark.parametrize("flag", [(), ("--no-guided-spots",)])
def test_the_pipeline_commands_pass_the_guided_search_switch_to_scale(
        flag: tuple[str, ...], monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from types import SimpleNamespace

    from click.testing import CliRunner

    import sfm_laserscale.commands.colmap as colmap_cmd
    from sfm_laserscale.cli import main

    seen = {}

    def fake_run(inputs: object, out: object, options: Any, overwrite: bool = False) -> Any:
        seen["guided"] = options.scale.guided.enabled
        return SimpleNamespace(summary="stub", scale=SimpleNamespace(success=True))

    monkeypatch.setattr(colmap_cmd, "run", fake_run)
    args = ["colmap", "--images", str(tmp_path), "--laser-images", str(tmp_path), "--rig",
            str(tmp_path / "rig.toml"), "--out", str(tmp_path / "out"), "--quiet", *flag]
    result = CliRunner().invoke(main, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert seen["guided"] is (not flag)
