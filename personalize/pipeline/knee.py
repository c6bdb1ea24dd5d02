"""The knee centre and axis: MRI (femur registered with the fused hip centre) and motion (SARA, Plug-in-Gait), fused.

The femur is registered from its knee markers, projected on the MRI knee axis,
and the fused hip centre; the MRI knee centre and axis reach the lab with the
registration's covariance, scaled by the calibrated factors below (TRAINING
phantoms; ``calibration.json``).  The knee centre is a point of the tibia too:
where the shank has three or more bony-landmark markers (`SHANK_LANDMARKS`),
the tibia registered on them alone carries the MRI knee centre into the lab
as well, and the two are fused (`shank_knee_centre`): the shank's markers are
independent of the femur's and of the hip, whose error the femur carries down.
Motion: the SARA axis of the thigh and shank clusters (else the Plug-in-Gait femur axis, else the transepicondylar line) and
the Plug-in-Gait knee centre of the static trial (else the midpoint of the
epicondyle markers, `motion.condylar_centre`).  Centres are fused as Gaussians, axes on the sphere
(`personalize.fusion`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from lowerlimb.errors import FitError, InputError
from lowerlimb.estimates import Gaussian

from ..fusion import Fused, fuse_axis, fuse_gaussian, fuse_intersection
from ..registration import Registration
from .joint_estimates import AxisEstimates, CentreEstimates, Direction, JointContext, JointEstimates
from .motion import (CONDYLES, PIG_KNEE_AXIS_SD_DEG, SHANK_MARKERS, THIGH_MARKERS, condylar_axis, condylar_centre,
                     motion_knee_axis, subject_marker_radius)
from .pig_uncertainty import pig_axis_sd_deg, pig_centre_propagated
from .segment_registration import carried_by_own_markers, register_with_centre
from .virtual_markers import STANDING_HIP_ROTATION_SD_DEG, virtual_medial_knee

__all__ = ["MRI_KNEE_AXIS_SD_SCALE", "MRI_KNEE_AXIS_MODEL_SD_DEG", "MRI_KNEE_AXIS_MODEL_SD_DEG_MEASURED",
           "MRI_KNEE_CENTRE_COV_SCALE", "MRI_KNEE_CENTRE_COV_SCALE_MEASURED", "MRI_KNEE_MODEL_SD", "MRI_KNEE_MODEL_SD_MEASURED",
           "MOTION_KNEE_MODEL_SD", "SHANK_LANDMARKS",
           "estimate_knee", "mri_centre", "shank_knee_centre"]

#: scale of the femur-registration knee axis sd: the claimed 2.2 deg median vs 0.34 deg rms actual on 24 TRAINING
#: phantom subjects (their knee markers sit exactly on the flexion axis; calibration.json)
MRI_KNEE_AXIS_SD_SCALE = 0.107
#: deg, model-error angle added in quadrature to the scaled MRI knee axis sd with prior soft tissue: palpated real
#: epicondyles turn the femur about its long axis by what the registration's noise model does not see (realistic
#: phantoms, Rayleigh maximum likelihood chosen on the LHDL_CT legs of seed 1000, 95 % coverage 1.00 there and on
#: ICL_MRI; the stated sd had covered 9 % of the real-anatomy legs; benchmarks/axis_calibration.py, calibration.json)
MRI_KNEE_AXIS_MODEL_SD_DEG = 5.19
#: deg, the same with the pelvic tissue measured (analytic phantoms: none needed)
MRI_KNEE_AXIS_MODEL_SD_DEG_MEASURED = 0.0
#: variance scale of the registered MRI knee centre: prior pelvic tissue, with `MRI_KNEE_MODEL_SD`, maximum
#: likelihood on the realistic phantoms (benchmarks/realistic_calibration.py, 32 legs of
#: 16 real-anatomy subjects of seed 1000, every marker set and lab); with the pelvic tissue measured (12 analytic
#: subjects with the skin label, 24 legs):
#: mean Mahalanobis d² = 3 (benchmarks/knee_ankle_calibration.py; calibration.json)
MRI_KNEE_CENTRE_COV_SCALE = 0.6539
MRI_KNEE_CENTRE_COV_SCALE_MEASURED = 0.017
#: model-error sd (m per axis) added to the scaled MRI knee centre covariance with prior soft tissue (realistic
#: phantoms, benchmarks/realistic_calibration.py; calibration.json)
MRI_KNEE_MODEL_SD = 0.00377
#: model-error sd (m per axis) added to the motion knee centre's stated covariance (realistic phantoms,
#: benchmarks/realistic_calibration.py; calibration.json)
MOTION_KNEE_MODEL_SD = 0.0
#: model-error sd (m per axis) added to the MRI knee centre covariance with the pelvic tissue measured (realistic
#: phantoms' analytic subjects, benchmarks/realistic_calibration.py; calibration.json)
MRI_KNEE_MODEL_SD_MEASURED = 0.00061


#: the shank's bony-landmark markers (side letter dropped): lateral and medial malleolus, tibial tuberosity, fibular head
SHANK_LANDMARKS = ("ANK", "MMA", "TTB", "HFB")


def shank_markers_site(ctx: JointContext, s: str) -> dict | None:
    """Malleolus markers on the transmalleolar axis (Plug-in-Gait) sit over the tips' projections, not the prominences."""
    S = s.upper()
    return {f"{S}ANK": "lateral_malleolus_tip", f"{S}MMA": "medial_malleolus_tip"} if ctx.markers_on_joint_axes else None


