"""``scale``'s scene references: each registered laser image searched again against its seafloor.

Once a laser image is registered, the model images nearest it are rendered into its pose
through the mesh (:func:`sfm_laserscale.scene_reference.render_scene_reference`), the render
is kept only where it fits the photograph (:func:`sfm_laserscale.scene_fit.fit_reference`),
and the detector runs again with it (``detect_spots(..., scene_rgb=)``): the seafloor's own
texture is subtracted before the search. Its spots replace those of the photograph alone.

An image keeps its first detection, with the reason in :class:`SceneUse`, when it is not
registered, its spots were given by hand, no model image can be read, or the render covers
too little of it. Model images are read from the model's source images folder
(``ScaleInputs.model_images``: ``--images`` or a pipeline folder's images/), a few at a time.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.detection import detect_spots
from sfm_laserscale.detection.options import DetectionOptions
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.images import read_rgb
from sfm_laserscale.io.meshes.mesh import TriangleMesh
from sfm_laserscale.model import Camera, Pose, SparseModel
from sfm_laserscale.model_stage import registered_view
from sfm_laserscale.provenance import progress_bar
from sfm_laserscale.raycast import MeshRaycaster, crop_for_rays, pixel_rays
from sfm_laserscale.rig import Rig
from sfm_laserscale.run_types import ImageRun, SceneUse
from sfm_laserscale.scene_fit import fit_reference
from sfm_laserscale.scene_reference import (
    ModelView,
    SceneReferenceOptions,
    SceneStageOptions,
    grid_xy,
    nearest_views,
    render_scene_reference,
)

logger = logging.getLogger(__name__)


class ModelImages:
    """The model's images by id, read from ``folder`` on demand (the last ``keep`` kept);
    those named in ``exclude`` (laser images that are also model images) are never used."""

    def __init__(self, model: SparseModel, folder: Path, keep: int,
                 exclude: Sequence[str] = ()) -> None:
        self.model = model
        self.folder = folder
        self.keep = max(keep, 1)
        skip = set(exclude)
        self.ids = sorted(i for i, im in model.images.items() if im.name not in skip)
        self.centres = np.array([model.images[i].cam_from_world.center for i in self.ids])
        self._views: OrderedDict[int, ModelView | None] = OrderedDict()

    def view(self, image_id: int) -> ModelView | None:
        """The model image as a view, None when its file is missing, unreadable or not its
        camera's size (logged once)."""
        if image_id in self._views:
            self._views.move_to_end(image_id)
            return self._views[image_id]
        image = self.model.images[image_id]
        camera = self.model.cameras[image.camera_id]
        path = self.folder / image.name
        view = None
        try:
            rgb = read_rgb(path)
        except InputError as exc:
            logger.warning("model image %s: %s; not used for scene references", path,
                           exc.problem)
        else:
            if rgb.shape[:2] != (camera.height, camera.width):
                logger.warning("model image %s is %d x %d, its camera %d x %d; not used for "
                               "scene references", path, rgb.shape[1], rgb.shape[0],
                               camera.width, camera.height)
            else:
                view = ModelView(camera, image.cam_from_world, rgb)
        self._views[image_id] = view
        while len(self._views) > self.keep:
            self._views.popitem(last=False)
        return view

    def nearest(self, cam_from_world: Pose, n: int) -> tuple[list[ModelView], list[str]]:
        """The ``n`` nearest readable model images (camera centres) and their names."""
        views, names = [], []
        for k in nearest_views(self.centres, cam_from_world.center, len(self.ids)):
            if (view := self.view(self.ids[k])) is not None:
                views.append(view)
                names.append(self.model.images[self.ids[k]].name)
            if len(views) == n:
                break
        return views, names


class MeshCasters:
    """Raycasters for the renders: one on the whole mesh when it has at most
    ``max_whole_triangles``; else, per laser image, the mesh cropped exactly to the rays the
    render casts (raycast.crop_for_rays), a grid every ``crop_grid_px`` (coarser than
    ``render.grid_px``: the crop's working memory grows with its rays)."""

    def __init__(self, mesh: TriangleMesh, options: SceneStageOptions) -> None:
        self.mesh = mesh
        self.options = options
        self._whole: MeshRaycaster | None = None

    def for_view(self, camera: Camera, cam_from_world: Pose
                 ) -> tuple[MeshRaycaster, SceneReferenceOptions]:
        """The caster to render the view ``camera`` at ``cam_from_world`` with, and the
        render's options (its grid)."""
        if len(self.mesh.triangles) <= self.options.max_whole_triangles:
            if self._whole is None:
                self._whole = MeshRaycaster(self.mesh.vertices, self.mesh.triangles)
            return self._whole, self.options.render
        step = max(self.options.crop_grid_px, self.options.render.grid_px)
        origins, directions = pixel_rays(camera, cam_from_world.inverse(),
                                         grid_xy(camera, step).reshape(-1, 2))
        crop = crop_for_rays(self.mesh.vertices, self.mesh.triangles, origins, directions)
        return crop.raycaster(), replace(self.options.render, grid_px=step)


