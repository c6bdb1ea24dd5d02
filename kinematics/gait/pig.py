"""Plug-in-Gait lower-body model (Davis et al. 1991; Kadaba et al. 1990), as in Vicon Nexus.

Every function is vectorised over frames: marker arrays are (F, 3) in metres,
rotation matrices (F, 3, 3) whose columns are the segment axes in the lab
frame.  All segment frames follow Plug-in-Gait: x anterior, y to the left,
z proximal (the foot's z points from the toe marker to the ankle centre).
Missing markers (NaN) give NaN outputs for those frames, never filled values.

Pipeline (right side; the left mirrors it)::

    pelvis    origin = (RASI + LASI)/2, y = LASI - RASI, x ⟂ y towards the ASIS from the PSIS mid-point
    hip       Davis (Newington-Gage) regression in the pelvis frame from leg length and inter-ASIS distance
    knee      chord(RTHI, hip, RKNE, knee_width/2 + marker_radius)
    ankle     chord(RTIB, knee, RANK, ankle_width/2 + marker_radius)
    femur     z = hip - knee, x = z × (RKNE - hip)
    tibia     z = knee - ankle, x = z × (RTIB - RANK), then tibial torsion about z
    foot      z = ankle - RTOE, y from the tibia, then the static plantar-flexion / rotation offsets

Joint angles are Cardan angles of the distal frame in the proximal frame,
sequence Y-X'-Z'' (flexion about the proximal lateral axis, ab/adduction about
the floating axis, rotation about the distal long axis), signed as Nexus
reports them (flexion, adduction, internal rotation positive on both sides).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lowerlimb.errors import InputError
from lowerlimb.geometry import marker_radius
from kinematics.io.markers import MarkerTrial
from kinematics.gait.subject import SubjectMeasurements

__all__ = [
    "SegmentPose", "PiGResult", "LOWER_BODY_MARKERS",
    "pelvis_frame", "davis_hip_offset", "chord_joint_centre",
    "femur_frame", "tibia_frame", "foot_frame", "cardan_yxz", "joint_angles",
    "static_foot_offsets", "plug_in_gait", "unit_vectors", "sacrum_marker", "leg_chain", "chord_centre_jacobians",
    "median_covariance",
]

# Davis et al. (1991) regression constants, exactly as in Plug-in-Gait.
DAVIS_THETA = 0.500000178813934  # rad (28.4 deg)
DAVIS_BETA = 0.314000427722931  # rad (18 deg)
# Validation studies report Davis hip-centre errors of 2-3 cm (Harrington et al. 2007, J Biomech 40:595).
DAVIS_HIP_SD = 0.02  # m, nominal isotropic sd reported with the regression hip centres

LOWER_BODY_MARKERS = ("RASI", "LASI", "RTHI", "RKNE", "RTIB", "RANK", "RTOE",
                      "LTHI", "LKNE", "LTIB", "LANK", "LTOE")


@dataclass(frozen=True)
class SegmentPose:
    """Pose of one segment over a trial.

    origin : (F, 3) m, lab frame
    axes : (F, 3, 3), columns x, y, z (unit) in the lab frame
    """

    origin: np.ndarray
    axes: np.ndarray

    def to_lab(self, local: np.ndarray) -> np.ndarray:
        """Lab coordinates (F, 3) of a segment-fixed point `local` (3,) or (F, 3)."""
        local = np.asarray(local, float)
        if local.ndim == 1:
            return self.origin + np.einsum("fij,j->fi", self.axes, local)
        return self.origin + np.einsum("fij,fj->fi", self.axes, local)

    def to_local(self, lab: np.ndarray) -> np.ndarray:
        """Segment coordinates (F, 3) of lab points (F, 3)."""
        return np.einsum("fji,fj->fi", self.axes, lab - self.origin)


@dataclass(frozen=True)
class PiGResult:
    """Plug-in-Gait outputs for one trial (SI units).

    segments : dict name -> SegmentPose, names ``pelvis, femur_r, tibia_r, foot_r, ..._l``
        (``tibia_r`` includes tibial torsion; ``tibia_untorsioned_r`` is the one used for knee angles)
    centres : dict name -> (F, 3) m: ``hip_r, knee_r, ankle_r, ..._l``
    centre_cov : dict name -> (3, 3) m², lab-frame covariance of each centre (median over
        frames): the Davis regression error (isotropic sd `DAVIS_HIP_SD`) propagated
        linearly through the chord functions
    angles : dict name -> (F, 3) rad: ``hip_r, knee_r, ankle_r, ..._l``, columns
        (flexion, adduction, internal rotation) for hip and knee and
        (dorsiflexion, inversion, internal rotation) for the ankle
    """

    segments: dict
    centres: dict
    centre_cov: dict
    angles: dict
    time: np.ndarray
    source: str | None = None
    notes: tuple = field(default_factory=tuple)


def unit_vectors(v: np.ndarray) -> np.ndarray:
    """Vectors v (..., 3) scaled to unit length; NaN (without a warning) where v is zero or NaN."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _frame(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    return np.stack([x, y, z], axis=-1)


