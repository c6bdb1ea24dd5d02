r"""What closes a leg segment's rotation about its long axis when it shows only its lateral landmark marker.

A femur registered from the hip centre and one knee marker (Plug-in-Gait's
KNE) is free to turn about the line through them, and a shank registered from
the knee centre and one ankle marker (ANK) likewise; Plug-in-Gait closes that
freedom with the thigh and shank wands, whose placement error turns its knee
and ankle centres by tens of degrees (realistic phantoms on real bones: knee
and ankle centres 47 mm off, which the registrations then inherited).

Femur: a virtual medial epicondyle marker built from the MRI's epicondylar
width and a population prior on the knee axis in standing (parallel to the
pelvis's medio-lateral axis, orthogonal to the thigh), that prior's spread
as its covariance:

.. math::

    v = m_{lat} + L\,\hat n, \qquad L = w_{MRI} + t_{lat} + t_{med} + 2 r, \qquad
    \Sigma_v = \Sigma_{lat} + R\,\operatorname{diag}(\sigma_w^2,\;
               (L \sin\sigma_\theta)^2,\; (L \sin\sigma_\phi)^2)\,R^T

with :math:`m_{lat}` the knee marker, :math:`w_{MRI}` the distance between
the epicondyles along the MRI knee axis, :math:`t` the soft-tissue priors,
:math:`r` the marker radius, :math:`R = [\hat n, \hat a, \hat z]` (medial,
anterior, along the thigh), :math:`\sigma_\theta` =
`STANDING_HIP_ROTATION_SD_DEG`, :math:`\sigma_\phi` = `AXIS_TILT_SD_DEG`.

Shank: two points of the MRI knee flexion axis, :math:`p_\pm = c \pm
\ell\,\hat u` (scanner frame), are points of both bones that knee flexion
does not move, so the femur registration carries them into the lab,

.. math::

    y_\pm = R_f\,p_\pm + t_f, \qquad
    \Sigma_\pm = J_\pm \Sigma_f J_\pm^T + (\ell \sin\sigma_k)^2 I,

and they are paired with the same scanner points on the shank; only the
knee's secondary rotations between the scanner and the standing pose move
them, with sd :math:`\sigma_k` = `KNEE_STANDING_ROTATION_SD_DEG`.  They are
placed about the knee centre the shank is registered to (`knee_axis_pairs`),
so they constrain the direction only.  The
tibia's own torsion then comes from the MRI, not from a wand.

Foot: the MRI ankle axis carried by the shank registration the same way
(`ankle_axis_pairs`, sd `FOOT_STANDING_ROTATION_SD_DEG`), so that the talus
hangs from the tibia at the ankle: registered from its heel and metatarsal
markers alone, a foot whose palpated markers are 10-15 mm off put the talus
15-36 mm from the ankle joint of the model built on it.
"""
from __future__ import annotations

import numpy as np

from lowerlimb.estimates import Gaussian
from lowerlimb.geometry import DEFAULT_MARKER_RADIUS

__all__ = ["STANDING_HIP_ROTATION_SD_DEG", "AXIS_TILT_SD_DEG", "KNEE_STANDING_ROTATION_SD_DEG", "KNEE_AXIS_HALF_LENGTH",
           "WIDTH_SD", "virtual_medial_knee", "knee_axis_pairs", "ankle_axis_pairs", "joint_axis_pairs",
           "FOOT_STANDING_ROTATION_SD_DEG", "ANKLE_AXIS_HALF_LENGTH"]

#: deg, sd of the standing hip rotation (knee flexion axis vs the pelvis's medio-lateral axis about the thigh).
#: An assumption: quiet-standing hip rotation is within about +-10 deg in healthy adults; the value is not
#: tuned on any data set
STANDING_HIP_ROTATION_SD_DEG = 10.0
#: deg, sd of the knee or transmalleolar axis out of the transverse plane in standing (assumed)
AXIS_TILT_SD_DEG = 5.0
#: deg, sd of the knee's ab/adduction and axial rotation between the scanner pose and standing (both knees near
#: extension, where the screw-home mechanism locks the axial rotation; assumed)
KNEE_STANDING_ROTATION_SD_DEG = 5.0
#: m, half the distance between the two knee-axis points (about half an epicondylar width)
KNEE_AXIS_HALF_LENGTH = 0.04
#: deg, sd of the foot's rotation off the ankle flexion axis between the scanner and standing: the ankle's
#: secondary rotations and the subtalar joint, which the one-body foot registration lumps (assumed: subtalar
#: inversion-eversion in quiet standing within about +-10 deg)
FOOT_STANDING_ROTATION_SD_DEG = 10.0
#: m, half the distance between the two ankle-axis points (about half a talar dome's width)
ANKLE_AXIS_HALF_LENGTH = 0.02
#: m, sd of the lateral-to-medial marker distance (two tissue priors and the landmarks)
WIDTH_SD = 0.004



def _unit(v: np.ndarray) -> np.ndarray | None:
    n = float(np.linalg.norm(v))
    return None if not np.isfinite(n) or n < 1e-9 else v / n


def _tissue(marker: str) -> float:
    from ..registration import skin_prior

    return float(skin_prior(marker)[0])


def _virtual(lateral: Gaussian, medial: np.ndarray, along: np.ndarray, L: float, rot_sd_deg: float) -> Gaussian:
    """v = lateral + L n with the covariance of the module docstring (n medial, `along` the segment's axis)."""
    z = _unit(along - np.dot(along, medial) * medial)
    a = np.cross(z, medial)
    R = np.column_stack([medial, a, z])
    D = np.diag([WIDTH_SD**2, (L * np.sin(np.radians(rot_sd_deg)))**2, (L * np.sin(np.radians(AXIS_TILT_SD_DEG)))**2])
    return Gaussian(lateral.mean + L * medial, lateral.cov + R @ D @ R.T)


