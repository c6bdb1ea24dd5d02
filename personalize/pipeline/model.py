"""The personalised model of a subject: the model builder's parameters from the joint estimates, the bone meshes."""
from __future__ import annotations

import numpy as np

from ..model_builder import SideParameters, SubjectParameters
from .inputs import SubjectInputs
from .joint_estimates import JointEstimates
from .marker_assignment import MarkerAssignment

__all__ = ["subject_parameters", "bone_meshes_lab"]


def subject_parameters(inputs: SubjectInputs, est: JointEstimates, static: dict,
                       markers: MarkerAssignment | None = None) -> SubjectParameters:
    """The model builder's input: fused centres and axes with their covariances, static markers, provenance.

    `static` : label -> `Gaussian` static marker positions (the trial's own labels); `markers`: their bodies
    (`marker_assignment.assign_markers`), None: the Plug-in-Gait name table of the builder.
    """

    sides = {}
    for s in inputs.sides:
        c, a, p = est.centres[s], est.axes[s], est.lines[s]
        sides[s] = SideParameters(
            hip=c["hip"].fused.mean, knee=c["knee"].fused.mean, knee_axis=a["knee"].fused.direction,
            ankle=c["ankle"].fused.mean, ankle_axis=a["ankle"].fused.direction,
            subtalar=p["subtalar"].point, subtalar_axis=p["subtalar"].direction, mtp=p["mtp"].point,
            mtp_axis=p["mtp"].direction, centre_cov={j: c[j].fused.cov for j in ("hip", "knee", "ankle")},
            axis_sd_deg={j: a[j].fused.sd_deg for j in ("knee", "ankle")})
    subj = inputs.subject
    mass = float(subj.mass) if subj.mass else 70.0
    height = float(subj.height) if subj.height else 1.75
    motion_centre = {j: (f"motion ({j}_centre_<side>_motion)" if any(k.startswith(f"{j}_centre_") for k in est.sources)
                         else "Plug-in-Gait static") for j in ("knee", "ankle")}
    sources = {"hip centres": "fused: MRI (pelvis registration) x motion (hip_<side>_motion)",
               "knee centres": f"fused: MRI (femur registration) x {motion_centre['knee']}",
               "knee axes": "fused: MRI (femur registration) x motion (knee_axis_<side>_motion)",
               "ankle centres": f"fused: MRI (shank registration) x {motion_centre['ankle']}",
               "ankle axes": "fused: MRI (shank registration) x motion (ankle_axis_<side>_motion)",
               "knee law": "default (model_builder.DEFAULT_KNEE_SLOPES); not fitted",
               "markers": "median static-trial positions",
               "mass": "subject.json" if subj.mass else "70 kg default (subject.json has no mass)"}
    if inputs.marker_set is not None:
        sources["marker set"] = inputs.marker_set_source or inputs.marker_set.name
    sources.update({k: v for k, v in est.sources.items()})
    return SubjectParameters(est.pelvis[0], est.pelvis[1], sides, {n: v.mean for n, v in static.items()},
                             mass, height, sources, name=inputs.folder.name or "subject",
                             marker_bodies=None if markers is None else dict(markers.bodies))




def bone_meshes_lab(surfaces: dict, est: JointEstimates, sides) -> dict:
    """Bone meshes moved into the static lab frame by their segment's registration: bone -> (mesh, body)."""
    seg_of = {"pelvis": ("pelvis", "pelvis")}
    for s in sides:
        seg_of.update({f"femur_{s}": (f"femur_{s}", f"femur_{s}"), f"patella_{s}": (f"femur_{s}", f"femur_{s}"),
                       f"tibia_{s}": (f"tibia_{s}", f"tibia_{s}"), f"fibula_{s}": (f"tibia_{s}", f"tibia_{s}"),
                       f"talus_{s}": (f"calcn_{s}", f"talus_{s}"), f"calcn_{s}": (f"calcn_{s}", f"calcn_{s}"),
                       f"toes_{s}": (f"calcn_{s}", f"toes_{s}")})
    out = {}
    for bone, surf in surfaces.items():
        if bone not in seg_of or seg_of[bone][0] not in est.registrations:
            continue
        reg = est.registrations[seg_of[bone][0]]
        m = surf.mesh.copy()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = reg.R, reg.t
        m.apply_transform(T)
        out[bone] = (m, seg_of[bone][1])
    return out
