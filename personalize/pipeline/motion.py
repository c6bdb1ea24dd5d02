"""Joint estimates from motion capture alone, in the lab frame of the static trial (m, unit vectors).

Marker clusters are referenced to their static positions, so a cluster frame
IS the static lab frame: SCoRE hip centres (pelvis vs thigh clusters, on the
functional trial), SARA knee axes (thigh vs shank clusters, on the other
dynamic trials); the Plug-in-Gait reconstruction of the static trial gives the
knee and ankle centres, the Davis hip and the torsioned-tibia ankle axis
(fall-backs without functional data or medial markers).  Each estimate carries
its covariance (sd) with the soft-tissue-artefact terms below, calibrated on
TRAINING phantoms (values and sources: ``calibration.json``).
"""
from __future__ import annotations

import numpy as np

from kinematics.io.markers import MarkerTrial
from lowerlimb.errors import InputError
from lowerlimb.estimates import Gaussian

from .inputs import PELVIS_MARKERS
from .joint_estimates import Direction

__all__ = ["motion_hip", "motion_knee_axis", "pig_static", "pig_centre", "aliased_static", "MOTION_HIP_STA_COV",
           "MOTION_KNEE_AXIS_SD_DEG", "MOTION_ANKLE_AXIS_SD_DEG", "PIG_ANKLE_AXIS_SD_DEG", "PIG_CENTRE_SD",
           "DAVIS_HIP_SD", "PIG_KNEE_AXIS_SD_DEG", "THIGH_MARKERS", "SHANK_MARKERS"]

#: soft-tissue-artefact covariance of a SCoRE hip centre (m²) in the pelvis axes (anterior, medial, up; left legs
#: mirrored): the second moment about zero of the training legs' SCoRE errors (sds 4.9, 7.2, 10.4 mm;
#: calibration.json ``motion_hip_sta_cov``)
MOTION_HIP_STA_COV = np.array([[23.7, 1.5, -21.4], [1.5, 51.6, 15.0], [-21.4, 15.0, 108.3]]) * 1e-6
#: soft-tissue-artefact sd of a SARA knee axis on skin-marker clusters (14 deg rms actual; calibration.json)
MOTION_KNEE_AXIS_SD_DEG = 10.0
#: the transmalleolar axis ANK - ANKM of the static trial: the palpation value (~3 mm per marker over a ~70 mm
#: malleolar span), not the phantoms' 0.07 deg (their malleolar markers sit exactly on the talocrural axis), which
#: would make the markers override the MRI on real data (calibration.json)
MOTION_ANKLE_AXIS_SD_DEG = 3.0
#: Plug-in-Gait torsioned-tibia ankle axis (no medial malleolus marker): assumed sd, not calibrated
PIG_ANKLE_AXIS_SD_DEG = 6.0
#: Plug-in-Gait knee / ankle centre sd (m per axis), calibrated on TRAINING phantoms
#: (benchmarks/knee_ankle_calibration.py, mean Mahalanobis d² = 3; calibration.json)
PIG_CENTRE_SD = {"knee": 0.0051, "ankle": 0.0083}
#: fall-backs without functional data: Davis regression hip centre (errors ~1-3 cm, Leardini et al. 1999),
#: Plug-in-Gait knee axis from the KNE/THI markers
DAVIS_HIP_SD = 0.015
PIG_KNEE_AXIS_SD_DEG = 8.0

THIGH_MARKERS = ("THI", "KNE", "THIP", "THIA", "KNEM", "TRO")
SHANK_MARKERS = ("TIB", "ANK", "ANKM", "TIBM1", "TIBM2", "TIBM3", "TTB", "HFB")
#: static-marker aliases to the landmark names of `personalize.registration` (medial markers)
_ALIASES = {"KNEM": "MFC", "ANKM": "MMA"}


def cluster_pose(static: MarkerTrial, trials, names):
    """Cluster poses over the concatenated trials; the cluster frame is the static lab frame."""
    from kinematics.algorithms.segments import rigid_pose

    from ..registration import static_marker_positions

    ref_of = {n: g.mean for n, g in static_marker_positions(static, names).items()}
    use = [n for n in ref_of if all(n in t.names for t in trials)]
    if len(use) < 3:
        return None
    ref = np.array([ref_of[n] for n in use])
    meas = np.concatenate([t.subset(use).positions for t in trials], axis=0)
    return rigid_pose(ref, meas)


def _sta_cov(axes, side: str) -> np.ndarray:
    """`MOTION_HIP_STA_COV` in the lab: A M Σ M Aᵀ (A the pelvis axes, M mirrors y for a left leg)."""
    M = np.diag([1.0, -1.0 if side == "l" else 1.0, 1.0])
    A = np.eye(3) if axes is None else np.asarray(axes, float)
    return A @ M @ MOTION_HIP_STA_COV @ M @ A.T


def motion_hip(static, functional: MarkerTrial, side: str, axes=None):
    """SCoRE hip centre (static lab frame, m) as a `Gaussian`, and the SCoRE estimate itself.

    Cov = SCoRE's residual covariance + the soft-tissue-artefact term
    `MOTION_HIP_STA_COV` (pelvis axes `axes`, 3x3 columns x, y, z; the static
    lab axes if None).
    """
    from kinematics.algorithms.functional import score

    S = side.upper()
    P = cluster_pose(static, [functional], PELVIS_MARKERS + ("SACR",))
    D = cluster_pose(static, [functional], tuple(S + m for m in THIGH_MARKERS))
    if P is None or D is None:
        raise InputError(functional.source, f"SCoRE needs 3 pelvis and 3 {S} thigh markers")
    est = score(P.R, P.t, D.R, D.t)
    return Gaussian(est.proximal, est.cov_proximal + _sta_cov(axes, side)), est


def motion_knee_axis(static, trials, side: str):
    """SARA knee axis (static lab frame) of the thigh and shank clusters over `trials`.

    sd = √(SARA's direction sd² + `MOTION_KNEE_AXIS_SD_DEG`²).
    """
    from kinematics.algorithms.functional import sara

    S = side.upper()
    P = cluster_pose(static, trials, tuple(S + m for m in THIGH_MARKERS))
    D = cluster_pose(static, trials, tuple(S + m for m in SHANK_MARKERS))
    if P is None or D is None:
        raise InputError(static.source, f"SARA needs 3 {S} thigh and 3 {S} shank markers")
    est = sara(P.R, P.t, D.R, D.t)
    return Direction(est.direction_proximal, float(np.hypot(np.degrees(est.direction_sd), MOTION_KNEE_AXIS_SD_DEG)))



def aliased_static(static: MarkerTrial) -> MarkerTrial:
    names = list(static.names)
    pos = [static.positions]
    for s in "RL":
        for a, b in _ALIASES.items():
            if s + a in static.names and s + b not in static.names:
                names.append(s + b)
                pos.append(static.marker(s + a)[:, None])
    return MarkerTrial(tuple(names), np.concatenate(pos, axis=1), static.rate, static.time, static.source, static.extra)



def pig_static(inputs):
    """Plug-in-Gait reconstruction of the static trial (knee and ankle centres, torsioned tibia)."""
    from kinematics.gait.reconstruction import reconstruct

    return reconstruct(inputs.static, "pig", static=inputs.static, subject=inputs.subject, check_static=False)



def pig_centre(rec, joint: str, side: str) -> Gaussian:
    """Plug-in-Gait knee or ankle centre of the static reconstruction `rec` (median over frames), sd `PIG_CENTRE_SD`."""
    return Gaussian.isotropic(np.median(rec.centres[f"{joint}_{side}"], axis=0), PIG_CENTRE_SD[joint])