# --------------------------------------------------------------------------- pelvis / hip


def pelvis_frame(rasi, lasi, sacrum) -> SegmentPose:
    """Plug-in-Gait pelvis: origin mid-ASIS, y = unit(LASI - RASI), x = the
    component of (origin - sacrum) orthogonal to y (Gram-Schmidt), z = x × y.

    `sacrum` is the SACR marker or the RPSI/LPSI mid-point, (F, 3) m.
    """
    origin = 0.5 * (rasi + lasi)
    y = unit_vectors(lasi - rasi)
    b = origin - sacrum
    x = unit_vectors(b - np.sum(b * y, axis=-1, keepdims=True) * y)
    z = np.cross(x, y)
    return SegmentPose(origin, _frame(x, y, z))


def davis_hip_offset(subject: SubjectMeasurements, side: str, inter_asis: float) -> np.ndarray:
    """Hip joint centre in the pelvis frame (m) by the Davis (Newington-Gage) regression.

    With C = 0.115 L̄ - 0.0153 (L̄ mean leg length), a = inter-ASIS / 2,
    t = ASIS-trochanter distance (0.1288 L - 0.04856 if not measured),
    r = marker radius, θ = 0.5 rad, β = 0.314 rad::

        x = C cosθ sinβ - (t + r) cosβ
        y = ±(a - C sinθ)            (+ left, - right; y points left)
        z = -C cosθ cosβ - (t + r) sinβ
    """
    s = side.upper()[0]
    leg = subject.right_leg_length if s == "R" else subject.left_leg_length
    at = subject.right_asis_trochanter if s == "R" else subject.left_asis_trochanter
    if at is None:
        at = 0.1288 * leg - 0.04856
    c = 0.115 * subject.mean_leg_length - 0.0153
    a = 0.5 * inter_asis
    r = marker_radius(subject.marker_diameter)
    x = c * np.cos(DAVIS_THETA) * np.sin(DAVIS_BETA) - (at + r) * np.cos(DAVIS_BETA)
    y = (a - c * np.sin(DAVIS_THETA)) * (1.0 if s == "L" else -1.0)
    z = -c * np.cos(DAVIS_THETA) * np.cos(DAVIS_BETA) - (at + r) * np.sin(DAVIS_BETA)
    return np.array([x, y, z])


# --------------------------------------------------------------------------- chord function


def chord_joint_centre(wand, proximal_centre, marker, delta) -> np.ndarray:
    """Plug-in-Gait chord function.

    The joint centre J lies in the plane of the wand marker a, the proximal
    joint centre b and the joint marker c, at distance ``delta`` (half joint
    width + marker radius) from c, with the angle b-J-c a right angle (J on
    the Thales circle of b c).  With u = unit(b - c), n = unit((a - c) × (b - c))
    and cos φ = delta / |b - c|::

        J = c + delta (cos φ u + sin φ (n × u))

    Parameters
    ----------
    wand, proximal_centre, marker : (F, 3) m
    delta : float, m

    Returns
    -------
    (F, 3) m; NaN where an input is NaN or |b - c| < delta.
    """
    a, b, c = (np.asarray(v, float) for v in (wand, proximal_centre, marker))
    bc = b - c
    d = np.linalg.norm(bc, axis=-1, keepdims=True)
    u = unit_vectors(bc)
    n = unit_vectors(np.cross(a - c, bc))
    with np.errstate(invalid="ignore"):
        cphi = np.where(d >= delta, delta / d, np.nan)
    sphi = np.sqrt(1.0 - cphi**2)
    return c + delta * (cphi * u + sphi * np.cross(n, u))


