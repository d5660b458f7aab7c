"""``apply``: rescale a sparse model and/or a mesh by a known scale (metres per model unit).

Writes the same files as ``scale`` does for its rescaled outputs (docs/OUTPUTS.md)::

    DIR/scaled/model/          the model, same format as the input (COLMAP binary or text:
                               the whole folder; OpenMVG: sfm_data.json)
    DIR/scaled/<mesh file>     the mesh, same format, only vertex positions changed
    DIR/transform.sim3         COLMAP Sim3d "scale qw qx qy qz tx ty tz"
    DIR/transform_4x4.txt      the 4x4 matrix (OpenMVS TransformScene, COLMAP 3.8)

into a temporary folder beside DIR that replaces DIR only when everything is written.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.colmap_write import write_scaled_colmap_model
from sfm_laserscale.io.meshes.mesh import write_scaled_mesh
from sfm_laserscale.io.models import load_model
from sfm_laserscale.io.openmvg import write_scaled_openmvg_sfm_data
from sfm_laserscale.io.outputs import check_output_dir, staged_output_dir
from sfm_laserscale.io.transforms import write_matrix_4x4, write_sim3

__all__ = ["ApplyInputs", "ApplyOptions", "ApplyResult", "run"]

logger = logging.getLogger(__name__)

#: File name of the rescaled OpenMVG model inside ``scaled/model/`` (as ``scale`` writes it).
OPENMVG_MODEL_NAME = "sfm_data.json"


@dataclass(frozen=True)
class ApplyInputs:
    """What to rescale: a model, a mesh or both (at least one)."""

    model: Path | None = None  # COLMAP model folder or OpenMVG sfm_data.json
    mesh: Path | None = None  # PLY, OBJ, glTF/GLB, OFF, STL


@dataclass(frozen=True)
class ApplyOptions:
    """The scale to apply."""

    scale: float  # metres per model unit: metric = scale x model coordinates


@dataclass(frozen=True)
class ApplyResult:
    """Where everything went (final paths under ``out_dir``)."""

    out_dir: Path
    scale: float
    model_format: str | None  # colmap-binary | colmap-text | openmvg | None (no model)
    model_files: tuple[Path, ...]
    mesh_files: tuple[Path, ...]  # the mesh first, then its side files (textures, MTL)
    transform_files: tuple[Path, ...]
    summary: str


def check_scale(scale: float) -> float:
    """The scale as a float; InputError unless it is a positive finite number."""
    try:
        value = float(scale)
    except (TypeError, ValueError):
        raise InputError(f"scale must be a number, got {scale!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"scale must be a positive finite number, got {scale!r}")
    return value


def check_apply_inputs(inputs: ApplyInputs) -> None:
    """InputError when neither a model nor a mesh is given, or a given path does not exist."""
    if inputs.model is None and inputs.mesh is None:
        raise InputError("nothing to rescale: give --model, --mesh or both")
    if inputs.model is not None and not inputs.model.exists():
        raise InputError("model not found", inputs.model)
    if inputs.mesh is not None and not inputs.mesh.is_file():
        raise InputError("mesh not found" if not inputs.mesh.exists() else "mesh is not a file",
                         inputs.mesh)


def _write_model(src: Path, scaled: Path, scale: float) -> tuple[str, list[Path]]:
    """Validate the model (every reader check) and write it rescaled under ``scaled/model``."""
    fmt = load_model(src).source_format
    if fmt == "openmvg":
        dst = write_scaled_openmvg_sfm_data(src, scaled / "model" / OPENMVG_MODEL_NAME, scale)
        return fmt, [dst]
    return fmt, write_scaled_colmap_model(src, scaled / "model", scale)


def _final(paths: list[Path], tmp: Path, out: Path) -> tuple[Path, ...]:
    """Paths written inside the staging folder, as they are after the move."""
    return tuple(out / p.relative_to(tmp) for p in paths)


def run(inputs: ApplyInputs, out_dir: Path, options: ApplyOptions,
        overwrite: bool = False) -> ApplyResult:
    """Rescale the model and/or mesh by ``options.scale`` and write them with the transforms."""
    scale = check_scale(options.scale)
    check_apply_inputs(inputs)
    check_output_dir(out_dir, overwrite)
    out = out_dir.resolve()
    fmt: str | None = None
    model_files: list[Path] = []
    mesh_files: list[Path] = []
    with staged_output_dir(out_dir, overwrite) as tmp:
        scaled = tmp / "scaled"
        scaled.mkdir()
        if inputs.model is not None:
            fmt, model_files = _write_model(inputs.model, scaled, scale)
        if inputs.mesh is not None:
            mesh_files = write_scaled_mesh(inputs.mesh, scaled, scale)
        transforms = [tmp / "transform.sim3", tmp / "transform_4x4.txt"]
        write_sim3(transforms[0], scale)
        write_matrix_4x4(transforms[1], scale)
        result_files = (_final(model_files, tmp, out), _final(mesh_files, tmp, out),
                        _final(transforms, tmp, out))
    what = [f"model ({fmt})"] * (fmt is not None) + ["mesh"] * bool(mesh_files)
    summary = f"scale {scale:.9g} m/unit applied to {' and '.join(what)}; written to {out}"
    logger.info(summary)
    return ApplyResult(out_dir=out, scale=scale, model_format=fmt, model_files=result_files[0],
                       mesh_files=result_files[1], transform_files=result_files[2],
                       summary=summary)
