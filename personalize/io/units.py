"""Bone sizes that are plausible, and the unit (m or mm) a bone file's size implies.

Unit detection compares each bone's largest bounding-box extent with an
anatomically plausible range (`PLAUSIBLE_EXTENT_M`).  The ranges are wide (a
factor >= 5 between bounds, children to large adults) yet much narrower than
the factor 1000 between millimetres and metres, so the decision is never
ambiguous; a size plausible in neither unit is refused.
"""
from __future__ import annotations

import os

from lowerlimb.errors import InputError

__all__ = ["PLAUSIBLE_EXTENT_M", "UNIT_SCALE", "detect_mesh_unit", "unit_candidates"]

#: plausible largest bounding-box extent (metres) of each bone type, (low, high);
#: wide enough for children and for the real STAPLE meshes (whose ``tibia`` may
#: include the fibula and whose ``calcn`` includes the mid-foot bones)
PLAUSIBLE_EXTENT_M: dict[str, tuple[float, float]] = {
    "pelvis": (0.08, 0.50),
    "femur": (0.12, 0.75),
    "tibia": (0.10, 0.65),
    "fibula": (0.10, 0.60),
    "patella": (0.015, 0.10),
    "talus": (0.02, 0.12),
    "calcn": (0.03, 0.30),
    "toes": (0.015, 0.20),
}

#: metres per unit of a file's coordinates
UNIT_SCALE = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "cm": 1e-2}


def _bone_type(bone: str) -> str:
    return bone[:-2] if bone.endswith(("_r", "_l")) else bone


def detect_mesh_unit(bone: str, extent: float, source: str | os.PathLike) -> str:
    """Decide whether a bone mesh is in metres or millimetres from its size.

    Parameters
    ----------
    bone : str
        Canonical bone name (the type sets the plausible range).
    extent : float
        Largest bounding-box extent in the file's units.
    source : path-like
        File named in the error.

    Returns
    -------
    str
        "m" or "mm".

    Raises
    ------
    InputError
        If the size is plausible in neither unit.
    """
    lo, hi = PLAUSIBLE_EXTENT_M[_bone_type(bone)]
    if lo <= extent <= hi:
        return "m"
    if lo <= extent * 1e-3 <= hi:
        return "mm"
    raise InputError(source, f"implausible size for a {bone}: largest extent {extent:.4g} is neither "
                     f"{lo:g}-{hi:g} m nor {lo * 1e3:g}-{hi * 1e3:g} mm; check the units")


def unit_candidates(bone: str, extent: float) -> list[str]:
    lo, hi = PLAUSIBLE_EXTENT_M[_bone_type(bone)]
    return [u for u, k in (("mm", 1e-3), ("m", 1.0)) if lo <= extent * k <= hi]
