"""The one exception the numerics raise for bad user input.

The CLI prints it as a single line (``error: <file>: <problem>. <fix>``) and exits non-zero (2
for an OptionError, a usage error; else 1); anything else that escapes is a bug in wavelight and
keeps its traceback.
"""

from __future__ import annotations

import contextlib
from pathlib import Path


class InputError(Exception):
    """Bad user input: names the file (if any), what is wrong and what to do about it."""

    def __init__(self, problem: str, path: str | Path | None = None, fix: str | None = None):
        self.problem = problem.rstrip(".")
        self.path = None if path is None else Path(path)
        self.fix = fix
        super().__init__(self.line())

    def line(self) -> str:
        where = f"{self.path}: " if self.path is not None else ""
        fix = f". {self.fix[:1].upper()}{self.fix[1:].rstrip('.')}." if self.fix else "."
        return f"{where}{self.problem}{fix}"


class OptionError(InputError):
    """A bad option value or combination (names the option, not a file): a usage error, for which
    the CLI exits 2 as click does for its own option errors."""


@contextlib.contextmanager
def option_errors():
    """Raise the InputErrors of the block as OptionErrors: for the checks of an options class
    that look at nothing but the options."""
    try:
        yield
    except OptionError:
        raise
    except InputError as exc:
        raise OptionError(exc.problem, exc.path, exc.fix) from None


def require_file(path: str | Path | None, fix: str) -> None:
    """Raise InputError unless `path` is an existing regular file (a folder of that name says so)."""
    if path is not None and Path(path).is_dir():
        raise InputError("is a folder, not a file", path, f"move the folder away, then {fix[:1].lower()}{fix[1:]}")
    if path is None or not Path(path).is_file():
        raise InputError("file not found", path, fix)
