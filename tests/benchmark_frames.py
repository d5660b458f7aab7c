"""Frames of the physical benchmark (scripts/bench_detection_physical.py) as its runs see them."""

from __future__ import annotations

import numpy as np
from script_loader import load_script

from sfm_laserscale.scene_fit import fit_reference
from sfm_laserscale.synthetic.underwater import CONDITIONS, Frame, render_frame


def fitted_frame(condition: str, seed: int, index: int) -> tuple[Frame, np.ndarray]:
    """A frame of the physical benchmark at 1920 × 1080 and its scene reference as the
    benchmark fits it (shifted 0.5 px, blurred 0.7 px, relit ±10 %, then fitted)."""
    bench = load_script("bench_detection_physical")
    ci = list(CONDITIONS).index(condition)
    frame = render_frame(condition, 1920, 1080, np.random.default_rng([seed, ci, 0, index]),
                         scene_reference=True)
    assert frame.image_scene_rgb is not None
    reference = bench.as_rendered(frame.image_scene_rgb, bench.SceneReference(0.5, 0.7, 0.1),
                                  np.random.default_rng([seed, ci, 0, index, 7]))
    return frame, fit_reference(frame.image_rgb, reference).rgb
