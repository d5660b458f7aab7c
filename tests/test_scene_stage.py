"""scale's scene-reference stage: model images read from their folder, rendered into a
registered laser image's pose, fitted, and the detector run again with the reference; every
image that is not searched again says why (closed-form views of a textured plane)."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest

from sfm_laserscale.detection import DetectionOptions
from sfm_laserscale.io.images import read_scene_reference
from sfm_laserscale.io.meshes.mesh import TriangleMesh
from sfm_laserscale.model import Image, SparseModel, Spot
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.run_types import ImageRun
from sfm_laserscale.scene_fit import SceneFitOptions
from sfm_laserscale.scene_reference import SceneStageOptions
from sfm_laserscale.scene_stage import (
    MeshCasters,
    ModelImages,
    detect_all_with_references,
    reference_png,
)
from tests.test_scene_reference import CAMERA, _pose, _view

LASER_POSE = _pose((0.0, 0.0, -2.0))
MODEL_POSES = {1: _pose((0.15, 0.05, -2.1), 2.0), 2: _pose((-0.1, 0.12, -1.95), -3.0),
               3: _pose((0.05, -0.1, -2.05), 1.0), 4: _pose((3.0, 0.0, -2.0))}
# one green beam from 0.1 right of the camera, meeting the floor (2 below) at pixel SPOT_XY
SPOT_XY = (201.3, 87.6)
_ON_FLOOR = [2.0 * (SPOT_XY[0] - 160.0) / 300.0, 2.0 * (SPOT_XY[1] - 120.0) / 300.0, 2.0]
RIG = rig_from_dict({"name": "one", "laser": [
    {"name": "L1", "origin": [0.1, 0.0, 0.0], "color": "green",
     "direction": [_ON_FLOOR[0] - 0.1, _ON_FLOOR[1], _ON_FLOOR[2]]}]})


def _write(path: Path, rgb: np.ndarray) -> None:
    cv2.imwrite(str(path), cv2.cvtColor(np.clip(np.rint(rgb), 0, 255).astype(np.uint8),
                                        cv2.COLOR_RGB2BGR))


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Four model images of the floor in images/, and a laser image with one green spot."""
    root = tmp_path_factory.mktemp("scene_stage")
    (root / "images").mkdir()
    for i, pose in MODEL_POSES.items():
        _write(root / "images" / f"m{i}.png", _view(pose))
    laser = _view(LASER_POSE)
    rows, cols = np.mgrid[0:CAMERA.height, 0:CAMERA.width]
    spot = 90.0 * np.exp(-((cols + 0.5 - SPOT_XY[0]) ** 2 + (rows + 0.5 - SPOT_XY[1]) ** 2)
                         / (2 * 1.6 ** 2))
    laser[..., 1] += spot
    _write(root / "laser.png", laser)
    model = SparseModel({1: CAMERA}, {i: Image(i, f"m{i}.png", 1, pose)
                                      for i, pose in MODEL_POSES.items()},
                        np.zeros(0, np.uint64), np.zeros((0, 3)))
    verts = np.array([[-3, -3, 0], [3, -3, 0], [3, 3, 0], [-3, 3, 0]], dtype=float)
    mesh = TriangleMesh(verts, np.array([[0, 1, 2], [0, 2, 3]]))
    return {"root": root, "model": model, "mesh": mesh}


def _run(path: Path, registered: bool = True, spots: tuple[Spot, ...] = ()) -> ImageRun:
    reg: Any = SimpleNamespace(cam_from_world=LASER_POSE, success=True) if registered else None
    return ImageRun(name=path.name, path=path, camera=CAMERA, registration=reg,
                    detection=None, spots=spots, hits=(), spot_reasons={"L1": "not found"},
                    estimates=None, reason=None if registered else "registration failed")


def test_a_registered_image_is_searched_again_with_its_reference(scene: dict[str, Any]
                                                                 ) -> None:
    runs = [_run(scene["root"] / "laser.png")]
    out = detect_all_with_references(runs, scene["model"], scene["mesh"], RIG,
                                     scene["root"] / "images", [], DetectionOptions(),
                                     SceneStageOptions(keep_png=True))
    use = out[0].scene
    assert use is not None and use.used and use.reason is None
    assert set(use.views) == {"m1.png", "m2.png", "m3.png"}  # not the far one
    assert use.coverage > 0.99 and use.kept_share > 0.9 and use.shift_median_px < 0.3
    assert use.spots_alone == 0 and out[0].detection is not None
    [spot] = out[0].spots
    assert spot.laser == "L1" and np.hypot(spot.x - SPOT_XY[0], spot.y - SPOT_XY[1]) < 0.3
    assert out[0].spot_reasons == {}
    assert use.png is not None
    saved = scene["root"] / "saved.png"
    saved.write_bytes(use.png)
    reference = read_scene_reference(saved)
    assert reference.shape == (CAMERA.height, CAMERA.width, 3)
    truth = _view(LASER_POSE)
    known = np.isfinite(reference[..., 0])
    assert np.abs(reference[known] - truth[known]).mean() < 1.0


def _saved(png: bytes | None, path: Path) -> Path:
    assert png is not None
    path.write_bytes(png)
    return path