# --------------------------------------------------------------------------- segment frames


def femur_frame(hip, knee, knee_marker, side: str) -> SegmentPose:
    """Femur: origin knee centre, z = unit(hip - knee), x ⟂ plane(hip, knee, KNE) pointing anterior."""
    z = unit_vectors(hip - knee)
    lateral = knee_marker - hip
    x = unit_vectors(np.cross(z, lateral) if side.upper()[0] == "R" else np.cross(lateral, z))
    return SegmentPose(knee, _frame(x, np.cross(z, x), z))


def tibia_frame(knee, ankle, tibia_marker, ankle_marker, side: str, torsion: float = 0.0) -> SegmentPose:
    """Tibia: origin ankle centre, z = unit(knee - ankle), x ⟂ plane(TIB, ANK, z) pointing anterior,
    then rotated by the tibial torsion τ about z (x' = cos τ x - sin τ y)."""
    z = unit_vectors(knee - ankle)
    lateral = tibia_marker - ankle_marker
    x = unit_vectors(np.cross(z, lateral) if side.upper()[0] == "R" else np.cross(lateral, z))
    y = np.cross(z, x)
    if torsion:
        x, y = np.cos(torsion) * x - np.sin(torsion) * y, np.sin(torsion) * x + np.cos(torsion) * y
    return SegmentPose(ankle, _frame(x, y, z))


def _uncorrected_foot(ankle, toe, tibia: SegmentPose) -> np.ndarray:
    z = unit_vectors(ankle - toe)
    x = unit_vectors(np.cross(tibia.axes[..., 1], z))
    return _frame(x, np.cross(z, x), z)


def foot_frame(ankle, toe, tibia: SegmentPose, side: str, plantar_flexion: float, rotation_offset: float) -> SegmentPose:
    """Foot: origin toe marker, z = unit(ankle - TOE), x = y_tibia × z, y = z × x, then the static
    offsets: rotation by the plantar-flexion offset about y, then by the rotation offset about x
    (sign mirrored on the right side, as in Plug-in-Gait)."""
    ax = _uncorrected_foot(ankle, toe, tibia)
    x, y, z = ax[..., 0], ax[..., 1], ax[..., 2]
    b = plantar_flexion
    a = -rotation_offset if side.upper()[0] == "R" else rotation_offset
    x, z = np.cos(b) * x + np.sin(b) * z, -np.sin(b) * x + np.cos(b) * z
    y, z = np.cos(a) * y - np.sin(a) * z, np.sin(a) * y + np.cos(a) * z
    return SegmentPose(np.asarray(toe, float), _frame(x, y, z))


# --------------------------------------------------------------------------- angles


def cardan_yxz(R: np.ndarray) -> np.ndarray:
    """Intrinsic Y-X'-Z'' Cardan angles of rotation matrices.

    R = R_y(b) R_x(a) R_z(g); returns (F, 3) = (b, a, g) in radians with
    a = asin(-R[1,2]) ∈ [-π/2, π/2], b = atan2(R[0,2], R[2,2]),
    g = atan2(R[1,0], R[1,1]).
    """
    R = np.asarray(R, float)
    a = np.arcsin(np.clip(-R[..., 1, 2], -1.0, 1.0))
    b = np.arctan2(R[..., 0, 2], R[..., 2, 2])
    g = np.arctan2(R[..., 1, 0], R[..., 1, 1])
    return np.stack([b, a, g], axis=-1)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def joint_angles(proximal: SegmentPose, distal: SegmentPose, joint: str, side: str) -> np.ndarray:
    """Plug-in-Gait joint angles (F, 3) in radians.

    With (b, a, g) = `cardan_yxz` of R = P^T D (distal axes in the proximal frame):

    - hip:   (flexion, adduction, internal rotation) = (-b, a, g) right, (-b, -a, -g) left
    - knee:  (flexion, adduction, internal rotation) = (b, a, g) right, (b, -a, -g) left
    - ankle: the foot's z points from toe to ankle, so the neutral foot is the
      tibia turned by -90° about y and the foot's long axis is its z:
      (dorsiflexion, inversion, internal rotation) = (-b - π/2, g, a) right,
      (-b - π/2, -g, -a) left (dorsiflexion wrapped to (-π, π]).

    These reproduce Vicon Nexus' LHipAngles ... RAnkleAngles to float precision
    when given Nexus' own segment frames (tests/test_pig.py).
    """
    R = np.einsum("fji,fjk->fik", proximal.axes, distal.axes)
    b, a, g = np.moveaxis(cardan_yxz(R), -1, 0)
    right = side.upper()[0] == "R"
    if joint == "hip":
        out = (-b, a, g) if right else (-b, -a, -g)
    elif joint == "knee":
        out = (b, a, g) if right else (b, -a, -g)
    elif joint == "ankle":
        # Foot z points posteriorly: the neutral foot is the tibia turned by -90° about y,
        # and the roles of x' and z'' swap (inversion is about the foot's long axis).
        out = (-b - np.pi / 2, g, a) if right else (-b - np.pi / 2, -g, -a)
        out = (_wrap(out[0]), out[1], out[2])
    else:
        raise ValueError(f"unknown joint {joint!r}")
    return np.stack(out, axis=-1)


