"""``detect``: laser spots of many images, with overlays, no model registration.

Writes (atomically: a staged folder replaces ``DIR`` only when everything is written)::

    DIR/spots.csv             image,laser,x,y,score,sigma_px,source (feeds ``scale --spots``)
    DIR/detections.json       per image: spots (with a ``review`` flag for low scores),
                              missing lasers with reasons, candidate count; learned beam lines
    DIR/overlays/<stem>.jpg   spots and scores, beam lines and their search bands

With a folder of scene references (``DetectInputs.scene``: ``<stem>.png`` or ``.tif`` per
laser image, the same view without the lasers, aligned pixel for pixel, RGBA alpha 0 where
unknown), each image is searched with its reference's texture removed
(:mod:`sfm_laserscale.detection.scene`); an image without one is searched as it is.

When the rig has uncalibrated lasers and at least ``min_images_for_lines`` images are given,
their beam lines are learned from all images first (:mod:`sfm_laserscale.detection.beam_lines`) and
searched like calibrated beams.
"""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap
from numpy.typing import NDArray

from sfm_laserscale.detection import DetectionOptions, DetectionResult, detect_spots
from sfm_laserscale.detection.beam_lines import (
    BeamLineOptions,
    BeamLinesResult,
    image_candidates,
    learn_beam_lines,
    rig_with_learned_lines,
)
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.images import (
    LaserImage,
    damage,
    find_laser_images,
    read_rgb,
    read_scene_reference,
)
from sfm_laserscale.io.models import load_model
from sfm_laserscale.io.outputs import check_output_dir, staged_output_dir
from sfm_laserscale.io.spots_csv import write_spots_csv
from sfm_laserscale.model import CAMERA_MODEL_IDS, Camera, SparseModel, Spot
from sfm_laserscale.report.overlays import draw_bands, draw_overlay, near_misses
from sfm_laserscale.rig import Rig, load_rig

