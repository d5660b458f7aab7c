"""Command line (docs/OUTPUTS.md): thin click commands that build the options and call one
command's ``run`` (:mod:`sfm_laserscale.commands`).

Exit status: 0 success; 1 the run finished but no scale could be estimated;
2 bad usage or bad input (one line on stderr, no traceback without --debug);
3 an internal error (a bug: please report it with the --debug traceback); 4 an external tool of a
pipeline command (``colmap``, ``openmvg``) failed: the line names the step;
143 / 130 stopped by SIGTERM / SIGINT (nothing written, workers stopped).
"""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from sfm_laserscale.errors import InputError, ToolFailedError
from sfm_laserscale.lifecycle import Interrupted, signals_as_exceptions
from sfm_laserscale.version import __version__

logger = logging.getLogger("sfm_laserscale")

EXIT_OK, EXIT_NO_SCALE, EXIT_BAD_INPUT, EXIT_INTERNAL, EXIT_TOOL = 0, 1, 2, 3, 4


class GreedyCommand(click.Command):
    """A command whose listed options take every following value: ``--opt a b c``.

    click options take a fixed number of values; the CLI contract has
    ``--laser-images PATH [PATH...]``, so the arguments are rewritten to
    ``--opt a --opt b --opt c`` (a ``multiple=True`` option) before parsing.
    """

    greedy: tuple[str, ...] = ("--laser-images",)

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
    from sfm_laserscale.registration.pose import configure_colmap_logging

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
            with signals_as_exceptions():  # SIGTERM/SIGINT: clean up, exit 143/130
                code = func(quiet=quiet, **kwargs)
        except Interrupted as exc:
            click.echo(f"sfm-laserscale: {exc}: stopped, no output written (an existing "
                       "output folder is kept as it was)", err=True)
            ctx.exit(exc.exit_status)
        except InputError as exc:
            if debug:
                raise
            click.echo(f"sfm-laserscale: error: {exc}", err=True)
            ctx.exit(EXIT_BAD_INPUT)
        except ToolFailedError as exc:  # an external tool of a pipeline failed at a step
            if debug:
                raise
            click.echo(f"sfm-laserscale: tool failed: {exc}", err=True)
            ctx.exit(EXIT_TOOL)
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
_NO_GUIDED_HELP = ("Do not search for missed spots where the model and the first scale put "
                   "them (docs/DETECTION.md).")
_NO_SCENE_HELP = ("Detect on the laser photographs alone: do not render the model images "
                  "into each registered laser image to remove the seafloor's texture "
                  "(docs/DETECTION.md).")


def _scene_options(kw: dict[str, Any]) -> Any:
    from sfm_laserscale.scene_reference import SceneStageOptions

    return SceneStageOptions(enabled=not kw["no_scene_reference"],
                             keep_png=bool(kw.get("save_scene_references")))


@main.command(cls=GreedyCommand)
@click.option(
    "--model",
    type=_path,
    help="COLMAP sparse model folder or OpenMVG sfm_data.json.",
)
@click.option(
    "--mesh", type=_path, help="Dense mesh in the model's frame (PLY, OBJ, ...)."
)
@click.option("--colmap-workspace", type=_path, help="A COLMAP workspace: database.db, "
              "sparse/<n>/, images/, dense/<n>/meshed-*.ply (explicit paths override).")
@click.option("--openmvg-project", type=_path, help="An OpenMVG + OpenMVS project: sfm_data, "
              "matches/, the most refined OpenMVS mesh (explicit paths override).")
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
@click.option(
    "--workers",
    type=click.IntRange(min=0),
    help="Worker processes extracting SIFT beside this one (laser images; model images "
    "re-extracted with --images) [one per free core, within half the available memory; "
    "0: none].",
)
@click.option("--reuse-model-poses", is_flag=True, help="A laser image that is also a model "
              "image takes the model's pose instead of being registered.")
@click.option("--no-guided-spots", is_flag=True, help=_NO_GUIDED_HELP)
@click.option("--no-scene-reference", is_flag=True, help=_NO_SCENE_HELP)
@click.option("--save-scene-references", is_flag=True, help="Write each laser image's scene "
              "reference to scene_references/<stem>.png (RGBA, alpha 0 where unknown; "
              "detect --scene reads them).")
