"""Exceptions that the CLI turns into exit status 2 with one clear line."""

from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """Bad user input: names the file (when there is one) and the problem."""

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.path = None if path is None else str(path)
        self.problem = message
        super().__init__(f"{self.path}: {message}" if self.path else message)


class ToolFailedError(RuntimeError):
    """An external tool of a pipeline (COLMAP, OpenMVG, OpenMVS) failed at one step: the CLI
    names the step and exits with its own status (4)."""

    def __init__(self, step: str, message: str, log: str | Path | None = None) -> None:
        self.step = step
        self.log = None if log is None else str(log)
        self.problem = message
        where = f" (log: {self.log})" if self.log else ""
        super().__init__(f"step {step!r} failed: {message}{where}")
