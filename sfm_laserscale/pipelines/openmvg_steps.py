"""The OpenMVG + OpenMVS command sequence of the ``openmvg`` command, as data: each step's
program, arguments and the files it must leave (a tool that exits 0 without them failed too).

Command names and arguments are those of OpenMVG 2.x (``openMVG_main_SfM -s INCREMENTAL``,
``PairGenerator``/``GeometricFilter``) and OpenMVS 2.1+ (``ReconstructMesh -p`` takes the dense
point cloud, ``RefineMesh``/``TextureMesh`` take ``-m`` mesh and ``-o`` scene, every app takes
``-w`` working folder and ``--max-threads``), checked against their sources at OpenMVG v2.1 and
OpenMVS v2.3.0 (docs/WORKSPACES.md). The output folder is an OpenMVG + OpenMVS project as
:func:`sfm_laserscale.io.workspace.find_openmvg_project` reads it::

    OUT/images_sfm/  OUT/matches/  OUT/reconstruction_sequential/  OUT/mvs/  OUT/scale/
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from sfm_laserscale.errors import InputError
from sfm_laserscale.pipelines.tools import ToolStep

OPENMVG_TOOLS = ("openMVG_main_SfMInit_ImageListing", "openMVG_main_ComputeFeatures",
                 "openMVG_main_PairGenerator", "openMVG_main_ComputeMatches",
                 "openMVG_main_GeometricFilter", "openMVG_main_SfM",
                 "openMVG_main_ConvertSfM_DataFormat", "openMVG_main_openMVG2openMVS")
OPENMVS_TOOLS = ("DensifyPointCloud", "ReconstructMesh", "RefineMesh", "TextureMesh",
                 "TransformScene")
FINAL_MESH = "scene_dense_mesh_refine_texture"


@dataclass(frozen=True)
class OpenMvgOptions:
    """Camera intrinsics for the listing (exactly one) and the tools' threads."""

    intrinsics_k: str | None = None  # "fx;0;cx;0;fy;cy;0;0;1", OpenMVG pixels (cx_colmap - 0.5)
    focal_px: float | None = None
    camera_db: Path | None = None  # sensor width database (EXIF)
    threads: int = 0  # threads of each tool (0: every core)

    def listing_args(self) -> tuple[str, ...]:
        """The intrinsics arguments of SfMInit_ImageListing (InputError unless exactly one)."""
        given = [a for a in ((("-k", self.intrinsics_k) if self.intrinsics_k else None),
                             (("-f", f"{self.focal_px:.12g}") if self.focal_px else None),
                             (("-d", str(self.camera_db)) if self.camera_db else None)) if a]
        if len(given) != 1:
            raise InputError("give exactly one of --intrinsics-k, --focal-px or --camera-db "
                             "(camera intrinsics for OpenMVG)")
        return given[0]


@dataclass(frozen=True)
class PlannedStep:
    """A step and the files it must leave."""

    step: ToolStep
    expects: tuple[Path, ...]


def _mvs(name: str, args: tuple[str, ...], mvs: Path, threads: int,
         expects: tuple[str, ...]) -> PlannedStep:
    full = (*args, "-w", str(mvs), "--max-threads", str(threads))
    return PlannedStep(ToolStep(name, name, full), tuple(mvs / e for e in expects))


def reconstruction_steps(out: Path, o: OpenMvgOptions) -> list[PlannedStep]:
    """OpenMVG SfM (incremental), its JSON form, then OpenMVS to the textured mesh."""
    images, m, rec, mvs = out / "images_sfm", out / "matches", out / "reconstruction_sequential", \
        out / "mvs"
    sfm0, n = str(m / "sfm_data.json"), str(o.threads)
    mvg = [
        ("openMVG_main_SfMInit_ImageListing", ("-i", str(images), "-o", str(m),
                                               *o.listing_args()), (m / "sfm_data.json",)),
        ("openMVG_main_ComputeFeatures", ("-i", sfm0, "-o", str(m), "-m", "SIFT", "-n", n),
         (m / "image_describer.json",)),
        ("openMVG_main_PairGenerator", ("-i", sfm0, "-o", str(m / "pairs.bin")),
         (m / "pairs.bin",)),
        ("openMVG_main_ComputeMatches", ("-i", sfm0, "-p", str(m / "pairs.bin"), "-o",
                                         str(m / "matches.putative.bin")),
         (m / "matches.putative.bin",)),
        ("openMVG_main_GeometricFilter", ("-i", sfm0, "-m", str(m / "matches.putative.bin"),
                                          "-o", str(m / "matches.f.bin")),
         (m / "matches.f.bin",)),
        ("openMVG_main_SfM", ("-s", "INCREMENTAL", "-i", sfm0, "-m", str(m), "-o", str(rec)),
         (rec / "sfm_data.bin",)),
        ("openMVG_main_ConvertSfM_DataFormat", ("-i", str(rec / "sfm_data.bin"), "-o",
                                                str(rec / "sfm_data.json")),
         (rec / "sfm_data.json",)),
        ("openMVG_main_openMVG2openMVS", ("-i", str(rec / "sfm_data.bin"), "-o",
                                          str(mvs / "scene.mvs"), "-d", str(mvs / "images"),
                                          "-n", n), (mvs / "scene.mvs",)),
    ]
    steps = [PlannedStep(ToolStep(name, name, args), expects) for name, args, expects in mvg]
    t = o.threads
    return steps + [
        _mvs("DensifyPointCloud", ("scene.mvs",), mvs, t, ("scene_dense.mvs", "scene_dense.ply")),
        _mvs("ReconstructMesh", ("scene_dense.mvs", "-p", "scene_dense.ply"), mvs, t,
             ("scene_dense_mesh.ply",)),
        _mvs("RefineMesh", ("scene_dense.mvs", "-m", "scene_dense_mesh.ply", "-o",
                            "scene_dense_mesh_refine.mvs"), mvs, t,
             ("scene_dense_mesh_refine.ply",)),
        _mvs("TextureMesh", ("scene_dense.mvs", "-m", "scene_dense_mesh_refine.ply", "-o",
                             f"{FINAL_MESH}.mvs"), mvs, t, (f"{FINAL_MESH}.ply",)),
    ]


def transform_step(out: Path, transform_4x4: Path, threads: int) -> PlannedStep:
    """OpenMVS's whole scene (cameras, dense cloud, textured mesh) made metric."""
    return _mvs("TransformScene", ("-i", f"{FINAL_MESH}.mvs", "--transform-file",
                                   str(transform_4x4.resolve()), "-o", "scene_metric.mvs"),
                out / "mvs", threads, ("scene_metric.mvs",))
