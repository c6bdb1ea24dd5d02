"""Joint frames from bone landmarks (OpenSim / STAPLE conventions).

Every joint frame is a rotation whose columns are the X, Y, Z axes in the
input frame; Z is the joint's main rotation axis:

============  ===========================================  =================================
joint         origin                                       Z (main axis) / Y hint
============  ===========================================  =================================
hip           femoral head centre                          pelvis ISB frame (Z = LASI->RASI)
knee          point of the condyle cylinder axis between   cylinder through the posterior
              the condyles (condyle centres' midpoint      condyles, to the right
              projected on it)                             / Y towards the hip centre
ankle         talar dome cylinder centre (mid-dome)        talar dome axis, to the right
                                                           / Y towards the knee centre
subtalar      posterior talocalcaneal facet centre (on     subtalar axis, anterior
              the axis; else the axis point closest to     / Y = foot superior
              the ankle)
mtp           midpoint of the 1st and 5th metatarsal       1st -> 5th head line, to the right
              head centres                                 / Y = foot superior
============  ===========================================  =================================

``frame_zy(z, y)`` keeps Z exactly and makes Y orthogonal to it
(``X = Y x Z``), as the phantom truth does, so outputs and truth compare
axis by axis.  Uncertainty: ``origin_cov`` is the covariance of the origin
landmark; ``axis_sd_deg`` the 1-sd angle of the Z axis.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Joint", "frame_zy", "frame_yz", "closest_on_line", "joints_from_landmarks", "JOINT_NAMES",
           "JOINT_BONES"]

JOINT_NAMES = ("hip", "knee", "ankle", "subtalar", "mtp")

#: bones each joint needs (parent, child), per side
JOINT_BONES = {
    "hip": ("pelvis", "femur"),
    "knee": ("femur", "tibia"),
    "ankle": ("tibia", "talus"),
    "subtalar": ("talus", "calcn"),
    "mtp": ("calcn", "toes"),
}


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def frame_zy(z, y_hint) -> np.ndarray:
    """Rotation with columns X, Y, Z: Z = unit(z), Y = y_hint made orthogonal to Z, X = Y x Z."""
    Z = _unit(z)
    Y = _unit(np.asarray(y_hint, float) - (np.asarray(y_hint, float) @ Z) * Z)
    return np.column_stack([np.cross(Y, Z), Y, Z])


def frame_yz(y, z_hint) -> np.ndarray:
    """Rotation with columns X, Y, Z: Y = unit(y), Z = z_hint made orthogonal to Y, X = Y x Z."""
    Y = _unit(y)
    Z = _unit(np.asarray(z_hint, float) - (np.asarray(z_hint, float) @ Y) * Y)
    return np.column_stack([np.cross(Y, Z), Y, Z])


def closest_on_line(point, direction, q) -> np.ndarray:
    """Point of the line (point, direction) closest to ``q``."""
    d = _unit(direction)
    return np.asarray(point, float) + float((np.asarray(q, float) - point) @ d) * d


@dataclass(frozen=True)
class Joint:
    """A joint frame in the input frame (metres)."""

    name: str
    origin: np.ndarray
    origin_cov: np.ndarray
    rotation: np.ndarray
    axis_sd_deg: float
    flags: tuple = ()

    def to_json(self) -> dict:
        return {"origin": np.round(self.origin, 9).tolist(), "origin_cov": np.round(self.origin_cov, 12).tolist(),
                "rotation": np.round(self.rotation, 9).tolist(), "axis_sd_deg": round(float(self.axis_sd_deg), 6),
                "flags": list(self.flags)}


def _flags(*bones) -> tuple:
    out = []
    for b in bones:
        if b is None:
            continue
        for f in b.flags:
            if f not in out:
                out.append(f)
    return tuple(out)


def joints_from_landmarks(ls) -> tuple[dict[str, Joint], dict[str, str]]:
    """Joint frames from a `personalize.landmarks.LandmarkSet`.

    Returns
    -------
    joints : dict[str, Joint]
        ``hip_r``, ``knee_r``, ... for every joint whose bones and landmarks
        were found.
    dropped : dict[str, str]
        Joint name -> reason, for every joint that could not be built.
    """
    B = ls.bones
    joints: dict[str, Joint] = {}
    dropped: dict[str, str] = {}

    def need(jname, *keys):
        miss = [k for k in keys if k not in B]
        if miss:
            dropped[jname] = "missing bone(s): " + ", ".join(miss)
            return False
        return True

    pel = B.get("pelvis")
    present = {b[-1] for b in B if b[-2:] in ("_r", "_l")}
    for s in ("r", "l"):
        if s not in present:
            continue                               # no bone of that leg at all: nothing to report
        fem, tib, tal, cal, toe = (B.get(f"{b}_{s}") for b in ("femur", "tibia", "talus", "calcn", "toes"))
        # ---- hip
        j = f"hip_{s}"
        if need(j, "pelvis", f"femur_{s}"):
            if "femoral_head_centre" not in fem.landmarks or "isb" not in pel.frames:
                dropped[j] = "femoral head or pelvic frame not detected"
            else:
                hc = fem.landmarks["femoral_head_centre"]
                R = pel.frames["isb"]["rotation"]
                asis = [pel.landmarks[k] for k in ("RASI", "LASI") if k in pel.landmarks]
                w = np.linalg.norm(asis[0].position - asis[1].position) if len(asis) == 2 else 0.2
                sd = np.degrees(np.sqrt(sum(np.trace(a.cov) / 3 for a in asis)) / w) if asis else float("nan")
                joints[j] = Joint(j, hc.position.copy(), hc.cov.copy(), R.copy(), float(sd), _flags(pel, fem))
        # ---- knee
        j = f"knee_{s}"
        if need(j, f"femur_{s}", f"tibia_{s}"):
            if "intercondylar_midpoint" not in fem.landmarks or "knee_axis" not in fem.axes:
                dropped[j] = "femoral condyles not detected"
            else:
                kc = fem.landmarks["intercondylar_midpoint"]
                ax = fem.axes["knee_axis"]
                if "femoral_head_centre" in fem.landmarks:
                    yh = fem.landmarks["femoral_head_centre"].position - kc.position
                else:
                    yh = fem.axes["shaft_axis"].direction
                joints[j] = Joint(j, kc.position.copy(), kc.cov.copy(), frame_zy(ax.direction, yh), ax.sd_deg,
                                  _flags(fem, tib))
        # ---- ankle
        j = f"ankle_{s}"
        if need(j, f"tibia_{s}", f"talus_{s}"):
            if "talar_dome_centre" not in tal.landmarks:
                dropped[j] = "talar dome not detected"
            else:
                ac = tal.landmarks["talar_dome_centre"]
                ax = tal.axes["ankle_axis"]
                if fem is not None and "intercondylar_midpoint" in fem.landmarks:
                    yh = fem.landmarks["intercondylar_midpoint"].position - ac.position
                elif "plateau_centre" in tib.landmarks:
                    yh = tib.landmarks["plateau_centre"].position - ac.position
                else:
                    yh = tib.axes["shaft_axis"].direction
                joints[j] = Joint(j, ac.position.copy(), ac.cov.copy(), frame_zy(ax.direction, yh), ax.sd_deg,
                                  _flags(tib, tal))
        # ---- subtalar
        j = f"subtalar_{s}"
        if need(j, f"talus_{s}", f"calcn_{s}"):
            if "subtalar_axis" not in tal.axes or "talar_dome_centre" not in tal.landmarks:
                dropped[j] = "subtalar axis not detected"
            else:
                ax = tal.axes["subtalar_axis"]
                # the posterior facet is the subtalar joint's main articulation; its sphere centre lies on the
                # axis (which runs through it), as the hand-built ICL-MRI model places the joint
                pf = tal.landmarks.get("posterior_facet_centre")
                if pf is not None:
                    o, cov = closest_on_line(ax.point, ax.direction, pf.position), pf.cov
                else:
                    ac = tal.landmarks["talar_dome_centre"]
                    o, cov = closest_on_line(ax.point, ax.direction, ac.position), ac.cov
                up = cal.frames["foot"]["rotation"][:, 1] if "foot" in cal.frames else tal.frames["anatomical"]["rotation"][:, 1]
                joints[j] = Joint(j, o, cov.copy(), frame_zy(ax.direction, up), ax.sd_deg, _flags(tal, cal))
        # ---- mtp
        j = f"mtp_{s}"
        if need(j, f"calcn_{s}", f"toes_{s}"):
            ax = cal.axes.get("mtp_axis") or toe.axes.get("mtp_axis")
            if ax is None or "foot" not in cal.frames:
                dropped[j] = "metatarsal heads not detected"
            else:
                m1 = cal.landmarks.get("met1_head_centre")
                m5 = cal.landmarks.get("met5_head_centre")
                cov = 0.25 * (m1.cov + m5.cov) if m1 is not None and m5 is not None else (0.002 ** 2) * np.eye(3)
                joints[j] = Joint(j, np.asarray(ax.point, float).copy(), cov,
                                  frame_zy(ax.direction, cal.frames["foot"]["rotation"][:, 1]), ax.sd_deg,
                                  _flags(cal, toe))
    return joints, dropped
