"""The ankle centre and axis (MRI and motion, fused), and the subtalar and metatarsophalangeal axes (MRI, else defaults).

The shank is registered from its ankle markers, projected on the MRI ankle
axis, and the fused knee centre; where the foot has three or more bony-landmark
markers, the foot registered on them alone carries the MRI ankle centre too and
the two are fused (`foot_ankle_centre`).  The foot is registered from its heel
and metatarsal markers (TOE over the second metatarsal head), the fused ankle centre
and the shank's ankle axis (else it follows the shank).  Motion: the transmalleolar axis ANK - MMA
of the static trial (else the Plug-in-Gait torsioned tibia) and the
Plug-in-Gait ankle centre (else the malleolus-marker midpoint,
`motion.condylar_centre`).  The scales are calibrated on TRAINING phantoms
(``calibration.json``).
"""
from __future__ import annotations

import numpy as np

from lowerlimb.errors import FitError, InputError
from lowerlimb.estimates import Gaussian

from ..frames import SUBTALAR_POPULATION, subtalar_direction
from ..fusion import Fused, fuse_axis, fuse_intersection
from ..registration import Registration
from .joint_estimates import AxisEstimates, AxisLine, CentreEstimates, Direction, JointContext, JointEstimates
from .knee import (SHANK_LANDMARKS, axis_sd, centre_model_error, centre_scale, condyle_labels, motion_centre,
                   mri_centre, shank_markers_site)
from .motion import MOTION_ANKLE_AXIS_SD_DEG, PIG_ANKLE_AXIS_SD_DEG
from .segment_registration import carried_by_own_markers, register_with_centre, toe_landmark
from .pig_uncertainty import pig_axis_sd_deg
from .virtual_markers import FOOT_STANDING_ROTATION_SD_DEG, KNEE_STANDING_ROTATION_SD_DEG, ankle_axis_pairs, knee_axis_pairs

__all__ = ["MRI_ANKLE_AXIS_SD_SCALE", "MRI_ANKLE_AXIS_MODEL_SD_DEG", "MRI_ANKLE_AXIS_MODEL_SD_DEG_MEASURED", "MRI_ANKLE_CENTRE_COV_SCALE", "MRI_ANKLE_CENTRE_COV_SCALE_MEASURED",
           "SUBTALAR_DEFAULT", "FOOT_LANDMARKS", "estimate_ankle", "foot_ankle_centre", "estimate_foot_axes", "MRI_ANKLE_MODEL_SD",
           "MRI_ANKLE_MODEL_SD_MEASURED", "MOTION_ANKLE_MODEL_SD"]

#: scale of the shank-registration ankle axis sd: claimed median 3.5 deg vs actual median 0.75 deg on 24 TRAINING
#: phantom subjects, with rare gross talus failures of 14-77 deg that carry large claimed sds (calibration.json)
MRI_ANKLE_AXIS_SD_SCALE = 0.51
#: deg, model-error angle added in quadrature to the scaled MRI ankle axis sd with prior soft tissue (realistic
#: phantoms, Rayleigh maximum likelihood chosen on the LHDL_CT legs of seed 1000, 95 % coverage 0.94 there, 1.00 on
#: ICL_MRI; the stated sd had covered 75 %; benchmarks/axis_calibration.py, calibration.json)
MRI_ANKLE_AXIS_MODEL_SD_DEG = 3.22
#: deg, the same with the pelvic tissue measured (analytic phantoms: none needed)
MRI_ANKLE_AXIS_MODEL_SD_DEG_MEASURED = 0.0
#: variance scale of the registered MRI ankle centre: prior pelvic tissue, with `MRI_ANKLE_MODEL_SD`, maximum
#: likelihood on the realistic phantoms (benchmarks/realistic_calibration.py, 32 legs of 16 real-anatomy subjects of
#: seed 1000, every marker set and lab, refitted on the phantoms with Plug-in-Gait's wands aimed as its protocol asks); with it
#: measured: analytic phantoms, mean Mahalanobis d² = 3 (benchmarks/knee_ankle_calibration.py; calibration.json)
MRI_ANKLE_CENTRE_COV_SCALE = 2.4793
MRI_ANKLE_CENTRE_COV_SCALE_MEASURED = 0.050
#: model-error sd (m per axis) added to the scaled MRI ankle centre covariance with prior soft tissue (realistic
#: phantoms, benchmarks/realistic_calibration.py; calibration.json)
MRI_ANKLE_MODEL_SD = 0.00161
#: model-error sd (m per axis) added to the MRI ankle centre covariance with the pelvic tissue measured (realistic
#: phantoms' analytic subjects, benchmarks/realistic_calibration.py; calibration.json)
MRI_ANKLE_MODEL_SD_MEASURED = 0.00025
#: model-error sd (m per axis) added to the motion ankle centre's stated covariance (realistic phantoms,
#: benchmarks/realistic_calibration.py; calibration.json)
MOTION_ANKLE_MODEL_SD = 0.0
#: default subtalar axis (Inman 1976): 42 deg up from the foot's long axis, 23 deg medial, in the static lab
SUBTALAR_DEFAULT = tuple(mean for mean, _ in SUBTALAR_POPULATION.values())


