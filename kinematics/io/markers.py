"""Marker trajectories: one container for every reader (TRC, C3D) and writer.

Positions are metres in the lab (or model) frame; gaps are NaN.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lowerlimb.errors import InputError

__all__ = ["MarkerTrial", "true_runs", "MAX_COORDINATE_M", "MAX_RATE_HZ", "LENGTH_UNITS"]

#: largest plausible |coordinate| of a marker, metres (a gait lab is ~20 m across; mm read as m lands beyond);
#: the C3D and TRC readers refuse files beyond it
MAX_COORDINATE_M = 100.0
#: largest plausible marker sampling rate, Hz
MAX_RATE_HZ = 100_000.0
#: length units of marker files (C3D POINT:UNITS, TRC Units, force-plate geometry) -> metres
LENGTH_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "meters": 1.0, "metres": 1.0, "millimeters": 1e-3,
                "millimetres": 1e-3}


def true_runs(mask) -> list[tuple[int, int]]:
    """(start, stop) index pairs of the True runs of a 1-D mask, stop exclusive (gap-free runs, loaded intervals)."""
    d = np.diff(np.concatenate([[0], np.asarray(mask).astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


@dataclass(frozen=True)
class MarkerTrial:
    """Marker trajectories of one trial.

    Attributes
    ----------
    names : tuple of str, length M
    positions : ndarray, shape (F, M, 3), metres; NaN where a marker is missing
    rate : float
        Sampling rate in Hz.
    time : ndarray, shape (F,), seconds
    source : str or None
        File the data came from, used in error messages.
    extra : dict
        Reader-specific metadata (e.g. analog channels, subject name).
    """

    names: tuple[str, ...]
    positions: np.ndarray
    rate: float
    time: np.ndarray
    source: str | None = None
    extra: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        pos = np.asarray(self.positions, dtype=float)
        if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[1] != len(self.names):
            raise InputError(self.source, f"marker array of shape {pos.shape} does not match {len(self.names)} marker names")
        if len(set(self.names)) != len(self.names):
            dup = sorted({n for n in self.names if self.names.count(n) > 1})
            raise InputError(self.source, f"duplicate marker names {dup}")
        object.__setattr__(self, "positions", pos)
        object.__setattr__(self, "time", np.asarray(self.time, dtype=float))
        object.__setattr__(self, "names", tuple(self.names))

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise InputError(self.source, f"marker {name!r} is missing") from None

    def marker(self, name: str) -> np.ndarray:
        """Trajectory of one marker, shape (F, 3) in metres."""
        return self.positions[:, self.index(name)]

    def require(self, names) -> None:
        """Raise one InputError naming every marker of `names` that is absent."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise InputError(self.source, f"missing markers: {', '.join(missing)}")

    def subset(self, names) -> "MarkerTrial":
        self.require(names)
        idx = [self.index(n) for n in names]
        return MarkerTrial(tuple(names), self.positions[:, idx], self.rate, self.time, self.source, dict(self.extra))

    def window(self, start: float | None = None, end: float | None = None) -> "MarkerTrial":
        """Frames with start <= time <= end (seconds)."""
        keep = np.ones(self.n_frames, bool)
        if start is not None:
            keep &= self.time >= start - 1e-9
        if end is not None:
            keep &= self.time <= end + 1e-9
        if not keep.any():
            raise InputError(self.source, f"no frame between {start} s and {end} s")
        return MarkerTrial(self.names, self.positions[keep], self.rate, self.time[keep], self.source, dict(self.extra))
