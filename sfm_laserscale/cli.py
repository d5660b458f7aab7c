"""Command line (DESIGN.md §5): thin click commands that build options and call one library
function.

Exit status: 0 success; 1 the run finished but no scale could be estimated;
2 bad usage or bad input (one line on stderr, no traceback without --debug);
3 an internal error (a bug: please report it with the --debug traceback).
"""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from sfm_laserscale import __version__
from sfm_laserscale.errors import InputError

logger = logging.getLogger("sfm_laserscale")

EXIT_OK, EXIT_NO_SCALE, EXIT_BAD_INPUT, EXIT_INTERNAL = 0, 1, 2, 3


class GreedyCommand(click.Command):
    """A command whose listed options take every following value: ``--opt a b c``.

    click options take a fixed number of values; the CLI contract has
    ``--laser-images PATH [PATH...]``, so the arguments are rewritten to
    ``--opt a --opt b --opt c`` (a ``multiple=True`` option) before parsing.
    """

    greedy = ("--laser-images",)

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        out: list[str] = []
        current: str | None = None
        for arg in args:
            if arg.startswith("-") and arg != "-":
                current = arg if arg in self.greedy else None
                out.append(arg)
            elif current is not None and out[-1] != current:
                out += [current, arg]
            else:
                out.append(arg)
        return super().parse_args(ctx, out)


def _setup_logging(verbose: bool, quiet: bool) -> None:
    # The terminal gets warnings and errors only (stderr stays one line on bad input);
    # --verbose shows every step. --quiet also turns progress bars off.
    level = logging.DEBUG if verbose else (logging.ERROR if quiet else logging.WARNING)
    root = logging.getLogger()
    for h in list(root.handlers):
        if getattr(h, "_sfm_laserscale", False):
            root.removeHandler(h)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    handler._sfm_laserscale = True  # type: ignore[attr-defined]
    handler.setLevel(level)
    root.addHandler(handler)
    root.setLevel(logging.DEBUG)
    logging.getLogger("sfm_laserscale").setLevel(logging.DEBUG)
    from sfm_laserscale.registration import configure_colmap_logging

    configure_colmap_logging(verbose)


def common_options(func: Callable[..., int]) -> Callable[..., None]:
    """--debug/--verbose/--quiet on every command; exceptions -> exit status and one line."""

    @click.option("--debug", is_flag=True, help="Show tracebacks.")
    @click.option("--verbose", "-v", is_flag=True, help="Show debug messages.")
    @click.option("--quiet", "-q", is_flag=True, help="Only warnings and errors; no progress bars.")
    @functools.wraps(func)
    def wrapper(debug: bool, verbose: bool, quiet: bool, **kwargs: Any) -> None:
        ctx = click.get_current_context()
        debug = debug or bool(ctx.obj and ctx.obj.get("debug"))
        _setup_logging(verbose, quiet)
        try:
            code = func(quiet=quiet, **kwargs)
        except InputError as exc:
            if debug:
                raise
            click.echo(f"sfm-laserscale: error: {exc}", err=True)
            ctx.exit(EXIT_BAD_INPUT)
        except (KeyboardInterrupt, click.exceptions.Exit, click.ClickException):
            raise
        except Exception as exc:
            if debug:
                raise
            click.echo(
                f"sfm-laserscale: internal error: {exc.__class__.__name__}: {exc} "
                "(run with --debug for the traceback and report it)",
                err=True,
            )
            ctx.exit(EXIT_INTERNAL)
        ctx.exit(code)

    return wrapper


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="sfm-laserscale")
@click.option("--debug", is_flag=True, help="Show tracebacks for errors.")
@click.pass_context
def main(ctx: click.Context, debug: bool) -> None:
    """Metric scale for monocular SfM models from laser scaler images."""
    ctx.obj = {"debug": debug}


_path = click.Path(path_type=Path)