def reference_png(rgb: NDArray[np.float32]) -> bytes:
    """The reference as a 16-bit RGBA PNG (8-bit levels × 257), alpha 0 where it is unknown:
    what ``detect --scene`` reads (io.images.read_scene_reference)."""
    known = np.isfinite(rgb).all(axis=2)
    rgba = np.zeros((*rgb.shape[:2], 4), dtype=np.uint16)
    rgba[..., :3] = np.clip(np.nan_to_num(rgb) * 257.0 + 0.5, 0, 65535).astype(np.uint16)
    rgba[..., 3] = np.where(known, 65535, 0)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    if not ok:
        raise RuntimeError("PNG encoding of a scene reference failed")
    return bytes(buf)


def detect_with_reference(run: ImageRun, rig: Rig, casters: MeshCasters, images: ModelImages,
                          detection: DetectionOptions, options: SceneStageOptions) -> ImageRun:
    """One registered laser image detected again with its scene reference, or as it was
    with the reason in ``run.scene``."""
    view = registered_view(run)
    if view is None:
        return replace(run, scene=SceneUse(used=False, reason="not registered"))
    camera, pose = view
    views, names = images.nearest(pose, options.render.n_views)
    if not views:
        return replace(run, scene=SceneUse(used=False, reason="no model image could be read"))
    caster, render = casters.for_view(camera, pose)
    rendered = render_scene_reference(camera, pose, caster, views, render)
    rgb = read_rgb(run.path)
    fit = fit_reference(rgb, rendered.rgb, options.fit)
    coverage = rendered.coverage * fit.kept_share
    use = SceneUse(used=coverage >= options.min_coverage, reason=None,
                   views=tuple(names[i] for i in rendered.views), coverage=rendered.coverage,
                   kept_share=fit.kept_share, shift_median_px=fit.shift_median_px,
                   residual_ratio_median=fit.ratio_median, spots_alone=len(run.spots))
    if not use.used:
        why = (f"the reference fits {100 * coverage:.1f} % of the image "
               f"(at least {100 * options.min_coverage:g} % needed)")
        return replace(run, scene=replace(use, reason=why))
    det = detect_spots(rgb, camera, rig, detection, scene_rgb=fit.rgb)
    png = reference_png(fit.rgb) if options.keep_png else None
    return replace(run, detection=det, spots=det.spots, spot_reasons=dict(det.missing),
                   scene=replace(use, png=png))


def detect_all_with_references(runs: Sequence[ImageRun], model: SparseModel,
                               mesh: TriangleMesh, rig: Rig, folder: Path | None,
                               manual: Sequence[str], detection: DetectionOptions,
                               options: SceneStageOptions, progress: bool = False
                               ) -> list[ImageRun]:
    """Every laser image with its scene reference's use (module docstring); ``folder``: the
    model images (None: none given), ``manual``: the images whose spots were given by hand."""
    if not options.enabled:
        return list(runs)
    if folder is None:
        why = "no model images (give --images, or a pipeline folder with its images)"
        return [replace(r, scene=SceneUse(used=False, reason=why)) for r in runs]
    by_hand = set(manual)
    todo = [r for r in runs if registered_view(r) is not None and r.name not in by_hand]
    casters = MeshCasters(mesh, options)  # its caster is built for the first render
    images = ModelImages(model, folder, keep=2 * options.render.n_views,
                         exclude=[r.name for r in runs])
    done = {}
    for r in progress_bar(progress, "scene references", iterable=todo, unit="img"):
        done[r.name] = detect_with_reference(r, rig, casters, images, detection, options)
        _log_use(done[r.name])
    return [done.get(r.name) or replace(r, scene=SceneUse(used=False,
                                                          reason=_skip_reason(r, manual)))
            for r in runs]


def _skip_reason(run: ImageRun, manual: Sequence[str]) -> str:
    return "spots given by hand (--spots)" if run.name in manual else "not registered"


def _log_use(run: ImageRun) -> None:
    use = run.scene
    if use is None:
        return
    if not use.used:
        logger.info("laser image %s: no scene reference (%s)", run.name, use.reason)
        return
    logger.info("laser image %s: scene reference from %s covers %.1f %% (%.1f %% kept by the "
                "fit, shift median %.2f px); spots %d alone, %d with it", run.name,
                ", ".join(use.views), 100 * use.coverage, 100 * use.kept_share,
                use.shift_median_px, use.spots_alone, len(run.spots))
