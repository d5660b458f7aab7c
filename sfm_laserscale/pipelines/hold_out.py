"""The laser images kept out of SfM: a source image is held out when it has a laser image's file
name or its content (SHA-256; hashed only on a size match, so a large survey costs one ``stat``
per image). Their spots would corrupt the features, and an image SfM has seen can no longer be
registered independently (docs/WORKSPACES.md).
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.images import IMAGE_SUFFIXES, expand_image_paths

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SfmImages:
    """The source images given to SfM and those held out (name, why)."""

    folder: Path
    names: tuple[str, ...]
    held_out: tuple[tuple[str, str], ...]

    def summary(self) -> str:
        """One line: how many images go to SfM and which were held out, by name or content."""
        if not self.held_out:
            return f"{len(self.names)} source images to SfM, no laser image among them"
        which = "; ".join(f"{n} ({why})" for n, why in self.held_out)
        return (f"{len(self.names)} source images to SfM; held out {len(self.held_out)} laser "
                f"image(s) found among them: {which}")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        while chunk := fh.read(1 << 22):
            h.update(chunk)
    return h.hexdigest()


def select_sfm_images(images: Path, laser_images: Sequence[Path],
                      min_images: int = 3) -> SfmImages:
    """The folder's images minus the laser images (by file name and by content)."""
    if not images.is_dir():
        raise InputError("source images folder not found", images)
    laser = expand_image_paths(laser_images)
    by_name = {p.name: p for p in laser}
    sizes = {p.stat().st_size for p in laser}
    laser_hash: dict[str, Path] | None = None
    names: list[str] = []
    held: list[tuple[str, str]] = []
    for f in sorted(images.iterdir()):
        if not (f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES):
            continue
        if f.name in by_name:
            held.append((f.name, f"same file name as laser image {by_name[f.name]}"))
            continue
        if f.stat().st_size in sizes:
            if laser_hash is None:
                laser_hash = {_sha256(p): p for p in laser}
            same = laser_hash.get(_sha256(f))
            if same is not None:
                held.append((f.name, f"same content as laser image {same}"))
                continue
        names.append(f.name)
    result = SfmImages(images, tuple(names), tuple(held))
    (logger.warning if held else logger.info)("%s", result.summary())
    if len(names) < min_images:
        raise InputError(f"SfM needs at least {min_images} source images, found {len(names)}",
                         images)
    return result
