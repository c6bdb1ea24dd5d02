"""Bone names, sides and the default label map.

Names follow the STAPLE / OpenSim convention used by the real data in
``shared/data/bones``: ``pelvis``, ``femur_r``, ``tibia_r``, ``fibula_r``,
``patella_r``, ``talus_r``, ``calcn_r``, ``toes_r`` and the ``_l`` twins.
"""
from __future__ import annotations

SIDED_BONES: tuple[str, ...] = ("femur", "patella", "tibia", "fibula", "talus", "calcn", "toes")
SIDES: tuple[str, ...] = ("r", "l")

#: every bone the project knows, in proximal-to-distal order
BONE_NAMES: tuple[str, ...] = ("pelvis",) + tuple(f"{b}_{s}" for s in SIDES for b in SIDED_BONES)

#: aliases accepted for input files (mesh folders, label maps) -> canonical name
ALIASES: dict[str, str] = {
    "pelvis_no_sacrum": "pelvis",
    "hip": "pelvis",
    "calcaneus_r": "calcn_r",
    "calcaneus_l": "calcn_l",
    "foot_r": "calcn_r",
    "foot_l": "calcn_l",
    "tibia_no_fib_r": "tibia_r",
    "tibia_no_fib_l": "tibia_l",
}

#: file stems of a whole foot in one mesh (tarsals, metatarsals, phalanges), side; a mesh folder's reader
#: splits it into talus, calcn and toes (`personalize.io.whole_foot`); a label map's ``foot_r`` is the calcn
WHOLE_FOOT: dict[str, str] = {"foot_r": "r", "foot_l": "l"}

#: when several files name one bone, the stem read (the others are listed as ignored): the hip bones without
#: the sacrum (what the pelvis detector expects), the tibia with its fibula (the fibula's lateral malleolus
#: gives the tibial ISB frame); any other stem comes after these
PREFERRED_STEMS: tuple[str, ...] = ("pelvis_no_sacrum", "tibia_r", "tibia_l")

#: default integer label of each bone in a label volume (0 is background)
DEFAULT_LABEL_MAP: dict[str, int] = {name: i + 1 for i, name in enumerate(BONE_NAMES)}


#: name of the non-bone label of a label volume: the whole soft-tissue envelope (everything inside the skin
#: that is not bone), used to measure the skin-to-bone distance under the markers (`personalize.skin`)
TISSUE_LABEL_NAME = "skin"
#: accepted label-map keys for it
TISSUE_ALIASES: tuple[str, ...] = ("skin", "body", "soft_tissue")
#: label the phantoms give it (after the bones)
DEFAULT_TISSUE_LABEL = len(BONE_NAMES) + 1


def is_tissue_name(name: str) -> bool:
    """True for a label-map key naming the body/skin envelope (``skin``, ``body``, ``soft_tissue``)."""
    return name.strip().lower().replace("-", "_").replace(" ", "_") in TISSUE_ALIASES


def canonical_bone_name(name: str) -> str | None:
    """Canonical bone name for a file stem or label-map key, or None if unknown."""
    key = name.strip().lower().replace("-", "_").replace(" ", "_")
    if key in BONE_NAMES:
        return key
    return ALIASES.get(key)


def side_of(bone: str) -> str | None:
    """'r', 'l' or None (pelvis) for a canonical bone name."""
    return bone[-1] if bone.endswith(("_r", "_l")) else None


def mirror_name(name: str) -> str:
    """Name of the contralateral bone, landmark or coordinate (``femur_r`` <-> ``femur_l``, ``RASI`` <-> ``LASI``)."""
    if name.endswith("_r"):
        return name[:-2] + "_l"
    if name.endswith("_l"):
        return name[:-2] + "_r"
    if name[:1] == "R" and name[1:2].isupper():
        return "L" + name[1:]
    if name[:1] == "L" and name[1:2].isupper():
        return "R" + name[1:]
    return name
