"""``demo``: a complete synthetic run with no input data — scene, SfM, laser images, ``scale``."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

from sfm_laserscale.commands.scale import ScaleResult
from sfm_laserscale.commands.scale import run as run_scale
from sfm_laserscale.io.outputs import check_output_dir
from sfm_laserscale.run_types import ScaleInputs, ScaleOptions
from sfm_laserscale.synthetic.dataset import DemoDataOptions, DemoDataset, make_demo_dataset

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemoOptions:
    """``small`` is the test-sized scene; ``seed`` drives every random choice.

    ``laser_color`` (red | green | blue) is the colour of the beams; ``water`` (clear | green)
    the water preset, None: green water for green beams, clear water otherwise.
    """

    small: bool = False
    seed: int = 0
    progress: bool = True
    laser_color: str = "red"
    water: str | None = None

    @property
    def resolved_water(self) -> str:
        """The water preset: ``water``, or the one that goes with the laser colour."""
        if self.water is not None:
            return self.water
        return "green" if self.laser_color == "green" else "clear"


@dataclass(frozen=True)
class DemoResult:
    """The generated data, the scale run on it, and how far the estimate is from the truth."""

    dataset: DemoDataset
    scale: ScaleResult
    true_scale: float
    error_percent: float
    seconds: float
    summary: str

    @property
    def success(self) -> bool:
        """True when a scale was estimated."""
        return self.scale.success


def scale_inputs_for(dataset: DemoDataset) -> ScaleInputs:
    """The inputs a user would give ``scale`` for this data set."""
    return ScaleInputs(
        model=dataset.model_dir,
        mesh=dataset.mesh_path,
        laser_images=(dataset.laser_images_dir,),
        rig=dataset.rig_path,
        database=dataset.database_path,
        model_images=dataset.images_dir,  # the model's images: scene references (scale)
    )


def run_demo(
    out: Path,
    options: DemoOptions = DemoOptions(),
    overwrite: bool = False,  # noqa: B008
) -> DemoResult:
    """Make the synthetic data in ``out/data`` and scale it into ``out/scale``."""
    t0 = time.perf_counter()
    check_output_dir(out, overwrite)
    data_opts = DemoDataOptions(small=options.small, seed=options.seed, progress=options.progress,
                                laser_color=options.laser_color, water=options.resolved_water)
    dataset = make_demo_dataset(out / "data", data_opts, overwrite=overwrite)
    inputs = scale_inputs_for(dataset)
    logger.info(
        "running: sfm-laserscale scale --model %s --mesh %s --laser-images %s --rig %s "
        "--database %s --out %s",
        inputs.model,
        inputs.mesh,
        inputs.laser_images[0],
        inputs.rig,
        inputs.database,
        out / "scale",
    )
    result = run_scale(
        inputs,
        out / "scale",
        ScaleOptions(seed=options.seed, progress=options.progress),
        overwrite=overwrite,
    )
    est = result.scale.value
    err = (
        100.0 * (est - dataset.true_scale) / dataset.true_scale if math.isfinite(est) else math.nan
    )
    seconds = time.perf_counter() - t0
    summary = (
        f"{result.summary}\ntrue scale = {dataset.true_scale:.6g} m per model unit; "
        f"error = {err:+.3f} % ({err / 100 * dataset.true_scale / result.scale.std:+.2f} σ); "
        f"demo took {seconds:.0f} s; report: {out / 'scale' / 'report.html'}"
        if math.isfinite(est)
        else f"{result.summary}\ntrue scale = {dataset.true_scale:.6g}; demo took {seconds:.0f} s"
    )
    return DemoResult(
        dataset=dataset,
        scale=result,
        true_scale=dataset.true_scale,
        error_percent=err,
        seconds=seconds,
        summary=summary,
    )
