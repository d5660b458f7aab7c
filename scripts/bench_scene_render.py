"""How well model images rendered through the mesh fit a registered laser image, and what the
detector gains from them (docs/DETECTION.md, "A scene reference").

Each survey of the independent generator (``synthetic/underwater/survey.py``: real SfM, the
true floor as the mesh, green beams in green water with pale clutter, 960 × 540 by default)
is made once and ``scale`` registers its laser images. For every registered laser image the
nearest model images are rendered into its pose (``scene_reference.render_scene_reference``),
and the script measures:

- coverage: the share of the laser image the reference covers;
- texture: the standard deviation (8-bit levels) of the laser image's fine texture (minus its
  Gaussian blur of 8 px) and of what is left of it after the reference's is subtracted, away
  from the spots (25 px);
- fit: per 64 × 64 patch away from the spots, the shift between the two textures (least
  squares, :func:`patch_shift`), its median and 90th percentile in px;
- the detector on the laser image alone and with the reference: spots within 1.5 px of the
  truth (``true_spots.csv``) and their mean error.

    python scripts/bench_scene_render.py --seeds 0-5 [--size 960x540] [--views 3]
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from bench_detection_physical import MATCH_PX, _seeds, _sizes
from numpy.typing import NDArray

from sfm_laserscale.detection import DetectionOptions, detect_spots
from sfm_laserscale.detection.scene import scene_texture
from sfm_laserscale.io.images import read_rgb
from sfm_laserscale.io.meshes.mesh import load_mesh
from sfm_laserscale.io.models import load_model
from sfm_laserscale.io.spots_csv import read_spots_csv
from sfm_laserscale.model import Camera
from sfm_laserscale.pipeline_folders import GivenInputs, resolve_scale_inputs
from sfm_laserscale.raycast import MeshRaycaster
from sfm_laserscale.rig import Rig, load_rig
from sfm_laserscale.run_types import ScaleOptions
from sfm_laserscale.scene_reference import (
    ModelView,
    SceneReferenceOptions,
    render_scene_reference,
)
from sfm_laserscale.synthetic.underwater.survey import SurveyOptions, make_survey

PATCH_PX = 64
SPOT_MASK_PX = 25


@dataclass(frozen=True)
class ImageFit:
    """One laser image: coverage, texture std before/after, patch shifts (px), and per
    variant (alone, with the reference) the spots found and their errors (px)."""

    name: str
    coverage: float
    texture_before: float
    texture_after: float
    shifts_px: tuple[float, ...]
    found: tuple[int, int]
    truths: int
    errors_px: tuple[tuple[float, ...], tuple[float, ...]]


def patch_shift(a: NDArray[np.float32], b: NDArray[np.float32]) -> tuple[float, float] | None:
    """The translation (dx, dy) px that carries texture ``b`` onto ``a`` (a(x) = b(x - d)):
    Gauss-Newton on the sum of squared differences (Lucas-Kanade), five steps from zero, the
    patch's 4 px rim left out; None when the patch has too little texture to tell."""
    gy, gx = (np.asarray(g) for g in np.gradient(b.astype(np.float64)))
    inner = (slice(4, -4), slice(4, -4))
    jac = np.stack([gx[inner].ravel(), gy[inner].ravel()], axis=1)
    normal = jac.T @ jac
    if np.linalg.cond(normal) > 1e3:
        return None
    rows, cols = np.mgrid[0:a.shape[0], 0:a.shape[1]].astype(np.float32)
    d = np.zeros(2)
    for _ in range(5):
        moved = cv2.remap(b, cols - np.float32(d[0]), rows - np.float32(d[1]), cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)
        residual = (a - moved).astype(np.float64)[inner].ravel()
        d -= np.linalg.solve(normal, jac.T @ residual)  # a - b(x - d - δ) ≈ r + ∇b·δ
    return float(d[0]), float(d[1])


def patch_shifts(a: NDArray[np.float32], b: NDArray[np.float32],
                 usable: NDArray[np.bool_]) -> list[float]:
    """|shift| (px) between two textures (:func:`patch_shift`) per PATCH_PX patch wholly
    ``usable`` and textured enough to tell."""
    out = []
    height, width = a.shape
    for y0 in range(0, height - PATCH_PX + 1, PATCH_PX):
        for x0 in range(0, width - PATCH_PX + 1, PATCH_PX):
            win = (slice(y0, y0 + PATCH_PX), slice(x0, x0 + PATCH_PX))
            if usable[win].all() and (d := patch_shift(a[win], b[win])) is not None:
                out.append(math.hypot(*d))
    return out


