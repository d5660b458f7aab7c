"""The Python API (docs/API.md): ``scale``, ``detect``, ``calibrate`` and ``apply``, each
returning its command's typed result, for notebooks and other pipelines.

They take paths (``str`` or ``Path``); ``scale`` and ``apply`` also take a
``pycolmap.Reconstruction`` and an ``open3d.geometry.TriangleMesh`` already in memory. Nothing
is written to disk unless ``out`` (an output folder) is given; then the files are those of the
CLI (docs/OUTPUTS.md), written the same atomic way. Bad input raises
:class:`~sfm_laserscale.errors.InputError`. Each function is a thin layer over
``sfm_laserscale.commands.<name>.run``, like the CLI: no maths here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from sfm_laserscale.calibration.target import CalibrateOptions, CalibrateResult
from sfm_laserscale.commands import apply as apply_command
from sfm_laserscale.commands import calibrate as calibrate_command
from sfm_laserscale.commands import detect as detect_command
from sfm_laserscale.commands import scale as scale_command
from sfm_laserscale.commands.detect import DetectRunOptions, DetectRunResult
from sfm_laserscale.commands.scale import ScaleResult
from sfm_laserscale.errors import InputError
from sfm_laserscale.io.in_memory import (
    MESH_LABEL,
    RECONSTRUCTION_LABEL,
    InMemoryInputs,
    mesh_from_open3d,
    model_from_reconstruction,
    scaled_open3d_mesh,
    scaled_reconstruction,
)
from sfm_laserscale.io.meshes.mesh import TriangleMesh, load_mesh
from sfm_laserscale.io.models import load_model
from sfm_laserscale.model import SparseModel
from sfm_laserscale.registration.sift_workers import SiftWorkerOptions
from sfm_laserscale.run_types import ScaleInputs, ScaleOptions

PathLike = str | Path


def _path(p: PathLike | None) -> Path | None:
    return None if p is None else Path(p)


def _paths(p: PathLike | Sequence[PathLike]) -> tuple[Path, ...]:
    return (Path(p),) if isinstance(p, str | Path) else tuple(Path(x) for x in p)


def _is_path(x: Any) -> bool:
    return isinstance(x, str | Path)


def _given(model: Any, mesh: Any) -> InMemoryInputs:
    """The model and mesh given as objects, read into the package's types."""
    return InMemoryInputs(
        model=None if _is_path(model) else model_from_reconstruction(model),
        mesh=None if _is_path(mesh) else mesh_from_open3d(mesh),
        reconstruction=None if _is_path(model) else model,
        open3d_mesh=None if _is_path(mesh) else mesh)


def scale(model: PathLike | Any, mesh: PathLike | Any,
          laser_images: PathLike | Sequence[PathLike], rig: PathLike, *,
          database: PathLike | None = None, images: PathLike | None = None,
          features: PathLike | None = None, spots: PathLike | None = None,
          out: PathLike | None = None, overwrite: bool = False, method: str = "all",
          seed: int = 0, workers: int | None = None, progress: bool = False,
          options: ScaleOptions | None = None) -> ScaleResult:
    """The model's metric scale from its laser images (``sfm-laserscale scale``).

    ``model``: a COLMAP folder, an OpenMVG sfm_data.json or a ``pycolmap.Reconstruction``;
    ``mesh``: a mesh file or an ``open3d.geometry.TriangleMesh``, in the model's frame. The
    model's descriptors come from ``database``, ``features`` or ``images`` as in the CLI.
    ``out``: write every output there (else nothing is written; ``result.report`` holds
    report.json's content). ``options`` (a ``ScaleOptions``) overrides every setting;
    ``method``, ``seed``, ``workers`` and ``progress`` are applied on top of it.
    """
    if method not in ("fcm", "pcm", "all"):
        raise InputError(f"method must be fcm, pcm or all, got {method!r}")
    inputs = ScaleInputs(
        model=Path(model) if _is_path(model) else Path(RECONSTRUCTION_LABEL),
        mesh=Path(mesh) if _is_path(mesh) else Path(MESH_LABEL),
        laser_images=_paths(laser_images), rig=Path(rig), images=_path(images),
        database=_path(database), features=_path(features), spots=_path(spots))
    opts = replace(options or ScaleOptions(), method=method, seed=seed, progress=progress,
                   sift_workers=SiftWorkerOptions(workers=workers))
    return scale_command.run(inputs, _path(out), opts, overwrite=overwrite,
                             given=_given(model, mesh))


