"""Marker trials by file type: one reader for the C3D and TRC files a gait lab exports.

`read_trial` picks the reader from the suffix (`kinematics.io.c3d.read_c3d` for
``.c3d``, `kinematics.io.storage.read_trc` for ``.trc``); both return a
`MarkerTrial` in metres, whatever unit the file states.
"""
from __future__ import annotations

import os
from pathlib import Path

from lowerlimb.errors import InputError

from .markers import MarkerTrial

__all__ = ["TRIAL_SUFFIXES", "read_trial"]

TRIAL_SUFFIXES = (".c3d", ".trc")


def read_trial(path: str | os.PathLike, subject_name: str | None = None) -> MarkerTrial:
    """Read a marker trial from a ``.c3d`` or ``.trc`` file.

    Parameters
    ----------
    path : marker file; the suffix (case-insensitive) picks the reader
    subject_name : Vicon subject whose labels to keep when a C3D holds several
        (``Name:RKNE``); ignored for TRC files

    Returns
    -------
    MarkerTrial
        positions (n_frames, n_markers, 3) in metres, lab frame of the file.

    Raises
    ------
    InputError
        The file does not exist, has another suffix, or its reader refuses it.
    """
    from .c3d import read_c3d
    from .storage import read_trc

    p = Path(path)
    if not p.is_file():
        raise InputError(path, "file not found")
    suffix = p.suffix.lower()
    if suffix == ".c3d":
        return read_c3d(p, subject=subject_name)
    if suffix == ".trc":
        return read_trc(p)
    raise InputError(path, f"unsupported marker file type {suffix!r} (expected {' or '.join(TRIAL_SUFFIXES)})")
