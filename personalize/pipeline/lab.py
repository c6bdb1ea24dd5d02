r"""The lab a subject was recorded in, read from its trials, and every trial expressed in the internal frame.

`read_lab` finds the lab's vertical, progression, floor and the static pose's
facing (`kinematics.gait.lab_frame.detect_lab`); `to_internal` re-expresses a
marker trial and `plates_to_internal` a trial's force plates in the internal
frame the whole pipeline works in (X the static pose's facing, Y left, Z up,
metres, the lab's origin):

.. math::

    x_{int} = R\, x_{lab}, \qquad R = `LabFrame.internal_from_lab`

When :math:`R` is a signed permutation (the facing within
`kinematics.gait.lab_frame.SNAP_DEG` of a lab axis, the usual case) the
coordinates are moved and negated, not multiplied, so the internal values are
the lab's bit for bit; the identity (a Z-up lab facing +X) returns the trial
itself.
"""
from __future__ import annotations

import numpy as np

from kinematics.gait.lab_frame import LabFrame, detect_lab
from kinematics.io.markers import MarkerTrial

__all__ = ["read_lab", "to_internal", "plates_to_internal", "rotate_points", "is_identity"]


def read_lab(static: MarkerTrial, trials) -> LabFrame:
    """The lab of a subject's static and dynamic trials (lab coordinates); `InputError` when ambiguous."""
    return detect_lab(static, list(trials))


def is_identity(R: np.ndarray) -> bool:
    """True when `R` is exactly the 3x3 identity."""
    return bool(np.array_equal(R, np.eye(3)))


def _permutation(R: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(column index, sign) per output axis when `R` is a signed permutation, else None."""
    if not np.all(np.isin(R, (-1.0, 0.0, 1.0))) or not np.all(np.abs(R).sum(axis=1) == 1.0):
        return None
    idx = np.argmax(np.abs(R), axis=1)
    return idx, R[np.arange(3), idx]


def rotate_points(R: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``R @ x`` over the last axis of `x` (..., 3); exact (indexing and sign) for a signed permutation."""
    x = np.asarray(x, float)
    if is_identity(R):
        return x
    perm = _permutation(R)
    if perm is not None:
        idx, sign = perm
        return x[..., idx] * sign
    return x @ np.asarray(R, float).T


def to_internal(trial: MarkerTrial, lab: LabFrame) -> MarkerTrial:
    """`trial` (lab coordinates) in the internal frame; the same object when the lab is already internal."""
    R = lab.internal_from_lab
    if is_identity(R):
        return trial
    return MarkerTrial(trial.names, rotate_points(R, trial.positions), trial.rate, trial.time, trial.source,
                       {**trial.extra, "internal_from_lab": R.tolist()})


def plates_to_internal(plates, lab: LabFrame):
    """`kinematics.io.forceplates.ForcePlates` of a lab trial in the internal frame (`ForcePlates.rotated`:
    corners, centre, plate axes, normal, force, moment, centre of pressure, free moment); the same object for
    the identity."""
    R = lab.internal_from_lab
    return plates if is_identity(R) else plates.rotated(R)
