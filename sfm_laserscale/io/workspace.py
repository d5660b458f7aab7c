"""The input files of a pipeline's own folder: a COLMAP workspace or an OpenMVG + OpenMVS project.

Only finds files; nothing is read beyond what choosing needs (the registered-image count of each
COLMAP model, from the head of ``images.bin`` or the comment of ``images.txt``) and nothing is
written. Each finder returns :class:`FoundInputs`: the paths found (None when absent), every
place it looked (for the messages), and one line per choice it made. Layouts
(docs/WORKSPACES.md):

- COLMAP (``automatic_reconstructor`` or the GUI): ``database.db``; ``sparse/<n>/`` (the model
  with the most registered images; ``sparse/`` itself when it holds a model); ``images/``; the
  dense mesh ``dense/<n>/meshed-poisson.ply``, else ``meshed-delaunay.ply``, of that same
  ``<n>`` (another model's dense folder is in another frame), or ``dense/`` itself.
- OpenMVG + OpenMVS: ``sfm_data.json`` (or ``.bin``) in ``reconstruction_sequential/``,
  ``reconstruction_global/`` or the project folder; the regions in ``matches/``; the most
  refined OpenMVS mesh under the project folder or ``mvs/``:
  ``scene_dense_mesh_refine_texture.*``, ``scene_dense_mesh_refine.*``, ``scene_dense_mesh.*``.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.colmap import MODEL_STEMS, read_colmap_model
from sfm_laserscale.io.meshes.mesh import MESH_SUFFIXES

COLMAP_MESHES = ("meshed-poisson.ply", "meshed-delaunay.ply")
OPENMVG_RECONSTRUCTIONS = ("reconstruction_sequential", "reconstruction_global", ".")
OPENMVS_MESH_STEMS = ("scene_dense_mesh_refine_texture", "scene_dense_mesh_refine",
                      "scene_dense_mesh")
_IMAGES_TXT_COUNT = re.compile(rb"^#\s*Number of images:\s*(\d+)", re.MULTILINE)


@dataclass(frozen=True)
class FoundInputs:
    """What a pipeline folder holds for ``scale``; None where nothing was found."""

    kind: str  # colmap-workspace | openmvg-project
    root: Path
    model: Path | None = None
    mesh: Path | None = None
    database: Path | None = None
    images: Path | None = None
    features: Path | None = None  # OpenMVG regions
    looked: dict[str, tuple[Path, ...]] = field(default_factory=dict)  # input -> places tried
    choices: tuple[str, ...] = ()  # one line per choice made (logged, reported)


def registered_image_count(model_dir: Path) -> int:
    """Registered images of a COLMAP model folder: the count at the head of ``images.bin``,
    the ``# Number of images`` comment of ``images.txt``, else the model read in full."""
    binary, text = model_dir / "images.bin", model_dir / "images.txt"
    if binary.is_file():
        with binary.open("rb") as fh:
            head = fh.read(8)
        if len(head) == 8:
            return int(struct.unpack("<Q", head)[0])
    elif text.is_file():
        with text.open("rb") as fh:
            m = _IMAGES_TXT_COUNT.search(fh.read(4096))
        if m is not None:
            return int(m.group(1))
    return len(read_colmap_model(model_dir).images)


def _is_colmap_model(folder: Path) -> bool:
    return folder.is_dir() and any(
        all((folder / f"{stem}{suffix}").is_file() for stem in MODEL_STEMS)
        for suffix in (".bin", ".txt"))


def _numbered(folder: Path) -> list[Path]:
    """Subfolders named by a number, in numeric order."""
    if not folder.is_dir():
        return []
    return sorted((p for p in folder.iterdir() if p.is_dir() and p.name.isdigit()),
                  key=lambda p: int(p.name))


