"""footprints.csv: one row per image (laser images first, then the model's), metric units."""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

#: The columns, in order (docs/OUTPUTS.md).
FOOTPRINT_COLUMNS = ("image", "area_m2", "gsd_mm_centre", "gsd_mm_median", "distance_m",
                     "footprint_on_mesh_fraction")


def _cell(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def write_footprints_csv(path: Path, rows: Sequence[Mapping[str, Any]]) -> None:
    """Rows with the keys of ``FOOTPRINT_COLUMNS``; a missing value (no footprint) is empty."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(FOOTPRINT_COLUMNS)
        for row in rows:
            w.writerow([_cell(row.get(c)) for c in FOOTPRINT_COLUMNS])


def read_footprints_csv(path: Path) -> list[dict[str, float | str | None]]:
    """The rows of a footprints.csv (numbers as floats, empty cells as None)."""
    with path.open(newline="", encoding="utf-8") as fh:
        return [{k: (v if k == "image" else (float(v) if v else None)) for k, v in row.items()}
                for row in csv.DictReader(fh)]