#: the foot's bony-landmark markers (side letter dropped): heel, first and fifth metatarsal heads, toe
FOOT_LANDMARKS = ("HEE", "D1M", "D5M", "TOE")


def foot_ankle_centre(ctx: JointContext, s: str, est: JointEstimates) -> Gaussian | None:
    """The MRI ankle centre carried into the lab by the foot registered on its own bony markers (three or more of
    `FOOT_LANDMARKS`; `segment_registration.carried_by_own_markers`), or None: independent of the shank's markers
    and of the knee.  The talus is taken with the calcaneus as it was scanned."""
    S = s.upper()
    return carried_by_own_markers(f"calcn_{s}", ctx.bones, [f"calcn_{s}", f"talus_{s}", f"toes_{s}"],
                                  tuple(S + m for m in FOOT_LANDMARKS), ctx.static, ctx.meshes,
                                  ctx.joints[f"ankle_{s}"].centre, virtual=toe_landmark(ctx.bones.get(f"calcn_{s}"), S),
                                  tissue_scale=ctx.tissue_scale(est))


def estimate_ankle(ctx: JointContext, s: str, knee: Fused, knee_scale: float,
                   est: JointEstimates) -> tuple[Registration, CentreEstimates, AxisEstimates, float]:
    """Shank registration, ankle centre and axis estimates of side `s`; returns them and the centre scale in force."""
    S = s.upper()
    j_knee, j_ankle = ctx.joints[f"knee_{s}"], ctx.joints[f"ankle_{s}"]
    pig, kind = motion_centre(ctx, "ankle", s, est)
    extra = ()
    if f"{S}MMA" not in ctx.static and f"femur_{s}" in est.registrations and f"femur_{s}" not in est.mri_dropped:
        # one ankle marker leaves the shank free to turn about the knee-marker line: the knee axis closes it (not
        # when the femur registration failed its gate: its knee axis is not to be trusted either)
        extra = knee_axis_pairs(est.registrations[f"femur_{s}"], j_knee.origin, j_knee.axis, knee.mean, s)
        est.sources[f"tibia_{s}_axial_rotation"] = (
            "the MRI knee flexion axis carried by the femur registration (knee rotation between scanner and standing "
            f"sd {KNEE_STANDING_ROTATION_SD_DEG:g} deg; pipeline.virtual_markers)")
    reg = register_with_centre(f"tibia_{s}", ctx.bones, [f"tibia_{s}", f"fibula_{s}"],
                               tuple(S + m for m in SHANK_LANDMARKS), ctx.static, ctx.meshes, j_knee.centre,
                               knee.gaussian.scaled(1.0 / knee_scale), axis=ctx.joint_axis(j_ankle),
                               fallback=[(f"{kind}_ankle_centre", j_ankle.centre, pig)], extra=extra,
                               sites=shank_markers_site(ctx, s), tissue_scale=ctx.tissue_scale(est))
    scale = centre_scale(ctx, MRI_ANKLE_CENTRE_COV_SCALE, MRI_ANKLE_CENTRE_COV_SCALE_MEASURED)
    mri = mri_centre(reg, j_ankle.centre, scale, centre_model_error(ctx, MRI_ANKLE_MODEL_SD, MRI_ANKLE_MODEL_SD_MEASURED),
                     foot_ankle_centre(ctx, s, est), est, f"ankle_centre_{s}_mri",
                     "MRI ankle centre carried by the shank registration (ankle markers and the fused knee) and by "
                     "the foot's own bony markers, fused")
    u, sd, _ = reg.transfer_direction(j_ankle.axis, j_ankle.axis_sd_deg)
    mri_axis = Direction(u, axis_sd(ctx, sd * MRI_ANKLE_AXIS_SD_SCALE, MRI_ANKLE_AXIS_MODEL_SD_DEG,
                                    MRI_ANKLE_AXIS_MODEL_SD_DEG_MEASURED))
    if f"{S}MMA" in ctx.static and f"{S}ANK" in ctx.static:
        motion_axis = Direction(ctx.static[f"{S}ANK"].mean - ctx.static[f"{S}MMA"].mean, MOTION_ANKLE_AXIS_SD_DEG)
        est.sources[f"ankle_axis_{s}_motion"] = f"transmalleolar axis {condyle_labels(ctx.view, 'ankle', s)} of the static trial"
    elif ctx.pig is not None:
        motion_axis = Direction(ctx.pig.segments[f"tibia_torsioned_{s}"].axes[0][:, 1],
                                pig_axis_sd_deg(ctx, f"tibia_torsioned_{s}", PIG_ANKLE_AXIS_SD_DEG))
        est.sources[f"ankle_axis_{s}_motion"] = "Plug-in-Gait torsioned tibia y axis (tibial torsion from subject.json)"
    else:
        raise InputError(ctx.inputs.static.source, f"no {S} ankle axis from the markers: needs the lateral and medial "
                                                   "malleolus markers or the Plug-in-Gait markers")
    axis = AxisEstimates(mri_axis, motion_axis, fuse_axis([mri_axis.direction, motion_axis.direction],
                                                          [mri_axis.sd_deg, motion_axis.sd_deg], ("mri", "motion")))
    pig = pig.inflated(MOTION_ANKLE_MODEL_SD ** 2 * np.eye(3))
    centre = CentreEstimates(mri, pig, fuse_intersection([mri, pig], ("mri", "motion")))
    return reg, centre, axis, scale


