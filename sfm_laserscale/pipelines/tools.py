"""External tools run one step at a time: each step has a name, its program and arguments; its
output goes to a log file; a non-zero exit (or a check of its result that fails) raises
:class:`~sfm_laserscale.errors.ToolFailedError` naming the step. Programs are found before any
work starts (a missing one is bad input, exit status 2).
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from sfm_laserscale.errors import InputError, ToolFailedError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ToolStep:
    """One step of a pipeline: ``program args...`` run in ``cwd`` (None: the current folder)."""

    name: str  # the step's name in messages (e.g. "mapper", "ReconstructMesh")
    program: str  # the executable's name (found on PATH or in a bin folder)
    args: tuple[str, ...]
    cwd: Path | None = None


def find_program(name: str, bin_dir: Path | None = None) -> str:
    """Full path of a program, from ``bin_dir`` when given, else the PATH (InputError)."""
    if bin_dir is not None:
        path = bin_dir / name
        if path.is_file() and os.access(path, os.X_OK):
            return str(path)
        raise InputError(f"{name} not found in the tools folder", bin_dir)
    found = shutil.which(name)
    if found is None:
        raise InputError(f"{name} not found on the PATH (install it, or give its folder)")
    return found


def find_programs(steps: Sequence[ToolStep], bin_dirs: dict[str, Path | None]) -> dict[str, str]:
    """Program name -> full path for every step (all checked before any runs); ``bin_dirs``:
    program name -> its folder (missing: the PATH)."""
    return {s.program: find_program(s.program, bin_dirs.get(s.program)) for s in steps}


def run_step(step: ToolStep, program: str, log: Path,
             env: dict[str, str] | None = None) -> None:
    """Run one step, its output appended to ``log``; ToolFailedError on a non-zero exit."""
    cmd = [program, *step.args]
    logger.info("step %s: %s", step.name, " ".join(cmd))
    full_env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", **(env or {})}  # never a display
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a", encoding="utf-8") as fh:
        fh.write(f"$ {' '.join(cmd)}" + (f"  (in {step.cwd})" if step.cwd else "") + "\n")
        fh.flush()
        try:
            proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=full_env,
                                  cwd=step.cwd, check=False)
        except OSError as exc:
            raise ToolFailedError(step.name, f"cannot run {program}: {exc.strerror}", log) \
                from None
    if proc.returncode != 0:
        raise ToolFailedError(step.name, f"{step.program} exited with status {proc.returncode}",
                              log)
