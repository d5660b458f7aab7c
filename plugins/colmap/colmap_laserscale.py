"""COLMAP plugin: source images + laser images + rig -> metric sparse model and mesh, one command.

Kept for existing scripts: it runs ``sfm-laserscale colmap`` (sfm_laserscale/commands/colmap.py)
with the same arguments; see plugins/colmap/README.md.

    python plugins/colmap/colmap_laserscale.py --images IMAGES --laser-images LASER \\
        --rig rig.toml --out OUT [--mesh MESH] [--backend auto|colmap|pycolmap] ...

Exit status: 0 a scale was estimated; 1 no scale could be estimated; 2 bad input; 3 a bug;
4 a COLMAP step failed (the message names it).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``sfm-laserscale colmap`` with these arguments; returns its exit status."""
    from sfm_laserscale.cli import main as cli

    args = list(sys.argv[1:] if argv is None else argv)
    try:
        cli.main(args=["colmap", *args], prog_name="colmap_laserscale.py")
    except SystemExit as exc:
        return int(exc.code or 0) if not isinstance(exc.code, str) else 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