def survey_fits(seed: int, size: tuple[int, int], views: int, work: Path) -> list[ImageFit]:
    """Make survey ``seed``, register its laser images with ``scale`` and measure each."""
    from sfm_laserscale.commands.scale import run

    survey = make_survey(work / f"survey_{seed}", SurveyOptions(
        width=size[0], height=size[1], seed=seed, progress=False))
    inputs = resolve_scale_inputs(GivenInputs(
        laser_images=(survey.laser_images_dir,), rig=survey.rig_path, model=survey.model_dir,
        mesh=survey.mesh_path, database=survey.database_path))
    result = run(inputs, None, ScaleOptions(progress=False))
    model = load_model(survey.model_dir)
    mesh = load_mesh(survey.mesh_path)
    caster = MeshRaycaster(mesh.vertices, mesh.triangles)
    model_views = [ModelView(model.cameras[im.camera_id], im.cam_from_world,
                             read_rgb(survey.images_dir / im.name))
                   for im in model.images.values()]
    rig = load_rig(survey.rig_path)
    truths = read_spots_csv(survey.spots_path, None, rig.names)
    fits = []
    for image in result.images:
        reg = image.registration
        if image.camera is None or reg is None or reg.cam_from_world is None:
            continue
        ref = render_scene_reference(image.camera, reg.cam_from_world, caster, model_views,
                                     SceneReferenceOptions(n_views=views))
        fits.append(_measure(image.name, read_rgb(image.path), ref.rgb, ref.coverage,
                             image.camera, rig,
                             {s.laser: (s.x, s.y) for s in truths.get(image.name, [])}))
    return fits


def _measure(name: str, rgb: NDArray[np.uint8], ref: NDArray[np.float32], coverage: float,
             camera: Camera, rig: Rig, truth: dict[str, tuple[float, float]]) -> ImageFit:
    known = np.isfinite(ref[..., 0])
    usable = known.copy()
    for x, y in truth.values():
        cv2.circle(usable.view(np.uint8), (int(x), int(y)), SPOT_MASK_PX, 0, -1)
    # the fine texture the detector would subtract (detection.scene), as grey
    sigma = DetectionOptions().scene_texture_sigma_px
    a = scene_texture(rgb.astype(np.float32), sigma).mean(axis=2)
    b = scene_texture(ref, sigma).mean(axis=2)
    found, errors = [], []
    for scene in (None, ref):
        res = detect_spots(rgb, camera, rig, DetectionOptions(), scene_rgb=scene)
        errs = [math.dist((s.x, s.y), truth[s.laser]) for s in res.spots if s.laser in truth]
        good = tuple(e for e in errs if e <= MATCH_PX)
        found.append(len(good))
        errors.append(good)
    return ImageFit(name, coverage, float(a[usable].std()), float((a - b)[usable].std()),
                    tuple(patch_shifts(a, b, usable)), (found[0], found[1]), len(truth),
                    (errors[0], errors[1]))


def pooled_lines(fits: Sequence[ImageFit]) -> list[str]:
    """The pooled figures of every measured image."""
    shifts = [s for f in fits for s in f.shifts_px]
    coverage = statistics.median(f.coverage for f in fits)
    lines = [f"{len(fits)} images: coverage median {coverage:.3f}; "
             f"fine texture {statistics.mean(f.texture_before for f in fits):.2f} -> "
             f"{statistics.mean(f.texture_after for f in fits):.2f} levels (mean std); "
             f"patch shifts (n = {len(shifts)}) median {np.median(shifts):.2f} px, "
             f"p90 {np.percentile(shifts, 90):.2f} px"]
    truths = sum(f.truths for f in fits)
    for k, label in enumerate(("alone", "with the reference")):
        errs = [e for f in fits for e in f.errors_px[k]]
        lines.append(f"{label}: {sum(f.found[k] for f in fits)} of {truths} spots within "
                     f"{MATCH_PX} px, mean error {np.mean(errs):.3f} px, median "
                     f"{np.median(errs):.3f} px")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=_seeds, default=list(range(6)))
    ap.add_argument("--size", type=_sizes, default=[(960, 540)])
    ap.add_argument("--views", type=int, default=3)
    args = ap.parse_args(argv)
    fits: list[ImageFit] = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            new = survey_fits(seed, args.size[0], args.views, Path(tmp))
            for f in new:
                print(f"seed {seed} {f.name}: coverage {f.coverage:.3f}, texture "
                      f"{f.texture_before:.2f} -> {f.texture_after:.2f}, shift median "
                      f"{np.median(f.shifts_px):.2f} px, found {f.found[0]} -> {f.found[1]} "
                      f"of {f.truths}", flush=True)
            fits.extend(new)
    print("\n".join(pooled_lines(fits)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
