"""One exception type for bad user input, so the CLI can print it without a traceback."""

from __future__ import annotations

from pathlib import Path


class D3LVOInputError(Exception):
    """Bad input: the message names the file (or folder) and what is wrong with it."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)

    def __reduce__(self):
        # rebuilt from (path, problem), not from the message: a scale-out worker's error reaches the
        # parent process (pickled) as the same one-line error
        return type(self), (self.path, self.problem)
