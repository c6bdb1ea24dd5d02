"""Foot-to-hip reconstruction of the leg (Tändl et al. 2010, section 3.3, eqs. 26-37).

Instead of starting at the hip (Plug-in-Gait), the knee and ankle axes are
found from the foot and shank markers, which carry less (or more predictable)
soft-tissue artefact, and the hip centre last, as the femur-fixed point that
moves least relative to the pelvis.  Knee and ankle are revolute joints.

Per frame, for one leg with knee marker KNE, ankle marker ANK, heel HEE and
toe TOE (lab, metres) and the anthropometric distances d_knee, d_ankle from
the joint centres to the markers (half the joint width plus the marker radius):

    d = |KNE - ANK|,  u_tibma = (KNE - ANK) / d
    sin α = (d_knee - d_ankle cos φ) / d                                   (26)
    n = ±unit(u_foot' × u_tibma)      (pointing laterally)
    u = cos α n + sin α u_tibma        (knee axis, lateral)                 (27)
    r_knee = KNE - d_knee u                                                 (28)
    u_a = Rot(u_tibma, φ) u,  r_ankle = ANK - d_ankle u_a

with u_foot' = Rot(u_tibma, β) unit(TOE - HEE).  The seed assumes the
heel-toe line perpendicular to both axes and the axes parallel (β = φ = 0,
which gives its equations exactly); `calibrate` finds β (heel-toe line vs
knee axis) and φ (ankle vs knee axis, i.e. tibial torsion) from a static
trial with medial knee and ankle markers, or φ from the measured tibial
torsion.  The femur frame (eq. 29) has e3 = u and e1 ∥ (THI - r_knee) × u.
The hip centre x* = (x1, x2, 0) in that frame minimises the spread of its
path in the pelvis frame (centre transformation technique, eqs. 30-37,
`kinematics.algorithms.functional.centre_transformation` with the basis [e1 e2]).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lowerlimb.errors import FitError, InputError
from lowerlimb.geometry import marker_radius
from kinematics.algorithms.functional import CentreEstimate, centre_transformation
from kinematics.io.markers import MarkerTrial
from kinematics.gait.pig import SegmentPose, unit_vectors
from kinematics.gait.subject import SubjectMeasurements

__all__ = ["FootToHipCalibration", "ShankEstimate", "calibrate", "knee_ankle_axes", "seed_femur_frame",
           "hip_centre_in_pelvis", "rotate_about", "REQUIRED_MARKERS"]

#: markers foot-to-hip needs on each side (plus the pelvis: ASI and PSI or SACR)
REQUIRED_MARKERS = ("THI", "KNE", "ANK", "HEE", "TOE")


def rotate_about(v: np.ndarray, axis: np.ndarray, angle) -> np.ndarray:
    """Rodrigues rotation of vectors v (F, 3) about unit axes (F, 3) by `angle` (scalar or (F,)), rad."""
    a = np.asarray(angle, float)[..., None] if np.ndim(angle) else float(angle)
    c, s = np.cos(a), np.sin(a)
    return v * c + np.cross(axis, v) * s + axis * np.sum(axis * v, axis=-1, keepdims=True) * (1 - c)


def _signed_angle(a, b, axis):
    """Angle (F,) rotating the projection of a onto the projection of b about `axis` (right hand)."""
    pa = a - np.sum(a * axis, -1, keepdims=True) * axis
    pb = b - np.sum(b * axis, -1, keepdims=True) * axis
    return np.arctan2(np.sum(np.cross(pa, pb) * axis, -1), np.sum(pa * pb, -1))


@dataclass(frozen=True)
class FootToHipCalibration:
    """Per-side constants of the foot-to-hip model (side key ``'R'``/``'L'``).

    d_knee, d_ankle : m, joint centre to marker centre along the axis
    foot_offset : rad, β, rotation of the heel-toe line about the shank line
        that makes it perpendicular to the knee axis (0 in the seed)
    axis_rotation : rad, φ, ankle axis = knee axis rotated about the shank line (0 in the seed)
    foot_offset_sd, axis_rotation_sd : rad, spread over the static frames (0 if not calibrated)
    source : how β and φ were obtained
    """

    d_knee: dict
    d_ankle: dict
    foot_offset: dict
    axis_rotation: dict
    foot_offset_sd: dict = field(default_factory=lambda: {"R": 0.0, "L": 0.0})
    axis_rotation_sd: dict = field(default_factory=lambda: {"R": 0.0, "L": 0.0})
    source: str = "seed"


@dataclass(frozen=True)
class ShankEstimate:
    """Knee and ankle axes and centres of one leg, per frame (lab, m).

    knee_axis, ankle_axis : (F, 3) unit, pointing laterally
    knee, ankle : (F, 3) m
    alpha : (F,) rad, eq. (26)
    """

    knee_axis: np.ndarray
    ankle_axis: np.ndarray
    knee: np.ndarray
    ankle: np.ndarray
    alpha: np.ndarray


def knee_ankle_axes(kne, ank, hee, toe, d_knee: float, d_ankle: float, side: str,
                    foot_offset: float = 0.0, axis_rotation: float = 0.0) -> ShankEstimate:
    """Knee and ankle axes and centres from the knee, ankle, heel and toe markers (eqs. 26-28).

    Parameters
    ----------
    kne, ank, hee, toe : (F, 3) m, lab
    d_knee, d_ankle : m
    side : 'R' or 'L'
    foot_offset, axis_rotation : rad, β and φ of the module docstring

    Returns
    -------
    ShankEstimate; NaN in frames where a marker is missing or |sin α| > 1.
    """
    kne, ank, hee, toe = (np.asarray(v, float) for v in (kne, ank, hee, toe))
    right = side.upper()[0] == "R"
    v = kne - ank
    d = np.linalg.norm(v, axis=-1)
    u_t = unit_vectors(v)
    u_f = unit_vectors(toe - hee)
    if foot_offset:
        u_f = rotate_about(u_f, u_t, foot_offset)
    # heel-toe points forward, the shank line up: forward x up points to the subject's left
    n = np.cross(u_f, u_t) if right else np.cross(u_t, u_f)
    n = unit_vectors(n - np.sum(n * u_t, -1, keepdims=True) * u_t)
    with np.errstate(invalid="ignore"):
        sa = (d_knee - d_ankle * np.cos(axis_rotation)) / d
        sa = np.where(np.abs(sa) <= 1, sa, np.nan)
    alpha = np.arcsin(sa)
    u = np.cos(alpha)[:, None] * n + np.sin(alpha)[:, None] * u_t
    u_a = rotate_about(u, u_t, axis_rotation) if axis_rotation else u
    return ShankEstimate(u, u_a, kne - d_knee * u, ank - d_ankle * u_a, alpha)


def seed_femur_frame(knee, knee_axis, thigh_marker, side: str) -> SegmentPose:
    """Femur frame of eq. (29) in Plug-in-Gait axes: origin knee centre, y = knee axis pointing left
    (e3 = ±y), x = unit(y × (THI - knee)) = e1 (anterior), z = x × y = e2 (proximal)."""
    right = side.upper()[0] == "R"
    y = -knee_axis if right else knee_axis
    x = unit_vectors(np.cross(y, np.asarray(thigh_marker, float) - knee))
    z = np.cross(x, y)
    return SegmentPose(np.asarray(knee, float), np.stack([x, y, z], axis=-1))


def hip_centre_in_pelvis(pelvis: SegmentPose, femur: SegmentPose, planar: bool = True) -> CentreEstimate:
    """Hip centre by the centre transformation technique (eqs. 30-37).

    The femur-fixed point x1 e1 + x2 e2 (the thigh-shank plane of the eq. 29
    frame) whose path in the pelvis frame has the least spread about its
    centroid; ``proximal`` is the centroid (pelvis frame), ``distal`` the point
    in the femur frame.  With ``planar=False`` the out-of-plane coordinate x3
    is estimated too (needs hip ab/adduction, e.g. a star-arc trial): the seed
    fixes x3 = 0 because gait alone barely shows it.
    """
    basis = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]]) if planar else np.eye(3)
    try:
        return centre_transformation(pelvis.axes, pelvis.origin, femur.axes, femur.origin, basis=basis)
    except FitError as exc:
        raise FitError(f"hip centre (centre transformation): {exc}") from None


def calibrate(subject: SubjectMeasurements, static: MarkerTrial | None = None) -> FootToHipCalibration:
    """Foot-to-hip constants of a subject.

    d_knee = knee width / 2 + marker radius and d_ankle = ankle width / 2 +
    marker radius (the seed's anthropometric distances).  With a static trial
    showing the medial knee (``RKNEM``) and medial ankle (``RANKM``) markers,
    β and φ are the median angles, about the shank line, between the eq. (27)
    axis and the epicondylar line KNE-KNEM, and between that line and the
    malleolar line ANK-ANKM.  Without them φ = -tibial torsion (measured,
    Plug-in-Gait convention) and β = 0 (the seed's assumption).
    """
    r = marker_radius(subject.marker_diameter)
    dk = {s: 0.5 * subject.side(s)["knee_width"] + r for s in "RL"}
    da = {s: 0.5 * subject.side(s)["ankle_width"] + r for s in "RL"}
    beta = {"R": 0.0, "L": 0.0}
    phi = {s: -float(subject.side(s)["tibial_torsion"]) for s in "RL"}
    beta_sd = {"R": 0.0, "L": 0.0}
    phi_sd = {"R": 0.0, "L": 0.0}
    sources = []
    for s in "RL":
        need = [f"{s}{m}" for m in ("KNE", "ANK", "HEE", "TOE", "KNEM")]
        if static is None or any(n not in static.names for n in need):
            sources.append(f"{s}: seed (heel-toe line perpendicular to the knee axis)")
            continue
        M = static.marker
        kne, ank = M(f"{s}KNE"), M(f"{s}ANK")
        u_t = unit_vectors(kne - ank)
        if f"{s}ANKM" in static.names:
            u_k = unit_vectors(kne - M(f"{s}KNEM"))
            u_a = unit_vectors(ank - M(f"{s}ANKM"))
            p = _signed_angle(u_k, u_a, u_t)
            ok = np.isfinite(p)
            if ok.sum() >= 3:
                phi[s], phi_sd[s] = float(np.median(p[ok])), float(np.std(p[ok]))
        est = knee_ankle_axes(kne, ank, M(f"{s}HEE"), M(f"{s}TOE"), dk[s], da[s], s, 0.0, phi[s])
        b = _signed_angle(est.knee_axis, unit_vectors(kne - M(f"{s}KNEM")), u_t)
        ok = np.isfinite(b)
        if ok.sum() < 3:
            raise InputError(static.source, f"{s} knee/ankle/foot markers never visible together in the static trial")
        beta[s], beta_sd[s] = float(np.median(b[ok])), float(np.std(b[ok]))
        sources.append(f"{s}: static medial markers")
    return FootToHipCalibration(dk, da, beta, phi, beta_sd, phi_sd, "; ".join(sources))
