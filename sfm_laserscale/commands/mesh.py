"""``mesh``: a coarse surface from a sparse model, for users without a dense (MVS) mesh.

Builds it with :func:`sfm_laserscale.meshing.coarse_mesh` (the surface the COLMAP pipeline
command builds when it has no mesh) and writes it as a binary PLY in the model's frame, ready
for ``scale --mesh``. What it interpolates is written beside it (``<mesh>.json``: the model, the
method, the points used, the edge lengths) and in the PLY header's comments: the surface only
interpolates the sparse points, so a laser hit between them is as good as the surface is
smooth there (an MVS mesh is better wherever one can be made).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sfm_laserscale import __version__
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.meshes.new_ply import write_new_ply
from sfm_laserscale.io.models import load_model
from sfm_laserscale.meshing import CoarseMesh, CoarseMeshOptions, coarse_mesh

__all__ = ["MeshInputs", "MeshOptions", "MeshResult", "run"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MeshInputs:
    """The sparse model to mesh: a COLMAP model folder or an OpenMVG sfm_data.json."""

    model: Path


@dataclass(frozen=True)
class MeshOptions:
    """How the surface is built."""

    mesh: CoarseMeshOptions = field(default_factory=CoarseMeshOptions)


@dataclass(frozen=True)
class MeshResult:
    """The written mesh, its description file and what it interpolates."""

    mesh_path: Path
    info_path: Path
    mesh: CoarseMesh
    info: dict[str, Any]
    summary: str


def interpolation_info(model: Path, mesh: CoarseMesh, options: CoarseMeshOptions
                       ) -> dict[str, Any]:
    """What the surface interpolates (the ``<mesh>.json`` written beside it)."""
    return {
        "version": __version__,
        "model": str(model),
        "method": mesh.method,
        "interpolates": "the model's sparse 3D points only: a laser hit between them is as "
                        "good as the surface is smooth there; use an MVS mesh when you have one",
        "points_total": mesh.points_total,
        "points_used": mesh.points_used,
        "min_track_length": options.min_track_length,
        "vertices": int(len(mesh.vertices)),
        "triangles": int(len(mesh.triangles)),
        "median_edge": mesh.median_edge,
        "max_edge": mesh.max_edge,
        "units": "model units (the model's frame)",
        "options": {k: getattr(options, k) for k in options.__dataclass_fields__},
    }


def _check_out(out: Path, overwrite: bool) -> None:
    if out.suffix.lower() != ".ply":
        raise InputError("the mesh is written as PLY: give an output file ending in .ply", out)
    if out.is_dir():
        raise InputError("output path is a folder (expected a .ply file)", out)
    if out.exists() and not overwrite:
        raise InputError("output file exists (use --overwrite to replace it)", out)


def run(inputs: MeshInputs, out: Path, options: MeshOptions = MeshOptions(),  # noqa: B008
        overwrite: bool = False) -> MeshResult:
    """Build the coarse mesh of ``inputs.model`` and write ``out`` (PLY) and ``out``.json."""
    _check_out(out, overwrite)
    model = load_model(inputs.model)
    mesh = coarse_mesh(model, options.mesh)
    info = interpolation_info(inputs.model, mesh, options.mesh)
    comments = [f"sfm-laserscale {__version__} mesh: coarse {mesh.method} surface of "
                f"{inputs.model}",
                f"interpolates {mesh.points_used} of {mesh.points_total} sparse points only; "
                f"median edge {mesh.median_edge:.6g}, max edge {mesh.max_edge:.6g} model units"]
    write_new_ply(out, mesh.vertices, mesh.triangles, comments)
    info_path = out.with_name(out.name + ".json")
    info_path.write_text(json.dumps(info, indent=2) + "\n", encoding="utf-8")
    summary = (f"coarse mesh ({mesh.method}) written to {out}: {len(mesh.triangles)} triangles "
               f"interpolating {mesh.points_used} of {mesh.points_total} sparse points (median "
               f"edge {mesh.median_edge:.4g} model units); see {info_path.name}")
    logger.info("%s", summary)
    return MeshResult(out, info_path, mesh, info, summary)
