"""Joint frames from bone landmarks (OpenSim / STAPLE conventions).

Every joint has two frames, as an OpenSim joint has them: the ``parent``
frame fixed in the proximal body and the ``child`` frame fixed in the distal
body, both given in the input frame (rotation columns X, Y, Z; Z the joint's
main rotation axis).  They coincide in the reference pose except for the hip
(pelvis ISB frame / femur frame) and for a turn about Z at the knee and
ankle (each body's own Y):

============  ===========================================  =================================
joint         origin                                       Z (main axis) / Y hint
============  ===========================================  =================================
hip           femoral head centre (cross-checked with the  parent: pelvis ISB frame
              acetabulum sphere)                           (Z = LASI->RASI); child: femur,
                                                           Y knee -> hip centre, Z knee axis
knee          point of the knee axis between the condyles  knee axis (cross-checked
              (cross-checked estimates, `femur`)           estimates), to the right
                                                           / parent Y towards the hip centre,
                                                           child Y along the tibia (ankle ->
                                                           knee)
ankle         talar dome cylinder centre (mid-dome)        talar dome axis, to the right
                                                           / parent Y towards the knee centre,
                                                           child Y the talus's superior
subtalar      posterior talocalcaneal facet centre (on     subtalar axis, anterior
              the axis; else the axis point closest to     / Y = foot superior (both)
              the ankle)
mtp           midpoint of the 1st and 5th metatarsal       1st -> 5th head line, to the right
              head centres                                 / Y = foot superior (both)
============  ===========================================  =================================

``origin`` / ``rotation`` of a `Joint` are its parent frame (the hip's
pelvis-side frame), kept for existing readers; without a pelvis the hip is
given from the femoral head alone: its child (femur) frame, the parent frame
marked missing.

``frame_zy(z, y)`` keeps Z exactly and makes Y orthogonal to it
(``X = Y x Z``), as the phantom truth does, so outputs and truth compare
axis by axis.

Uncertainty: ``origin_cov`` is the covariance of the joint centre and
``axis_sd_deg`` the 1-sd angle of the Z axis, each the sum of three terms:
the fit (``origin_cov_detection``, ``axis_sd_detection_deg``), the spread of
independent estimates that disagreed (`personalize.landmarks.crosscheck`),
and a model-error term (`MODEL_ERROR`): how far a detected joint lies from an
expert's hand-built one on real bones.  `joints_document` is the one writer of
``joints.json``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lowerlimb.estimates import Gaussian
from lowerlimb.geometry import frame_yz, frame_zy, orient, unit

__all__ = ["Joint", "JointFrame", "closest_on_line", "joints_from_landmarks", "MODEL_ERROR", "joints_document",
           "JOINTS_CONVENTION"]


def closest_on_line(point, direction, q) -> np.ndarray:
    """Point of the line (point, direction) closest to ``q``."""
    d = unit(direction)
    return np.asarray(point, float) + float((np.asarray(q, float) - point) @ d) * d


@dataclass(frozen=True)
class JointFrame:
    """One side's frame of a joint: the body it is fixed in, origin (m) and rotation, input frame.

    ``missing`` says why the frame is not given (origin and rotation None);
    ``axis_sd_deg`` the 1-sd angle of this frame's Z axis when it differs from
    the joint's (the hip's femur frame).
    """

    body: str
    origin: np.ndarray | None = None
    rotation: np.ndarray | None = None
    missing: str | None = None
    axis_sd_deg: float | None = None

    def to_json(self) -> dict:
        if self.origin is None:
            return {"body": self.body, "missing": self.missing or "not detected"}
        out = {"body": self.body, "origin": np.round(self.origin, 9).tolist(),
               "rotation": np.round(self.rotation, 9).tolist()}
        if self.axis_sd_deg is not None:
            out["axis_sd_deg"] = round(float(self.axis_sd_deg), 6)
        return out

    @classmethod
    def from_json(cls, d: dict) -> "JointFrame":
        if "origin" not in d:
            return cls(d["body"], missing=d.get("missing"))
        return cls(d["body"], np.asarray(d["origin"], float), np.asarray(d["rotation"], float),
                   axis_sd_deg=d.get("axis_sd_deg"))


@dataclass(frozen=True)
class Joint:
    """A joint in the input frame (metres): centre, main axis, both frames, uncertainty.

    ``origin`` / ``rotation``: the parent frame (the child frame when the
    parent body is missing); ``origin_cov`` (m²) and ``axis_sd_deg`` the
    stated uncertainty (fit + spread + model error), ``origin_cov_detection``
    and ``axis_sd_detection_deg`` the fit alone; ``cross_check`` how the
    independent estimates agreed; ``model_error`` the model-error term used.
    """

    name: str
    origin: np.ndarray
    origin_cov: np.ndarray
    rotation: np.ndarray
    axis_sd_deg: float
    flags: tuple = ()
    parent: JointFrame | None = None
    child: JointFrame | None = None
    origin_cov_detection: np.ndarray | None = None
    axis_sd_detection_deg: float | None = None
    cross_check: dict | None = None
    model_error: dict | None = None

    @property
    def centre(self) -> Gaussian:
        """The joint centre and its stated covariance (input frame, m, m²)."""
        return Gaussian(self.origin, self.origin_cov)

    @property
    def axis(self) -> np.ndarray:
        """(3,) main rotation axis: the Z column of `rotation`."""
        return np.asarray(self.rotation, float)[:, 2]

    def without_model_error(self) -> "Joint":
        """This joint with the model-error term taken out of ``origin_cov`` and ``axis_sd_deg``.

        For consumers whose covariance scales were calibrated on phantoms, where
        the detectors' conventions and the truth's coincide (`personalize.pipeline`):
        the fit and the spread of disagreeing estimates stay in.
        """
        me = self.model_error
        if not me:
            return self
        return replace(self, origin_cov=np.asarray(self.origin_cov, float) - me["centre_sd_m"] ** 2 * np.eye(3),
                       axis_sd_deg=float(np.sqrt(max(float(self.axis_sd_deg) ** 2 - me["axis_sd_deg"] ** 2, 0.0))))

    def to_json(self) -> dict:
        out = {"origin": np.round(self.origin, 9).tolist(), "origin_cov": np.round(self.origin_cov, 12).tolist(),
               "rotation": np.round(self.rotation, 9).tolist(), "axis_sd_deg": round(float(self.axis_sd_deg), 6),
               "flags": list(self.flags)}
        if self.parent is not None:
            out["parent"] = self.parent.to_json()
        if self.child is not None:
            out["child"] = self.child.to_json()
        if self.origin_cov_detection is not None:
            out["origin_cov_detection"] = np.round(self.origin_cov_detection, 12).tolist()
            out["axis_sd_detection_deg"] = round(float(self.axis_sd_detection_deg), 6)
        if self.cross_check:
            out["cross_check"] = self.cross_check
        if self.model_error:
            me = self.model_error
            out["model_error"] = {**me, "centre_sd_m": round(float(me["centre_sd_m"]), 9),
                                  "articular_radius_m": round(float(me["articular_radius_m"]), 6)}
        return out

    @classmethod
    def from_json(cls, name: str, d: dict) -> "Joint":
        """One joint of a joints.json (`to_json`)."""
        det = d.get("origin_cov_detection")
        return cls(name, np.asarray(d["origin"], float), np.asarray(d["origin_cov"], float),
                   np.asarray(d["rotation"], float), float(d["axis_sd_deg"]), tuple(d.get("flags", ())),
                   parent=JointFrame.from_json(d["parent"]) if "parent" in d else None,
                   child=JointFrame.from_json(d["child"]) if "child" in d else None,
                   origin_cov_detection=None if det is None else np.asarray(det, float),
                   axis_sd_detection_deg=d.get("axis_sd_detection_deg"), cross_check=d.get("cross_check"),
                   model_error=d.get("model_error"))


JOINTS_CONVENTION = ("rotation columns are the joint frame's X, Y, Z axes; Z is the main rotation axis (hip and knee "
                     "flexion, talocrural, subtalar, metatarsophalangeal); Z to the subject's right except subtalar "
                     "(anterior). 'parent' / 'child': the joint's frames fixed in the proximal / distal body (OpenSim); "
                     "'origin' / 'rotation' repeat the parent frame (the child frame when the parent is missing). "
                     "origin_cov (m^2) and axis_sd_deg include the fit, the spread of disagreeing estimates and a "
                     "model-error term; *_detection the fit alone")


def joints_document(joints: dict, dropped: dict, *, input: str | None = None, frame: str = "input") -> dict:
    """The ``joints.json`` document (JSON-ready): units, frame, convention, joints, dropped."""
    doc = {"units": "m", "frame": frame}
    if input is not None:
        doc["input"] = str(input)
    doc["convention"] = JOINTS_CONVENTION
    doc["joints"] = {k: v.to_json() for k, v in joints.items()}
    doc["dropped"] = dict(dropped)
    return doc


def _flags(*bones) -> tuple:
    out = []
    for b in bones:
        if b is None:
            continue
        for f in b.flags:
            if f not in out:
                out.append(f)
    return tuple(out)


#: Model-error term of the stated uncertainty, per joint: the joint-centre sd as a fraction of the
#: joint's articular radius (femoral head, condyles, talar dome, posterior talocalcaneal facet,
#: metatarsal head) and the axis sd in degrees.  It is the distance between a joint detected here
#: and the one an expert built by hand on the same bones, which the fit covariance does not see
#: (conventions of which surface defines the joint, non-circular articular arcs).  Chosen on
#: each real set, checked on the other (`personalize.evaluation.reference_models.calibrate_model_error`,
#: ``benchmarks/landmarks.py --sets-only``): one centre fraction and one axis sd pooled over the
#: hip, knee, ankle and subtalar joints, not a constant per joint tuned to one subject.  Neither
#: set's own calibration covers the other (ICL-MRI: 0.018 R, 0.57 deg; LHDL-CT: 0.007 R, 1.0 deg),
#: so the larger of the two, rounded up, is in force.
MODEL_ERROR = {k: {"centre": 0.020, "axis_deg": 1.2} for k in ("hip", "knee", "ankle", "subtalar")}
MODEL_ERROR["mtp"] = {"centre": 0.1, "axis_deg": 3.0}       # no expert reference: a wide term
#: articular radius used when the fit gives none (m)
_DEFAULT_RADIUS = {"hip": 0.024, "knee": 0.024, "ankle": 0.021, "subtalar": 0.015, "mtp": 0.008}
#: model sd of the acetabulum sphere centre as a hip-centre estimate, fraction of its radius (the
#: lunate surface is a horseshoe, its sphere includes the cartilage gap)
ACETABULUM_MODEL_SD = 0.1
#: model sd of the femoral head sphere centre as a hip-centre estimate, fraction of its radius
HEAD_MODEL_SD = 0.02


#: model sd of each ankle estimate: centre as a fraction of the talar dome radius, axis in degrees.  The
#: tibial plafond is the dome's concave partner (used when its radius is within 25 % above the dome's);
#: the malleoli's midpoint and line are a coarse check (the bimalleolar line runs ~20 deg from the
#: talocrural axis) and the tibial plateau's medio-lateral line (tibial torsion, normally 15-40 deg
#: external) are checks only: they vote on agreement, not in the combined value
#: deg, largest angle between a talar dome axis and the bimalleolar line for the dome to be the talocrural axis:
#: the detected dome axis and the malleolus tips' line differ by 22-25 deg on the real bone sets (ICL_MRI and
#: LHDL_CT right, TLEM2_MRI both sides, an LHDL_CT label volume's right side); that label volume's left dome was
#: 78 deg off (80 deg from the expert's axis)
ANKLE_AXIS_MALLEOLAR_MAX_DEG = 40.0
ANKLE_MODEL_SD = {"talar_dome": (0.04, 1.0), "tibial_plafond": (0.2, None), "malleoli": (0.4, 12.0),
                  "tibial_torsion": (None, 20.0)}


def _ankle_centre(tal, tib, fib, s):
    """Talar dome centre and axis, cross-checked with the tibial plafond and the malleoli (`crosscheck`)."""
    from personalize.landmarks.crosscheck import Estimate, cross_check, cross_check_directions

    ac, ax = tal.landmarks["talar_dome_centre"], tal.axes["ankle_axis"]
    rd = _scalar(tal, "talar_dome_radius") or _DEFAULT_RADIUS["ankle"]
    u = ax.direction
    on = lambda p, d: np.asarray(p, float) + float((ac.position - p) @ d) * d   # noqa: E731
    ec = [Estimate("talar_dome", ac.position, ac.cov, ANKLE_MODEL_SD["talar_dome"][0] * rd)]
    eu = [Estimate("talar_dome", u, np.radians(ax.sd_deg) ** 2 * np.eye(3), np.radians(ANKLE_MODEL_SD["talar_dome"][1]))]
    pf = tib.fits.get("plafond") if tib is not None else None
    if pf is not None and rd <= float(pf["radius"]) <= 1.25 * rd and "ankle_axis" in tib.axes:
        ta = tib.axes["ankle_axis"]
        ec.append(Estimate("tibial_plafond", on(ta.point, unit(ta.direction)), (0.001 ** 2) * np.eye(3),
                           ANKLE_MODEL_SD["tibial_plafond"][0] * rd))
    if tib is not None and fib is not None and "medial_malleolus_tip" in tib.landmarks and "lateral_malleolus_tip" in fib.landmarks:
        a, b = tib.landmarks["medial_malleolus_tip"], fib.landmarks["lateral_malleolus_tip"]
        d = unit(b.position - a.position)
        ec.append(Estimate("malleoli", on(0.5 * (a.position + b.position), d), 0.25 * (a.cov + b.cov),
                           ANKLE_MODEL_SD["malleoli"][0] * rd, check=True))
        eu.append(Estimate("malleoli", d, np.radians(2.0) ** 2 * np.eye(3), np.radians(ANKLE_MODEL_SD["malleoli"][1]),
                           check=True))
    if len(eu) > 1 and eu[1].source == "malleoli" and \
            np.degrees(np.arccos(min(1.0, abs(float(u @ eu[1].value))))) > ANKLE_AXIS_MALLEOLAR_MAX_DEG:
        # a talar dome axis this far from the bimalleolar line is no talocrural axis (a dome fitted on a ridge
        # of a noisy label surface): the malleoli's line is the estimate, the dome a check against it
        m = eu[1]
        eu = [Estimate("malleoli", m.value, m.cov, m.model_sd), Estimate("talar_dome", u, eu[0].cov, eu[0].model_sd,
                                                                          check=True)]
    if tib is not None and "knee_axis" in tib.axes:
        ka = tib.axes["knee_axis"]
        eu.append(Estimate("tibial_torsion", ka.direction, np.radians(ka.sd_deg) ** 2 * np.eye(3),
                           np.radians(ANKLE_MODEL_SD["tibial_torsion"][1]), check=True))
    if len(ec) == 1 and len(eu) == 1:
        return ac.position, ac.cov, None, u, ax.sd_deg, None, ()
    rc = cross_check(ec, plane_normal=u)
    ru = cross_check_directions(eu)
    sd = float(np.degrees(np.sqrt(np.trace(ru.cov_fit) / 2)))
    spread = rc.cov_spread
    fl = () if rc.agree and ru.agree else ("low_confidence",)
    return rc.value, rc.cov_fit, spread, ru.value, sd, {"centre": rc.to_json("m"), "axis": ru.to_json("rad")}, fl


#: model sd of each subtalar centre estimate across the axis, as a fraction of the talar facet radius: the
#: talar facet's sphere centre is the joint's (the expert models place it there); the calcaneal facet is the
#: other side of the same articulation, fitted on a shallower, rougher cap (chosen on ICL_MRI, where the two
#: are 1.2 mm apart across the axis; checked on LHDL_CT 0.7 mm and MC22 1.3 / 3.0 mm; on TLEM2_MRI the
#: talar facet's 9-13 mm sphere is 11-21 mm off the calcaneal one and is flagged)
SUBTALAR_MODEL_SD = {"talar_facet": 0.04, "calcaneal_facet": 0.10}


def _subtalar_centre(tal, ax):
    """Subtalar origin on its axis from the talar posterior facet, cross-checked with the calcaneal facet.

    Returns (origin, fit covariance, spread covariance or None, cross-check json or None, flags)."""
    from personalize.landmarks.crosscheck import Estimate, cross_check

    pf = tal.landmarks.get("posterior_facet_centre")
    pf = tal.landmarks["talar_dome_centre"] if pf is None else pf
    o = closest_on_line(ax.point, ax.direction, pf.position)
    cf = tal.landmarks.get("calcaneal_facet_centre")
    if cf is None or "posterior_facet_centre" not in tal.landmarks:
        return o, pf.cov, None, None, ()
    r = _radius("subtalar", None, tal)
    rc = cross_check([Estimate("talar_facet", o, pf.cov, SUBTALAR_MODEL_SD["talar_facet"] * r),
                      Estimate("calcaneal_facet", cf.position, cf.cov, SUBTALAR_MODEL_SD["calcaneal_facet"] * r,
                               check=True)], plane_normal=ax.direction)
    return rc.value, rc.cov_fit, rc.cov_spread, {"centre": rc.to_json("m")}, (() if rc.agree else ("low_confidence",))


#: the subtalar axis in the foot frame (plantar support plane, forward): its inclination above the plantar plane
#: and medial deviation from the foot's long axis, mean and sd (deg) over 46 cadaver feet (Inman 1976, The Joints
#: of the Ankle: 42 +- 9 and 23 +- 11 deg, ranges 20.5-68.5 and 4-47 deg).  The detected axes of ICL-MRI (32, 26),
#: LHDL-CT (45, 6; the expert models 32, 26 and 44, 10) and MC22 (22-23, 11-12) lie within 2 sd; both TLEM2-MRI
#: tali's (-45 and -33 deg: pointing down in front) 8-10 sd away
SUBTALAR_POPULATION = {"inclination_deg": (42.0, 9.0), "medial_deviation_deg": (23.0, 11.0)}
#: sd beyond which a detected subtalar axis is not used
SUBTALAR_PLAUSIBLE_SD = 3.0


def subtalar_angles(direction, foot_rotation, side: str) -> tuple[float, float]:
    """Inclination above the plantar plane and medial deviation from the foot's long axis (deg) of a subtalar axis
    direction (pointed forward), given the foot frame's rotation (columns forward, up, right)."""
    x, y, z = np.asarray(foot_rotation, float).T @ np.asarray(direction, float)
    if x < 0:
        x, y, z = -x, -y, -z
    med = -z if side == "r" else z
    return float(np.degrees(np.arctan2(y, np.hypot(x, z)))), float(np.degrees(np.arctan2(med, x)))


