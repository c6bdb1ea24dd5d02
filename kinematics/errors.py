"""Exceptions shared by the whole project.

`InputError` is the one type for bad user input: the CLI prints it as a single
line ``error: <file>: <problem>`` and exits with code 2.  `personalize` re-exports
it, so library code on either side raises the same class.
"""
from __future__ import annotations

import os


class InputError(ValueError):
    """A user-supplied file or value is unusable.

    Parameters
    ----------
    source : str or os.PathLike or None
        The file (or option name) at fault; shown first in the message.
    problem : str
        One sentence saying what is wrong, no trailing period needed.
    """

    def __init__(self, source: str | os.PathLike | None, problem: str):
        self.source = None if source is None else os.fspath(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}" if self.source else problem)


class FitError(RuntimeError):
    """A numerical estimate could not be obtained (degenerate data, no convergence)."""
