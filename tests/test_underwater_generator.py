"""Behaviour of the independent underwater laser-scaler generator (synthetic.underwater):
camera model, spot truth, clipping and colour, sensor output, conditions, reproducibility."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from sfm_laserscale.synthetic.underwater import (
    CONDITIONS,
    optics,
    render_frame,
    sensor,
    spectra,
    water,
)
from sfm_laserscale.synthetic.underwater import beams as beams_mod
from sfm_laserscale.synthetic.underwater.surface import make_seafloor

PACKAGE = Path(__file__).resolve().parents[1] / "sfm_laserscale" / "synthetic" / "underwater"
CAM = optics.CameraModel(640, 480, 520.0, 518.0, 322.5, 238.0, -0.12, 0.02, 3e-4, -2e-4)


def _flat_floor(distance_m: float, tilt_deg: float = 0.0):  # type: ignore[no-untyped-def]
    return make_seafloor(distance_m, tilt_deg, -math.pi / 2, np.zeros((0, 4)))


# --- camera model -------------------------------------------------------------------------

def test_pinhole_projection_by_hand() -> None:
    cam = optics.CameraModel(100, 80, 200.0, 210.0, 50.0, 40.0)
    xy = optics.project_px(np.array([[0.1, -0.2, 2.0], [0.0, 0.0, 1.0]]), cam)
    # x = fx X/Z + cx = 200*0.05 + 50 = 60; y = 210*(-0.1) + 40 = 19; the axis hits (cx, cy)
    assert np.allclose(xy, [[60.0, 19.0], [50.0, 40.0]], atol=1e-12)
    assert np.allclose(optics.unproject_px(xy, cam), [[0.05, -0.1, 1.0], [0.0, 0.0, 1.0]])


def test_project_unproject_inverse_with_distortion() -> None:
    rng = np.random.default_rng(0)
    xy = np.column_stack([rng.uniform(0, CAM.width, 500), rng.uniform(0, CAM.height, 500)])
    rays = optics.unproject_px(xy, CAM)
    assert np.allclose(optics.project_px(rays * rng.uniform(0.5, 9.0, (500, 1)), CAM), xy,
                       atol=1e-9)


def test_distortion_matches_colmap_opencv_model() -> None:
    spec = optics.colmap_camera_spec(CAM).split()
    assert spec[:3] == ["OPENCV", "640", "480"]
    cam = pycolmap.Camera(model="OPENCV", width=640, height=480,
                          params=[float(v) for v in spec[3:]])
    pts = np.array([[0.3, -0.2, 1.5], [-0.4, 0.3, 1.0], [0.01, 0.02, 3.0]])
    assert np.allclose(optics.project_px(pts, CAM), cam.img_from_cam(pts), atol=1e-9)


# --- spot truth ---------------------------------------------------------------------------

def _spot(tilt_deg: float, halo: bool = False, speckle: float = 0.0, peak: float = 0.8,
          psf: float = 0.6) -> tuple[beams_mod.SpotRender, beams_mod.Hit]:
    sf = _flat_floor(2.5, tilt_deg)
    beam = beams_mod.Beam("L1", np.array([0.15, -0.1, 0.0]),
                          np.array([0.02, 0.03, 1.0]) / np.linalg.norm([0.02, 0.03, 1.0]),
                          532.0, 2.0e-3, 0.8e-3)
    hit = beams_mod.hit_surface(beam, sf, CAM)
    assert hit is not None

    def grey(s, t, fp):  # type: ignore[no-untyped-def]
        return np.full((*np.shape(s), 3), 0.3, np.float32)

    opts = beams_mod.SpotOptions(peak_over_white=peak, speckle_contrast=speckle, halo=halo,
                                 psf_sigma_px=psf)
    spot = beams_mod.render_spot(beam, hit, CAM, sf, grey, water.WATER_TYPES["neutral"], opts,
                                 np.random.default_rng(1))
    return spot, hit


def _centroid(img: np.ndarray, x0: int, y0: int) -> np.ndarray:
    h, w = img.shape
    gx, gy = np.meshgrid(x0 + np.arange(w) + 0.5, y0 + np.arange(h) + 0.5)
    return np.array([(img * gx).sum(), (img * gy).sum()]) / img.sum()


def test_truth_is_the_projected_axis_hit_on_a_plane() -> None:
    spot, hit = _spot(0.0)
    beam_dir = np.array([0.02, 0.03, 1.0]) / np.linalg.norm([0.02, 0.03, 1.0])
    lam = 2.5 / beam_dir[2]  # flat plane z = 2.5, origin on z = 0
    point = np.array([0.15, -0.1, 0.0]) + lam * beam_dir
    assert np.allclose(hit.point_m, point, atol=1e-10)
    assert np.allclose(hit.truth_px, optics.project_px(point[None], CAM)[0], atol=1e-9)


@pytest.mark.parametrize("tilt_deg", [0.0, 35.0])
def test_irradiance_centroid_equals_truth(tilt_deg: float) -> None:
    """No noise, speckle, halo or sensor (only the lens PSF, sigma 0.6 px): the intensity
    centroid of the rendered irradiance (pixel values) is the truth within 0.01 px
    (fronto-parallel and tilted plane, distorted camera); so is the continuous centroid of
    the footprint without PSF (the perspective/distortion effect alone)."""
    spot, hit = _spot(tilt_deg)
    c = _centroid(spot.light[..., 1].astype(np.float64), spot.x0, spot.y0)
    assert np.hypot(*(c - hit.truth_px)) < 0.01
    assert spot.meta["geometric_shift_px"] < 0.01
    sharp, _ = _spot(tilt_deg, psf=0.0)
    assert sharp.meta["geometric_shift_px"] < 0.01


def test_speckle_and_halo_change_the_spot() -> None:
    plain, _ = _spot(0.0)
    speckled, _ = _spot(0.0, speckle=0.4)
    haloed, _ = _spot(0.0, halo=True)
    assert speckled.meta["speckle_contrast_pixel"] > 0.05
    assert plain.meta["speckle_contrast_pixel"] < 1e-9
    assert haloed.light.shape[0] > 3 * plain.light.shape[0]  # a much wider crop
    assert haloed.meta["halo_energy_ratio"] > 0.0


# --- colour, clipping, sensor -------------------------------------------------------------

def test_laser_crosstalk() -> None:
    r, g, b = spectra.laser_rgb(532.0)
    assert g == 1.0 and 0.02 <= r <= 0.15 and 0.02 <= b <= 0.15
    assert spectra.dominant_channel(450.0) == 2 and 0.03 < spectra.laser_rgb(450.0)[1] < 0.3
    assert spectra.dominant_channel(638.0) == 0 and spectra.color_name(638.0) == "red"


def test_bright_green_spot_has_white_core_and_green_halo() -> None:
    """At a real image size (spots wider than a Bayer cell): peak > 20x white."""
    for seed in range(10):
        frame = render_frame("clipped_cores", 1920, 1080, np.random.default_rng(seed))
        bright = [n for n, m in frame.meta["spots"].items()
                  if m["peak_over_white"] > 20.0 and m["sigma_major_px"] > 0.7]
        if bright:
            break
    else:
        pytest.fail("no bright spot in 10 frames")
    img = frame.image_rgb.astype(int)
    x, y = frame.truth[bright[0]]
    i, j = int(y), int(x)
    core = img[i - 1:i + 2, j - 1:j + 2].reshape(-1, 3)
    assert core.min(axis=1).max() >= 245  # clipped to white in all three channels
    gy, gx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    ring = (np.hypot(gx + 0.5 - x, gy + 0.5 - y) < 10) & (img.min(axis=2) < 235)
    bg_g = np.median(img[i - 40:i + 40, j - 40:j + 40, 1])
    halo = img[ring & (img[..., 1] > bg_g + 30)]
    assert len(halo) >= 4
    assert np.mean(halo[:, 1] - halo[:, 0]) > 40 and np.mean(halo[:, 1] - halo[:, 2]) > 20


def test_jpeg_output_is_420() -> None:
    rng = np.random.default_rng(3)
    img = cv2.resize((rng.random((60, 80, 3)) * 255).astype(np.uint8), (320, 240),
                     interpolation=cv2.INTER_NEAREST)
    img = np.ascontiguousarray(np.roll(img, (3, 5), axis=(0, 1)))  # edges inside 2x2 blocks

    def block_chroma_std(rgb: np.ndarray) -> float:
        ycc = cv2.cvtColor(rgb, cv2.COLOR_RGB2YCrCb).astype(float)[..., 1:]
        blocks = ycc.reshape(120, 2, 160, 2, 2)
        return float(blocks.std(axis=(1, 3)).mean())

    s420 = block_chroma_std(sensor.jpeg_roundtrip(img, 95, True))
    s444 = block_chroma_std(sensor.jpeg_roundtrip(img, 95, False))
    assert s420 < 0.5 * s444


def test_sensor_maps_channels_and_clips() -> None:
    s = sensor.SensorSettings(noise=False, jpeg=False, glare_fraction=0.0, tone=0.0,
                              wb_gains=(1.0, 1.0, 1.0), ccm=((1, 0, 0), (0, 1, 0), (0, 0, 1)))
    for ch in range(3):
        rad = np.zeros((32, 32, 3), np.float32)
        rad[..., ch] = 0.25
        out = sensor.capture(rad, s, np.random.default_rng(0))[16, 16]
        assert out[ch] > 100 and np.delete(out, ch).max() < 5
    out = sensor.capture(np.full((32, 32, 3), 7.0, np.float32), s, np.random.default_rng(0))
    assert out.min() == 255


# --- scenes and conditions ----------------------------------------------------------------

def test_a_spot_at_the_frame_edge_keeps_its_pixels() -> None:
    """The sensor is wider than the recorded frame: a spot 2 px from the edge renders as the
    same spot in the middle does (OpenCV demosaicing the frame alone copied the edge pixels
    from their inner neighbours: up to 190 levels more on the outermost column)."""
    s = sensor.SensorSettings(noise=False, jpeg=False, sharpen=0.3, glare_fraction=0.0)
    yy, xx = np.mgrid[0:16, 0:16] + 0.5
    light = np.exp(-0.5 * ((xx - 8.0) ** 2 + (yy - 8.0) ** 2) / 0.9**2)[..., None]
    crop = np.ascontiguousarray(np.repeat(light, 3, axis=2) * np.float32(0.6), np.float32)
    rad = np.full((40, 64, 3), 0.05, np.float32)
    # spot centres at x = 2.0 (6 px of the crop beyond the left edge) and x = 34.0, y = 20.0
    edge = sensor.capture(rad, s, np.random.default_rng(1), [(-6, 12, crop)]).astype(float)
    mid = sensor.capture(rad, s, np.random.default_rng(1), [(26, 12, crop)]).astype(float)
    # the same Bayer phase 32 px apart: the same pixels
    assert np.abs(edge[14:27, 0:8] - mid[14:27, 32:40]).max() <= 1

def test_pale_clutter_reads_green_cyan_in_green_water() -> None:
    frame = render_frame("green_all", 640, 480, np.random.default_rng(2))
    img = frame.image_rgb.astype(float)
    patches = [(x, y) for x, y, d in frame.meta["pale_clutter_sample"] if d >= 5.0]
    assert len(patches) >= 5
    vals = np.array([img[int(y), int(x)] for x, y in patches])
    bg = np.median(img.reshape(-1, 3), axis=0)
    assert np.mean(vals[:, 1]) > bg[1] + 10  # brighter than the seabed
    assert np.mean(vals[:, 1] - vals[:, 0]) > 15  # green ...
    assert np.mean(vals[:, 2]) > np.mean(vals[:, 0])  # ... -cyan (blue above red)


def test_green_water_background_level() -> None:
    frame = render_frame("green_water", 640, 480, np.random.default_rng(4))
    g = np.median(frame.image_rgb[..., 1]) / 255.0
    assert 0.55 <= g <= 0.85
    med = np.median(frame.image_rgb.reshape(-1, 3), axis=0)
    assert med[1] > med[0] and med[1] > med[2]


@pytest.mark.parametrize("name", list(CONDITIONS))
def test_every_condition_renders_small(name: str) -> None:
    frame = render_frame(name, 320, 240, np.random.default_rng(7))
    assert frame.image_rgb.shape == (240, 320, 3) and frame.image_rgb.dtype == np.uint8
    assert frame.camera_spec.startswith("OPENCV 320 240 ")
    assert set(frame.truth) == {"L1", "L2", "L3", "L4"}
    for xy in frame.truth.values():
        if xy is not None:
            assert all(math.isfinite(v) for v in xy)
            assert 0.0 <= xy[0] <= 320.0 and 0.0 <= xy[1] <= 240.0
    visible = [v for v in frame.truth.values() if v is not None]
    if name == "no_lasers":
        assert not visible
    elif name == "old_missing":
        assert 2 <= len(visible) <= 3
    else:
        assert len(visible) == 4
    assert "sigma_origin" in frame.rig_toml and "sigma_direction" in frame.rig_toml


def test_rig_file_is_valid_and_close_to_truth() -> None:
    import tomllib

    from sfm_laserscale.rig import rig_from_dict

    frame = render_frame("red_clean", 320, 240, np.random.default_rng(9))
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    assert rig.names == ["L1", "L2", "L3", "L4"]
    assert {las.color for las in rig.lasers} == {"red"}
    for las in rig.lasers:
        assert 0.09 < float(np.linalg.norm(las.origin)) < 0.27
        off_axis = math.degrees(math.acos(float(las.direction[2])))
        assert 0.2 < off_axis < 3.5


def test_same_seed_same_image() -> None:
    a = render_frame("marine_snow", 320, 240, np.random.default_rng(11))
    b = render_frame("marine_snow", 320, 240, np.random.default_rng(11))
    c = render_frame("marine_snow", 320, 240, np.random.default_rng(12))
    assert np.array_equal(a.image_rgb, b.image_rgb) and a.truth == b.truth
    assert a.rig_toml == b.rig_toml
    assert not np.array_equal(a.image_rgb, c.image_rgb)


def imported_modules(path: Path) -> list[str]:
    """Every module a Python file imports (``import a.b``, ``from a.b import c``)."""
    mods: list[str] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            mods.append(node.module)
        elif isinstance(node, ast.Import):
            mods += [a.name for a in node.names]
    return mods


def test_generator_imports_nothing_from_the_rest_of_the_package() -> None:
    allowed = {"numpy", "scipy", "cv2", "math", "dataclasses", "collections", "functools", "typing",
               "__future__"}
    for path in PACKAGE.glob("*.py"):
        if path.name == "survey.py":  # SfM and writers only: tests/test_underwater_survey.py
            continue
        for mod in imported_modules(path):
            ok = (mod.split(".")[0] in allowed
                  or mod.startswith("sfm_laserscale.synthetic.underwater"))
            assert ok, f"{path.name} imports {mod}"


def test_an_unencoded_laser_free_capture_differs_from_the_frame_by_its_jpeg_alone() -> None:
    """``laser_free_jpeg=False``: the same frame, and a laser-free capture before JPEG, which
    away from the lasers' light differs from the frame by the frame's compression only (a
    few levels), where the encoded capture matches the frame exactly."""
    frame = render_frame("red_clean", 640, 480, np.random.default_rng([3, 1]), laser_free=True,
                         laser_free_jpeg=False)
    encoded = render_frame("red_clean", 640, 480, np.random.default_rng([3, 1]), laser_free=True)
    np.testing.assert_array_equal(frame.image_rgb, encoded.image_rgb)
    raw, dark = frame.image_laser_free_rgb, encoded.image_laser_free_rgb
    assert raw is not None and dark is not None
    away = np.all(dark == encoded.image_rgb, axis=2)  # away from the lasers' light
    diff = np.abs(raw.astype(int) - frame.image_rgb.astype(int))[away]
    assert 0.3 < diff.mean() < 4.0
    assert np.any(raw != dark)


def test_laser_free_capture_differs_only_near_the_lasers_light() -> None:
    """The same frame without the lasers (same noise): identical away from the spots and the
    beams' glow, and each spot changes the photograph plainly (visible_levels)."""
    rng = np.random.default_rng([3, 1])
    frame = render_frame("red_clean", 640, 480, rng, laser_free=True)
    again = render_frame("red_clean", 640, 480, np.random.default_rng([3, 1]))
    np.testing.assert_array_equal(frame.image_rgb, again.image_rgb)  # the flag changes nothing
    dark = frame.image_laser_free_rgb
    assert dark is not None and dark.shape == frame.image_rgb.shape
    same = np.all(dark == frame.image_rgb, axis=2)
    assert same.mean() > 0.8
    for name, xy in frame.truth.items():
        if xy is None:
            continue
        assert frame.meta["spots"][name]["visible_levels"] >= 20
        col, row = int(xy[0]), int(xy[1])
        assert not same[row, col]


