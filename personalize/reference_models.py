"""Joint centres and axes of reference OpenSim models, for comparison with detections.

Reads the parent-side joint frame of each joint (``hip_r``, ``knee_r``,
``ankle_r``, ``subtalar_r``, ...) of an ``.osim`` model whose bodies are
expressed in the imaging frame (as in the STAPLE data sets: manual and
automatic ICL-MRI models), so the frame's origin and Z axis are directly
comparable with the joints detected on the bone meshes.

OpenSim 3 files (``location_in_parent`` / ``orientation_in_parent``) and
OpenSim 4 files (``PhysicalOffsetFrame`` translation / orientation) are read
through the ``opensim`` API when it is importable (it converts v3 files),
otherwise parsed with ``defusedxml``.  Orientations are body-fixed XYZ Euler
angles (radians).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.errors import InputError

__all__ = ["ReferenceJoint", "read_reference_joints", "compare_joints"]


@dataclass(frozen=True)
class ReferenceJoint:
    """Joint frame of a reference model: origin (m) and rotation (columns X, Y, Z)."""

    name: str
    origin: np.ndarray
    rotation: np.ndarray


def _euler(v) -> np.ndarray:
    return Rotation.from_euler("XYZ", np.asarray(v, float)).as_matrix()


def _floats(text: str | None) -> np.ndarray:
    return np.array([float(x) for x in (text or "").split()], float)


def _read_xml(path: Path) -> dict[str, ReferenceJoint]:
    import defusedxml.ElementTree as ET

    root = ET.parse(str(path)).getroot()
    out: dict[str, ReferenceJoint] = {}
    for j in root.iter():
        tag = j.tag.split("}")[-1]
        if not tag.endswith("Joint") or "name" not in j.attrib or tag in ("JointSet",):
            continue
        name = j.attrib["name"]
        loc = j.find("location_in_parent")
        if loc is not None:                         # OpenSim 3
            ori = j.find("orientation_in_parent")
            out[name] = ReferenceJoint(name, _floats(loc.text), _euler(_floats(ori.text)))
            continue
        parent_ref = j.find("socket_parent_frame")
        frames = j.find("frames")
        if parent_ref is None or frames is None:
            continue
        pname = parent_ref.text.strip()
        for f in frames:
            if f.attrib.get("name") == pname:
                t = _floats(f.findtext("translation"))
                o = _floats(f.findtext("orientation"))
                out[name] = ReferenceJoint(name, t, _euler(o))
    return out


def _read_opensim(path: Path) -> dict[str, ReferenceJoint]:
    import opensim as osim

    try:  # the model's mesh files are not needed: keep OpenSim's warnings quiet
        osim.Logger.setLevelString("error")
    except AttributeError:  # pragma: no cover - older bindings
        pass
    model = osim.Model(str(path))
    model.initSystem()
    out = {}
    js = model.getJointSet()
    for i in range(js.getSize()):
        j = js.get(i)
        tf = j.getParentFrame().findTransformInBaseFrame()
        p = np.array([tf.p().get(k) for k in range(3)])
        R = np.array([[tf.R().get(r, c) for c in range(3)] for r in range(3)])
        out[j.getName()] = ReferenceJoint(j.getName(), p, R)
    return out


def read_reference_joints(path: str | os.PathLike, *, use_opensim: bool | None = None) -> dict[str, ReferenceJoint]:
    """Parent-side joint frames of an .osim model, in the model's body (imaging) frame.

    Raises
    ------
    InputError
        If the file is missing or is not a readable OpenSim model.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "reference model not found")
    if use_opensim is None:
        try:
            import opensim  # noqa: F401
            use_opensim = True
        except ImportError:
            use_opensim = False
    try:
        return _read_opensim(p) if use_opensim else _read_xml(p)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - opensim raises generic RuntimeErrors
        raise InputError(p, f"not a readable OpenSim model ({type(exc).__name__}: {exc})") from None


def compare_joints(detected: dict, reference: dict[str, ReferenceJoint], names=None,
                   line_distance: tuple[str, ...] = ("subtalar",)) -> dict[str, dict]:
    """Distances (mm) between joint origins and unsigned angles (deg) between Z axes.

    For joints listed in `line_distance` (revolute joints whose origin along
    the axis is a convention, e.g. the subtalar joint), the distance from the
    reference origin to the detected axis line is reported too.

    Parameters
    ----------
    detected : dict name -> object with ``origin`` (3,) and ``rotation`` (3, 3)
    reference : output of `read_reference_joints`
    """
    out = {}
    for name in names or sorted(set(detected) & set(reference)):
        if name not in detected or name not in reference:
            continue
        d, r = detected[name], reference[name]
        o = np.asarray(d.origin, float)
        zd, zr = np.asarray(d.rotation)[:, 2], r.rotation[:, 2]
        ang = float(np.degrees(np.arccos(np.clip(abs(zd @ zr), 0.0, 1.0))))
        row = {"distance_mm": float(np.linalg.norm(o - r.origin) * 1e3), "angle_deg": ang}
        if any(name.startswith(k) for k in line_distance):
            v = r.origin - o
            row["line_distance_mm"] = float(np.linalg.norm(v - (v @ zd) * zd) * 1e3)
        out[name] = row
    return out