@main.command(cls=GreedyCommand)
@click.option(
    "--model",
    required=True,
    type=_path,
    help="COLMAP sparse model folder or OpenMVG sfm_data.json.",
)
@click.option(
    "--mesh", required=True, type=_path, help="Dense mesh in the model's frame (PLY, OBJ, ...)."
)
@click.option(
    "--laser-images",
    required=True,
    multiple=True,
    type=_path,
    help="Laser image files and/or folders (several values allowed).",
)
@click.option("--rig", required=True, type=_path, help="Laser rig TOML file.")
@click.option("--out", required=True, type=_path, help="Output folder (created).")
@click.option("--images", type=_path, help="The model's source images (when no database).")
@click.option("--database", type=_path, help="COLMAP database with the model's features.")
@click.option(
    "--features",
    type=_path,
    help="OpenMVG regions folder (default: matches/ beside sfm_data.json).",
)
@click.option(
    "--method", type=click.Choice(["fcm", "pcm", "all"]), default="all", show_default=True
)
@click.option(
    "--spots", type=_path, help="CSV image,laser,x,y replacing detection for the images it names."
)
@click.option(
    "--seed", type=int, default=0, show_default=True, help="Seed for every random choice."
)
@click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder.")
@common_options
def scale(**kw: Any) -> int:
    """Estimate the model's metric scale and write the rescaled model, mesh and report."""
    from sfm_laserscale.pipeline import ScaleInputs, ScaleOptions, run_scale

    inputs = ScaleInputs(
        model=kw["model"],
        mesh=kw["mesh"],
        laser_images=tuple(kw["laser_images"]),
        rig=kw["rig"],
        images=kw["images"],
        database=kw["database"],
        features=kw["features"],
        spots=kw["spots"],
    )
    options = ScaleOptions(method=kw["method"], seed=kw["seed"], progress=not kw["quiet"])
    result = run_scale(inputs, kw["out"], options, overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK if result.success else EXIT_NO_SCALE


@main.command()
@click.option(
    "--out", type=_path, default=Path("demo_out"), show_default=True, help="Output folder."
)
@click.option("--small", is_flag=True, help="A smaller, faster scene (as in the tests).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder.")
@common_options
def demo(**kw: Any) -> int:
    """Complete synthetic run with no input data: render, SfM, laser images, then `scale`."""
    from sfm_laserscale.demo import DemoOptions, run_demo

    options = DemoOptions(small=kw["small"], seed=kw["seed"], progress=not kw["quiet"])
    result = run_demo(kw["out"], options, overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK if result.success else EXIT_NO_SCALE


@main.command()
@click.option("--scale", "scale_value", required=True, type=float,
              help="Metres per model unit (metric = scale x model coordinates).")
@click.option("--model", type=_path, help="COLMAP sparse model folder or OpenMVG sfm_data.json.")
@click.option("--mesh", type=_path, help="Mesh in the model's frame (PLY, OBJ, glTF, OFF, STL).")
@click.option("--out", required=True, type=_path, help="Output folder (created).")
@click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder.")
@common_options
def apply(**kw: Any) -> int:
    """Rescale a model and/or a mesh by a known scale; write them with the transform files."""
    from sfm_laserscale.apply import ApplyInputs, ApplyOptions, apply_scale

    result = apply_scale(ApplyInputs(model=kw["model"], mesh=kw["mesh"]), kw["out"],
                         ApplyOptions(scale=kw["scale_value"]), overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK


@main.command()
@click.argument("images", nargs=-1, required=True, type=_path)
@click.option("--rig", required=True, type=_path, help="Laser rig TOML file.")
@click.option("--out", required=True, type=_path, help="Output folder (created).")
@click.option("--model", type=_path, help="Take the camera from this model (matched by size).")
@click.option("--camera", help='Camera as "MODEL W H params...", e.g. "PINHOLE W H fx fy cx cy".')
@click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder.")
@common_options
def detect(**kw: Any) -> int:
    """Detect laser spots: write spots.csv (for scale --spots), detections.json, overlays."""
    from sfm_laserscale.detect_run import DetectInputs, run_detect

    inputs = DetectInputs(images=tuple(kw["images"]), rig=kw["rig"], model=kw["model"],
                          camera=kw["camera"])
    result = run_detect(inputs, kw["out"], overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK if result.success else EXIT_NO_SCALE


@main.command()
@click.argument("images", nargs=-1, required=True, type=_path)
@click.option("--board", default="9x6", show_default=True,
              help="Chessboard inner corners COLSxROWS (as OpenCV counts them).")
@click.option("--square-size", required=True, type=float, help="Chessboard square size (metres).")
@click.option("--colors", default="red", show_default=True,
              help="Laser colour(s) to look for, comma separated (red, green, blue).")
@click.option("--model", type=_path, help="COLMAP model / OpenMVG sfm_data.json with the "
              "camera intrinsics (the camera of the images' size).")
@click.option("--self-calibrate", is_flag=True,
              help="Estimate the intrinsics from the target images (OpenCV model).")
@click.option("--names", help="Laser names left to right, comma separated (default L1, L2, ...;"
              " their number = lasers expected).")
@click.option("--rig-name", default="calibrated laser rig", show_default=True)
@click.option("--out", required=True, type=_path, help="Output folder (created).")
@click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder.")
@common_options
def calibrate(**kw: Any) -> int:
    """Calibrate the laser rig from images of a chessboard at several distances."""
    from sfm_laserscale.calibrate_run import CalibrateInputs, CalibrateOptions, run_calibrate

    if (kw["model"] is None) == (not kw["self_calibrate"]):
        raise InputError("give exactly one of --model PATH or --self-calibrate")
    try:
        cols, rows = (int(v) for v in kw["board"].lower().split("x"))
    except ValueError:
        raise InputError(f"--board must be COLSxROWS like 9x6, got {kw['board']!r}") from None
    names = tuple(n.strip() for n in kw["names"].split(",")) if kw["names"] else None
    options = CalibrateOptions(
        board=(cols, rows), square_m=kw["square_size"], names=names, rig_name=kw["rig_name"],
        colors=tuple(c.strip() for c in kw["colors"].split(",")))
    result = run_calibrate(CalibrateInputs(images=tuple(kw["images"]), model=kw["model"]),
                           kw["out"], options, overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK


if __name__ == "__main__":  # pragma: no cover
    main()