def shank_knee_centre(ctx: JointContext, s: str, est: JointEstimates) -> Gaussian | None:
    """The MRI knee centre carried into the lab by the tibia registered on its own bony markers (three or more of
    `SHANK_LANDMARKS`; `segment_registration.carried_by_own_markers`), or None: independent of the hip's error and
    of the femur's markers."""
    S = s.upper()
    return carried_by_own_markers(f"tibia_{s}", ctx.bones, [f"tibia_{s}", f"fibula_{s}"],
                                  tuple(S + m for m in SHANK_LANDMARKS), ctx.static, ctx.meshes,
                                  ctx.joints[f"knee_{s}"].centre, axis=ctx.joint_axis(ctx.joints[f"ankle_{s}"]),
                                  sites=shank_markers_site(ctx, s), tissue_scale=ctx.tissue_scale(est))


def mri_centre(reg: Registration, centre: Gaussian, scale: float, model: np.ndarray, distal: Gaussian | None,
               est: JointEstimates, key: str, described: str) -> Gaussian:
    """The MRI joint `centre` carried by `reg`, its covariance scaled by the calibrated `scale` plus the `model`
    error; fused (product of Gaussians) with the distal bone's own estimate `distal` under the same scale and model
    error when there is one, its source then `described` under ``est.sources[key]``."""
    g = reg.transfer_estimate(centre).scaled(scale).inflated(model)
    if distal is None:
        return g
    est.sources[key] = described
    return fuse_gaussian([g, distal.scaled(scale).inflated(model)]).gaussian


def centre_model_error(ctx: JointContext, sd: float, sd_measured: float) -> np.ndarray:
    """The model-error covariance σ² I (m²) of an MRI centre: σ = `sd` with prior soft tissue, `sd_measured` with
    the pelvic tissue measured."""
    return float(sd_measured if ctx.tissue_measured else sd) ** 2 * np.eye(3)


def axis_sd(ctx: JointContext, sd_deg: float, model_deg: float, model_deg_measured: float) -> float:
    """An MRI axis's stated sd (deg): its registration-propagated `sd_deg` with the model-error angle in
    quadrature (`model_deg` with prior soft tissue, `model_deg_measured` with the pelvic tissue measured)."""
    return float(np.hypot(sd_deg, model_deg_measured if ctx.tissue_measured else model_deg))


def centre_scale(ctx: JointContext, prior: float, measured: float) -> float:
    return measured if ctx.tissue_measured else prior


def _unsided(label: str) -> str:
    """`label` without its side letter (RKNE, R.Knee.Lat, R_Knee -> KNE, Knee.Lat, Knee)."""
    if label[:1] in ("R", "L") and len(label) > 2 and label[1] in "._- ":
        return label[2:]
    return label[1:] if label[:1] in ("R", "L") else label


def condyle_labels(view, joint: str, s: str) -> str:
    """'ANK - ANKM': the lab's own labels (side letter dropped) of a joint's lateral and medial markers."""
    lat, med = (view.label(s.upper() + n) for n in CONDYLES[joint])
    return f"{_unsided(lat)} - {_unsided(med)}"


def motion_centre(ctx: JointContext, joint: str, s: str, est: JointEstimates):
    """The motion estimate of the knee or ankle centre: Plug-in-Gait's (chord function) with its markers, else the
    condyle-marker midpoint (`motion.condylar_centre`); the `Gaussian` and its kind ("pig" or "motion")."""
    if ctx.pig is not None:
        g = pig_centre_propagated(ctx, joint, s)
        est.sources[f"{joint}_centre_{s}_motion"] = (
            "Plug-in-Gait chord function of the static trial, covariance propagated from the markers' placement "
            f"(sd {', '.join(f'{x * 1e3:.0f}' for x in np.sqrt(np.diag(g.cov)))} mm along the lab axes)")
        return g, "pig"
    try:
        g = condylar_centre(ctx.static, joint, s, marker_radius=subject_marker_radius(ctx.inputs))
    except InputError as exc:
        raise InputError(ctx.inputs.static.source, f"{exc.problem}: without the Plug-in-Gait markers the "
                                                   f"{joint} centre comes from its lateral and medial markers") from None
    what = "epicondyle" if joint == "knee" else "malleolus"
    est.sources[f"{joint}_centre_{s}_motion"] = (
        f"midpoint of the {what} markers {condyle_labels(ctx.view, joint, s)} moved in by marker radius + soft tissue "
        f"(sd {np.sqrt(np.trace(g.cov) / 3) * 1e3:.1f} mm per axis)")
    return g, "motion"