# --------------------------------------------------------------------------- model


def sacrum_marker(trial: MarkerTrial) -> np.ndarray:
    """SACR trajectory (F, 3) m, or the mid-point of RPSI and LPSI when the trial has no SACR."""
    if "SACR" in trial.names:
        return trial.marker("SACR")
    trial.require(["RPSI", "LPSI"])
    return 0.5 * (trial.marker("RPSI") + trial.marker("LPSI"))


def _inter_asis(subject: SubjectMeasurements, trial: MarkerTrial) -> float:
    if subject.inter_asis_distance is not None:
        return subject.inter_asis_distance
    d = np.linalg.norm(trial.marker("RASI") - trial.marker("LASI"), axis=1)
    d = d[np.isfinite(d)]
    if d.size == 0:
        raise InputError(trial.source, "inter-ASIS distance not measured and RASI/LASI never both visible")
    return float(np.median(d))


def _chain(trial: MarkerTrial, subject: SubjectMeasurements):
    """Pelvis, hip, knee, ankle centres and pelvis/femur/tibia frames of both sides."""
    missing = [m for m in LOWER_BODY_MARKERS if m not in trial.names]
    if "SACR" not in trial.names:
        missing += [m for m in ("RPSI", "LPSI") if m not in trial.names]
    if missing:
        raise InputError(trial.source, f"missing Plug-in-Gait markers: {', '.join(missing)} (need SACR or RPSI+LPSI)")
    rot = [n for n in ("left_thigh_rotation", "right_thigh_rotation", "left_shank_rotation", "right_shank_rotation")
           if getattr(subject, n)]
    if rot:
        # Refuse rather than silently ignore: these offsets change the knee/ankle planes.
        raise InputError(subject.source, f"non-zero {', '.join(rot)} (wand-marker rotation offsets) are not supported")
    pelvis = pelvis_frame(trial.marker("RASI"), trial.marker("LASI"), sacrum_marker(trial))
    iad = _inter_asis(subject, trial)
    legs, centres = leg_chain(trial, subject, {s: pelvis.to_lab(davis_hip_offset(subject, s, iad)) for s in "RL"})
    return {"pelvis": pelvis, **legs}, centres