def test_a_large_mesh_is_cropped_per_image_to_the_same_render(scene: dict[str, Any],
                                                              tmp_path: Path) -> None:
    """Every mesh counted as large (max_whole_triangles 0): each image's render casts rays
    every 8 px on the mesh cropped to them, and gives the reference the whole mesh gives, up
    to the coarser grid's interpolation. The floor is a grid of 80 000 triangles, so that the
    crop keeps a part of it."""
    n = 201
    xs = np.linspace(-3.0, 3.0, n)
    gx, gy = np.meshgrid(xs, xs)
    verts = np.stack([gx.ravel(), gy.ravel(), np.zeros(n * n)], axis=1)
    k = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    tris = np.concatenate([np.stack([k, k + 1, k + n + 1], 1), np.stack([k, k + n + 1, k + n], 1)])
    fine = TriangleMesh(verts, tris.astype(np.int32))
    casters = MeshCasters(fine, SceneStageOptions(max_whole_triangles=0))
    crop, render = casters.for_view(CAMERA, LASER_POSE)
    assert crop.coverage is not None and len(crop.triangles) < 0.5 * len(tris)
    assert render.grid_px == 8
    runs = [_run(scene["root"] / "laser.png")]
    args = (scene["model"], fine, RIG, scene["root"] / "images", [], DetectionOptions())
    whole = detect_all_with_references(runs, *args, SceneStageOptions(keep_png=True))
    cropped = detect_all_with_references(runs, *args, SceneStageOptions(
        keep_png=True, max_whole_triangles=0))
    assert whole[0].scene is not None and cropped[0].scene is not None
    assert cropped[0].scene.used and whole[0].scene.used
    a, b = (read_scene_reference(_saved(r.scene.png, tmp_path / f"{k}.png"))
            for k, r in (("whole", whole[0]), ("cropped", cropped[0])))
    known = np.isfinite(a[..., 0]) & np.isfinite(b[..., 0])
    truth = _view(LASER_POSE)
    # views' places interpolated over 8 px instead of 4: 0.4 levels apart on average, about
    # 0.04 px of this texture (10 levels per px); both as near the truth
    assert known.mean() > 0.97 and np.abs(a[known] - b[known]).mean() < 0.5
    assert np.abs(b[known] - truth[known]).mean() < 1.0
    [spot] = cropped[0].spots
    assert np.hypot(spot.x - SPOT_XY[0], spot.y - SPOT_XY[1]) < 0.3


def test_images_not_searched_again_say_why(scene: dict[str, Any], tmp_path: Path) -> None:
    laser = scene["root"] / "laser.png"
    hand = Spot(laser="L1", x=10.0, y=10.0, score=1.0, source="manual")
    runs = [_run(laser, registered=False), _run(laser.with_name("other.png"), spots=(hand,))]
    args = (scene["model"], scene["mesh"], RIG)
    out = detect_all_with_references(runs, *args, scene["root"] / "images", ["other.png"],
                                     DetectionOptions(), SceneStageOptions())
    assert [r.scene.reason if r.scene else None for r in out] == [
        "not registered", "spots given by hand (--spots)"]
    assert out[1].spots == (hand,)
    out = detect_all_with_references(runs[:1], *args, None, [], DetectionOptions(),
                                     SceneStageOptions())
    assert out[0].scene is not None and "give --images" in str(out[0].scene.reason)
    assert detect_all_with_references(runs, *args, None, [], DetectionOptions(),
                                      SceneStageOptions(enabled=False)) == runs
    empty = tmp_path / "empty"
    empty.mkdir()
    out = detect_all_with_references([_run(laser)], *args, empty, [], DetectionOptions(),
                                     SceneStageOptions())
    assert out[0].scene is not None and out[0].scene.reason == "no model image could be read"


def test_a_reference_that_does_not_fit_is_not_used(scene: dict[str, Any]) -> None:
    """A fit that keeps nothing (every shift above a limit of 1e-6 px): the first detection
    stands, and the reason says how much fitted."""
    first = _run(scene["root"] / "laser.png")
    strict = SceneStageOptions(fit=SceneFitOptions(max_shift_px=1e-6))
    [out] = detect_all_with_references([first], scene["model"], scene["mesh"], RIG,
                                       scene["root"] / "images", [], DetectionOptions(), strict)
    assert out.scene is not None and not out.scene.used and out.scene.kept_share == 0.0
    assert out.scene.reason == "the reference fits 0.0 % of the image (at least 5 % needed)"
    assert out.spots == first.spots and out.detection is None


def test_model_images_are_read_when_usable(scene: dict[str, Any], tmp_path: Path,
                                           caplog: pytest.LogCaptureFixture) -> None:
    folder = tmp_path / "images"
    folder.mkdir()
    _write(folder / "m1.png", _view(MODEL_POSES[1]))
    _write(folder / "m2.png", _view(MODEL_POSES[2])[:100])  # not its camera's size
    (folder / "m3.png").write_bytes(b"not an image")
    images = ModelImages(scene["model"], folder, keep=2, exclude=["m4.png"])
    assert images.ids == [1, 2, 3]
    with caplog.at_level(logging.WARNING):
        views, names = images.nearest(LASER_POSE, 3)
    assert names == ["m1.png"] and len(views) == 1
    assert "is 320 x 100, its camera 320 x 240" in caplog.text
    assert "m3.png" in caplog.text
    assert len(images._views) == 2  # only the last `keep` are held


def test_the_png_marks_unknown_pixels(tmp_path: Path) -> None:
    rgb = np.full((4, 5, 3), 100.4, np.float32)
    rgb[0, 0] = np.nan
    path = tmp_path / "r.png"
    path.write_bytes(reference_png(rgb))
    back = read_scene_reference(path)
    assert np.isnan(back[0, 0]).all()
    np.testing.assert_allclose(back[1:], 100.4, atol=0.002)
