"""The lower-limb topology: joints, the bones they join, their coordinates, names, signs and ranges.

Defined once here and used by every model the project builds (the
personalised model of `personalize.model_builder`, the phantom skeleton of
`phantoms.skeleton`) and by the code that reads their coordinates.

Names and signs are OpenSim gait2392's (``hip_flexion_r``, ``ankle_angle_l``,
...; flexion, adduction, internal rotation, dorsiflexion, inversion and toe
extension positive, on both sides).  One deliberate difference: the knee is a
six-coordinate joint (three rotations ``knee_flexion``, ``knee_adduction``,
``knee_rotation`` and three translations ``knee_tx/ty/tz`` coupled to them),
not gait2392's one ``knee_angle`` (which is NEGATIVE in flexion); the
``knee_flexion`` of these models is positive in flexion, as Plug-in-Gait and
ISB report it.  ``knee_angle`` is listed too, for models read from gait2392 or
STAPLE ``.osim`` files (`phantoms.real_anatomy`).

Ranges (rad, m) are gait2392's wherever gait2392 has the coordinate: read
with the opensim API from ``gait2392_thelen2003muscle.osim`` and
``subject01_simbody_adjusted.osim`` (opensim-org/opensim-models; identical in
both): hip ±120°, knee_angle -120°..10° (so knee_flexion -10°..120°), ankle,
subtalar and mtp ±90°.  The knee's secondary rotations (adduction ±0.6 rad,
rotation ±0.9 rad) and translations (±30 mm) have no gait2392 counterpart;
they bound the coupled laws' range, well outside the few degrees and
millimetres of healthy knees.  The pelvis (free joint placing the subject in
the lab) is unbounded: gait2392's ±90° and metre bounds are for its own lab
and are not clamped there either.  The personalised model
(`personalize.model_builder`) clamps the leg's rotational coordinates to
these ranges (its IK and OpenSim's keep them inside); gait2392 clamps none.

The pelvis coordinates are gait2392's: in OpenSim's ground (X forward, Y up,
Z right) ``pelvis_tilt`` about Z, ``pelvis_list`` about X,
``pelvis_rotation`` about Y (body-fixed, in that order), ``pelvis_tx/ty/tz``
the pelvis origin along X, Y, Z (``pelvis_ty`` its height).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CoordinateDef", "COORDINATES", "JOINTS", "JOINT_BONES", "JOINT_COORDINATES", "KNEE_ROTATIONS", "KNEE_TRANSLATIONS", "PELVIS_ROTATIONS",
           "PELVIS_TRANSLATIONS", "GROUND_JOINT", "sided", "coordinate_def", "leg_coordinates"]

_DEG = np.pi / 180.0


@dataclass(frozen=True)
class CoordinateDef:
    """One generalised coordinate of the lower-limb model, side-free (``stem`` + ``_r``/``_l`` is its name).

    Attributes
    ----------
    stem : str, e.g. ``hip_flexion``
    joint : str, the joint it belongs to without side (``hip``; ``ground_pelvis`` for the pelvis)
    kind : ``rotational`` (rad) or ``translational`` (m)
    range : (lo, hi), rad or m
    positive : what a positive value means (the same on both sides)
    """

    stem: str
    joint: str
    kind: str
    range: tuple[float, float]
    positive: str


_INF = (-np.inf, np.inf)
_G2392_HIP = (-120.0 * _DEG, 120.0 * _DEG)
_G2392_FOOT = (-90.0 * _DEG, 90.0 * _DEG)

#: every coordinate, by stem
COORDINATES: dict[str, CoordinateDef] = {c.stem: c for c in (
    CoordinateDef("pelvis_tilt", "ground_pelvis", "rotational", _INF, "posterior tilt (about ground Z, to the right)"),
    CoordinateDef("pelvis_list", "ground_pelvis", "rotational", _INF, "list: the left side up (about ground X, forward)"),
    CoordinateDef("pelvis_rotation", "ground_pelvis", "rotational", _INF, "rotation towards the left (about ground Y, up)"),
    CoordinateDef("pelvis_tx", "ground_pelvis", "translational", _INF, "pelvis origin along ground X (forward)"),
    CoordinateDef("pelvis_ty", "ground_pelvis", "translational", _INF, "pelvis origin along ground Y (up): the pelvis height"),
    CoordinateDef("pelvis_tz", "ground_pelvis", "translational", _INF, "pelvis origin along ground Z (right)"),
    CoordinateDef("hip_flexion", "hip", "rotational", _G2392_HIP, "flexion"),
    CoordinateDef("hip_adduction", "hip", "rotational", _G2392_HIP, "adduction"),
    CoordinateDef("hip_rotation", "hip", "rotational", _G2392_HIP, "internal rotation"),
    CoordinateDef("knee_flexion", "knee", "rotational", (-10.0 * _DEG, 120.0 * _DEG), "flexion"),
    CoordinateDef("knee_adduction", "knee", "rotational", (-0.6, 0.6), "adduction (varus)"),
    CoordinateDef("knee_rotation", "knee", "rotational", (-0.9, 0.9), "internal rotation of the tibia"),
    CoordinateDef("knee_tx", "knee", "translational", (-0.03, 0.03), "tibia anterior (coupled)"),
    CoordinateDef("knee_ty", "knee", "translational", (-0.03, 0.03), "tibia proximal (coupled)"),
    CoordinateDef("knee_tz", "knee", "translational", (-0.03, 0.03), "tibia lateral (coupled)"),
    CoordinateDef("knee_angle", "knee", "rotational", (-120.0 * _DEG, 10.0 * _DEG), "extension (gait2392: flexion < 0)"),
    CoordinateDef("ankle_angle", "ankle", "rotational", _G2392_FOOT, "dorsiflexion"),
    CoordinateDef("subtalar_angle", "subtalar", "rotational", _G2392_FOOT, "inversion"),
    CoordinateDef("mtp_angle", "mtp", "rotational", _G2392_FOOT, "toe extension (dorsiflexion)"),
)}

#: the joints of one leg, proximal to distal
JOINTS: tuple[str, ...] = ("hip", "knee", "ankle", "subtalar", "mtp")

#: bones each joint joins (parent, child), without side (the pelvis has none)
JOINT_BONES: dict[str, tuple[str, str]] = {
    "hip": ("pelvis", "femur"),
    "knee": ("femur", "tibia"),
    "ankle": ("tibia", "talus"),
    "subtalar": ("talus", "calcn"),
    "mtp": ("calcn", "toes"),
}

#: coordinate stems of each joint of the models this project builds, in the joint's order
JOINT_COORDINATES: dict[str, tuple[str, ...]] = {
    "hip": ("hip_flexion", "hip_adduction", "hip_rotation"),
    "knee": ("knee_flexion", "knee_adduction", "knee_rotation", "knee_tx", "knee_ty", "knee_tz"),
    "ankle": ("ankle_angle",),
    "subtalar": ("subtalar_angle",),
    "mtp": ("mtp_angle",),
}

#: the knee's rotations (independent) and its translations (coupled to them by the knee law)
KNEE_ROTATIONS: tuple[str, ...] = JOINT_COORDINATES["knee"][:3]
KNEE_TRANSLATIONS: tuple[str, ...] = JOINT_COORDINATES["knee"][3:]

#: the ground-pelvis free joint's name and coordinates (gait2392's)
GROUND_JOINT = "ground_pelvis"
PELVIS_ROTATIONS: tuple[str, ...] = ("pelvis_tilt", "pelvis_list", "pelvis_rotation")
PELVIS_TRANSLATIONS: tuple[str, ...] = ("pelvis_tx", "pelvis_ty", "pelvis_tz")


def sided(stem: str, side: str) -> str:
    """Name of a sided joint, coordinate or bone: ``sided("knee_flexion", "r") == "knee_flexion_r"``."""
    if side not in ("r", "l"):
        raise ValueError(f"side must be 'r' or 'l', not {side!r}")
    return f"{stem}_{side}"


def coordinate_def(name: str) -> CoordinateDef:
    """Definition of a coordinate by its name, sided (``ankle_angle_l``) or not (``pelvis_tilt``)."""
    stem = name[:-2] if name.endswith(("_r", "_l")) else name
    try:
        return COORDINATES[stem]
    except KeyError:
        raise KeyError(f"{name!r} is not a lower-limb coordinate") from None


def leg_coordinates(side: str, joints: tuple[str, ...] = JOINTS) -> list[tuple[str, CoordinateDef]]:
    """(name, definition) of every coordinate of the given joints of one leg, proximal to distal."""
    return [(sided(c, side), COORDINATES[c]) for j in joints for c in JOINT_COORDINATES[j]]