def estimate_knee(ctx: JointContext, s: str, hip: Fused, hip_scale: float,
                  est: JointEstimates) -> tuple[Registration, CentreEstimates, AxisEstimates, float]:
    """Femur registration, knee centre and axis estimates of side `s`; returns them and the centre scale in force.

    The registration's marker noise model is the uncalibrated (conservative) one, so the hip anchor enters
    on that scale too (``hip.cov / hip_scale``): otherwise the calibrated hip would outweigh the knee markers.
    """
    S = s.upper()
    j_hip, j_knee = ctx.joints[f"hip_{s}"], ctx.joints[f"knee_{s}"]
    pig, kind = motion_centre(ctx, "knee", s, est)
    static = ctx.static
    if f"{S}MFC" not in static:
        # one knee marker leaves the femur free to turn about the hip-marker line: a virtual medial marker closes it
        v = virtual_medial_knee(static, ctx.bones, s, hip.mean, est.pelvis[1], j_knee.axis)
        if v is not None:
            static = {**static, f"{S}MFC": v}
            est.sources[f"femur_{s}_axial_rotation"] = (
                "virtual medial epicondyle marker: knee marker + MRI epicondylar width along the pelvis's medio-lateral "
                f"axis (standing hip rotation sd {STANDING_HIP_ROTATION_SD_DEG:g} deg; pipeline.virtual_markers)")
    reg = register_with_centre(f"femur_{s}", ctx.bones, [f"femur_{s}"], (f"{S}KNE", f"{S}MFC", f"{S}TRO"), static,
                               ctx.meshes, j_hip.centre, hip.gaussian.scaled(1.0 / hip_scale),
                               axis=ctx.joint_axis(j_knee), fallback=[(f"{kind}_knee_centre", j_knee.centre, pig)],
                               tissue_scale=ctx.tissue_scale(est))
    scale = centre_scale(ctx, MRI_KNEE_CENTRE_COV_SCALE, MRI_KNEE_CENTRE_COV_SCALE_MEASURED)
    mri = mri_centre(reg, j_knee.centre, scale, centre_model_error(ctx, MRI_KNEE_MODEL_SD, MRI_KNEE_MODEL_SD_MEASURED),
                     shank_knee_centre(ctx, s, est), est, f"knee_centre_{s}_mri",
                     "MRI knee centre carried by the femur registration (knee markers and the fused hip) and by the "
                     "tibia's own bony markers, fused")
    u, sd, _ = reg.transfer_direction(j_knee.axis, j_knee.axis_sd_deg)
    mri_axis = Direction(u, axis_sd(ctx, sd * MRI_KNEE_AXIS_SD_SCALE, MRI_KNEE_AXIS_MODEL_SD_DEG,
                                    MRI_KNEE_AXIS_MODEL_SD_DEG_MEASURED))
    ctx.say(f"knee {S}: functional axis")
    view = ctx.view
    try:
        motion_axis = motion_knee_axis(view.static, ctx.dynamic, s,
                                       thigh=view.segment_markers(f"femur_{s}", tuple(S + m for m in THIGH_MARKERS)),
                                       shank=view.segment_markers(f"tibia_{s}", tuple(S + m for m in SHANK_MARKERS)))
        est.sources[f"knee_axis_{s}_motion"] = "SARA (thigh and shank clusters) on " + ", ".join(
            Path(t.source).name for t in ctx.dynamic)
    except (InputError, FitError) as exc:
        if ctx.pig is not None:
            motion_axis = Direction(ctx.pig.segments[f"femur_{s}"].axes[0][:, 1],
                                    pig_axis_sd_deg(ctx, f"femur_{s}", PIG_KNEE_AXIS_SD_DEG))
            est.sources[f"knee_axis_{s}_motion"] = "Plug-in-Gait femur y axis of the static trial"
            est.notes.append(f"knee {S}: no functional knee axis ({exc}); Plug-in-Gait axis used")
        else:
            motion_axis = condylar_axis(ctx.static, "knee", s)
            est.sources[f"knee_axis_{s}_motion"] = (f"transepicondylar line {condyle_labels(view, 'knee', s)} of the "
                                                    f"static trial (sd {motion_axis.sd_deg:.1f} deg)")
            est.notes.append(f"knee {S}: no functional knee axis ({exc}); transepicondylar line used")
    axis = AxisEstimates(mri_axis, motion_axis, fuse_axis([mri_axis.direction, motion_axis.direction],
                                                          [mri_axis.sd_deg, motion_axis.sd_deg], ("mri", "motion")))
    pig = pig.inflated(MOTION_KNEE_MODEL_SD ** 2 * np.eye(3))
    centre = CentreEstimates(mri, pig, fuse_intersection([mri, pig], ("mri", "motion")))
    return reg, centre, axis, scale
