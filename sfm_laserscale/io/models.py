"""One entry point for sparse models, whatever tool wrote them: ``load_model``."""

from __future__ import annotations

from pathlib import Path

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.colmap import read_colmap_model
from sfm_laserscale.io.openmvg import read_openmvg_sfm_data
from sfm_laserscale.model import SparseModel


def _is_openmvg(path: Path) -> bool:
    """An OpenMVG sfm_data file (JSON is read; .bin/.xml get a conversion hint)."""
    suffix = path.suffix.lower()
    return path.is_file() and (suffix == ".json" or (suffix in (".bin", ".xml")
                                                     and "sfm_data" in path.name))


def load_model(path: Path) -> SparseModel:
    """COLMAP model folder (binary or text) or OpenMVG sfm_data.json (with its regions'
    keypoints when found beside it); InputError for anything else."""
    if not path.exists():
        raise InputError("model not found", path)
    if _is_openmvg(path):
        return read_openmvg_sfm_data(path)
    return read_colmap_model(path)