def _width(bones: dict, bone_names, lat: str, med: str, axis) -> float | None:
    """Distance (m) between the lateral and medial landmarks along the MRI joint axis `axis` (else straight)."""
    found = {}
    for b in bone_names:
        for n in (lat, med):
            if b in bones and n in bones[b].landmarks:
                found[n] = bones[b].landmarks[n].position
    if len(found) < 2:
        return None
    d = np.asarray(found[med], float) - np.asarray(found[lat], float)
    if axis is not None:
        u = _unit(np.asarray(axis, float))
        if u is not None:
            return float(abs(np.dot(d, u)))
    return float(np.linalg.norm(d))


def virtual_medial_knee(static: dict, bones: dict, side: str, hip: np.ndarray, pelvis_axes: np.ndarray,
                        knee_axis_mri=None) -> Gaussian | None:
    """Virtual medial epicondyle marker (``RMFC``/``LMFC``) from the knee marker and the pelvis axes.

    Parameters
    ----------
    static : marker -> `Gaussian` static position (lab, m); needs ``<S>KNE``
    bones : bone -> `personalize.landmarks.BoneLandmarks` (scanner, m); needs ``<S>KNE``, ``<S>MFC`` on the femur
    hip : (3,) the hip centre in the lab (m); pelvis_axes : (3, 3) columns x anterior, y left, z up
    knee_axis_mri : (3,) the MRI knee axis (scanner) along which the epicondylar width is measured

    Returns
    -------
    `Gaussian` (3,) m, (3, 3) m², or None when a marker or landmark is missing.
    """
    S = side.upper()
    lat = static.get(f"{S}KNE")
    w = _width(bones, [f"femur_{side}"], f"{S}KNE", f"{S}MFC", knee_axis_mri)
    if lat is None or w is None:
        return None
    thigh = _unit(np.asarray(hip, float) - lat.mean)
    y_left = np.asarray(pelvis_axes, float)[:, 1]
    n = y_left if side == "r" else -y_left
    n = _unit(n - np.dot(n, thigh) * thigh) if thigh is not None else None
    if n is None:
        return None
    L = w + _tissue(f"{S}KNE") + _tissue(f"{S}MFC") + 2.0 * DEFAULT_MARKER_RADIUS
    return _virtual(lat, n, thigh, L, STANDING_HIP_ROTATION_SD_DEG)


def joint_axis_pairs(reg_proximal, centre, axis, centre_lab, name: str, half_length: float,
                     rotation_sd_deg: float) -> list:
    """Two points of a joint's flexion axis as (name, scanner `Gaussian`, lab `Gaussian`) pairs.

    Placed about the joint centre the distal segment is registered to (`centre_lab`, lab, m; the fused one),
    along the proximal registration's axis, so that they add the axis's direction and nothing else:
    y± = k ± ℓ R_p u, Σ± = ℓ² [R_p u]× Ω_p [R_p u]×ᵀ + (ℓ sin σ)² I (Ω_p the registration's rotation
    covariance, ℓ = `half_length`, σ = `rotation_sd_deg` the joint's rotation off that axis between the scanner
    and standing).  `centre`, `axis` : (3,) the MRI joint centre and flexion axis (scanner, m); pairs named
    ``<name>_a``, ``<name>_b``.  Pass them as `register_with_centre`'s ``extra``.
    """
    from lowerlimb.geometry import skew

    u = _unit(np.asarray(axis, float))
    c = np.asarray(centre, float)
    w = reg_proximal.R @ u
    Om = np.asarray(reg_proximal.cov, float)[:3, :3]
    ell = float(half_length)
    C = ell**2 * skew(w) @ Om @ skew(w).T + (ell * np.sin(np.radians(rotation_sd_deg)))**2 * np.eye(3)
    k = np.asarray(centre_lab, float)
    return [(f"{name}_{tag}", Gaussian(c + sign * ell * u, 1e-8 * np.eye(3)), Gaussian(k + sign * ell * w, C))
            for sign, tag in ((1.0, "a"), (-1.0, "b"))]


def knee_axis_pairs(reg_femur, knee_centre, knee_axis, knee_lab, side: str) -> list:
    """The two knee-axis points of the module docstring (`joint_axis_pairs` of the femur registration,
    ``knee_axis_<side>_a``/``_b``, ℓ = `KNEE_AXIS_HALF_LENGTH`, σ = `KNEE_STANDING_ROTATION_SD_DEG`)."""
    return joint_axis_pairs(reg_femur, knee_centre, knee_axis, knee_lab, f"knee_axis_{side}", KNEE_AXIS_HALF_LENGTH,
                            KNEE_STANDING_ROTATION_SD_DEG)


def ankle_axis_pairs(reg_shank, ankle_centre, ankle_axis, ankle_lab, side: str) -> list:
    """The two ankle-axis points that hang the foot from the shank (`joint_axis_pairs` of the shank
    registration, ``ankle_axis_<side>_a``/``_b``, ℓ = `ANKLE_AXIS_HALF_LENGTH`, σ = `FOOT_STANDING_ROTATION_SD_DEG`)."""
    return joint_axis_pairs(reg_shank, ankle_centre, ankle_axis, ankle_lab, f"ankle_axis_{side}", ANKLE_AXIS_HALF_LENGTH,
                            FOOT_STANDING_ROTATION_SD_DEG)
