"""Registration of a leg segment from its markers plus the proximal joint centre already located in the lab.

A joint centre is a point of both bones: once the fused hip centre is known in
the lab, the femur is registered from its markers (`personalize.marker_registration.marker_correspondences`)
and that centre, the shank from its markers and the fused knee centre, the foot
from its markers and the fused ankle centre, so each MRI joint centre and axis
reaches the lab with its propagated covariance.
"""
from __future__ import annotations

import numpy as np

from lowerlimb.errors import FitError, InputError
from lowerlimb.estimates import Gaussian

from ..marker_registration import marker_correspondences
from ..registration import GATE_P, Registration, gate_statistic, scaled_skin_prior

__all__ = ["register_with_centre", "carried_by_own_markers", "toe_landmark"]


def register_with_centre(seg: str, bones: dict, bone_names, marker_names, static: dict, meshes: dict,
                         centre_mri: Gaussian | None, centre_lab: Gaussian | None, axis=None, virtual=None,
                         fallback=(), extra=(), sites=None, tissue_scale=None) -> Registration:
    """Register one segment from its markers plus one joint centre known in both frames.

    ``axis = (point, direction)`` (scanner frame): the landmarks are projected on
    that joint axis first (`marker_correspondences`, which also takes `sites`).  ``virtual``: {marker name:
    (scanner point, outward normal)} for markers over a point that is not itself a
    landmark (TOE over the mid-point of the first and fifth metatarsal heads).
    ``fallback``: extra (name, mri `Gaussian`, lab `Gaussian`) pairs used only when
    fewer than 3 correspondences are available (a Plug-in-Gait marker set without
    medial knee/ankle markers: the distal joint centre of Plug-in-Gait stands in,
    and the MRI estimates of that segment are then not independent of the motion ones).  ``extra``: (name,
    mri `Gaussian`, lab `Gaussian`) pairs always used (`virtual_markers.joint_axis_pairs`).  The joint centre and
    the ``extra`` pairs tie the segment to its proximal neighbour and are never rejected as outliers: a segment
    whose markers disagree with them fails its chi-square gate instead of coming loose from the joint.
    """
    thick = sd = None
    if tissue_scale is not None:
        # the subject's soft-tissue scale (estimated with the pelvis) on every site prior
        prior = {n: scaled_skin_prior(n, *tissue_scale) for n in marker_names}
        thick = {n: t for n, (t, _) in prior.items()}
        sd = {n: d for n, (_, d) in prior.items()}
    corr = marker_correspondences(bones, bone_names, marker_names, static, surfaces=meshes, axis=axis, sites=sites,
                                  skin_thickness=thick, skin_sd=sd, palpated=True)
    for n, (p, nrm) in (virtual or {}).items():
        if n in static:
            corr.add_marker(n, Gaussian(p, np.zeros((3, 3))), static[n], nrm, palpated=True)
    if centre_mri is not None and centre_lab is not None:
        corr.add("joint_centre", centre_mri, centre_lab)
    for name, mri, lab in extra:
        corr.add(name, mri, lab)
    if len(corr) < 3:
        for name, mri, lab in fallback:
            corr.add(name, mri, lab)
    if len(corr) < 3:
        raise InputError(seg, f"only {len(corr)} correspondences ({', '.join(corr.names) or 'none'}) to register the segment")
    return corr.register(seg, fixed=("joint_centre", *(name for name, _, _ in extra)))


def carried_by_own_markers(seg: str, bones: dict, bone_names, marker_names, static: dict, meshes: dict, point, *,
                           axis=None, sites=None, virtual=None, tissue_scale=None) -> Gaussian | None:
    """`point` (scanner frame) carried into the lab by segment `seg` registered on its own bony markers alone.

    A joint centre is a point of both its bones; the distal bone registered without the proximal joint's anchor
    gives an estimate whose error is independent of the proximal chain's.  None when fewer than three of
    `marker_names` pair with MRI landmarks or the registration fails its chi-square gate (`registration.GATE_P`).
    The covariance is the registration's, uncalibrated (the caller scales it).
    """
    if sum(n in static for n in marker_names) < 3:
        return None
    try:
        reg = register_with_centre(seg, bones, bone_names, marker_names, static, meshes, None, None, axis=axis,
                                   sites=sites, virtual=virtual, tissue_scale=tissue_scale)
    except (InputError, FitError):
        return None
    if len(reg.names) < 3 or gate_statistic(reg)[2] < GATE_P:
        return None
    return reg.transfer_estimate(point)


def toe_landmark(calcn, S: str) -> dict:
    """Virtual TOE landmark where the foot detector found no ``<S>TOE`` (the dorsum over the second metatarsal
    head, `personalize.landmarks.foot`): the mid-point of the dorsal points of the metatarsal head spheres
    (``met1_dorsal``, ``met5_dorsal``), normal = the foot frame's up (Y) axis; {} when the detector found it."""
    if calcn is None:
        return {}
    lm, fr = calcn.landmarks, calcn.frames
    if f"{S}TOE" in lm or "met1_dorsal" not in lm or "met5_dorsal" not in lm or "foot" not in fr:
        return {}
    mid = 0.5 * (lm["met1_dorsal"].position + lm["met5_dorsal"].position)
    return {f"{S}TOE": (mid, np.asarray(fr["foot"]["rotation"], float)[:, 1])}
