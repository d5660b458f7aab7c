"""A scene reference: its texture finer than ``scene_texture_sigma_px`` is subtracted from the
laser image before detection, its light is not, and clipped or uncovered pixels stay as the
image has them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from script_loader import load_script

from sfm_laserscale.cli import main
from sfm_laserscale.detection import DetectionOptions
from sfm_laserscale.detection.scene import low_pass, remove_scene, scene_texture, texture_gain
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.images import read_scene_reference
from sfm_laserscale.synthetic.underwater import CONDITIONS, render_frame

H, W = 120, 160


def _texture() -> np.ndarray:
    """A fine texture (periods 3-7 px, ±30 levels) on a grey floor, (H, W, 3) float."""
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    pattern = 18 * np.sin(2 * np.pi * cols / 5.0) * np.sin(2 * np.pi * rows / 7.0) \
        + 12 * np.cos(2 * np.pi * (cols + rows) / 3.0)
    return np.repeat(pattern[..., None], 3, axis=2) * np.array([1.0, 0.8, 0.6])


def _spot(x: float, y: float, sigma: float, peak: float) -> np.ndarray:
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    return peak * np.exp(-((cols + 0.5 - x) ** 2 + (rows + 0.5 - y) ** 2) / (2 * sigma**2))


def _image(light: float = 110.0) -> np.ndarray:
    """The laser image: lamp light with a slope, the texture, a green spot at (80.3, 60.6)."""
    cols = np.arange(W)[None, :, None]
    img = light + 0.2 * cols + _texture()
    img[..., 1] += _spot(80.3, 60.6, 1.5, 60.0)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def test_the_texture_goes_and_the_light_and_the_spot_stay() -> None:
    """The reference is lit otherwise (darker, no slope) and noisy: the image minus its
    texture is the image's own light plus the spot, to within its noise."""
    rng = np.random.default_rng(3)
    scene = (70.0 + _texture() + rng.normal(0, 1.0, (H, W, 3))).astype(np.float32)
    out = remove_scene(_image(), scene, 8.0).astype(np.float64)
    cols = np.arange(W)[None, :]
    expected = 110.0 + 0.2 * cols + np.zeros((H, W))
    expected_g = expected + _spot(80.3, 60.6, 1.5, 60.0)
    inner = (slice(20, H - 20), slice(20, W - 20))
    before = _image().astype(np.float64)[..., 1][inner] - expected_g[inner]
    after = out[..., 1][inner] - expected_g[inner]
    assert np.std(before) > 8.0
    assert np.std(after) < 1.5
    assert np.abs(out[..., 0][inner] - expected[inner]).max() < 6.0
    peak = np.unravel_index(np.argmax(out[..., 1] - expected), (H, W))
    assert (int(peak[1]), int(peak[0])) == (80, 60)


def test_clipped_channels_and_uncovered_pixels_are_kept() -> None:
    image = _image()
    image[60, 80, 1] = 255
    scene = (70.0 + _texture()).astype(np.float32)
    scene[:, :40] = np.nan
    # a bright speck of the seafloor that clips in the image is the scene's: not kept
    image[30, 100, 1] = 255
    scene[30, 100, 1] = 255.0
    out = remove_scene(image, scene, 8.0)
    assert out[60, 80, 1] == 255
    assert out[30, 100, 1] < 200
    np.testing.assert_array_equal(out[:, :40], image[:, :40])
    assert not np.array_equal(out[:, 60:], image[:, 60:])
    texture = scene_texture(scene, 8.0)
    assert np.all(texture[:, :40] == 0.0) and np.all(np.isfinite(texture))
    # beside the unknown pixels the blur is normalised over known ones: no step at x = 40
    assert abs(float(np.mean(texture[20:100, 40:44]))) < 3.0


def _hot_spot() -> np.ndarray:
    """A lamp's hot spot (H, W): the light 2.5 times stronger at (110, 50), sigma 30 px."""
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    return 1.0 + 1.5 * np.exp(-((cols - 110) ** 2 + (rows - 50) ** 2) / (2 * 30.0**2))


