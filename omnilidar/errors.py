"""The one error type for bad input: it names the file and the problem."""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad input data or configuration.

    The CLI prints ``str(error)`` as a single line and exits with status 2, so the
    message must say which file (or config key) is wrong and how.
    """

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)