def subtalar_direction(forward, up, medial, inclination_deg: float, medial_deviation_deg: float) -> np.ndarray:
    """The unit axis `inclination_deg` above the plane of `forward` and `medial` and `medial_deviation_deg` from
    `forward` towards `medial` (the inverse of `subtalar_angles`)."""
    i, d = np.radians(inclination_deg), np.radians(medial_deviation_deg)
    return unit(np.cos(i) * (np.cos(d) * np.asarray(forward, float) + np.sin(d) * np.asarray(medial, float))
                + np.sin(i) * np.asarray(up, float))


def _population_subtalar(tal, foot_rotation, side: str, direction):
    """None when the detected subtalar axis is a plausible foot's (`SUBTALAR_POPULATION`), else the population
    mean axis through the talar head centre (its sd the population's two sds combined), its origin the point
    nearest the talar dome centre, and a centre spread of the dome radius (where the axis crosses the talus is
    then unknown to about the talus' size): ``(Axis, origin, fit cov, spread cov, info)``."""
    from personalize.landmarks.common import Axis

    inc, dev = subtalar_angles(direction, foot_rotation, side)
    (mi, si), (md, sdv) = SUBTALAR_POPULATION.values()
    z = max(abs(inc - mi) / si, abs(dev - md) / sdv)
    if z <= SUBTALAR_PLAUSIBLE_SD:
        return None
    F = np.asarray(foot_rotation, float)
    a = subtalar_direction(F[:, 0], F[:, 1], -F[:, 2] if side == "r" else F[:, 2], mi, md)
    hc = tal.landmarks.get("talar_head_centre") or tal.landmarks["talar_dome_centre"]
    dome = tal.landmarks["talar_dome_centre"].position
    o = closest_on_line(hc.position, a, dome)
    r = _radius("ankle", None, tal)
    info = {"detected_inclination_deg": round(inc, 2), "detected_medial_deviation_deg": round(dev, 2),
            "sd_from_population": round(z, 2), "limit_sd": SUBTALAR_PLAUSIBLE_SD,
            "used": "population mean axis (Inman 1976) through the talar head centre"}
    return Axis(o, a, float(np.hypot(si, sdv))), o, hc.cov, (r ** 2) * np.eye(3), info


