"""The held-out check: a laser image that is also an image of the model (same file name, or the
same bytes under another name) was not held out of SfM, so registering it only gives back the
pose SfM found for it, from its own features. ``scale`` warns about each one in its report
(``held_out``), and ``--reuse-model-poses`` takes those poses on purpose.

Content is compared by SHA-256, only for model image files of a laser image's byte size (one
``stat`` per model image, a hash only on a size match), so a large survey costs little.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from sfm_laserscale.io.images import LaserImage
from sfm_laserscale.model import SparseModel
from sfm_laserscale.registration.options import RegistrationOptions
from sfm_laserscale.registration.pose import RegistrationResult, model_pose_registration

logger = logging.getLogger(__name__)
_CHUNK = 1 << 22


@dataclass(frozen=True)
class HeldOutMatch:
    """A laser image found among the model's images."""

    laser_image: str  # its name in the run
    model_image: str  # the model image's name
    by: str  # "name" | "content" (same SHA-256 under another name)


@dataclass(frozen=True)
class HeldOutCheck:
    """Which laser images are model images; ``images_dir``: where contents were compared
    (None: by name only, the model's image files were not available)."""

    matches: tuple[HeldOutMatch, ...]
    images_dir: Path | None

    def model_image(self, laser_image: str) -> str | None:
        """The model image a laser image is, or None."""
        return next((m.model_image for m in self.matches if m.laser_image == laser_image), None)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _size(path: Path) -> int | None:
    try:
        return path.stat().st_size if path.is_file() else None
    except OSError:
        return None


def _by_content(laser: Sequence[LaserImage], names: Sequence[str],
                images_dir: Path) -> list[HeldOutMatch]:
    """Laser images whose bytes equal a model image's (sizes first, then SHA-256)."""
    sizes = {li.name: _size(li.path) for li in laser}
    wanted = {s for s in sizes.values() if s is not None}
    candidates = [(n, images_dir / n) for n in names]
    candidates = [(n, p) for n, p in candidates if _size(p) in wanted]
    if not candidates:
        return []
    model_hash: dict[str, str] = {}
    for name, path in candidates:
        model_hash.setdefault(_sha256(path), name)
    candidate_sizes = {_size(p) for _, p in candidates}
    out = []
    for li in laser:
        if sizes[li.name] is None or sizes[li.name] not in candidate_sizes:
            continue
        same = model_hash.get(_sha256(li.path))
        if same is not None:
            out.append(HeldOutMatch(li.name, same, "content"))
    return out


def check_held_out(laser: Sequence[LaserImage], model: SparseModel,
                   images_dir: Path | None) -> HeldOutCheck:
    """Laser images that are model images, by file name and, with ``images_dir`` (the model's
    source images), by content."""
    names = [im.name for im in model.images.values()]
    by_name = {Path(n).name: n for n in names}
    matches = [HeldOutMatch(li.name, by_name[li.name], "name") for li in laser
               if li.name in by_name]
    if images_dir is not None and images_dir.is_dir():
        named = {m.laser_image for m in matches}
        rest = [li for li in laser if li.name not in named]
        matches += _by_content(rest, names, images_dir)
    else:
        images_dir = None
    for m in matches:
        logger.warning("laser image %s is the model's image %s (same %s): it was not held out "
                       "of SfM, so its pose comes from SfM, not from registration",
                       m.laser_image, m.model_image, m.by)
    return HeldOutCheck(tuple(matches), images_dir)


def reused_registrations(check: HeldOutCheck, laser: Sequence[LaserImage], model: SparseModel,
                         options: RegistrationOptions
                         ) -> tuple[tuple[LaserImage, ...], dict[str, RegistrationResult]]:
    """``--reuse-model-poses``: each laser image that is a model image gets the model's pose
    and camera (needs the model's observations: call before they are dropped); the laser
    images come back with those cameras."""
    out: list[LaserImage] = []
    reused: dict[str, RegistrationResult] = {}
    for li in laser:
        name = check.model_image(li.name)
        image = None if name is None or li.camera is None else model.image_by_name(name)
        if image is None:
            out.append(li)
            continue
        camera = model.cameras[image.camera_id]
        reused[li.name] = model_pose_registration(image, camera, model, options)
        out.append(replace(li, camera=camera))
        logger.info("laser image %s: the model's pose of %s is reused (--reuse-model-poses)",
                    li.name, name)
    return tuple(out), reused
