"""Equivalent poses of gait2392 and the personalised model: the same anatomical posture in both coordinate sets.

The two models' joint frames differ (the personalised pelvis is the ISB frame of the bone's ASIS-PSIS plane,
gait2392's is about 19 deg from it; the knee flexion's sign is the opposite of ``knee_angle``'s), so the same
coordinate values are not the same posture.  With the bodies' maps (`bone_registration.BoneMap`, rotation part
``R_b`` = the polar factor of ``A_b``), a generic posture's relative rotation of child ``c`` in parent ``p``,
``R_g(q_g)``, is the subject's ``R_s = R_p R_g(q_g) R_cᵀ``.  Each leg joint's offsets are solved once at the
all-zero generic pose (least squares on the joint's coordinates, `joint_offsets`), and poses are carried as

    q_s = sign q_g + offset          (sign -1 for ``knee_angle`` -> ``knee_flexion``, +1 elsewhere),

the personalised knee's ab/adduction and axial rotation held at their offsets (gait2392's knee has neither).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CoordinateMap", "joint_offsets", "set_pose", "GENERIC_TO_SUBJECT"]

#: generic coordinate base name -> (subject coordinate base name, sign)
GENERIC_TO_SUBJECT = {"hip_flexion": ("hip_flexion", 1.0), "hip_adduction": ("hip_adduction", 1.0),
                      "hip_rotation": ("hip_rotation", 1.0), "knee_angle": ("knee_flexion", -1.0),
                      "ankle_angle": ("ankle_angle", 1.0), "subtalar_angle": ("subtalar_angle", 1.0),
                      "mtp_angle": ("mtp_angle", 1.0)}
_JOINT_BODIES = {"hip": ("pelvis", "femur"), "knee": ("femur", "tibia"), "ankle": ("tibia", "talus"),
                 "subtalar": ("talus", "calcn"), "mtp": ("calcn", "toes")}


@dataclass(frozen=True)
class CoordinateMap:
    """q_s = sign q_g + offset per coordinate; `fixed`: subject coordinates held at a value (rad or m).

    entries : generic coordinate name -> (subject coordinate name, sign, offset rad)
    fixed : subject coordinate name -> value (the knee's ab/adduction and rotation offsets)
    """

    entries: dict
    fixed: dict

    def subject_pose(self, q_generic: dict) -> dict:
        """Subject coordinate values of a generic pose (coordinates not given: their zero-pose equivalents)."""
        out = dict(self.fixed)
        for g, (s, sign, off) in self.entries.items():
            out[s] = sign * float(q_generic.get(g, 0.0)) + off
        return out

    def subject_range(self, generic: str, lo: float, hi: float) -> tuple[str, float, float]:
        """A generic coordinate's interval in the subject's coordinate: (name, lo', hi')."""
        s, sign, off = self.entries[generic]
        a, b = sorted((sign * lo + off, sign * hi + off))
        return s, a, b

    def to_json(self) -> dict:
        return {"q_subject": "sign * q_generic + offset", "units": "rad",
                "coordinates": {g: {"subject": s, "sign": sg, "offset": round(o, 6)}
                                for g, (s, sg, o) in self.entries.items()},
                "held": {k: round(v, 6) for k, v in self.fixed.items()}}


def _couplers(model) -> list:
    """(dependent coordinate, independent coordinate names, opensim Function) of the model's couplers."""
    out = []
    cs = model.getConstraintSet()
    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    for i in range(cs.getSize()):
        c = osim.CoordinateCouplerConstraint.safeDownCast(cs.get(i))
        if c is None:
            continue
        ind = c.getIndependentCoordinateNames()
        out.append((c.getDependentCoordinateName(), [ind.get(k) for k in range(ind.getSize())], c.getFunction()))
    return out


def set_pose(model, state, values: dict, couplers: list | None = None) -> None:
    """Set coordinates (name -> value; the others untouched), then each coupled coordinate from its coupler's
    function, and realise the position stage."""
    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    cs = model.getCoordinateSet()
    for n, v in values.items():
        cs.get(n).setValue(state, float(v), False)
    for dep, ind, f in (couplers if couplers is not None else _couplers(model)):
        x = osim.Vector(len(ind), 0.0)
        for k, n in enumerate(ind):
            x.set(k, cs.get(n).getValue(state))
        cs.get(dep).setValue(state, f.calcValue(x), False)
    model.realizePosition(state)


def _rotation(model, state, parent: str, child: str) -> np.ndarray:
    bs = model.getBodySet()
    X = bs.get(child).findTransformBetween(state, bs.get(parent))
    R = X.R()
    return np.array([[R.get(r, c) for c in range(3)] for r in range(3)])


def _in_parent(generic, parent: str, child: str, x):
    """A child-frame point in the parent's frame at the generic all-zero pose (None stays None)."""
    if x is None:
        return None
    T = np.linalg.solve(generic.poses[parent], generic.poses[child])
    return T[:3, :3] @ np.asarray(x, float) + T[:3, 3]


def joint_offsets(generic, subject_model, maps: dict, sides) -> CoordinateMap:
    """The `CoordinateMap` of the module docstring.

    generic : `personalize.muscles.generic.GenericModel`; subject_model : initialised opensim.Model (personalised);
    maps : body -> `BoneMap`; sides : the sides to map ('r', 'l')
    """
    from scipy.optimize import least_squares

    from .generic import zero_state

    gstate = zero_state(generic.model)
    sstate = zero_state(subject_model)
    couplers = _couplers(subject_model)
    names = {subject_model.getCoordinateSet().get(i).getName()
             for i in range(subject_model.getCoordinateSet().getSize())}
    entries, fixed = {}, {}
    for s in sides:
        for joint, (pb, cb) in _JOINT_BODIES.items():
            p, c = f"{pb}_{s}" if pb != "pelvis" else pb, f"{cb}_{s}"
            if p not in maps or c not in maps:
                continue
            # each map's turn at the joint (a twisted long bone turns by its torsion there)
            at = generic.joint_points[c].get(f"{joint}_{s}")
            Rp, Rc = (maps[b].frame(np.eye(3), at=None if at is None else x)[0]
                      for b, x in ((p, _in_parent(generic, p, c, at)), (c, at)))
            target = Rp @ _rotation(generic.model, gstate, p, c) @ Rc.T
            coords = [n for n in (f"{joint}_flexion_{s}", f"{joint}_adduction_{s}", f"{joint}_rotation_{s}",
                                  f"{joint}_angle_{s}") if n in names]
            if not coords:
                continue

            def res(x):
                set_pose(subject_model, sstate, dict(zip(coords, x)), couplers)
                return (_rotation(subject_model, sstate, p, c) - target).ravel()

            sol = least_squares(res, np.zeros(len(coords)), x_scale=0.1)
            off = dict(zip(coords, sol.x))
            set_pose(subject_model, sstate, {n: 0.0 for n in coords}, couplers)
            for g, (sub, sign) in GENERIC_TO_SUBJECT.items():
                if f"{sub}_{s}" in off:
                    entries[f"{g}_{s}"] = (f"{sub}_{s}", sign, float(off.pop(f"{sub}_{s}")))
            fixed.update({k: float(v) for k, v in off.items()})
    return CoordinateMap(entries, fixed)
