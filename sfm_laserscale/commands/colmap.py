"""``colmap``: the COLMAP pipeline with ``scale`` appended: SfM of the source images with the
laser images held out (by name and content), a coarse mesh when none is given, then ``scale`` on
the workspace it made. Outputs in OUT::

    sfm/database.db  sfm/sparse/<n>/  sfm/colmap.log   the SfM (a COLMAP workspace)
    sfm/mesh_coarse.ply (+ .json)                      only without --mesh (``mesh`` command)
    scale/                                             what ``scale --out`` writes

A failed SfM step raises ToolFailedError naming it (exit status 4).
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

from sfm_laserscale.commands import mesh as mesh_command
from sfm_laserscale.commands import scale as scale_command
from sfm_laserscale.errors import InputError
from sfm_laserscale.meshing import CoarseMeshOptions
from sfm_laserscale.pipeline_folders import GivenInputs, resolve_scale_inputs
from sfm_laserscale.pipelines.colmap_sfm import SfmResult, resolve_backend, run_sfm
from sfm_laserscale.pipelines.hold_out import SfmImages, select_sfm_images
from sfm_laserscale.registration.mapping import SfmOptions
from sfm_laserscale.run_types import ScaleOptions

__all__ = ["ColmapInputs", "ColmapOptions", "ColmapResult", "run"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ColmapInputs:
    """Paths given to the ``colmap`` command."""

    images: Path  # the source images (laser images found among them are held out)
    laser_images: tuple[Path, ...]
    rig: Path
    mesh: Path | None = None  # a mesh in the frame of the model this run builds (rare)
    pairs: Path | None = None  # COLMAP pair list "name1 name2" per line (else exhaustive)
    spots: Path | None = None


@dataclass(frozen=True)
class ColmapOptions:
    """Every stage's options."""

    sfm: SfmOptions = field(default_factory=SfmOptions)
    mesh: CoarseMeshOptions = field(default_factory=CoarseMeshOptions)
    scale: ScaleOptions = field(default_factory=ScaleOptions)


@dataclass(frozen=True)
class ColmapResult:
    """SfM, mesh and scale of one run."""

    images: SfmImages
    sfm: SfmResult
    mesh_path: Path
    mesh_is_coarse: bool
    scale: scale_command.ScaleResult
    out_dir: Path
    summary: str


def prepare_out(out: Path, overwrite: bool, subfolders: tuple[str, ...]) -> None:
    """Create OUT; a non-empty OUT is refused unless ``overwrite`` (then its subfolders go)."""
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out)
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise InputError("output folder is not empty (use --overwrite to replace it)", out)
        for sub in subfolders:
            shutil.rmtree(out / sub, ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)


def run(inputs: ColmapInputs, out_dir: Path,
        options: ColmapOptions = ColmapOptions(),  # noqa: B008
        overwrite: bool = False) -> ColmapResult:
    """SfM (laser images held out), mesh (given or coarse), then ``scale``."""
    images = select_sfm_images(inputs.images, inputs.laser_images)
    if inputs.mesh is not None and not inputs.mesh.is_file():
        raise InputError("mesh not found", inputs.mesh)
    resolve_backend(options.sfm.backend, options.sfm.colmap)  # a bad choice fails before work
    prepare_out(out_dir, overwrite, ("sfm", "scale"))
    sfm = run_sfm(images, out_dir / "sfm", inputs.pairs, options.sfm)
    mesh_path, coarse = inputs.mesh, inputs.mesh is None
    if mesh_path is None:
        built = mesh_command.run(mesh_command.MeshInputs(sfm.model_dir),
                                 out_dir / "sfm" / "mesh_coarse.ply",
                                 mesh_command.MeshOptions(options.mesh), overwrite=True)
        mesh_path = built.mesh_path
        logger.warning("no --mesh: a COARSE mesh (%s) was built from the sparse points; give an "
                       "MVS mesh for the best scale", options.mesh.method)
    scale_inputs = resolve_scale_inputs(GivenInputs(
        laser_images=inputs.laser_images, rig=inputs.rig, mesh=mesh_path, spots=inputs.spots,
        colmap_workspace=out_dir / "sfm"))
    scale = scale_command.run(replace(scale_inputs, model_images=inputs.images),
                              out_dir / "scale", options.scale)
    summary = (f"SfM ({sfm.backend}): {sfm.n_registered}/{sfm.n_images} images "
               f"({len(images.held_out)} laser image(s) held out); mesh: "
               f"{'coarse ' if coarse else ''}{mesh_path.name}; {scale.summary}")
    return ColmapResult(images, sfm, mesh_path, coarse, scale, out_dir, summary)