def foot_points(static: dict, S: str, view=None):
    """Heel and toe points of a foot (static lab, m) and what the toe point is: the TOE marker, else the
    mid-point of the metatarsal-head markers (D1M, D5M), else the foot marker of the set (`view`, a
    `markers.MarkerView`) farthest from the heel."""
    if f"{S}HEE" not in static:
        raise InputError("static trial", f"the {S} foot needs a heel marker ({S}HEE)")
    hee = static[f"{S}HEE"].mean
    if f"{S}TOE" in static:
        return hee, static[f"{S}TOE"].mean, "TOE marker"
    if f"{S}D1M" in static and f"{S}D5M" in static:
        return hee, 0.5 * (static[f"{S}D1M"].mean + static[f"{S}D5M"].mean), "mid-point of the metatarsal-head markers"
    s = S.lower()
    foot = [] if view is None else [n for b in (f"calcn_{s}", f"toes_{s}") for n in view.segment_markers(b)
                                    if n in static and n != f"{S}HEE"]
    if foot:
        far = max(foot, key=lambda n: float(np.linalg.norm(static[n].mean - hee)))
        return hee, static[far].mean, f"{view.label(far)} marker"
    raise InputError("static trial", f"the {S} foot needs a toe marker ({S}TOE), both metatarsal-head markers "
                                     f"({S}D1M, {S}D5M) or another foot marker in the marker set")


def estimate_foot_axes(ctx: JointContext, s: str, ankle: Fused, ankle_scale: float, reg_shank: Registration,
                       est: JointEstimates) -> tuple[Registration, dict]:
    """Foot registration and the subtalar and mtp axes of side `s` (`AxisLine`, MRI else defaults)."""
    S = s.upper()
    j_ankle = ctx.joints[f"ankle_{s}"]
    extra = ()
    if f"tibia_{s}" in est.registrations and f"tibia_{s}" not in est.mri_dropped:
        # the talus hangs from the tibia: the shank's ankle axis keeps the foot on the ankle joint
        extra = ankle_axis_pairs(reg_shank, j_ankle.origin, j_ankle.axis, ankle.mean, s)
        est.sources[f"foot_{s}_ankle_axis"] = (
            "the MRI ankle axis carried by the shank registration (foot rotation off it between scanner and standing "
            f"sd {FOOT_STANDING_ROTATION_SD_DEG:g} deg; pipeline.virtual_markers)")
    try:
        reg = register_with_centre(f"calcn_{s}", ctx.bones, [f"calcn_{s}", f"talus_{s}", f"toes_{s}"],
                                   (f"{S}HEE", f"{S}D1M", f"{S}D5M", f"{S}TOE"), ctx.static, ctx.meshes,
                                   j_ankle.centre, ankle.gaussian.scaled(1.0 / ankle_scale), extra=extra,
                                   virtual=toe_landmark(ctx.bones.get(f"calcn_{s}"), S), tissue_scale=ctx.tissue_scale(est))
    except (InputError, FitError) as exc:
        reg = reg_shank
        est.notes.append(f"foot {S}: registered with the shank ({exc})")
    else:
        # on the model's ankle: the centre's residual would otherwise part the talus from the joint it hangs on
        reg = reg.shifted(ankle.mean - (reg.R @ np.asarray(j_ankle.origin, float) + reg.t))
    lines = {}
    for jn in ("subtalar", "mtp"):
        j = ctx.joints.get(f"{jn}_{s}")
        if j is not None:
            o, _ = reg.transfer_point(j.origin)
            u, _, _ = reg.transfer_direction(j.axis)
            lines[jn] = AxisLine(o, u)
            est.sources[f"{jn}_{s}"] = "MRI"
    hee, toe, toe_what = foot_points(ctx.static, S, ctx.view)
    fwd = toe - hee
    fwd[2] = 0.0
    fwd /= np.linalg.norm(fwd)
    left = np.cross([0.0, 0.0, 1.0], fwd)
    med = left if s == "r" else -left
    if "subtalar" not in lines:
        d = subtalar_direction(fwd, [0.0, 0.0, 1.0], med, *SUBTALAR_DEFAULT)
        lines["subtalar"] = AxisLine(ankle.mean + np.array([0.0, 0.0, -0.03]), d)
        est.sources[f"subtalar_{s}"] = "default axis (Inman 1976: 42 deg up, 23 deg medial), 3 cm below the ankle centre"
    if "mtp" not in lines:
        lines["mtp"] = AxisLine(toe - 0.01 * fwd + np.array([0.0, 0.0, -0.02]), left)
        est.sources[f"mtp_{s}"] = f"default: medio-lateral axis under the {toe_what}"
    return reg, lines