def test_the_texture_is_scaled_to_the_image_light() -> None:
    """The image is lit by a hot spot the reference lacks, so its texture is up to 2.5 times
    the reference's there. The local gain reads the light's mean over its window (at the
    centre 1 + 1.5 * 30^2 / (30^2 + 16^2) = 2.17, far from it 1) and takes the texture out,
    where the unscaled reference leaves more than half of it."""
    light = _hot_spot()[..., None]
    texture = _texture()
    image = np.clip(np.rint(60.0 + light * (20.0 + texture)), 0, 255).astype(np.uint8)
    scene = (90.0 + texture).astype(np.float32)
    known = np.ones((H, W), bool)
    gain = texture_gain(image, scene_texture(scene, 8.0), known, 8.0, 16.0)
    assert abs(float(gain[50, 110, 0]) - (1.0 + 1.5 * 900 / (900 + 256))) < 0.1
    assert abs(float(gain[100, 15, 0]) - 1.0) < 0.1
    spot = (slice(35, 66), slice(95, 126))  # the hot spot's core
    flat = 60.0 + light[..., 0] * 20.0
    unscaled = remove_scene(image, scene, 8.0).astype(np.float64)[..., 0][spot] - flat[spot]
    scaled = remove_scene(image, scene, 8.0, 16.0).astype(np.float64)[..., 0][spot] - flat[spot]
    before = (image[..., 0].astype(np.float64) - flat)[spot]
    assert np.std(unscaled) > 0.5 * np.std(before)
    assert np.std(scaled) < 0.2 * np.std(before)  # measured 0.13 (0.58 unscaled)


def test_a_reference_of_noise_alone_is_not_added() -> None:
    """Where the reference holds only its own noise (no texture the image shares) the gain
    falls near 0, so the image keeps its own noise instead of gaining the reference's; where a
    channel clips in most of the window the gain is 1."""
    rng = np.random.default_rng(5)
    image = np.clip(np.rint(100.0 + rng.normal(0, 2.0, (H, W, 3))), 0, 255).astype(np.uint8)
    scene = (100.0 + rng.normal(0, 2.0, (H, W, 3))).astype(np.float32)
    known = np.ones((H, W), bool)
    gain = texture_gain(image, scene_texture(scene, 8.0), known, 8.0, 16.0)
    assert float(np.median(gain)) < 0.2
    out = remove_scene(image, scene, 8.0, 16.0).astype(np.float64)
    assert np.std(out - image) < 0.6
    image[..., 1] = 255
    gain = texture_gain(image, scene_texture(scene, 8.0), known, 8.0, 16.0)
    np.testing.assert_allclose(gain[..., 1], 1.0)