def leg_chain(trial: MarkerTrial, subject: SubjectMeasurements, hips: dict) -> tuple[dict, dict]:
    """Knee and ankle centres and femur/tibia frames of both legs from given hip centres.

    Parameters
    ----------
    hips : dict ``'R'``/``'L'`` -> (F, 3) m, hip centres in the lab

    Returns
    -------
    segments : dict ``femur_r, tibia_untorsioned_r, tibia_r, ..._l`` -> SegmentPose
        (``tibia`` includes the tibial torsion)
    centres : dict ``hip_r, knee_r, ankle_r, ..._l`` -> (F, 3) m, knee and ankle
        from `chord_joint_centre` (half the joint width plus the marker radius)
    """
    M = trial.marker
    r = marker_radius(subject.marker_diameter)
    segs, centres = {}, {}
    for s, sfx in (("R", "_r"), ("L", "_l")):
        hip = hips[s]
        m = subject.side(s)
        knee = chord_joint_centre(M(f"{s}THI"), hip, M(f"{s}KNE"), 0.5 * m["knee_width"] + r)
        ankle = chord_joint_centre(M(f"{s}TIB"), knee, M(f"{s}ANK"), 0.5 * m["ankle_width"] + r)
        centres.update({f"hip{sfx}": hip, f"knee{sfx}": knee, f"ankle{sfx}": ankle})
        segs[f"femur{sfx}"] = femur_frame(hip, knee, M(f"{s}KNE"), s)
        segs[f"tibia_untorsioned{sfx}"] = tibia_frame(knee, ankle, M(f"{s}TIB"), M(f"{s}ANK"), s)
        segs[f"tibia{sfx}"] = tibia_frame(knee, ankle, M(f"{s}TIB"), M(f"{s}ANK"), s, m["tibial_torsion"])
    return segs, centres


