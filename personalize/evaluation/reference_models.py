"""Joint centres and axes of reference OpenSim models, for comparison with detections.

Reads both frames of each joint (``hip_r``, ``knee_r``, ``ankle_r``,
``subtalar_r``, ...) of an ``.osim`` model whose bodies are expressed in the
imaging frame (as in the STAPLE data sets: manual and automatic ICL-MRI and
LHDL-CT models): the parent-side frame (``origin``, ``rotation``) and the
child-side frame (``child_origin``, ``child_rotation``), so both are directly
comparable with the joints detected on the bone meshes.  For the hip the
child frame is the femur's; for the knee and ankle it differs from the parent
frame by a turn about the common Z axis.

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

from lowerlimb.errors import InputError

__all__ = ["ReferenceJoint", "read_reference_joints", "compare_joints", "error_rows", "calibrate_model_error", "coverage",
           "CHECKED_FRAMES"]


@dataclass(frozen=True)
class ReferenceJoint:
    """Joint frames of a reference model: origin (m) and rotation (columns X, Y, Z), parent and child side."""

    name: str
    origin: np.ndarray
    rotation: np.ndarray
    child_origin: np.ndarray | None = None
    child_rotation: np.ndarray | None = None

    def side(self, which: str) -> "ReferenceJoint":
        """This joint's ``"parent"`` or ``"child"`` frame as a `ReferenceJoint` (origin, rotation)."""
        if which == "parent" or self.child_origin is None:
            return self
        return ReferenceJoint(self.name, self.child_origin, self.child_rotation)


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
        if loc is not None:                         # OpenSim 3: child frame = location / orientation
            ori = j.find("orientation_in_parent")
            cl, co = j.findtext("location"), j.findtext("orientation")
            child = (_floats(cl), _euler(_floats(co))) if cl is not None and co is not None else (None, None)
            out[name] = ReferenceJoint(name, _floats(loc.text), _euler(_floats(ori.text)), *child)
            continue
        parent_ref, child_ref = j.find("socket_parent_frame"), j.find("socket_child_frame")
        frames = j.find("frames")
        if parent_ref is None or frames is None:
            continue
        got = {}
        for f in frames:
            got[f.attrib.get("name")] = (_floats(f.findtext("translation")), _euler(_floats(f.findtext("orientation"))))
        pname = parent_ref.text.strip()
        cname = child_ref.text.strip() if child_ref is not None and child_ref.text else None
        if pname in got:
            out[name] = ReferenceJoint(name, *got[pname], *(got.get(cname) or (None, None)))
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
        pr = []
        for fr in (j.getParentFrame(), j.getChildFrame()):
            tf = fr.findTransformInBaseFrame()
            pr += [np.array([tf.p().get(k) for k in range(3)]),
                   np.array([[tf.R().get(r, c) for c in range(3)] for r in range(3)])]
        out[j.getName()] = ReferenceJoint(j.getName(), *pr)
    return out


