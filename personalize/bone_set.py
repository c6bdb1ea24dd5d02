"""Landmarks and joints of a set of bone surfaces: the stage ``personalize bones`` and ``personalize run`` share.

`analyse_bones` takes bone surfaces (`personalize.surfaces.load_bones` or
`surfaces_from_labels`), detects every bone's landmarks
(`personalize.landmarks.detect_landmarks`), refuses a bone whose shape
contradicts its name or side unless ``trust_names`` (bones reconstructed from
point clouds are only flagged), adds a point-cloud bone's sampling sd to its
landmark covariances (`personalize.io.point_clouds.add_sampling_uncertainty`)
and builds the joint frames (`personalize.frames.joints_from_landmarks`).  The
result, a `BoneSet`, is what later stages read; `write_bone_files` is the one
writer of ``landmarks.json``, ``joints.json`` and ``fits.json`` (all in the
input's frame, metres).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from lowerlimb.atomic import inside, write_text
from lowerlimb.errors import InputError

from .frames import Joint, joints_document, joints_from_landmarks
from .landmarks import LandmarkSet

__all__ = ["BoneSet", "analyse_bones", "write_bone_files", "read_bone_set"]


@dataclass
class BoneSet:
    """Bone surfaces with their landmarks and joints, input frame (m).

    input : the bone images (label volume or mesh folder) as given
    surfaces : bone -> `personalize.surfaces.BoneSurface` (a `BoneSurfaces` with ``rejected`` and ``notes``)
    landmarks : `LandmarkSet`; joints : joint name -> `personalize.frames.Joint`
    dropped : joint name -> why it could not be built
    """

    input: str
    surfaces: dict
    landmarks: LandmarkSet
    joints: dict[str, Joint]
    dropped: dict[str, str]

    def landmarks_json(self) -> dict:
        """The ``landmarks.json`` document: per bone landmarks, axes, scalars, frames, flags; the inputs read."""
        doc = self.landmarks.to_json()
        doc["input"] = self.input
        doc["missing_bones"] = list(self.landmarks.missing)
        doc["input_notes"] = list(getattr(self.surfaces, "notes", []))
        doc["inputs"] = {b: {"source": s.source, "repairs": list(s.report.get("repairs", [])),
                             **{k: s.report[k] for k in ("whole_foot", "fibula_split") if k in s.report}}
                         for b, s in self.surfaces.items()}
        return doc

    def joints_json(self) -> dict:
        """The ``joints.json`` document (`personalize.frames.joints_document`)."""
        return joints_document(self.joints, self.dropped, input=self.input)


def analyse_bones(surfaces: dict, *, input: str | Path, trust_names: bool = False,
                  progress: Callable[[str], None] | None = None) -> BoneSet:
    """Landmarks and joints of `surfaces` (see the module docstring).

    Raises
    ------
    InputError : no recognisable bone; a bone whose shape says it is another bone or the
        other side (unless `trust_names`)
    """
    from .io.point_clouds import add_sampling_uncertainty
    from .landmarks import detect_landmarks

    if not surfaces:
        raise InputError(input, "no recognisable bone surfaces")
    ls = detect_landmarks(surfaces, progress=progress, trust_names=True)
    _check_names(ls, surfaces, trust_names)
    add_sampling_uncertainty(ls, surfaces)
    joints, dropped = joints_from_landmarks(ls)
    _refuse_cloud_plantar_mtp(ls, surfaces, joints, dropped)
    rejected = dict(getattr(surfaces, "rejected", {}))
    for b, why in rejected.items():
        ls.rejected.setdefault(b, why)
    for j, why in dropped.items():
        bad = [b for b in rejected if b in why]
        if bad:
            dropped[j] = why + "; " + "; ".join(f"{b} left out ({rejected[b]})" for b in bad)
    return BoneSet(str(input), surfaces, ls, joints, dropped)


def _refuse_cloud_plantar_mtp(ls: LandmarkSet, surfaces, joints: dict, dropped: dict) -> None:
    """Drop an mtp taken from the plantar metatarsal head spheres of a forefoot reconstructed from points.

    The reconstruction bridges the metatarsal heads (0-3 mm apart), so no head's articular surface is found and
    the plantar spheres sit on the bridges: ICL-MRI's forefoot sampled at 20 % gave an axis 30 deg from its
    mesh's (4.4 stated sd).  Downstream the mtp then takes the toe marker's default axis, named as such.
    """
    from .landmarks.foot import plantar_mtp_reason

    cloud = _cloud_bones(surfaces)
    for s in ("r", "l"):
        cal, j = f"calcn_{s}", f"mtp_{s}"
        if j in joints and cal in cloud and plantar_mtp_reason(ls.bones[cal]) is not None:
            del joints[j]
            dropped[j] = (f"{cal} is reconstructed from points and no metatarsal head articular surface was found "
                          "against the toes: the plantar head spheres of a reconstructed forefoot are not vouched for")


def _cloud_bones(surfaces) -> set[str]:
    """The bones whose surface was reconstructed from a point cloud."""
    return {b for b, s in surfaces.items() if s.report.get("input") == "point cloud"}


def _check_names(ls: LandmarkSet, surfaces, trust_names: bool) -> None:
    """Refuse (unless `trust_names`) a bone whose shape says it is another bone or the other side.

    Bones reconstructed from point clouds are only flagged: the smoothed
    surface can round an articular end enough to pass for a femoral head (the
    ICL tibia sampled at 20-50 % of its vertices does), so their shape is no
    proof against the name.
    """
    from .landmarks import _refuse_names as refuse
    from .landmarks import name_problems

    cloud = _cloud_bones(surfaces)
    for b, why in name_problems(ls).items():
        if b in cloud:
            ls.bones[b].notes.append(f"{b}: not refused ({why}): its surface is reconstructed from points; "
                                     "check the name")
    if not trust_names:
        refuse(LandmarkSet(bones={k: v for k, v in ls.bones.items() if k not in cloud}), surfaces)


def write_bone_files(stage: Path, bs: BoneSet, *, fits: bool = True, pictures: bool = False) -> None:
    """``landmarks.json``, ``joints.json`` (and ``fits.json``; ``<bone>.png`` with `pictures`) into `stage`."""
    write_text(inside(stage, "landmarks.json"), json.dumps(bs.landmarks_json(), indent=1) + "\n")
    write_text(inside(stage, "joints.json"), json.dumps(bs.joints_json(), indent=1) + "\n")
    if fits:
        write_text(inside(stage, "fits.json"), json.dumps(bs.landmarks.fits_json(), indent=1) + "\n")
    if pictures:
        from .landmarks.plot import plot_bone

        for name, res in bs.landmarks.bones.items():
            s = bs.surfaces.get(name)
            if s is not None:
                plot_bone(s.mesh if hasattr(s, "mesh") else s, res, inside(stage, f"{name}.png"))


def read_bone_set(input: str | Path, label_map: str | Path | None = None, *, trust_names: bool = False,
                  progress: Callable[[str], None] | None = None,
                  status: Callable[[str], None] | None = None) -> BoneSet:
    """`analyse_bones` of the surfaces read from a label volume or a mesh folder (`personalize.surfaces.load_bones`).

    `progress` is told ``"surface <bone>"`` then ``"landmarks <bone>"`` (two steps per bone); `status`
    what a long bone read is doing (`load_bones`).  Point clouds of the surfaces are not sampled: no stage
    here reads them."""
    from .surfaces import load_bones

    say = progress or (lambda m: None)
    surfaces = load_bones(input, label_map, eager_points=False, progress=lambda b: say(f"surface {b}"),
                          status=status)
    return analyse_bones(surfaces, input=input, trust_names=trust_names, progress=lambda b: say(f"landmarks {b}"))
