"""Error types (shared with `kinematics`, which owns `InputError` and `FitError`) and termination signals."""
from __future__ import annotations

import signal

from kinematics.errors import FitError, InputError

__all__ = ["InputError", "FitError", "Interrupted", "handle_termination"]


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
