"""Exceptions shared by the whole project.

`InputError` is the one type for bad user input: the CLI prints it as a single
line ``error: <file>: <problem>`` and exits with code 2.  `Interrupted` is a
stop by a signal (the CLI exits 130 / 143).
"""
from __future__ import annotations

import os
import signal


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

class Interrupted(BaseException):
    """The run was stopped by a signal (SIGINT: Ctrl-C, SIGTERM: ``kill``, a scheduler's time limit).

    A `BaseException` like `KeyboardInterrupt`, so that no ``except Exception``
    swallows it, but not one: typer turns a KeyboardInterrupt into a silent
    exit 130.  The CLI prints ``interrupted (SIGTERM)`` plus `detail` and exits
    with ``128 + signum`` (130 for SIGINT, 143 for SIGTERM), as shells report a
    process killed by it.
    """

    def __init__(self, signum: int = signal.SIGINT, detail: str = ""):
        super().__init__(signum)
        self.signum = int(signum)
        self.detail = detail

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    @property
    def signal_name(self) -> str:
        try:
            return signal.Signals(self.signum).name
        except ValueError:
            return f"signal {self.signum}"


def _raise_interrupted(signum, frame):  # pragma: no cover - exercised through subprocess tests
    raise Interrupted(signum)


def handle_termination() -> None:
    """Make SIGINT and SIGTERM raise `Interrupted` in the main thread (the command line's handlers)."""
    signal.signal(signal.SIGTERM, _raise_interrupted)
    signal.signal(signal.SIGINT, _raise_interrupted)