__all__ = ["DetectInputs", "DetectRunOptions", "DetectRunResult", "run"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DetectInputs:
    """Images (files and/or folders), the rig, and the camera: a model or a camera string."""

    images: tuple[Path, ...]
    rig: Path
    model: Path | None = None
    camera: str | None = None  # "PINHOLE W H fx fy cx cy" (any COLMAP model name and params)
    scene: Path | None = None  # folder of scene references, <stem>.png / .tif per image


@dataclass(frozen=True)
class DetectRunOptions:
    """``detection``: per-image detector settings; spots scoring below ``review_score`` are
    flagged for review; ``lines``: beam line learning (uncalibrated lasers, >= 3 images)."""

    detection: DetectionOptions = field(default_factory=DetectionOptions)
    lines: BeamLineOptions = field(default_factory=BeamLineOptions)
    review_score: float = 0.5
    min_images_for_lines: int = 3
    overlays: bool = True


@dataclass(frozen=True)
class DetectRunResult:
    """Spots per image name, what was learned, where it went, a one-paragraph summary."""

    out_dir: Path | None  # None: nothing written (the Python API)
    spots: dict[str, tuple[Spot, ...]]
    missing: dict[str, dict[str, str]]
    learned: BeamLinesResult | None
    n_images: int
    summary: str
    record: dict[str, Any] = field(default_factory=dict)  # detections.json's content

    @property
    def success(self) -> bool:
        """True when at least one spot was found."""
        return any(self.spots.values())


def parse_camera(text: str) -> Camera:
    """A Camera from "MODEL W H p1 p2 ..." (COLMAP model name and parameter order)."""
    parts = text.replace(",", " ").split()
    if len(parts) < 4 or parts[0].upper() not in CAMERA_MODEL_IDS:
        raise InputError(f"--camera must be 'MODEL W H params...' (e.g. 'PINHOLE 1920 1080 "
                         f"1500 1500 960 540'), got {text!r}")
    try:
        w, h = int(parts[1]), int(parts[2])
        params = np.array([float(p) for p in parts[3:]], dtype=np.float64)
    except ValueError:
        raise InputError(f"--camera: not numbers in {text!r}") from None
    cam = Camera(1, parts[0].upper(), w, h, params)
    expected = len(pycolmap.Camera.create_from_model_name(1, cam.model, 1.0, 1, 1).params)
    if expected != len(params) or w <= 0 or h <= 0 or not np.all(np.isfinite(params)):
        raise InputError(f"--camera {text!r}: {cam.model} needs W H > 0 and {expected} "
                         f"finite parameters, got {len(params)}")
    return cam


def _camera_model(inputs: DetectInputs) -> SparseModel:
    """The model whose cameras the images are matched to (by size)."""
    if (inputs.model is None) == (inputs.camera is None):
        raise InputError("give exactly one of --model (cameras from a model) or --camera")
    if inputs.model is not None:
        if not inputs.model.exists():
            raise InputError("model not found", inputs.model)
        return load_model(inputs.model)
    cam = parse_camera(str(inputs.camera))
    return SparseModel(cameras={1: cam}, images={}, point3D_ids=np.zeros(0, np.uint64),
                       points_xyz=np.zeros((0, 3)))


@dataclass(frozen=True)
class Frame:
    """One image to detect in: its name, camera, a loader of its (H, W, 3) uint8 RGB and
    of its scene reference ((H, W, 3) float32, NaN where unknown; None: no reference)."""

    name: str
    camera: Camera
    load: Callable[[], NDArray[np.uint8]]
    load_scene: Callable[[], NDArray[np.float32]] | None = None

    def detect(self, rig: Rig, options: DetectionOptions) -> DetectionResult:
        """The detector's result on this frame (with its scene reference if it has one)."""
        scene = None if self.load_scene is None else self.load_scene()
        return detect_spots(self.load(), self.camera, rig, options, scene_rgb=scene)


@dataclass(frozen=True)
class ManyResult:
    """Per-image detections, the learned lines (None if not tried), the rig searched in pass 2
    (uncalibrated lasers with a learned line carry a pseudo beam: a search aid only)."""

    results: dict[str, DetectionResult]
    learned: BeamLinesResult | None
    search_rig: Rig


def detect_many(frames: Sequence[Frame], rig: Rig, options: DetectRunOptions) -> ManyResult:
    """Detect in every frame; learn beam lines first when the rig has uncalibrated lasers."""
    d = options.detection
    first = {f.name: f.detect(rig, d) for f in frames}
    if all(las.calibrated for las in rig.lasers) or len(frames) < options.min_images_for_lines:
        return ManyResult(first, None, rig)
    cands = [image_candidates(first[f.name], f.camera) for f in frames]
    focal = float(np.median([f.camera.focal_px for f in frames]))
    learned = learn_beam_lines(cands, rig, focal, options.lines)
    if not learned.lines:
        for res in first.values():
            res.missing.update(learned.missing)
        return ManyResult(first, learned, rig)
    search_rig = rig_with_learned_lines(rig, learned, d.min_range_m, d.max_range_m)
    second = {f.name: f.detect(search_rig, d) for f in frames}
    for res in second.values():
        res.missing.update(learned.missing)
    return ManyResult(second, learned, search_rig)


def _image_record(name: str, res: DetectionResult | None, review: float,
                  reason: str | None = None, scene: Path | None = None) -> dict[str, Any]:
    """detections.json entry of one image (``reason``: why an image was not searched;
    ``scene``: its scene reference, if it was searched with one)."""
    if res is None:
        return {"name": name, "readable": False, "reason": reason or "not a readable image",
                "spots": [], "missing": {}, "num_candidates": 0}
    rules = res.taken_by()
    return {
        "name": name, "readable": True,
        "scene_reference": None if scene is None else str(scene),
        "spots": [{"laser": s.laser, "x": s.x, "y": s.y, "score": s.score,
                   "sigma_px": s.sigma_px, "review": s.score < review,
                   "taken_by": rules.get(s.laser, "")} for s in res.spots],
        "missing": dict(res.missing),
        "near_misses": {laser: [{"x": c.x, "y": c.y, "score": c.score, "source": c.source,
                                 "reason": c.reason, "evidence": dict(c.evidence)}
                                for c in cands]
                        for laser, cands in res.near_misses.items()},
        "num_candidates": len(res.candidates),
        "num_valid_candidates": sum(c.score > 0 for c in res.candidates),
    }


def _lines_record(learned: BeamLinesResult | None) -> dict[str, Any] | None:
    if learned is None:
        return None
    return {"lines": {n: {"point_normalised": ln.point.tolist(),
                          "direction_normalised": ln.direction.tolist(),
                          "segment": list(ln.s_range), "n_images": ln.n_images,
                          "rms_px": ln.rms_px, "shared_with": ln.shared_with}
                      for n, ln in learned.lines.items()},
            "missing": learned.missing}


def _write_overlay(path: Path, li: LaserImage, rig: Rig, res: DetectionResult,
                   options: DetectionOptions) -> None:
    """overlays/<stem>.jpg: bands, beams, spots, and each spot's score."""
    assert li.camera is not None  # callers pass readable images only
    rgb = read_rgb(li.path)
    img = draw_overlay(draw_bands(rgb, li.camera, rig, options), li.camera, rig, res.spots, {},
                       None, options.min_range_m, options.max_range_m,
                       near_misses=near_misses(res))
    f = img.shape[1] / rgb.shape[1]
    for s in res.spots:
        org = (int(s.x * f + 18 * f), int(s.y * f + 30 * f))
        for color, thick in (((0, 0, 0), 4), ((255, 255, 255), 1)):
            cv2.putText(img, f"{s.score:.2f}", org, cv2.FONT_HERSHEY_DUPLEX, 0.6 * max(f, 1.0),
                        color, thick, cv2.LINE_AA)
    cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 88])