def detect(images: PathLike | Sequence[PathLike], rig: PathLike, *,
           model: PathLike | None = None, camera: str | None = None,
           out: PathLike | None = None, overwrite: bool = False,
           options: DetectRunOptions | None = None) -> DetectRunResult:
    """Laser spots of images, no registration (``sfm-laserscale detect``): the camera from
    ``model`` (matched by image size) or ``camera`` ("PINHOLE W H fx fy cx cy", any COLMAP
    model). ``out``: write spots.csv, detections.json and overlays there (else nothing)."""
    inputs = detect_command.DetectInputs(images=_paths(images), rig=Path(rig),
                                         model=_path(model), camera=camera)
    return detect_command.run(inputs, _path(out), options or DetectRunOptions(),
                              overwrite=overwrite)


def calibrate(images: PathLike | Sequence[PathLike], square_size: float, *,
              model: PathLike | None = None, self_calibrate: bool = False,
              board: tuple[int, int] = (9, 6), target: str = "chessboard",
              colors: Sequence[str] = ("red",), names: Sequence[str] | None = None,
              rig_name: str = "calibrated laser rig", marker_size: float | None = None,
              dictionary: str = "DICT_5X5_100", out: PathLike | None = None,
              overwrite: bool = False) -> CalibrateResult:
    """The laser rig from images of a chessboard or ChArUco board (``target="charuco"``,
    ``board`` = its squares) at several distances (``sfm-laserscale calibrate``); the
    intrinsics from ``model`` or estimated (``self_calibrate``). ``out``: write rig.toml and
    calibration_report.json there (else nothing); ``result.rig`` is the rig."""
    if (model is None) == (not self_calibrate):
        raise InputError("give exactly one of model=PATH or self_calibrate=True")
    options = CalibrateOptions(board=tuple(board), square_m=square_size,  # type: ignore[arg-type]
                               names=None if names is None else tuple(names),
                               rig_name=rig_name, colors=tuple(colors), target=target,
                               marker_m=marker_size, dictionary=dictionary)
    inputs = calibrate_command.CalibrateInputs(images=_paths(images), model=_path(model))
    return calibrate_command.run(inputs, _path(out), options, overwrite=overwrite)


@dataclass(frozen=True)
class ApplyOutcome:
    """``apply``'s result. Without ``out``: the rescaled model and mesh in memory, of the type
    given (a ``pycolmap.Reconstruction`` / Open3D mesh for objects, the package's
    ``SparseModel`` / ``TriangleMesh`` for files). With ``out``: ``files``, what was written
    (``model`` and ``mesh`` None: read the files)."""

    scale: float
    model: Any = None
    mesh: Any = None
    files: apply_command.ApplyResult | None = None


def _scaled_model(model: Any, s: float) -> Any:
    if model is None:
        return None
    if not _is_path(model):
        return scaled_reconstruction(model, s)
    m: SparseModel = load_model(Path(model))
    return m.scaled(s)


def _scaled_mesh(mesh: Any, s: float) -> Any:
    if mesh is None:
        return None
    if not _is_path(mesh):
        return scaled_open3d_mesh(mesh, s)
    m: TriangleMesh = load_mesh(Path(mesh))
    return TriangleMesh(vertices=m.vertices.astype("float64") * s, triangles=m.triangles)


def apply(scale: float, *, model: PathLike | Any = None, mesh: PathLike | Any = None,
          out: PathLike | None = None, overwrite: bool = False) -> ApplyOutcome:
    """Rescale a model and/or a mesh by a known scale, metres per model unit (``sfm-laserscale
    apply``). With ``out`` (paths only): scaled/ and the transform files are written there, as
    the CLI writes them; without it, the rescaled model and mesh are returned in memory."""
    s = apply_command.check_scale(scale)
    if model is None and mesh is None:
        raise InputError("nothing to rescale: give model, mesh or both")
    if out is None:
        return ApplyOutcome(scale=s, model=_scaled_model(model, s), mesh=_scaled_mesh(mesh, s))
    if not all(x is None or _is_path(x) for x in (model, mesh)):
        raise InputError("apply(out=...) rewrites files: give paths (objects in memory are "
                         "returned rescaled with out=None)")
    files = apply_command.run(apply_command.ApplyInputs(model=_path(model), mesh=_path(mesh)),
                              Path(out), apply_command.ApplyOptions(scale=s),
                              overwrite=overwrite)
    return ApplyOutcome(scale=s, files=files)


__all__ = ["ApplyOutcome", "apply", "calibrate", "detect", "scale"]