#: largest distance (m) between a joint centre and the neighbouring bone's articular landmark (tibial
#: plateau centre for the knee, plafond centre or medial malleolus for the ankle) in an assembled set;
#: farther, the two bones are not articulated in the input frame (scanned or exported apart) and the joint
#: is flagged (adult knees and ankles: 15-35 mm)
ARTICULATION_MAX = 0.05


def _articulation(centre, other) -> tuple[tuple, dict | None]:
    if other is None:
        return (), None
    d = float(np.linalg.norm(np.asarray(centre) - np.asarray(other)))
    info = {"distance_mm": round(d * 1e3, 2), "limit_mm": ARTICULATION_MAX * 1e3, "articulated": d <= ARTICULATION_MAX}
    return (() if d <= ARTICULATION_MAX else ("low_confidence", "not_articulated")), info


def _scalar(b, key):
    return float(b.scalars[key]) if b is not None and key in b.scalars else None


def _radius(kind, *bones) -> float:
    fem, tal, cal = (bones + (None, None, None))[:3]
    r = None
    if kind == "hip":
        r = _scalar(fem, "femoral_head_radius")
    elif kind == "knee":
        rs = [_scalar(fem, f"{c}_condyle_b") for c in ("medial", "lateral")]
        r = float(np.mean(rs)) if all(x is not None for x in rs) else None
    elif kind == "ankle":
        r = _scalar(tal, "talar_dome_radius")
    elif kind == "subtalar" and tal is not None and "posterior_calcaneal_facet" in tal.fits:
        r = float(tal.fits["posterior_calcaneal_facet"]["radius"])
    return r if r is not None and np.isfinite(r) and r > 0 else _DEFAULT_RADIUS[kind]


