"""Fusion of the derived joint parameters both sources estimate: segment lengths and the knee's standing translation.

Issue P1 (item 2) fuses, besides the joint centres and axes, the segment
lengths and the intercepts of the correlative knee law.

Segment lengths.  A length is a distance between two joint centres, so it
does not depend on the frame: the MRI length is measured in the scanner
(between the detected centres, whose covariances are the detectors'), the
motion length in the lab (functional hip centre, marker-based knee and
ankle centres).  To first order, with u = (p - q) / |p - q|,

    L = |p - q|,    σ_L² = uᵀ (C_p + C_q - C_pq - C_pqᵀ) u,

and the two sources are fused as 1-D Gaussians (`personalize.fusion.fuse_gaussian`).

Knee law intercept.  The law t = S q + c (`kinematics.mechanisms.correlative`) is
stored with its constant term as the knee translation at the standing pose,
t_st (`personalize.model_builder`).  MRI: the femur's and the tibia's knee
points are one point of the scan, t_st = 0, with the detection covariance
of the knee centre plus an assumed posture term (supine and unloaded in the
scanner, standing and loaded in the lab: `MRI_POSTURE_SD`).  Motion: t_st of
the law fitted to IK with free knee translations, with the fit's own
covariance plus the soft-tissue-artefact floor `MOTION_KNEE_TRANSLATION_SD`:
on 8 training phantoms (16 legs; `personalize run`, then IK with free knee
translations on the gait and crouch trials, flexion law fitted; truth 0) the
standing translation was off by 2.5 / 2.2 / 2.3 mm rms (anterior, proximal,
lateral) while the fit's formal sd was about 0.1 mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lowerlimb.errors import InputError
from lowerlimb.estimates import Gaussian
from .fusion import Fused, fuse_gaussian

__all__ = ["SegmentLength", "SEGMENTS", "MRI_POSTURE_SD", "MOTION_KNEE_TRANSLATION_SD", "segment_length", "fuse_segment_lengths",
           "fuse_knee_standing_translation"]

#: segment -> (proximal centre, distal centre)
SEGMENTS = {"thigh": ("hip", "knee"), "shank": ("knee", "ankle")}
#: m, knee translation between the supine unloaded scan and standing (assumed: cartilage compression and
#: laxity of about a millimetre)
MRI_POSTURE_SD = 0.001
#: m per axis, soft-tissue-artefact floor of the motion standing translation (training phantoms, see module doc)
MOTION_KNEE_TRANSLATION_SD = 0.0023


def segment_length(p, q, cov_p, cov_q, cov_pq=None) -> tuple[float, float]:
    """Distance |p - q| (m) and its first-order variance (m²).

    Parameters
    ----------
    p, q : (3,) m
    cov_p, cov_q : (3, 3) m²
    cov_pq : (3, 3) m², cross-covariance E[(p - p̄)(q - q̄)ᵀ], optional

    Raises
    ------
    InputError
        Coincident points (no direction).
    """
    d = np.asarray(p, float) - np.asarray(q, float)
    L = float(np.linalg.norm(d))
    if not np.isfinite(L) or L < 1e-9:
        raise InputError("segment length", "the two centres coincide or are not finite")
    u = d / L
    C = np.asarray(cov_p, float) + np.asarray(cov_q, float)
    if cov_pq is not None:
        X = np.asarray(cov_pq, float)
        C = C - X - X.T
    return L, float(u @ C @ u)


@dataclass(frozen=True)
class SegmentLength:
    """A segment length from both sources and fused (m; variances m²): 1-D Gaussians."""

    mri: Gaussian
    motion: Gaussian
    fused: Fused

    def summary(self) -> dict:
        """JSON-ready: mri, mri_sd, motion, motion_sd (m) and the fused `Fused.summary()`."""
        return {"mri": float(self.mri.mean[0]), "mri_sd": float(self.mri.sd[0]), "motion": float(self.motion.mean[0]),
                "motion_sd": float(self.motion.sd[0]), "fused": self.fused.summary()}


def fuse_segment_lengths(mri: dict, motion: dict, sides=("r", "l")) -> dict[str, SegmentLength]:
    """MRI and motion thigh and shank lengths fused as Gaussians.

    Parameters
    ----------
    mri, motion : dict centre name (``hip_r``, ``knee_r``, ``ankle_r``, ``_l``) -> `Gaussian` (position (3,) m,
        covariance (3, 3) m²), each in its own frame
    sides : sides to report

    Returns
    -------
    dict ``thigh_r``, ``shank_r``, ... -> `SegmentLength` (each variance floored at 1e-12 m² for the fusion);
    segments a source cannot measure are left out
    """
    out = {}
    for s in sides:
        for seg, (a, b) in SEGMENTS.items():
            ka, kb = f"{a}_{s}", f"{b}_{s}"
            if not all(k in src for src in (mri, motion) for k in (ka, kb)):
                continue
            Lm, vm = segment_length(mri[ka].mean, mri[kb].mean, mri[ka].cov, mri[kb].cov)
            Lk, vk = segment_length(motion[ka].mean, motion[kb].mean, motion[ka].cov, motion[kb].cov)
            f = fuse_gaussian([(Lm, max(vm, 1e-12)), (Lk, max(vk, 1e-12))], ("mri", "motion"))
            out[f"{seg}_{s}"] = SegmentLength(Gaussian(Lm, vm), Gaussian(Lk, vk), f)
    return out


def fuse_knee_standing_translation(mri_knee_cov, motion_translation, motion_cov=None, *,
                                   posture_sd: float = MRI_POSTURE_SD,
                                   motion_floor: float = MOTION_KNEE_TRANSLATION_SD) -> Fused:
    """Fused knee translation at the standing pose (the knee law's intercept; module docstring).

    Model: MRI t_st = 0 with covariance C_K + posture_sd² I (C_K the knee centre's detection covariance);
    motion t_st = t_m with covariance C_m + motion_floor² I; the product of the two Gaussians.

    Parameters
    ----------
    mri_knee_cov : (3, 3) m², detection covariance of the MRI knee centre, on the law's axes
        (anterior, proximal, lateral of the knee frame: Rᵀ C R for a lab covariance C and knee frame R)
    motion_translation : (3,) m, (knee_tx, knee_ty, knee_tz) of the fitted law at the standing pose
    motion_cov : (3, 3) m², the fit's covariance of that prediction (optional)

    Returns
    -------
    Fused (sources "mri", "motion"; mean (3,) m in the law's (tx, ty, tz) order)
    """
    tm = np.asarray(motion_translation, float).reshape(3)
    Cm = (np.zeros((3, 3)) if motion_cov is None else np.asarray(motion_cov, float)) + motion_floor**2 * np.eye(3)
    Cr = np.asarray(mri_knee_cov, float) + posture_sd**2 * np.eye(3)
    return fuse_gaussian([(np.zeros(3), Cr), (tm, Cm)], ("mri", "motion"))