def read_reference_joints(path: str | os.PathLike, *, use_opensim: bool | None = None) -> dict[str, ReferenceJoint]:
    """Parent- and child-side joint frames of an .osim model, in the model's body (imaging) frame.

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
                   line_distance: tuple[str, ...] = ("subtalar",), frame: str = "parent") -> dict[str, dict]:
    """Distances (mm) between joint origins and unsigned angles (deg) between Z axes.

    For joints listed in `line_distance` (revolute joints whose origin along
    the axis is a convention, e.g. the subtalar joint), the distance from the
    reference origin to the detected axis line is reported too.

    Parameters
    ----------
    detected : dict name -> object with ``origin`` (3,) and ``rotation`` (3, 3);
        with ``frame="child"`` a `personalize.frames.Joint` (its ``child``
        frame is used) or a `ReferenceJoint` (its child frame)
    reference : output of `read_reference_joints`
    frame : ``"parent"`` or ``"child"``
        Which side of each joint is compared.  Joints without that frame are left out.
    """
    out = {}
    for name in names or sorted(set(detected) & set(reference)):
        if name not in detected or name not in reference:
            continue
        d, r = detected[name], reference[name]
        if isinstance(r, ReferenceJoint):
            r = r.side(frame)
        if frame == "child":
            if isinstance(d, ReferenceJoint):
                d = d.side("child")
            elif getattr(d, "child", None) is not None:
                d = d.child
            if getattr(d, "origin", None) is None:
                continue
        o = np.asarray(d.origin, float)
        zd, zr = np.asarray(d.rotation)[:, 2], r.rotation[:, 2]
        ang = float(np.degrees(np.arccos(np.clip(abs(zd @ zr), 0.0, 1.0))))
        row = {"distance_mm": float(np.linalg.norm(o - r.origin) * 1e3), "angle_deg": ang}
        if any(name.startswith(k) for k in line_distance):
            v = r.origin - o
            row["line_distance_mm"] = float(np.linalg.norm(v - (v @ zd) * zd) * 1e3)
        out[name] = row
    return out


#: joint frames compared with an expert-built model: (joint, side of the joint)
CHECKED_FRAMES = (("hip", "parent"), ("hip", "child"), ("knee", "parent"), ("ankle", "parent"),
                  ("subtalar", "parent"))


def error_rows(joints: dict, reference: dict[str, ReferenceJoint], side: str = "r") -> list[dict]:
    """Per checked joint frame: error against the reference and the stated uncertainty without its model term.

    Each row: ``joint``, ``frame``, ``kind``, ``centre_error`` (3,) m, ``cov_without_model`` (3, 3) m²,
    ``angle_deg`` (Z axes, unsigned), ``sd_without_model_deg``, ``radius`` (articular, m) and the
    stated ``cov`` / ``sd_deg``.  ``centre_error`` is None for a child frame (same centre).
    """
    rows = []
    for kind, which in CHECKED_FRAMES:
        name = f"{kind}_{side}"
        if name not in joints or name not in reference:
            continue
        j, r = joints[name], reference[name].side(which)
        fr = j.parent if which == "parent" else j.child
        if fr is None or fr.origin is None:
            continue
        me = j.model_error or {"centre_sd_m": 0.0, "axis_sd_deg": 0.0, "articular_radius_m": 0.02}
        sd = float(fr.axis_sd_deg) if fr.axis_sd_deg is not None else float(j.axis_sd_deg)
        zd, zr = np.asarray(fr.rotation)[:, 2], r.rotation[:, 2]
        row = {"joint": name, "frame": which, "kind": kind,
               "angle_deg": float(np.degrees(np.arccos(np.clip(abs(zd @ zr), 0.0, 1.0)))),
               "sd_deg": sd, "sd_without_model_deg": float(np.sqrt(max(sd ** 2 - me["axis_sd_deg"] ** 2, 0.0))),
               "radius": float(me["articular_radius_m"]), "centre_error": None}
        if which == "parent":
            cov = np.asarray(j.origin_cov, float)
            row.update(centre_error=np.asarray(fr.origin, float) - r.origin, cov=cov,
                       cov_without_model=cov - me["centre_sd_m"] ** 2 * np.eye(3))
        rows.append(row)
    return rows


def calibrate_model_error(rows: list[dict]) -> dict:
    r"""Model-error constants from one set's error rows (pooled over its joints).

    Centre: the fraction :math:`k` of the articular radius :math:`R_j` with
    :math:`k^2 = \operatorname{mean}_j \max(0, (|e_j|^2 - \operatorname{tr} C_j) / 3) / R_j^2`
    (the per-component mean square error left unexplained by the fit
    covariance :math:`C_j`).  Axis: :math:`s^2 = \operatorname{mean}_j
    \max(0, \theta_j^2 / 2 - \sigma_j^2)` (deg²; two tilt directions).
    """
    kc = [max(0.0, (float(r["centre_error"] @ r["centre_error"]) - float(np.trace(r["cov_without_model"]))) / 3.0)
          / r["radius"] ** 2 for r in rows if r["centre_error"] is not None]
    sa = [max(0.0, r["angle_deg"] ** 2 / 2.0 - r["sd_without_model_deg"] ** 2) for r in rows]
    return {"centre": float(np.sqrt(np.mean(kc))) if kc else 0.0, "axis_deg": float(np.sqrt(np.mean(sa))) if sa else 0.0}


def coverage(rows: list[dict], model: dict | None = None, k: float = 3.0) -> dict:
    """Which centres and axes lie within ``k`` sd of the reference.

    A centre is covered when its Mahalanobis distance under the stated
    covariance (or, with `model`, the covariance without its model term plus
    ``(model["centre"] R)^2 I``) is at most ``k``; an axis when its angle is at
    most ``k`` times the stated (or re-modelled) sd.

    Returns ``{"covered": n, "total": n, "fraction": f, "rows": [...]}``.
    """
    out = []
    for r in rows:
        sd = r["sd_deg"] if model is None else float(np.hypot(r["sd_without_model_deg"], model["axis_deg"]))
        out.append({"what": f"{r['joint']} {r['frame']} axis", "error": r["angle_deg"], "sd": sd,
                    "ratio": r["angle_deg"] / sd if sd > 0 else np.inf})
        if r["centre_error"] is not None:
            C = r["cov"] if model is None else r["cov_without_model"] + (model["centre"] * r["radius"]) ** 2 * np.eye(3)
            e = r["centre_error"]
            md = float(np.sqrt(e @ np.linalg.solve(C, e)))
            out.append({"what": f"{r['joint']} centre", "error": float(np.linalg.norm(e)) * 1e3,
                        "sd": float(np.sqrt(e @ C @ e / max(e @ e, 1e-30))) * 1e3, "ratio": md})
    n = sum(o["ratio"] <= k for o in out)
    return {"covered": int(n), "total": len(out), "fraction": n / len(out) if out else float("nan"), "rows": out}