def _joint(name, kind, origin, cov_det, parent, child, sd_det, flags, radius, spread_cov=None, cross=None,
           axis_spread_deg=0.0):
    """A `Joint` whose stated uncertainty is fit + spread + model error (`MODEL_ERROR`).

    ``spread_cov`` / ``axis_spread_deg``: the spread of disagreeing estimates when not already in
    ``cov_det`` / ``sd_det`` (the knee's are: `femur` states them in its landmarks)."""
    me = MODEL_ERROR[kind]
    sd_c = me["centre"] * radius
    cov = np.asarray(cov_det, float) + sd_c ** 2 * np.eye(3)
    if spread_cov is not None:
        cov = cov + spread_cov
    sd = float(np.sqrt(float(sd_det) ** 2 + me["axis_deg"] ** 2 + axis_spread_deg ** 2))
    ref = parent if parent.origin is not None else child
    return Joint(name, np.asarray(origin, float).copy(), 0.5 * (cov + cov.T), ref.rotation.copy(), sd, flags,
                 parent=parent, child=child, origin_cov_detection=np.asarray(cov_det, float).copy(),
                 axis_sd_detection_deg=float(sd_det), cross_check=cross,
                 model_error={"centre_sd_m": float(sd_c), "axis_sd_deg": me["axis_deg"],
                              "articular_radius_m": float(radius)})


