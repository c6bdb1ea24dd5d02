"""Transfer of a correlative knee law to a model with other segment frames (Pronost et al. 2010, 4.2).

`scale_factor` is eq. (3) (applied by `CorrelativeLaw.scaled`),
`knee_landmark_frame` the knee frame of section 3.1 and `transfer_law` the
five-step transfer.  Landmarks in metres.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from kinematics.mechanisms.correlative import CorrelativeLaw
from lowerlimb.errors import InputError

__all__ = ["scale_factor", "knee_landmark_frame", "LawTransfer", "transfer_law"]


def scale_factor(target: Mapping[str, np.ndarray], source: Mapping[str, np.ndarray],
                 trochanter: str = "RGT", lateral: str = "RLFE", medial: str = "RMFE") -> float:
    """Seed eq. (3): ``s = (s1 + s2) / 2``.

    ``s1 = |GT - LFE|_target / |GT - LFE|_source``,
    ``s2 = |MFE - LFE|_target / |MFE - LFE|_source``; landmarks in metres
    (any frame of each model: only distances are used).
    """
    for lm, name in ((target, "target"), (source, "source")):
        missing = [n for n in (trochanter, lateral, medial) if n not in lm]
        if missing:
            raise InputError(name, f"landmarks missing: {', '.join(missing)}")

    def dist(lm, a, b):
        d = float(np.linalg.norm(np.asarray(lm[a], float) - np.asarray(lm[b], float)))
        if not d > 1e-6:
            raise InputError(None, f"landmarks {a} and {b} coincide")
        return d

    s1 = dist(target, trochanter, lateral) / dist(source, trochanter, lateral)
    s2 = dist(target, medial, lateral) / dist(source, medial, lateral)
    return 0.5 * (s1 + s2)


def knee_landmark_frame(trochanter, lateral, medial, side: str = "r") -> np.ndarray:
    """Seed section 3.1 knee frame from three femoral landmarks, as a (3, 3) rotation.

    Columns are the axes in the input coordinates: Z parallel to the
    epicondyle line pointing to the subject's right, Y in the plane of the
    epicondyles and the trochanter, orthogonal to Z, pointing cranially,
    X = Y x Z pointing anteriorly.
    """
    gt, lfe, mfe = (np.asarray(v, dtype=float).reshape(3) for v in (trochanter, lateral, medial))
    z = (lfe - mfe) if side == "r" else (mfe - lfe)
    nz = np.linalg.norm(z)
    if nz < 1e-6:
        raise InputError(None, "epicondyle landmarks coincide")
    z /= nz
    up = gt - 0.5 * (lfe + mfe)
    y = up - np.dot(up, z) * z
    ny = np.linalg.norm(y)
    if ny < 1e-6:
        raise InputError(None, "trochanter lies on the epicondyle line: knee frame undefined")
    y /= ny
    x = np.cross(y, z)
    return np.column_stack([x, y, z])


@dataclass(frozen=True, eq=False)
class LawTransfer:
    """Result of `transfer_law`.

    Attributes
    ----------
    law : CorrelativeLaw
        The law expressed in the target model's parent frame.
    rotation : ndarray (3, 3)
        ``R = R_target R_source^T``: maps directions of the source law frame to
        the target parent frame; it is the orientation to give the correlative
        joint's frame (its rotation axes) in the target parent body (step 5).
    scale : float
        Eq. (3) factor applied.
    """

    law: CorrelativeLaw
    rotation: np.ndarray
    scale: float


def transfer_law(law: CorrelativeLaw, source_landmarks: Mapping[str, np.ndarray],
                 target_landmarks: Mapping[str, np.ndarray], names: Sequence[str] = ("RGT", "RLFE", "RMFE"),
                 side: str = "r", source_origin=None, target_origin=None) -> LawTransfer:
    """Five-step transfer of a knee law to a model with other segment frames (seed 4.2).

    1-2. three landmarks (trochanter, lateral and medial epicondyle, `names`) on
         the parent body of the source and of the target model, each in that
         model's parent-body frame (metres);
    3.   scale factor ``s`` by eq. (3);
    4.   landmark frames ``R_source``, ``R_target`` (`knee_landmark_frame`);
    5.   composition ``R = R_target R_source^T``; the translations map as::

             T_target = o_target + s R (T_source - o_source)

         so the new slopes are ``s R C`` and the new constant
         ``o_target + s R (c0 - o_source)``.  The origins default to zero: the
         law's translations are measured from the parent-joint origin (the hip
         for the knee, seed 3.2), which is where eq. (3) scales about.

    The dependents must be the three translations (m) along the source frame axes.
    """
    if len(law.dependent) != 3 or any(u != "m" for u in law.dependent_units):
        raise InputError(None, f"law {law.joint!r}: transfer needs three translational dependents (m)")
    gt, lat, med = names
    s = scale_factor(target_landmarks, source_landmarks, gt, lat, med)
    Rs = knee_landmark_frame(source_landmarks[gt], source_landmarks[lat], source_landmarks[med], side)
    Rt = knee_landmark_frame(target_landmarks[gt], target_landmarks[lat], target_landmarks[med], side)
    R = Rt @ Rs.T
    o_s = np.zeros(3) if source_origin is None else np.asarray(source_origin, float)
    o_t = np.zeros(3) if target_origin is None else np.asarray(target_origin, float)
    new = law.transformed(s * R, o_t - s * R @ o_s)
    return LawTransfer(law=new, rotation=R, scale=s)

