"""``scale``'s inputs from what the user gave: explicit paths override what a pipeline folder
(``--colmap-workspace``, ``--openmvg-project``) holds (:mod:`sfm_laserscale.io.workspace` finds
the files). A missing input is one :class:`~sfm_laserscale.errors.InputError` that says where
it looked (exit status 2); a missing mesh suggests ``sfm-laserscale mesh``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.openmvg import openmvg_regions_are_sift
from sfm_laserscale.io.workspace import FoundInputs, find_colmap_workspace, find_openmvg_project
from sfm_laserscale.run_types import ScaleInputs

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class GivenInputs:
    """What the user gave ``scale``: explicit paths and/or one pipeline folder."""

    laser_images: tuple[Path, ...]
    rig: Path
    model: Path | None = None
    mesh: Path | None = None
    images: Path | None = None
    database: Path | None = None
    features: Path | None = None
    spots: Path | None = None
    colmap_workspace: Path | None = None
    openmvg_project: Path | None = None


def _looked(found: FoundInputs, key: str) -> str:
    return ", ".join(str(p) for p in found.looked.get(key, ()))


def _found(given: GivenInputs) -> FoundInputs | None:
    if given.colmap_workspace is not None and given.openmvg_project is not None:
        raise InputError("give --colmap-workspace or --openmvg-project, not both")
    if given.colmap_workspace is not None:
        return find_colmap_workspace(given.colmap_workspace)
    if given.openmvg_project is not None:
        return find_openmvg_project(given.openmvg_project)
    return None


def _model(given: GivenInputs, found: FoundInputs | None) -> Path:
    if given.model is not None:
        return given.model
    if found is None:
        raise InputError("give --model and --mesh, or a pipeline folder (--colmap-workspace DIR "
                         "or --openmvg-project DIR)")
    if found.model is None:
        what = "COLMAP model" if found.kind == "colmap-workspace" else "OpenMVG sfm_data"
        raise InputError(f"no {what} found (looked in {_looked(found, 'model')}); give --model",
                         found.root)
    return found.model


def _mesh(given: GivenInputs, found: FoundInputs | None, model: Path) -> Path:
    if given.mesh is not None:
        return given.mesh
    hint = (f"give --mesh, or build a coarse surface from the sparse model: "
            f"sfm-laserscale mesh --model {model} --out mesh.ply")
    if found is None:
        raise InputError(f"no mesh given: {hint}")
    raise InputError(f"no dense mesh found (looked for {_looked(found, 'mesh')}); {hint}",
                     found.root)


def _descriptor_sources(given: GivenInputs, found: FoundInputs | None
                        ) -> tuple[Path | None, Path | None, Path | None]:
    """(database, images, features): the explicit ones, else the pipeline folder's source of
    the model's descriptors (a database, SIFT regions, else the source images)."""
    explicit = (given.database, given.images, given.features)
    if found is None or any(p is not None for p in explicit):
        return explicit
    if found.database is not None:
        return found.database, None, None
    if found.features is not None and openmvg_regions_are_sift(found.features):
        return None, None, found.features
    if found.images is not None:
        return None, found.images, None
    raise InputError("found no source of the model's descriptors (looked for "
                     f"{_looked(found, 'database') or _looked(found, 'features')} and "
                     f"{_looked(found, 'images')}); give --database, --features or --images",
                     found.root)


def _choices(given: GivenInputs, found: FoundInputs, sources: dict[str, Path | None]
             ) -> list[str]:
    """One line per input of the folder: the finder's choices not overridden, the descriptor
    source used, and each explicit path that overrides the folder."""
    overridden = {k for k in ("model", "mesh", "database", "images", "features")
                  if getattr(given, k) is not None}
    lines = [c for c in found.choices if c.split(":", 1)[0] not in overridden]
    lines += [f"{k}: {p}" for k, p in sources.items() if p is not None and k not in overridden]
    lines += [f"{k}: {getattr(given, k)} (given; overrides the {found.kind})"
              for k in sorted(overridden)]
    return lines


def resolve_scale_inputs(given: GivenInputs) -> ScaleInputs:
    """The paths ``scale`` uses: explicit ones first, then what the pipeline folder holds."""
    found = _found(given)
    model = _model(given, found)
    mesh = found.mesh if given.mesh is None and found is not None else None
    mesh = mesh or _mesh(given, found, model)
    database, images, features = _descriptor_sources(given, found)
    choices = [] if found is None else _choices(given, found, {
        "database": database, "images": images, "features": features})
    model_images = images or given.images or (found.images if found is not None else None)
    return ScaleInputs(model=model, mesh=mesh, laser_images=given.laser_images, rig=given.rig,
                       images=images, database=database, features=features, spots=given.spots,
                       colmap_workspace=given.colmap_workspace,
                       openmvg_project=given.openmvg_project, model_images=model_images,
                       found=tuple(choices))