@click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder.")
@common_options
def scale(**kw: Any) -> int:
    """Estimate the model's metric scale and write the rescaled model, mesh and report."""
    from sfm_laserscale.commands.scale import ScaleOptions, run
    from sfm_laserscale.guided_spots import GuidedSpotOptions
    from sfm_laserscale.pipeline_folders import GivenInputs, resolve_scale_inputs
    from sfm_laserscale.registration.sift_workers import SiftWorkerOptions

    inputs = resolve_scale_inputs(GivenInputs(
        laser_images=tuple(kw["laser_images"]), rig=kw["rig"], model=kw["model"],
        mesh=kw["mesh"], images=kw["images"], database=kw["database"],
        features=kw["features"], spots=kw["spots"], colmap_workspace=kw["colmap_workspace"],
        openmvg_project=kw["openmvg_project"]))
    options = ScaleOptions(method=kw["method"], seed=kw["seed"], progress=not kw["quiet"],
                           reuse_model_poses=kw["reuse_model_poses"],
                           sift_workers=SiftWorkerOptions(workers=kw["workers"]),
                           guided=GuidedSpotOptions(enabled=not kw["no_guided_spots"]),
                           scene=_scene_options(kw))
    result = run(inputs, kw["out"], options, overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK if result.success else EXIT_NO_SCALE


@main.command()
@click.option(
    "--out", type=_path, default=Path("demo_out"), show_default=True, help="Output folder."
)
@click.option("--small", is_flag=True, help="A smaller, faster scene (as in the tests).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--laser-color", type=click.Choice(["red", "green", "blue"]), default="red",
              show_default=True, help="Colour of the four beams.")
@click.option("--water", type=click.Choice(["clear", "green"]),
              help="clear, or green coastal water with pale clutter on the floor "
              "[green for green beams, clear otherwise].")
@click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder.")
@common_options
def demo(**kw: Any) -> int:
    """Complete synthetic run with no input data: render, SfM, laser images, then `scale`."""
    from sfm_laserscale.commands.demo import DemoOptions, run_demo

    options = DemoOptions(small=kw["small"], seed=kw["seed"], progress=not kw["quiet"],
                          laser_color=kw["laser_color"], water=kw["water"])
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
    from sfm_laserscale.commands.apply import ApplyInputs, ApplyOptions, run

    result = run(ApplyInputs(model=kw["model"], mesh=kw["mesh"]), kw["out"],
                 ApplyOptions(scale=kw["scale_value"]), overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK


@main.command()
@click.option("--model", required=True, type=_path,
              help="COLMAP sparse model folder or OpenMVG sfm_data.json.")
@click.option("--out", required=True, type=_path, help="The mesh to write (.ply).")
@click.option("--method", type=click.Choice(["delaunay25d", "poisson"]), default="delaunay25d",
              show_default=True, help="delaunay25d: a height field seen from the cameras "
              "(surveys); poisson: Open3D's screened Poisson surface.")
@click.option("--min-track-length", type=click.IntRange(min=1), default=3, show_default=True,
              help="Use only points seen by at least this many images.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@common_options
def mesh(**kw: Any) -> int:
    """A coarse surface from the sparse model when there is no dense mesh (for scale --mesh);
    writes what it interpolates beside it (<out>.json)."""
    from sfm_laserscale.commands.mesh import MeshInputs, MeshOptions, run
    from sfm_laserscale.meshing import CoarseMeshOptions

    options = MeshOptions(CoarseMeshOptions(method=kw["method"],
                                            min_track_length=kw["min_track_length"]))
    result = run(MeshInputs(kw["model"]), kw["out"], options, overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK


@main.command()
@click.argument("images", nargs=-1, required=True, type=_path)
@click.option("--rig", required=True, type=_path, help="Laser rig TOML file.")
@click.option("--out", required=True, type=_path, help="Output folder (created).")
@click.option("--model", type=_path, help="Take the camera from this model (matched by size).")
@click.option("--camera", help='Camera as "MODEL W H params...", e.g. "PINHOLE W H fx fy cx cy".')
@click.option("--scene", type=_path,
              help="Folder of scene references: <stem>.png/.tif per image, the same view "
                   "without the lasers (RGBA: alpha 0 where unknown); their texture is removed.")
@click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder.")
@common_options
def detect(**kw: Any) -> int:
    """Detect laser spots: write spots.csv (for scale --spots), detections.json, overlays."""
    from sfm_laserscale.commands.detect import DetectInputs, run

    inputs = DetectInputs(images=tuple(kw["images"]), rig=kw["rig"], model=kw["model"],
                          camera=kw["camera"], scene=kw["scene"])
    result = run(inputs, kw["out"], overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK if result.success else EXIT_NO_SCALE


@main.command()
@click.argument("images", nargs=-1, required=True, type=_path)
@click.option("--board", default="9x6", show_default=True,
              help="Chessboard inner corners COLSxROWS (as OpenCV counts them), or 'charuco'.")
@click.option("--squares", help="ChArUco board squares COLSxROWS (with --board charuco).")
@click.option("--square-size", required=True, type=float, help="Square size (metres).")
@click.option("--marker-size", type=float,
              help="ChArUco marker side (metres; default 0.7 x the square size).")
@click.option("--dictionary", default="DICT_5X5_100", show_default=True,
              help="ChArUco markers: OpenCV ArUco dictionary name.")
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
    """Calibrate the laser rig from images of a chessboard or ChArUco board at several
    distances."""
    from sfm_laserscale.commands.calibrate import CalibrateInputs, CalibrateOptions, run

    if (kw["model"] is None) == (not kw["self_calibrate"]):
        raise InputError("give exactly one of --model PATH or --self-calibrate")
    charuco = kw["board"].lower() == "charuco"
    if charuco != (kw["squares"] is not None):
        raise InputError("--squares COLSxROWS goes with --board charuco (and is required by it)")
    grid = kw["squares"] if charuco else kw["board"]
    try:
        cols, rows = (int(v) for v in grid.lower().split("x"))
    except ValueError:
        raise InputError(f"--board/--squares must be COLSxROWS like 9x6, got {grid!r}") from None
    names = tuple(n.strip() for n in kw["names"].split(",")) if kw["names"] else None
    options = CalibrateOptions(
        board=(cols, rows), square_m=kw["square_size"], names=names, rig_name=kw["rig_name"],
        colors=tuple(c.strip() for c in kw["colors"].split(",")),
        target="charuco" if charuco else "chessboard", marker_m=kw["marker_size"],
        dictionary=kw["dictionary"])
    result = run(CalibrateInputs(images=tuple(kw["images"]), model=kw["model"]), kw["out"],
                 options, overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK


class _SimulateCommand(GreedyCommand):
    greedy = ("--config", "--distance", "--sigma-f", "--sigma-l")


@main.command(cls=_SimulateCommand)
@click.option("--out", required=True, type=_path, help="Output folder (created).")
@click.option("--mode", type=click.Choice(["grid", "random", "noise-table", "mismatch"]),
              default="grid", show_default=True, help="grid: pitch x roll -40..40 deg in 5 deg "
              "steps over a smooth and a rough area; random: random surface points and view "
              "angles; noise-table: camera above the smooth area, every sigma_f x sigma_l x "
              "distance; mismatch: surveys whose data carry errors the estimator is not told "
              "about (--trials surveys per setting, --group-size views each).")
@click.option("--config", "configs", multiple=True,
              type=click.Choice(["A", "B", "C", "A-adjacent", "C-nonparallel"]),
              help="Laser configuration(s), several allowed: A 4 beams parallel to the axis, "
              "B two tilted parallel pairs, C misaligned ROV rig, A-adjacent A with adjacent "
              "pairs, C-nonparallel C with its non-parallel pair [grid/random: A B C; "
              "noise-table: B C; mismatch: C].")
@click.option("--rig", type=_path, help="Rig TOML instead of the configurations (every laser "
              "needs origin and direction).")
@click.option("--mesh", type=_path, help="Metric mesh (scale 1) instead of the demo's seafloor.")
@click.option("--distance", "distances", multiple=True, type=float,
              help="Camera altitude(s) above the local surface, metres [2 3 4].")
@click.option("--trials", type=int, help="grid: noise draws per view [1]; random: views in all "
              "[10000]; noise-table: draws per cell [500].")
@click.option("--sigma-f", "sigma_f", multiple=True, type=float,
              help="Feature noise sigma, px, several allowed [0.5; noise-table: 0.5 1].")
@click.option("--sigma-l", "sigma_l", multiple=True, type=float,
              help="Laser spot noise sigma, px, several allowed [0.25; noise-table: 0.25 0.5].")
@click.option("--outliers", type=float, default=0.1, show_default=True,
              help="Fraction of feature matches moved to random pixels.")
@click.option("--group-size", type=int, default=5, show_default=True,
              help="Views per PCM-joint estimate.")
@click.option("--max-angle", type=float, default=40.0, show_default=True,
              help="Largest |pitch|, |roll| (deg) of grid and random views.")
@click.option("--angle-step", type=float, default=5.0, show_default=True,
              help="Pitch/roll step of the grid (deg).")
@click.option("--camera", type=(int, int, float), default=(1920, 1080, 1500.0),
              show_default=True, help="PINHOLE camera: WIDTH HEIGHT FOCAL (px).")
@click.option("--antithetic", is_flag=True,
              help="Pair each noise draw with its negation (per-view bias from one pair).")
@click.option("--workers", type=int, help="Worker processes [the CPUs available].")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every draw.")
@click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder.")
@common_options
def simulate(**kw: Any) -> int:
    """The paper's synthetic experiments through the code of `scale`: results.json, table.md,
    trials.csv.gz and figures (errors in % of the true scale, reported sigma vs Monte Carlo)."""
    from sfm_laserscale.commands.simulate import SimulationInputs, SimulationOptions, run
    from sfm_laserscale.resources import available_cpus
    from sfm_laserscale.synthetic.simulate.configs import pinhole_camera

    if kw["mode"] == "mismatch":
        return _simulate_mismatch(kw)

    options = SimulationOptions(
        mode=kw["mode"], configs=tuple(kw["configs"]) or None,
        distances_m=tuple(kw["distances"]) or (2.0, 3.0, 4.0), trials=kw["trials"],
        sigma_f_px=tuple(kw["sigma_f"]) or None, sigma_l_px=tuple(kw["sigma_l"]) or None,
        outlier_ratio=kw["outliers"], group_size=kw["group_size"],
        max_angle_deg=kw["max_angle"], angle_step_deg=kw["angle_step"],
        camera=pinhole_camera(*kw["camera"]), antithetic=kw["antithetic"],
        workers=kw["workers"] or available_cpus(), seed=kw["seed"],
        progress=not kw["quiet"])
    result = run(SimulationInputs(rig=kw["rig"], mesh=kw["mesh"]), kw["out"], options,
                 overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK if len(result.collected.table) else EXIT_NO_SCALE


_WORKERS_HELP = ("SIFT worker processes of scale; the pipeline's tools get workers + 1 threads "
                 "[scale's default; tools: every core].")


class _PipelineCommand(GreedyCommand):
    greedy = ("--laser-images",)


def pipeline_run_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """How every pipeline command (``colmap``, ``openmvg``) runs its ``scale`` and writes."""
    for option in reversed((
        click.option("--method", type=click.Choice(["fcm", "pcm", "all"]), default="all",
                     show_default=True),
        click.option("--seed", type=int, default=0, show_default=True),
        click.option("--workers", type=click.IntRange(min=0), help=_WORKERS_HELP),
        click.option("--no-guided-spots", is_flag=True, help=_NO_GUIDED_HELP),
        click.option("--no-scene-reference", is_flag=True, help=_NO_SCENE_HELP),
        click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder."),
    )):
        func = option(func)
    return func


def pipeline_inputs(func: Callable[..., Any]) -> Callable[..., Any]:
    """The inputs every pipeline command (``colmap``, ``openmvg``) takes."""
    for option in reversed((
        click.option("--images", required=True, type=_path,
                     help="The source images (laser images among them are held out of SfM)."),
        click.option("--laser-images", required=True, multiple=True, type=_path,
                     help="Laser image files and/or folders."),
        click.option("--rig", required=True, type=_path, help="Laser rig TOML file."),
        click.option("--out", required=True, type=_path, help="Output folder (created)."),
    )):
        func = option(func)
    return func


@main.command(cls=_PipelineCommand)
@pipeline_inputs
@click.option("--mesh", type=_path, help="A mesh in the frame of the model built here (rare).")
@click.option("--pairs", type=_path, help="Image pairs to match, 'name1 name2' per line.")
@click.option("--spots", type=_path, help="CSV image,laser,x,y replacing detection.")
@click.option("--backend", type=click.Choice(["auto", "colmap", "pycolmap"]), default="auto",
              show_default=True, help="auto: COLMAP's command line when found, else pycolmap.")
@click.option("--colmap", "colmap_exe", default="colmap", show_default=True,
              help="The COLMAP executable.")
@click.option("--camera-model", default="SIMPLE_RADIAL", show_default=True)
@click.option("--camera-params", help="Known intrinsics, comma separated (held fixed).")
@click.option("--max-features", type=int, default=8192, show_default=True)
@click.option("--sift-first-octave", type=int, default=-1, show_default=True)
@click.option("--mesh-method", type=click.Choice(["delaunay25d", "poisson"]),
              default="delaunay25d", show_default=True)
@pipeline_run_options
@common_options
def colmap(**kw: Any) -> int:
    """COLMAP SfM (laser images held out), a coarse mesh when none is given, then scale."""
    from sfm_laserscale.commands.colmap import ColmapInputs, ColmapOptions, run
    from sfm_laserscale.meshing import CoarseMeshOptions
    from sfm_laserscale.registration.mapping import SfmOptions

    params = None
    if kw["camera_params"] is not None:
        try:
            params = tuple(float(x) for x in kw["camera_params"].split(","))
        except ValueError:
            raise InputError("--camera-params must be comma-separated numbers, got "
                             f"{kw['camera_params']!r}") from None
    sfm = SfmOptions(backend=kw["backend"], colmap=kw["colmap_exe"],
                     camera_model=kw["camera_model"], camera_params=params,
                     max_features=kw["max_features"], sift_first_octave=kw["sift_first_octave"],
                     threads=-1 if kw["workers"] is None else kw["workers"] + 1, seed=kw["seed"])
    options = ColmapOptions(sfm=sfm, mesh=CoarseMeshOptions(method=kw["mesh_method"]),
                            scale=_scale_options(kw))
    inputs = ColmapInputs(images=kw["images"], laser_images=tuple(kw["laser_images"]),
                          rig=kw["rig"], mesh=kw["mesh"], pairs=kw["pairs"], spots=kw["spots"])
    result = run(inputs, kw["out"], options, overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK if result.scale.success else EXIT_NO_SCALE


def _scale_options(kw: dict[str, Any]) -> Any:
    from sfm_laserscale.guided_spots import GuidedSpotOptions
    from sfm_laserscale.registration.sift_workers import SiftWorkerOptions
    from sfm_laserscale.run_types import ScaleOptions

    return ScaleOptions(method=kw["method"], seed=kw["seed"], progress=not kw["quiet"],
                        sift_workers=SiftWorkerOptions(workers=kw["workers"]),
                        guided=GuidedSpotOptions(enabled=not kw["no_guided_spots"]),
                        scene=_scene_options(kw))


@main.command(cls=_PipelineCommand)
@pipeline_inputs
@click.option("--intrinsics-k", help='Calibrated camera "fx;0;cx;0;fy;cy;0;0;1" (OpenMVG '
              "pixels: cx = cx_colmap - 0.5).")
@click.option("--focal-px", type=float, help="Focal length in pixels.")
@click.option("--camera-db", type=_path, help="OpenMVG sensor width database (EXIF).")
@click.option("--openmvg-bin", type=_path, help="Folder of the OpenMVG tools [the PATH].")
@click.option("--openmvs-bin", type=_path, help="Folder of the OpenMVS tools [the PATH].")
@click.option("--spots", type=_path, help="CSV image,laser,x,y replacing detection.")
@pipeline_run_options
@common_options
def openmvg(**kw: Any) -> int:
    """OpenMVG SfM and OpenMVS mesh (laser images held out), scale, then TransformScene."""
    from sfm_laserscale.commands.openmvg import OpenMvgInputs, OpenMvgPipelineOptions, run
    from sfm_laserscale.pipelines.openmvg_steps import OpenMvgOptions

    tools = OpenMvgOptions(intrinsics_k=kw["intrinsics_k"], focal_px=kw["focal_px"],
                           camera_db=kw["camera_db"],
                           threads=0 if kw["workers"] is None else kw["workers"] + 1)
    inputs = OpenMvgInputs(images=kw["images"], laser_images=tuple(kw["laser_images"]),
                           rig=kw["rig"], spots=kw["spots"], openmvg_bin=kw["openmvg_bin"],
                           openmvs_bin=kw["openmvs_bin"])
    result = run(inputs, kw["out"], OpenMvgPipelineOptions(tools, _scale_options(kw)),
                 overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK if result.scale.success else EXIT_NO_SCALE


@main.command()
@click.argument("manifest", type=_path)
@click.option("--out", required=True, type=_path, help="Output folder: DIR/<name>/ per model, "
              "DIR/summary.csv, DIR/summary.html.")
@click.option("--jobs", type=click.IntRange(min=1), help="Models at once, on a local Dask "
              "cluster of processes [one per available core]; 1: in this process.")
@click.option("--scheduler", help="Run on an existing Dask cluster (tcp://host:8786); its "
              "workers need the package and the paths.")
@click.option("--method", type=click.Choice(["fcm", "pcm", "all"]), default="all",
              show_default=True, help="For rows without a method.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--overwrite", is_flag=True, help="Redo models whose inputs and options are "
              "unchanged (skipped otherwise).")
@click.option("--no-guided-spots", is_flag=True, help=_NO_GUIDED_HELP)
@click.option("--no-scene-reference", is_flag=True, help=_NO_SCENE_HELP)
@common_options
def batch(**kw: Any) -> int:
    """Scale every model of a manifest (CSV) on Dask; one failed model never stops the others."""
    from sfm_laserscale.commands.batch import BatchInputs, BatchOptions, run

    options = BatchOptions(jobs=kw["jobs"], scheduler=kw["scheduler"], method=kw["method"],
                           seed=kw["seed"], progress=not kw["quiet"],
                           guided_spots=not kw["no_guided_spots"],
                           scene_reference=not kw["no_scene_reference"])
    result = run(BatchInputs(kw["manifest"]), kw["out"], options, overwrite=kw["overwrite"])
    click.echo(result.summary)
    return EXIT_OK if result.all_scaled else EXIT_NO_SCALE


def _simulate_mismatch(kw: dict[str, Any]) -> int:
    """``simulate --mode mismatch`` (commands/simulate.py: run_mismatch_command)."""
    from sfm_laserscale.commands.simulate import MismatchOptions, run_mismatch_command
    from sfm_laserscale.synthetic.simulate.configs import pinhole_camera

    options = MismatchOptions(
        surveys=kw["trials"] or 200, views=kw["group_size"],
        config=kw["configs"][0] if kw["configs"] else "C",
        sigma_f_px=(kw["sigma_f"] or (0.5,))[0], sigma_l_px=(kw["sigma_l"] or (0.25,))[0],
        outlier_ratio=kw["outliers"], camera=pinhole_camera(*kw["camera"]), seed=kw["seed"],
        progress=not kw["quiet"])
    result = run_mismatch_command(kw["out"], options, overwrite=kw["overwrite"])
    click.echo(result["summary"])
    return EXIT_OK if any(s.get("n") for s in result["settings"]) else EXIT_NO_SCALE


if __name__ == "__main__":  # pragma: no cover
    main()