def test_srgb_decode_inverts_srgb_encode() -> None:
    from sfm_laserscale.synthetic.underwater.sensor import srgb_decode, srgb_encode
    lin = np.linspace(0.0, 1.0, 101, dtype=np.float32)
    np.testing.assert_allclose(srgb_decode(srgb_encode(lin)), lin, atol=1e-6)


def test_the_scene_reference_is_the_seafloor_alone() -> None:
    """``scene_reference=True`` leaves the frame as it was and captures the seafloor without
    the lamp's hot spot: the photograph is brighter than it where the hot spot is aimed."""
    args = ("strobe_hotspots", 480, 360)
    plain = render_frame(*args, np.random.default_rng(4))
    frame = render_frame(*args, np.random.default_rng(4), scene_reference=True)
    np.testing.assert_array_equal(frame.image_rgb, plain.image_rgb)
    assert plain.image_scene_rgb is None and frame.image_scene_rgb is not None
    excess = frame.image_rgb.astype(float).mean(axis=2) - frame.image_scene_rgb.mean(axis=2)
    rows, cols = np.mgrid[0:360, 0:480]
    (x, y), *_ = frame.meta["hotspot_aims_px"]
    near = np.hypot(cols - x, rows - y) < 15
    assert near.any() and excess[near].mean() > excess[~near].mean() + 20.0
