"""``openmvg``: the OpenMVG + OpenMVS pipeline with ``scale`` appended: the source images minus
the laser images (by name and content) linked into OUT/images_sfm/, OpenMVG's incremental SfM,
OpenMVS's dense cloud, mesh, refined and textured mesh (:mod:`sfm_laserscale.pipelines.
openmvg_steps`), ``scale`` on the project it made (OUT/scale/), then OpenMVS's
``TransformScene`` makes the whole scene metric (OUT/mvs/scene_metric.mvs) when a scale was
found. Every tool is found before any runs (missing: exit 2); a failed step raises
ToolFailedError naming it (exit 4); the tools' output goes to OUT/tools.log.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

from sfm_laserscale.commands import scale as scale_command
from sfm_laserscale.commands.colmap import prepare_out
from sfm_laserscale.errors import ToolFailedError
from sfm_laserscale.pipeline_folders import GivenInputs, resolve_scale_inputs
from sfm_laserscale.pipelines.hold_out import SfmImages, select_sfm_images
from sfm_laserscale.pipelines.openmvg_steps import (
    OPENMVG_TOOLS,
    OpenMvgOptions,
    PlannedStep,
    reconstruction_steps,
    transform_step,
)
from sfm_laserscale.pipelines.tools import find_programs, run_step
from sfm_laserscale.run_types import ScaleOptions

__all__ = ["OpenMvgInputs", "OpenMvgPipelineOptions", "OpenMvgResult", "run"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class OpenMvgInputs:
    """Paths given to the ``openmvg`` command."""

    images: Path
    laser_images: tuple[Path, ...]
    rig: Path
    spots: Path | None = None
    openmvg_bin: Path | None = None  # folder of the OpenMVG tools (None: the PATH)
    openmvs_bin: Path | None = None  # folder of the OpenMVS tools (None: the PATH)


@dataclass(frozen=True)
class OpenMvgPipelineOptions:
    """The tools' options and ``scale``'s."""

    openmvg: OpenMvgOptions = field(default_factory=OpenMvgOptions)
    scale: ScaleOptions = field(default_factory=ScaleOptions)


@dataclass(frozen=True)
class OpenMvgResult:
    """What ran and the scale."""

    images: SfmImages
    steps: tuple[str, ...]  # the steps run, in order
    scale: scale_command.ScaleResult
    metric_scene: Path | None  # OUT/mvs/scene_metric.mvs when a scale was found
    out_dir: Path
    summary: str


def _run_planned(planned: PlannedStep, programs: dict[str, str], log: Path) -> None:
    run_step(planned.step, programs[planned.step.program], log)
    missing = [p for p in planned.expects if not p.exists()]
    if missing:
        raise ToolFailedError(planned.step.name, f"exited 0 but wrote no {missing[0]}", log)


def _link_images(images: SfmImages, folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in images.names:
        os.symlink((images.folder / name).resolve(), folder / name)


def run(inputs: OpenMvgInputs, out_dir: Path,
        options: OpenMvgPipelineOptions = OpenMvgPipelineOptions(),  # noqa: B008
        overwrite: bool = False) -> OpenMvgResult:
    """The whole pipeline into ``out_dir`` (docs/WORKSPACES.md)."""
    images = select_sfm_images(inputs.images, inputs.laser_images)
    out = out_dir.resolve()
    steps = reconstruction_steps(out, options.openmvg)
    final = transform_step(out, out / "scale" / "transform_4x4.txt", options.openmvg.threads)
    bins = {p.step.program: (inputs.openmvg_bin if p.step.program in OPENMVG_TOOLS
                             else inputs.openmvs_bin) for p in [*steps, final]}
    programs = find_programs([p.step for p in [*steps, final]], bins)
    prepare_out(out, overwrite, ("images_sfm", "matches", "reconstruction_sequential", "mvs",
                                 "scale", "tools.log"))
    _link_images(images, out / "images_sfm")
    (out / "mvs").mkdir(exist_ok=True)
    (out / "matches").mkdir(exist_ok=True)
    log = out / "tools.log"
    for planned in steps:
        _run_planned(planned, programs, log)
    scale_inputs = resolve_scale_inputs(GivenInputs(
        laser_images=inputs.laser_images, rig=inputs.rig, spots=inputs.spots,
        openmvg_project=out))
    scale = scale_command.run(replace(scale_inputs, model_images=inputs.images), out / "scale",
                              options.scale)
    ran = [p.step.name for p in steps]
    metric = None
    if scale.success:
        _run_planned(final, programs, log)
        ran.append(final.step.name)
        metric = out / "mvs" / "scene_metric.mvs"
    summary = (f"OpenMVG + OpenMVS: {len(images.names)} images ({len(images.held_out)} laser "
               f"image(s) held out), {len(ran)} steps; {scale.summary}"
               + (f"; metric OpenMVS scene: {metric}" if metric else ""))
    return OpenMvgResult(images, tuple(ran), scale, metric, out_dir, summary)