def _summary(spots: dict[str, tuple[Spot, ...]], n_images: int, review: int,
             learned: BeamLinesResult | None) -> str:
    n = sum(len(v) for v in spots.values())
    with_spots = sum(bool(v) for v in spots.values())
    text = f"{n} spots in {with_spots} of {n_images} images ({review} flagged for review)"
    if learned is not None:
        text += f"; learned beam lines: {', '.join(sorted(learned.lines)) or 'none'}"
    return text


def _damaged(images: Sequence[LaserImage]) -> dict[str, str]:
    """Image name -> why its data is damaged (a truncated JPEG), for the readable images."""
    found = {}
    for li in images:
        why = damage(li.path) if li.camera is not None else None
        if why is not None:
            logger.warning("%s: %s; reported and skipped", li.path, why)
            found[li.name] = why
    return found


SCENE_SUFFIXES = (".png", ".tif", ".tiff")


def scene_references(folder: Path | None, images: Sequence[LaserImage]) -> dict[str, Path]:
    """Image name -> its scene reference in ``folder`` (``<stem>.png``/``.tif``/``.tiff``);
    images without one are left out. InputError when the folder is missing or matches none."""
    if folder is None:
        return {}
    if not folder.is_dir():
        raise InputError("the scene reference folder does not exist", folder)
    found = {}
    for li in images:
        stem = Path(li.name).stem
        path = next((p for s in SCENE_SUFFIXES if (p := folder / (stem + s)).is_file()), None)
        if path is not None:
            found[li.name] = path
    if images and not found:
        raise InputError("no scene reference matches a laser image (<stem>"
                         f"{'/'.join(SCENE_SUFFIXES)})", folder)
    return found


def _read_scene(path: Path, camera: Camera) -> NDArray[np.float32]:
    """A laser image's scene reference, refused (InputError naming it) unless it has the
    image's size."""
    scene = read_scene_reference(path)
    if scene.shape[:2] != (camera.height, camera.width):
        raise InputError(f"the scene reference is {scene.shape[1]}x{scene.shape[0]} px but "
                         f"its laser image's camera is {camera.width}x{camera.height} px", path)
    return scene


def run(inputs: DetectInputs, out_dir: Path | None,
        options: DetectRunOptions = DetectRunOptions(),  # noqa: B008 (frozen)
        overwrite: bool = False) -> DetectRunResult:
    """Detect spots in every image and write spots.csv, detections.json and overlays (``out_dir``
    None: nothing written; ``DetectRunResult.record`` holds detections.json's content)."""
    if out_dir is not None:
        check_output_dir(out_dir, overwrite)
    rig = load_rig(inputs.rig)
    images = find_laser_images(list(inputs.images), _camera_model(inputs))
    damaged = _damaged(images)
    scenes = scene_references(inputs.scene, images)
    frames = [Frame(li.name, li.camera, functools.partial(read_rgb, li.path, check=False),
                    None if li.name not in scenes
                    else functools.partial(_read_scene, scenes[li.name], li.camera))
              for li in images if li.camera is not None and li.name not in damaged]
    many = detect_many(frames, rig, options)
    results, learned, search_rig = many.results, many.learned, many.search_rig
    spots = {li.name: results[li.name].spots for li in images if li.name in results}
    review = sum(s.score < options.review_score for v in spots.values() for s in v)
    record = {"images": [_image_record(li.name, results.get(li.name), options.review_score,
                                       damaged.get(li.name), scenes.get(li.name))
                         for li in images],
              "learned_beam_lines": _lines_record(learned),
              "review_score": options.review_score}
    if out_dir is not None:
        _write(out_dir, overwrite, record, spots, images, results, search_rig, options)
    missing = {n: dict(r.missing) for n, r in results.items()}
    return DetectRunResult(out_dir=out_dir, spots=spots, missing=missing, learned=learned,
                           n_images=len(images),
                           summary=_summary(spots, len(images), review, learned),
                           record=record)


def _write(out_dir: Path, overwrite: bool, record: dict[str, Any],
           spots: dict[str, tuple[Spot, ...]], images: Sequence[LaserImage],
           results: dict[str, DetectionResult], search_rig: Rig,
           options: DetectRunOptions) -> None:
    """spots.csv, detections.json and the overlays, staged then moved into ``out_dir``."""
    with staged_output_dir(out_dir, overwrite) as tmp:
        write_spots_csv(tmp / "spots.csv", spots)
        (tmp / "detections.json").write_text(json.dumps(record, indent=2), encoding="utf-8")
        if options.overlays:
            (tmp / "overlays").mkdir()
            for li in images:
                if li.name in results:
                    _write_overlay(tmp / "overlays" / (Path(li.name).stem + ".jpg"), li,
                                   search_rig, results[li.name], options.detection)
