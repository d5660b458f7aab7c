"""report.json keys about the inputs a ``scale`` run used beyond ``inputs``/``provenance``: the
held-out check (``held_out``) and its warnings (docs/OUTPUTS.md)."""

from __future__ import annotations

from typing import Any

from sfm_laserscale.held_out import HeldOutCheck
from sfm_laserscale.run_types import ScaleInputs


def held_out_dict(held: HeldOutCheck | None, reused: bool) -> dict[str, Any]:
    """``held_out``: laser images found among the model's images, and whether their model poses
    were taken (``--reuse-model-poses``)."""
    matches = () if held is None else held.matches
    return {
        "content_compared_in": None if held is None or held.images_dir is None
        else str(held.images_dir),
        "in_model": [{"image": m.laser_image, "model_image": m.model_image, "by": m.by}
                     for m in matches],
        "reuse_model_poses": bool(reused),
    }


def _warning(image: str, model_image: str, by: str, reused: bool) -> dict[str, str]:
    same = "the same file name" if by == "name" else "the same content (SHA-256)"
    what = ("its model pose was taken as you asked (--reuse-model-poses)" if reused else
            "registering it only gives back the pose SfM found for it from its own features: "
            "its pose comes from SfM, not from an independent registration. Hold laser images "
            "out of SfM, or pass --reuse-model-poses to take those poses on purpose")
    return {"level": "note" if reused else "warning", "code": "laser_image_in_model",
            "message": f"Laser image {image} is the model's image {model_image} ({same}): "
                       f"it was not held out of SfM; {what}."}


def add_input_keys(report: dict[str, Any], inputs: ScaleInputs, held: HeldOutCheck | None,
                   reused: bool) -> None:
    """Add ``held_out`` and its warnings to a built report (in place)."""
    report["held_out"] = held_out_dict(held, reused)
    for m in () if held is None else held.matches:
        report.setdefault("warnings", []).insert(
            0, _warning(m.laser_image, m.model_image, m.by, reused))
    report.setdefault("inputs", {})["found"] = list(inputs.found)