def test_the_shrunk_blur_is_the_full_size_one() -> None:
    """The low pass is formed on planes shrunk 4 times (sigma 8 px): against OpenCV's blur at
    full size, on a texture of sigma 30 levels, it differs by 0.015 levels RMS (measured)
    where the low pass itself varies by 1 level; a sigma under 4 px is blurred at full
    size."""
    rng = np.random.default_rng(11)
    texture = cv2.GaussianBlur(rng.normal(0, 30, (270, 480, 3)).astype(np.float32), (0, 0), 1.5)
    inner = (slice(40, -40), slice(40, -40))
    for sigma in (8.0, 3.0):
        full = cv2.GaussianBlur(texture, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        fast = low_pass(texture, sigma)
        assert fast.shape == texture.shape and fast.dtype == np.float32
        rms = float(np.sqrt(np.mean((full[inner] - fast[inner]) ** 2)))
        assert rms < 0.05 * float(np.std(full[inner])), (sigma, rms)


def test_a_reference_that_does_not_fit_is_refused() -> None:
    image = _image()
    with pytest.raises(InputError, match="aligned pixel for pixel"):
        remove_scene(image, np.zeros((H, W - 1, 3), np.float32), 8.0)
    with pytest.raises(InputError, match="must be float"):
        remove_scene(image, np.zeros((H, W, 3), np.uint8), 8.0)
    with pytest.raises(InputError, match="sigma must be positive"):
        remove_scene(image, np.zeros((H, W, 3), np.float32), 0.0)
    with pytest.raises(InputError, match="scene gain's sigma"):
        remove_scene(image, np.zeros((H, W, 3), np.float32), 8.0, 0.0)
    with pytest.raises(InputError, match="scene_texture_sigma_px"):
        DetectionOptions(scene_texture_sigma_px=0.0)
    with pytest.raises(InputError, match="scene_gain_sigma_px"):
        DetectionOptions(scene_gain_sigma_px=-1.0)


def test_scene_references_are_read_in_8_bit_levels_with_unknown_pixels(tmp_path: Path) -> None:
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 10, 20, 30
    cv2.imwrite(str(tmp_path / "a.png"), rgb[..., ::-1])
    np.testing.assert_array_equal(read_scene_reference(tmp_path / "a.png")[0, 0], [10, 20, 30])
    deep = (rgb.astype(np.uint16) * 257)[..., ::-1]
    alpha = np.full((4, 5, 1), 65535, np.uint16)
    alpha[1, 2] = 0
    cv2.imwrite(str(tmp_path / "b.png"), np.concatenate([deep, alpha], axis=2))
    read = read_scene_reference(tmp_path / "b.png")
    assert read.dtype == np.float32
    np.testing.assert_allclose(read[0, 0], [10, 20, 30])
    assert np.isnan(read[1, 2]).all() and np.isfinite(read[1, 3]).all()
    (tmp_path / "c.png").write_bytes(b"not an image")
    with pytest.raises(InputError, match="not a readable RGB"):
        read_scene_reference(tmp_path / "c.png")


def test_detect_with_a_scene_reference_finds_the_spots_its_texture_hid(tmp_path: Path) -> None:
    """``green_all`` 6 of seed 3 (the independent generator, 1920 × 1080): on the photograph
    alone no laser is taken (scores 0.07-0.54, each left out or below ``min_score``). With
    the seafloor's own capture as the reference, as a render from the model would give it
    (shifted 0.5 px, blurred 0.7 px, relit ±10 %: the benchmark's ``as_rendered``), all
    four spots are found within 0.6 px (measured 0.06-0.53 px). The reference's left
    strip is marked unknown (alpha 0) and its PNG is 16-bit."""
    bench = load_script("bench_detection_physical")
    ci = list(CONDITIONS).index("green_all")
    frame = render_frame("green_all", 1920, 1080, np.random.default_rng([3, ci, 0, 6]),
                         scene_reference=True)
    assert frame.image_scene_rgb is not None
    images, scenes = tmp_path / "images", tmp_path / "scenes"
    images.mkdir()
    scenes.mkdir()
    cv2.imwrite(str(images / "laser_006.png"), frame.image_rgb[..., ::-1])
    reference = bench.as_rendered(frame.image_scene_rgb, bench.SceneReference(0.5, 0.7, 0.1),
                                  np.random.default_rng([3, ci, 0, 6, 7]))
    deep = np.rint(np.clip(reference, 0, 255) * 257).astype(np.uint16)[..., ::-1]
    alpha = np.full((*deep.shape[:2], 1), 65535, np.uint16)
    alpha[:, :200] = 0
    cv2.imwrite(str(scenes / "laser_006.png"), np.concatenate([deep, alpha], axis=2))
    rig = tmp_path / "rig.toml"
    rig.write_text(frame.rig_toml)
    args = ["detect", str(images), "--rig", str(rig), "--camera", frame.camera_spec]
    alone = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "alone")])
    assert alone.exit_code == 1, alone.output
    record = json.loads((tmp_path / "alone" / "detections.json").read_text())["images"][0]
    assert record["spots"] == [] and record["scene_reference"] is None
    with_scene = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "scene"),
                                           "--scene", str(scenes)])
    assert with_scene.exit_code == 0, with_scene.output
    record = json.loads((tmp_path / "scene" / "detections.json").read_text())["images"][0]
    assert record["scene_reference"] == str(scenes / "laser_006.png")
    errors = {s["laser"]: math.dist((s["x"], s["y"]), frame.truth[s["laser"]] or (0, 0))
              for s in record["spots"]}
    assert sorted(errors) == ["L1", "L2", "L3", "L4"]
    assert max(errors.values()) < 0.6
    # a reference of another size is bad input, named
    small = tmp_path / "small"
    small.mkdir()
    cv2.imwrite(str(small / "laser_006.png"), frame.image_rgb[:540, :960, ::-1])
    bad = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "bad"), "--scene", str(small)])
    assert bad.exit_code == 2 and "960x540 px" in bad.output and "laser_006.png" in bad.output
    # a folder that holds no reference of these images is bad input
    empty = tmp_path / "empty"
    empty.mkdir()
    bad = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "bad"), "--scene", str(empty)])
    assert bad.exit_code == 2 and "no scene reference matches" in bad.output
