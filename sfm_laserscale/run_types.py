"""The types of a ``scale`` run that the command (:mod:`sfm_laserscale.commands.scale`) and the
report writer (:mod:`sfm_laserscale.report.writer`) share: the inputs and options given, what
was loaded, each laser image's run, the stage timer."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from sfm_laserscale.detection import DetectionOptions, DetectionResult
from sfm_laserscale.footprints import FootprintOptions
from sfm_laserscale.fusion import FusionOptions
from sfm_laserscale.guided_spots import GuidedSpotOptions
from sfm_laserscale.held_out import HeldOutCheck
from sfm_laserscale.io.images import LaserImage
from sfm_laserscale.io.meshes.mesh import TriangleMesh
from sfm_laserscale.mesh_error import MeshErrorOptions, SpotMeshError
from sfm_laserscale.model import Camera, SparseModel, Spot
from sfm_laserscale.model_checks import ModelCheckOptions
from sfm_laserscale.raycast import CropOptions, SpotCastOptions, SpotHit
from sfm_laserscale.registration.covariance import IntrinsicsOptions
from sfm_laserscale.registration.index import DescriptorIndex
from sfm_laserscale.registration.options import (
    IndexOptions,
    RegistrationOptions,
    SiftOptions,
    TieOptions,
)
from sfm_laserscale.registration.pose import RegistrationResult
from sfm_laserscale.registration.sift_workers import SiftPool, SiftWorkerOptions
from sfm_laserscale.rig import Rig
from sfm_laserscale.scene_reference import SceneStageOptions
from sfm_laserscale.uncertainty import EstimationOptions, ImageEstimates, ImageObservation


@dataclass(frozen=True)
class ScaleInputs:
    """Paths given to ``scale`` (docs/OUTPUTS.md)."""

    model: Path
    mesh: Path
    laser_images: tuple[Path, ...]
    rig: Path
    images: Path | None = None
    database: Path | None = None
    features: Path | None = None
    spots: Path | None = None
    # the pipeline folder the paths above were found in (sfm_laserscale.pipeline_folders)
    colmap_workspace: Path | None = None
    openmvg_project: Path | None = None
    model_images: Path | None = None  # the model's source images: only for the held-out check
    found: tuple[str, ...] = ()  # what was found in the pipeline folder and chosen, one line each


@dataclass(frozen=True)
class ScaleOptions:
    """Options of the scale job; each stage's options are nested."""

    method: str = "all"  # fcm | pcm | all (the headline method's candidates)
    seed: int = 0
    # a laser image that is also a model image takes the model's pose (not registered)
    reuse_model_poses: bool = False
    progress: bool = True
    overlays: bool = True
    detection: DetectionOptions = field(default_factory=DetectionOptions)
    sift: SiftOptions = field(default_factory=SiftOptions)
    sift_workers: SiftWorkerOptions = field(default_factory=SiftWorkerOptions)
    tie: TieOptions = field(default_factory=TieOptions)
    index: IndexOptions = field(default_factory=IndexOptions)
    registration: RegistrationOptions = field(default_factory=RegistrationOptions)
    spot_cast: SpotCastOptions = field(default_factory=SpotCastOptions)
    crop: CropOptions = field(default_factory=CropOptions)
    # the mesh–model check: inlier points within mesh_check_near (share of the model's extent)
    # of a spot's ray, at least mesh_check_min_points of them (the nearest), at most
    # mesh_check_points (a seeded subset); exact up to mesh_check_radius (2× its limit)
    mesh_check_near: float = 0.02
    mesh_check_min_points: int = 50
    mesh_check_points: int = 20000
    mesh_check_radius: float = 0.01
    estimation: EstimationOptions = field(default_factory=EstimationOptions)
    fusion: FusionOptions = field(default_factory=FusionOptions)
    # the reconstruction's own error in σ (docs/DESIGN.md §4): the model's intrinsics, the mesh
    intrinsics: IntrinsicsOptions = field(default_factory=IntrinsicsOptions)
    mesh_error: MeshErrorOptions = field(default_factory=MeshErrorOptions)
    model_checks: ModelCheckOptions = field(default_factory=ModelCheckOptions)
    footprints: FootprintOptions = field(default_factory=FootprintOptions)  # footprints.csv
    # spots the detector missed, searched where the model puts them (guided_spots.py)
    guided: GuidedSpotOptions = field(default_factory=GuidedSpotOptions)
    # each registered laser image detected again against its seafloor (scene_stage.py)
    scene: SceneStageOptions = field(default_factory=SceneStageOptions)


@dataclass(frozen=True)
class LoadedInputs:
    """Everything read from disk before the per-image work."""

    model: SparseModel  # without its images' 2D observations (the index holds what is needed)
    mesh: TriangleMesh | None  # None once cropped (scale.run releases it: peak memory)
    rig: Rig
    laser_images: tuple[LaserImage, ...]
    manual_spots: dict[str, list[Spot]]
    index: DescriptorIndex | None  # None once every laser image is registered (peak memory)
    descriptors_indexed: int  # the index's size, for the report
    # worker processes extracting the laser images' SIFT meanwhile; scale.run closes it
    sift_pool: SiftPool | None = None
    held_out: HeldOutCheck | None = None  # laser images that are also model images
    # --reuse-model-poses: laser image name -> the model's pose as its registration
    reused_poses: dict[str, RegistrationResult] = field(default_factory=dict)


@dataclass(frozen=True)
class SceneUse:
    """How a laser image's scene reference was used (scene_stage.py): ``used`` or the
    ``reason`` it was not; the model images rendered, the share of the image the render
    covers, the share of that the fit kept, the fit's median |shift| (px) and residual ratio
    (NaN: not measured), the spots found on the photograph alone, and the reference as a PNG
    when it is to be saved."""

    used: bool
    reason: str | None
    views: tuple[str, ...] = ()
    coverage: float = 0.0
    kept_share: float = 0.0
    shift_median_px: float = float("nan")
    residual_ratio_median: float = float("nan")
    spots_alone: int = 0
    png: bytes | None = field(default=None, repr=False)


@dataclass(frozen=True)
class ImageRun:
    """What happened to one laser image (kept whether it worked or not)."""

    name: str
    path: Path
    camera: Camera | None
    registration: RegistrationResult | None
    detection: DetectionResult | None
    spots: tuple[Spot, ...]
    hits: tuple[SpotHit, ...]
    spot_reasons: dict[str, str]  # laser -> why it has no usable hit
    estimates: ImageEstimates | None
    reason: str | None  # why the image gave no estimate, None when it did
    observation: ImageObservation | None = None  # what the estimators saw (with model error)
    mesh_errors: tuple[SpotMeshError, ...] = ()  # each hit's mesh check
    scene: SceneUse | None = None  # the scene reference's use (None: not tried)


class Timer:
    """Wall time per named stage (seconds), summed over calls."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._start = time.perf_counter()

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0

    def as_dict(self) -> dict[str, float]:
        out = {
            k: round(self.seconds.get(k, 0.0), 4)
            for k in ("load", "detect", "register", "raycast", "estimate", "write")
        }
        # the stages that do not always run, when they ran
        for k in ("sift_here", "sift_in_workers", "scene", "footprints", "guided"):
            if k in self.seconds:
                out[k] = round(self.seconds[k], 4)
        out["total"] = round(time.perf_counter() - self._start, 4)
        return out