def _hip_centre(fem, pel, s):
    """Femoral head centre, cross-checked with the acetabulum sphere when the pelvis is there."""
    hc = fem.landmarks["femoral_head_centre"]
    if pel is None or f"acetabulum_centre_{s}" not in pel.landmarks:
        return hc.position, hc.cov, None, None, ()
    from personalize.landmarks.crosscheck import Estimate, cross_check

    ac = pel.landmarks[f"acetabulum_centre_{s}"]
    rh = _scalar(fem, "femoral_head_radius") or _DEFAULT_RADIUS["hip"]
    ra = _scalar(pel, f"acetabulum_radius_{s}") or rh
    r = cross_check([Estimate("femoral_head", hc.position, hc.cov, HEAD_MODEL_SD * rh),
                     Estimate("acetabulum", ac.position, ac.cov, ACETABULUM_MODEL_SD * ra)])
    flags = () if r.agree else ("low_confidence",)
    return r.value, r.cov_fit, r.cov_spread, {"centre": r.to_json("m")}, flags


def joints_from_landmarks(ls) -> tuple[dict[str, Joint], dict[str, str]]:
    """Joint frames from a `personalize.landmarks.LandmarkSet`.

    Returns
    -------
    joints : dict[str, Joint]
        ``hip_r``, ``knee_r``, ... for every joint whose bones and landmarks
        were found (the hip also without a pelvis: femur-side frame only).
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
        knee_c = fem.landmarks["intercondylar_midpoint"].position if fem is not None and \
            "intercondylar_midpoint" in fem.landmarks else None
        # ---- hip
        j = f"hip_{s}"
        if need(j, f"femur_{s}"):
            if "femoral_head_centre" not in fem.landmarks:
                dropped[j] = "femoral head not detected"
            else:
                o, cov, spread, cross, fl = _hip_centre(fem, pel, s)
                hc = o
                if knee_c is not None and "knee_axis" in fem.axes:
                    Rf = frame_yz(hc - knee_c, fem.axes["knee_axis"].direction)
                elif "isb" in fem.frames:
                    Rf = fem.frames["isb"]["rotation"]
                else:
                    Rf = fem.frames["anatomical"]["rotation"]
                ka_sd = fem.axes["knee_axis"].sd_deg if "knee_axis" in fem.axes else 3.0
                child = JointFrame(f"femur_{s}", hc.copy(), Rf.copy(),
                                   axis_sd_deg=float(np.hypot(ka_sd, MODEL_ERROR["hip"]["axis_deg"])))
                sd = float("nan")
                if pel is None:
                    parent = JointFrame("pelvis", missing="no pelvis among the bones")
                    sd = fem.axes["knee_axis"].sd_deg if "knee_axis" in fem.axes else 1.0
                elif "isb" not in pel.frames:
                    parent = JointFrame("pelvis", missing="pelvic frame not detected")
                    sd = fem.axes["knee_axis"].sd_deg if "knee_axis" in fem.axes else 1.0
                else:
                    R = pel.frames["isb"]["rotation"]
                    parent = JointFrame("pelvis", hc.copy(), R.copy())
                    asis = [pel.landmarks[k] for k in ("RASI", "LASI") if k in pel.landmarks]
                    w = np.linalg.norm(asis[0].position - asis[1].position) if len(asis) == 2 else 0.2
                    sd = np.degrees(np.sqrt(sum(np.trace(a.cov) / 3 for a in asis)) / w) if asis else 1.0
                joints[j] = _joint(j, "hip", hc, cov, parent, child, sd, _flags(pel, fem) + tuple(
                    f for f in fl if f not in _flags(pel, fem)), _radius("hip", fem), spread, cross)
        # ---- knee
        j = f"knee_{s}"
        if need(j, f"femur_{s}", f"tibia_{s}"):
            if knee_c is None or "knee_axis" not in fem.axes:
                dropped[j] = "femoral condyles not detected"
            else:
                kc = fem.landmarks["intercondylar_midpoint"]
                ax = fem.axes["knee_axis"]
                if "femoral_head_centre" in fem.landmarks:
                    yh = fem.landmarks["femoral_head_centre"].position - kc.position
                else:
                    yh = fem.axes["shaft_axis"].direction
                if tal is not None and "talar_dome_centre" in tal.landmarks:
                    yt = kc.position - tal.landmarks["talar_dome_centre"].position
                elif "plafond_centre" in tib.landmarks:
                    yt = kc.position - tib.landmarks["plafond_centre"].position
                else:
                    yt = tib.axes["shaft_axis"].direction
                cross = fem.fits.get("knee_cross_check")
                cross = {k: v for k, v in cross.items() if k in ("centre", "axis")} if cross else {}
                art, info = _articulation(kc.position, tib.landmarks["plateau_centre"].position
                                          if "plateau_centre" in tib.landmarks else None)
                if info:
                    cross["articulation"] = info
                flags = _flags(fem, tib) + tuple(f for f in art if f not in _flags(fem, tib))
                joints[j] = _joint(j, "knee", kc.position, kc.cov,
                                   JointFrame(f"femur_{s}", kc.position.copy(), frame_zy(ax.direction, yh)),
                                   JointFrame(f"tibia_{s}", kc.position.copy(), frame_zy(ax.direction, yt)),
                                   ax.sd_deg, flags, _radius("knee", fem), None, cross or None)
        # ---- ankle
        j = f"ankle_{s}"
        if need(j, f"tibia_{s}", f"talus_{s}"):
            if "talar_dome_centre" not in tal.landmarks:
                dropped[j] = "talar dome not detected"
            else:
                ao, acov, spread, au, asd, cross, fl = _ankle_centre(tal, tib, B.get(f"fibula_{s}"), s)
                au = orient(au, tal.axes["ankle_axis"].direction)
                if knee_c is not None:
                    yh = knee_c - ao
                elif "plateau_centre" in tib.landmarks:
                    yh = tib.landmarks["plateau_centre"].position - ao
                else:
                    yh = tib.axes["shaft_axis"].direction
                yt = tal.frames["anatomical"]["rotation"][:, 1] if "anatomical" in tal.frames else yh
                lm = tib.landmarks.get("plafond_centre") or tib.landmarks.get("medial_malleolus_tip")
                art, info = _articulation(ao, lm.position if lm is not None else None)
                if info:
                    cross = dict(cross or {}, articulation=info)
                flags = _flags(tib, tal) + tuple(f for f in fl + art if f not in _flags(tib, tal))
                flags = tuple(dict.fromkeys(flags))
                joints[j] = _joint(j, "ankle", ao, acov,
                                   JointFrame(f"tibia_{s}", ao.copy(), frame_zy(au, yh)),
                                   JointFrame(f"talus_{s}", ao.copy(), frame_zy(au, yt)),
                                   asd, flags, _radius("ankle", None, tal), spread, cross,
                                   float((cross or {}).get("axis", {}).get("spread_deg", 0.0)))
        # ---- subtalar
        j = f"subtalar_{s}"
        if need(j, f"talus_{s}", f"calcn_{s}"):
            if "subtalar_axis" not in tal.axes or "talar_dome_centre" not in tal.landmarks:
                dropped[j] = "subtalar axis not detected"
            else:
                ax = tal.axes["subtalar_axis"]
                # the posterior facet is the subtalar joint's main articulation; its sphere centre lies on the
                # axis (which runs through it), as the hand-built ICL-MRI model places the joint
                o, cov, spread, cross, fl = _subtalar_centre(tal, ax)
                sd = ax.sd_deg
                if "foot" in cal.frames:
                    alt = _population_subtalar(tal, cal.frames["foot"]["rotation"], s, ax.direction)
                    if alt is not None:
                        # the facets gave an axis no foot has: the population's, with its spread, is stated instead
                        ax, o, cov, spread, info = alt
                        sd, fl = ax.sd_deg, ("low_confidence",)
                        cross = dict(cross or {}, population_axis=info)
                up = cal.frames["foot"]["rotation"][:, 1] if "foot" in cal.frames else tal.frames["anatomical"]["rotation"][:, 1]
                R = frame_zy(ax.direction, up)
                joints[j] = _joint(j, "subtalar", o, cov, JointFrame(f"talus_{s}", o.copy(), R.copy()),
                                   JointFrame(f"calcn_{s}", o.copy(), R.copy()), sd,
                                   tuple(dict.fromkeys(_flags(tal, cal) + fl)), _radius("subtalar", None, tal),
                                   spread, cross)
        # ---- mtp
        j = f"mtp_{s}"
        if need(j, f"calcn_{s}", f"toes_{s}"):
            ax = cal.axes.get("mtp_axis") or toe.axes.get("mtp_axis")
            if ax is None or "foot" not in cal.frames:
                dropped[j] = "metatarsal heads not detected"
            else:
                c = cal.landmarks.get("mtp_centre")
                cov = c.cov if c is not None else (0.002 ** 2) * np.eye(3)
                o = np.asarray(ax.point, float)
                R = frame_zy(ax.direction, cal.frames["foot"]["rotation"][:, 1])
                joints[j] = _joint(j, "mtp", o, cov, JointFrame(f"calcn_{s}", o.copy(), R.copy()),
                                   JointFrame(f"toes_{s}", o.copy(), R.copy()), ax.sd_deg, _flags(cal, toe),
                                   _radius("mtp"))
    return joints, dropped