def choose_sparse_model(sparse: Path) -> tuple[Path | None, int, str]:
    """The model under ``sparse`` with the most registered images (ties: the lowest number),
    its count and one line saying why; ``sparse`` itself when it holds a model."""
    if _is_colmap_model(sparse):
        n = registered_image_count(sparse)
        return sparse, n, f"model: {sparse} ({n} registered images, the only model)"
    counts = [(registered_image_count(p), p) for p in _numbered(sparse) if _is_colmap_model(p)]
    if not counts:
        return None, 0, ""
    best = max(counts, key=lambda c: (c[0], -int(c[1].name)))
    others = ", ".join(f"{p.name}: {n}" for n, p in counts if p != best[1])
    line = f"model: {best[1]} ({best[0]} registered images"
    return best[1], best[0], line + (f"; the others: {others})" if others else
                                     ", the only model)")


def _colmap_mesh(root: Path, model: Path | None) -> tuple[Path | None, tuple[Path, ...]]:
    """``dense/<n>/meshed-*.ply`` of the chosen model ``<n>``, or ``dense/meshed-*.ply``."""
    dense = root / "dense"
    folders = [dense / model.name] if model is not None and model.name.isdigit() else []
    folders.append(dense)
    looked = tuple(f / name for f in folders for name in COLMAP_MESHES)
    return next((p for p in looked if p.is_file()), None), looked


def find_colmap_workspace(root: Path) -> FoundInputs:
    """The inputs in a COLMAP workspace folder (InputError when it is not a folder)."""
    if not root.is_dir():
        raise InputError("COLMAP workspace not found (expected a folder)", root)
    model, _, why = choose_sparse_model(root / "sparse")
    choices = [why] if model is not None else []
    mesh, mesh_looked = _colmap_mesh(root, model)
    if mesh is not None:
        choices.append(f"mesh: {mesh}")
    database = root / "database.db"
    images = root / "images"
    return FoundInputs(
        kind="colmap-workspace", root=root, model=model, mesh=mesh,
        database=database if database.is_file() else None,
        images=images if images.is_dir() else None,
        looked={"model": (root / "sparse" / "<n>", root / "sparse"), "mesh": mesh_looked,
                "database": (database,), "images": (images,)},
        choices=tuple(choices))


def _openmvg_sfm_data(root: Path) -> tuple[Path | None, tuple[Path, ...]]:
    """The first ``sfm_data.json`` (else ``.bin``) of the reconstruction folders."""
    folders = [root / sub if sub != "." else root for sub in OPENMVG_RECONSTRUCTIONS]
    looked = tuple(f / f"sfm_data{ext}" for ext in (".json", ".bin") for f in folders)
    return next((p for p in looked if p.is_file()), None), looked


def _openmvs_mesh(root: Path) -> tuple[Path | None, tuple[Path, ...]]:
    """The most refined OpenMVS mesh in a readable format under ``root`` or ``root/mvs``."""
    looked: list[Path] = []
    for stem in OPENMVS_MESH_STEMS:
        for folder in (root, root / "mvs"):
            looked.append(folder / f"{stem}.*")
            hits = [folder / f"{stem}{ext}" for ext in MESH_SUFFIXES]
            found = [p for p in hits if p.is_file()]
            if found:
                return found[0], tuple(looked)
    return None, tuple(looked)


def find_openmvg_project(root: Path) -> FoundInputs:
    """The inputs in an OpenMVG + OpenMVS project folder (InputError when not a folder)."""
    if not root.is_dir():
        raise InputError("OpenMVG project not found (expected a folder)", root)
    model, model_looked = _openmvg_sfm_data(root)
    mesh, mesh_looked = _openmvs_mesh(root)
    matches, images = root / "matches", root / "images"
    choices = [f"model: {model}"] if model is not None else []
    if mesh is not None:
        choices.append(f"mesh: {mesh} (the most refined OpenMVS mesh found)")
    return FoundInputs(
        kind="openmvg-project", root=root, model=model, mesh=mesh,
        features=matches if matches.is_dir() else None,
        images=images if images.is_dir() else None,
        looked={"model": model_looked, "mesh": mesh_looked, "features": (matches,),
                "images": (images,)},
        choices=tuple(choices))