def chord_centre_jacobians(trial: MarkerTrial, subject: SubjectMeasurements, side: str, hip: np.ndarray,
                           knee: np.ndarray, h: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """J_k = ∂knee/∂hip and J_a = ∂ankle/∂knee (F, 3, 3) of the chord functions (central differences, step `h` m)."""
    m = subject.side(side)
    r = marker_radius(subject.marker_diameter)
    dk = 0.5 * m["knee_width"] + r
    da = 0.5 * m["ankle_width"] + r
    thi, kne, tib, ank = (trial.marker(f"{side}{n}") for n in ("THI", "KNE", "TIB", "ANK"))
    Jk = np.empty(hip.shape + (3,))
    Ja = np.empty(hip.shape + (3,))
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        Jk[..., i] = (chord_joint_centre(thi, hip + e, kne, dk) - chord_joint_centre(thi, hip - e, kne, dk)) / (2 * h)
        Ja[..., i] = (chord_joint_centre(tib, knee + e, ank, da) - chord_joint_centre(tib, knee - e, ank, da)) / (2 * h)
    return Jk, Ja


def static_foot_offsets(static: MarkerTrial, subject: SubjectMeasurements, *, flat_foot: bool = False) -> SubjectMeasurements:
    """Calibrate the foot offsets from a static trial (Plug-in-Gait static processing).

    The anatomical foot axis runs from the heel marker to the toe marker
    (with ``flat_foot`` the heel is lowered to the toe height, the foot being
    flat on the floor).  The offsets are the Y-X' Cardan angles (plantar
    flexion b, rotation a) rotating the uncorrected foot frame (z = ankle - TOE)
    onto the frame whose z is the anatomical foot axis, averaged over the frames.

    Returns a copy of `subject` with ``*_static_plantar_flexion`` and
    ``*_static_rotation_offset`` set (radians).
    """
    static.require(["RHEE", "LHEE"])
    segs, centres = _chain(static, subject)
    kw = {}
    for s, sfx, name in (("R", "_r", "right"), ("L", "_l", "left")):
        toe, hee = static.marker(f"{s}TOE"), static.marker(f"{s}HEE").copy()
        ankle = centres[f"ankle{sfx}"]
        if flat_foot:
            hee[:, 2] = toe[:, 2]
        unc = _uncorrected_foot(ankle, toe, segs[f"tibia{sfx}"])
        z = unit_vectors(hee - toe)
        x = unit_vectors(np.cross(unc[..., 1], z))
        cor = _frame(x, np.cross(z, x), z)
        R = np.einsum("fji,fjk->fik", unc, cor)
        b, a, _ = np.moveaxis(cardan_yxz(R), -1, 0)
        ok = np.isfinite(b) & np.isfinite(a)
        if not ok.any():
            raise InputError(static.source, f"{s} foot markers never visible together in the static trial")
        b_mean, a_mean = float(np.mean(b[ok])), float(np.mean(a[ok]))
        # `foot_frame` applies R_y(-plantar_flexion) then R_x(±rotation_offset): invert those signs.
        kw[f"{name}_static_plantar_flexion"] = -b_mean
        kw[f"{name}_static_rotation_offset"] = a_mean if s == "R" else -a_mean
    return subject.with_static_offsets(**kw)


def plug_in_gait(trial: MarkerTrial, subject: SubjectMeasurements) -> PiGResult:
    """Run the Plug-in-Gait lower-body model on a (dynamic or static) trial.

    Parameters
    ----------
    trial : MarkerTrial with the Plug-in-Gait lower-body markers (metres)
    subject : SubjectMeasurements; the static foot offsets (see
        `static_foot_offsets`) are needed for ankle angles, else they are NaN.

    Returns
    -------
    PiGResult
    """
    segs, centres = _chain(trial, subject)
    cov = _centre_covariance(trial, subject, centres)
    angles, notes = leg_angles(trial, subject, segs, centres, "run static_foot_offsets")
    return PiGResult(segs, centres, cov, angles, trial.time, trial.source, tuple(notes))


def leg_angles(trial: MarkerTrial, subject: SubjectMeasurements, segs: dict, centres: dict,
               uncalibrated_hint: str) -> tuple[dict, list[str]]:
    """Plug-in-Gait hip, knee and ankle angles of both legs; adds the ``foot_r/_l`` segments to `segs`.

    `segs` uses this module's names (``tibia_untorsioned`` for the knee, ``tibia``
    with torsion for the ankle).  Without static foot offsets the ankle angles
    are NaN and a note (ending with `uncalibrated_hint`) says so.

    Returns
    -------
    angles : dict ``hip_r, knee_r, ankle_r, ..._l`` -> (F, 3) radians
    notes : list of str
    """
    angles, notes = {}, []
    for s, sfx in (("R", "_r"), ("L", "_l")):
        m = subject.side(s)
        angles[f"hip{sfx}"] = joint_angles(segs["pelvis"], segs[f"femur{sfx}"], "hip", s)
        angles[f"knee{sfx}"] = joint_angles(segs[f"femur{sfx}"], segs[f"tibia_untorsioned{sfx}"], "knee", s)
        pf, ro = m["static_plantar_flexion"], m["static_rotation_offset"]
        if pf is None or ro is None:
            notes.append(f"{s} foot offsets not calibrated ({uncalibrated_hint}): ankle angles are NaN")
            angles[f"ankle{sfx}"] = np.full((trial.n_frames, 3), np.nan)
        else:
            segs[f"foot{sfx}"] = foot_frame(centres[f"ankle{sfx}"], trial.marker(f"{s}TOE"), segs[f"tibia{sfx}"], s, pf, ro)
            angles[f"ankle{sfx}"] = joint_angles(segs[f"tibia{sfx}"], segs[f"foot{sfx}"], "ankle", s)
    return angles, notes


def _centre_covariance(trial: MarkerTrial, subject: SubjectMeasurements, centres: dict, h: float = 1e-4) -> dict:
    """Covariance of hip/knee/ankle centres from the hip regression error.

    Cov(hip) = σ² I; Cov(knee) = J_k Cov(hip) J_kᵀ with J_k = ∂knee/∂hip of the
    chord function (central differences, step `h` m); Cov(ankle) likewise
    through ∂ankle/∂knee.  Median over frames of the per-frame matrices.
    """
    out = {}
    for s, sfx in (("R", "_r"), ("L", "_l")):
        Jk, Ja = chord_centre_jacobians(trial, subject, s, centres[f"hip{sfx}"], centres[f"knee{sfx}"], h)
        c_hip = DAVIS_HIP_SD**2 * np.eye(3)
        c_knee = np.einsum("fij,jk,flk->fil", Jk, c_hip, Jk)
        c_ankle = np.einsum("fij,fjk,flk->fil", Ja, c_knee, Ja)
        out[f"hip{sfx}"] = c_hip
        out[f"knee{sfx}"] = median_covariance(c_knee)
        out[f"ankle{sfx}"] = median_covariance(c_ankle)
    return out


def median_covariance(c: np.ndarray) -> np.ndarray:
    """Element-wise median (3, 3) of per-frame covariances c (F, 3, 3) over the finite frames (NaN if none)."""
    ok = np.all(np.isfinite(c), axis=(1, 2))
    return np.median(c[ok], axis=0) if ok.any() else np.full((3, 3), np.nan)
