"""What ``simulate`` runs: the laser configurations A, B and C (or a rig file), the
camera, the options and inputs, and the laser settings (rig × spot noise) of a run."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from sfm_laserscale.errors import InputError
from sfm_laserscale.fusion import FusionOptions
from sfm_laserscale.model import Camera
from sfm_laserscale.raycast import SpotCastOptions
from sfm_laserscale.registration.options import PoseOptions
from sfm_laserscale.rig import Pair, Rig, rig_from_dict
from sfm_laserscale.synthetic.dataset import make_rig
from sfm_laserscale.uncertainty import EstimationOptions

MODES = ("grid", "random", "noise-table")
CONFIGS = ("A", "B", "C", "A-adjacent", "C-nonparallel")
AREAS = ("smooth", "rough")

#: Defaults per mode: configurations, trials, σ_f (px), σ_l (px).
MODE_DEFAULTS: dict[str, dict[str, Any]] = {
    "grid": {"configs": ("A", "B", "C"), "trials": 1, "sigma_f": (0.5,), "sigma_l": (0.25,)},
    "random": {"configs": ("A", "B", "C"), "trials": 10000, "sigma_f": (0.5,),
               "sigma_l": (0.25,)},
    "noise-table": {"configs": ("B", "C"), "trials": 500, "sigma_f": (0.5, 1.0),
                    "sigma_l": (0.25, 0.5)},
}


def pinhole_camera(width: int, height: int, focal_px: float) -> Camera:
    """PINHOLE camera with the principal point at the image centre."""
    if width < 16 or height < 16 or not focal_px > 0:
        raise InputError(f"camera needs width, height >= 16 px and a positive focal length, "
                         f"got {width} {height} {focal_px}")
    return Camera(1, "PINHOLE", int(width), int(height),
                  np.array([focal_px, focal_px, width / 2.0, height / 2.0]))


def default_camera() -> Camera:
    """PINHOLE 1920 × 1080, f = 1500 px, principal point at the image centre."""
    return pinhole_camera(1920, 1080, 1500.0)


# --------------------------------------------------------------------------- configurations


def _unit(v: Sequence[float]) -> list[float]:
    a = np.asarray(v, dtype=np.float64)
    return [float(x) for x in a / np.linalg.norm(a)]


def _rig(name: str, origins: dict[str, tuple[float, float, float]],
         dirs: dict[str, list[float]], pairs: list[tuple[str, str, float]]) -> Rig:
    lasers = [{"name": k, "origin": list(o), "direction": dirs[k], "color": "red"}
              for k, o in origins.items()]
    return rig_from_dict({"name": name, "laser": lasers,
                          "pair": [{"lasers": [a, b], "separation": s} for a, b, s in pairs]},
                         f"<configuration {name}>")


def config_rig(name: str) -> Rig:
    """The paper's laser configurations A, B, C (metres, camera frame).

    A: four beams parallel to the optical axis, origins 10 cm from the camera centre on the x
    and y axes; pairs (L1, L2) and (L3, L4), 0.2 m apart. B: two pairs of parallel beams 0.1 m
    apart, origins (±0.05, ∓0.10); pair L1+L2 tilted 2° towards −y, pair L3+L4 3° towards +y
    (tilts in the y–z plane keep the camera equidistant from both beams of a pair). C: the
    demo's misaligned ROV scaler (``dataset.make_rig("rov")``): origins 16.5 cm from the centre,
    directions 1.5–2.8° off the axis, one parallel pair L1+L2. ``A-adjacent``: A with its four
    adjacent pairs (L1+L3, L3+L2, L2+L4, L4+L1, 0.141 m) for PCM. ``C-nonparallel``: C with
    L3+L4 declared a pair too, as the paper's configuration C has it: those beams are 4.8°
    apart, so PCM refuses that pair (rig_checks.py).
    """
    if name == "A-adjacent":
        a = config_rig("A")
        s = float(np.hypot(0.1, 0.1))
        return replace(a, name="A-adjacent", pairs=tuple(
            Pair((x, y), s) for x, y in (("L1", "L3"), ("L3", "L2"), ("L2", "L4"), ("L4", "L1"))))
    if name == "C-nonparallel":
        c = make_rig("rov")
        return replace(c, name="C-nonparallel", pairs=(*c.pairs, Pair(("L3", "L4"), 0.234)))
    if name == "A":
        axis = [0.0, 0.0, 1.0]
        return _rig("A", {"L1": (0.1, 0.0, 0.0), "L2": (-0.1, 0.0, 0.0),
                          "L3": (0.0, 0.1, 0.0), "L4": (0.0, -0.1, 0.0)},
                    dict.fromkeys(("L1", "L2", "L3", "L4"), axis),
                    [("L1", "L2", 0.2), ("L3", "L4", 0.2)])
    if name == "B":
        a, b = np.radians(2.0), np.radians(3.0)
        va, vb = _unit([0.0, -np.sin(a), np.cos(a)]), _unit([0.0, np.sin(b), np.cos(b)])
        return _rig("B", {"L1": (-0.05, -0.10, 0.0), "L2": (0.05, -0.10, 0.0),
                          "L3": (-0.05, 0.10, 0.0), "L4": (0.05, 0.10, 0.0)},
                    {"L1": va, "L2": va, "L3": vb, "L4": vb},
                    [("L1", "L2", 0.1), ("L3", "L4", 0.1)])
    if name == "C":
        return make_rig("rov")
    raise InputError(f"unknown laser configuration {name!r} (known: {', '.join(CONFIGS)})")


def check_rig(rig: Rig, where: str) -> None:
    """Simulation needs the true beams: every laser must have an origin and a direction."""
    missing = [las.name for las in rig.lasers if not las.calibrated]
    if missing:
        raise InputError(f"simulation needs every laser's origin and direction; "
                         f"{', '.join(missing)} have none", where)


def is_parallel_axis_rig(rig: Rig) -> bool:
    """True for four calibrated beams parallel to the optical axis (Davis & Tusting)."""
    return len(rig.lasers) == 4 and all(
        las.direction is not None and float(las.direction[2]) > 1 - 1e-9 for las in rig.lasers)


# --------------------------------------------------------------------------- options


@dataclass(frozen=True)
class SimulationOptions:
    """What ``simulate`` runs. ``None`` fields take the mode's default (``MODE_DEFAULTS``)."""

    mode: str = "grid"
    configs: tuple[str, ...] | None = None  # A | B | C (ignored when a rig file is given)
    distances_m: tuple[float, ...] = (2.0, 3.0, 4.0)  # altitude above the local surface
    trials: int | None = None  # grid: per view; random: views in all; noise-table: per cell
    sigma_f_px: tuple[float, ...] | None = None  # feature noise, per axis
    sigma_l_px: tuple[float, ...] | None = None  # spot noise, per axis
    outlier_ratio: float = 0.1  # fraction of features moved to random pixels
    n_points: int = 1500
    group_size: int = 5  # views per PCM-joint estimate
    max_angle_deg: float = 40.0
    angle_step_deg: float = 5.0
    area_radius_m: float = 0.5
    areas: tuple[str, ...] = AREAS  # grid mode: which areas
    antithetic: bool = False
    camera: Camera = field(default_factory=default_camera)
    true_scale: float = 1.0  # metres per model unit
    scene_seed: int = 0  # make_scene's seed (the demo's scene)
    seed: int = 0
    workers: int = 1
    progress: bool = True
    pose: PoseOptions = field(default_factory=PoseOptions)
    spot_cast: SpotCastOptions = field(default_factory=SpotCastOptions)
    estimation: EstimationOptions = field(default_factory=EstimationOptions)
    fusion: FusionOptions = field(default_factory=FusionOptions)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise InputError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        for c in self.configs or ():
            if c not in CONFIGS:
                raise InputError(f"configuration must be one of {', '.join(CONFIGS)}, got {c!r}")
        if not self.distances_m or min(self.distances_m) <= 0:
            raise InputError("distances must be positive metres")
        if self.trials is not None and self.trials < 1:
            raise InputError(f"trials must be >= 1, got {self.trials}")
        noise = (*(self.sigma_f_px or ()), *(self.sigma_l_px or ()))
        if any(not (math.isfinite(s) and s >= 0) for s in noise):
            raise InputError("noise sigmas must be finite and >= 0 pixels")
        if not 0 <= self.outlier_ratio < 0.9:
            raise InputError(f"outlier ratio must be in [0, 0.9), got {self.outlier_ratio}")
        if not self.areas or any(a not in AREAS for a in self.areas):
            raise InputError(f"areas must be among {', '.join(AREAS)}, got {self.areas}")
        if self.n_points < 10 or self.group_size < 3 or self.workers < 1:
            raise InputError("need n_points >= 10, group_size >= 3 and workers >= 1")
        if not (0 < self.max_angle_deg < 80 and self.angle_step_deg > 0 and self.true_scale > 0
                and self.area_radius_m > 0):
            raise InputError("need 0 < max angle < 80°, a positive angle step, true scale and "
                             "area radius")

    def resolved(self, key: str) -> Any:
        """The mode's default for configs / trials / sigma_f / sigma_l when unset."""
        value = {"configs": self.configs, "trials": self.trials, "sigma_f": self.sigma_f_px,
                 "sigma_l": self.sigma_l_px}[key]
        return MODE_DEFAULTS[self.mode][key] if value is None else value


@dataclass(frozen=True)
class SimulationInputs:
    """Optional files: a rig replacing the configurations, a metric mesh replacing the scene."""

    rig: Path | None = None
    mesh: Path | None = None


@dataclass(frozen=True)
class LaserSetting:
    """One laser rig with one spot noise level."""

    config: str
    rig: Rig
    sigma_l_px: float


def load_settings(inputs: SimulationInputs, options: SimulationOptions
                  ) -> tuple[LaserSetting, ...]:
    """(configuration, rig, σ_l) of every laser setting to simulate."""
    if inputs.rig is not None:
        from sfm_laserscale.rig import load_rig

        rig = load_rig(inputs.rig)
        check_rig(rig, str(inputs.rig))
        rigs = [(Path(inputs.rig).stem, rig)]
    else:
        rigs = [(c, config_rig(c)) for c in options.resolved("configs")]
    return tuple(LaserSetting(name, rig, float(s)) for name, rig in rigs
                 for s in options.resolved("sigma_l"))
