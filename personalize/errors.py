"""Error types (shared with `kinematics`, which owns `InputError` and `FitError`) and termination signals."""
from __future__ import annotations

import signal

from kinematics.errors import FitError, InputError

__all__ = ["InputError", "FitError", "Interrupted", "handle_termination"]


class Interrupted(KeyboardInterrupt):
    """The run was stopped by a signal (SIGINT: Ctrl-C, SIGTERM: ``kill``, a scheduler's time limit).

    A `KeyboardInterrupt`, so that no ``except Exception`` swallows it; the CLI
    prints ``interrupted (SIGTERM)`` plus `detail` and exits with ``128 + signum``
    (130 for SIGINT, 143 for SIGTERM), as shells report a process killed by it.
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
    """Make SIGTERM raise `Interrupted` in the main thread (SIGINT already raises KeyboardInterrupt)."""
    signal.signal(signal.SIGTERM, _raise_interrupted)
