"""The hip centres: MRI (pelvis registration) and motion (SCoRE, else Davis), fused jointly for both sides.

MRI: the hip centre's error is the pelvis registration's (the femoral head
centre itself is found to ~0.1 mm), and where the femur has its KNE, MFC and
TRO markers the femur registered on them alone observes the same centre
independently (`femur_hip_centre`); the registration's propagated covariance
(per-site soft-tissue prior sd, `kinematics.gait.soft_tissue`: ASIS 9.7 ± 7.0 mm,
PSIS 19.6 ± 10.9 mm; marker placement sd; landmark covariances) keeps its
structure and its cross-covariance between the two hips (one shared
registration) and is scaled by `MRI_HIP_COV_SCALE`, or by
`MRI_HIP_COV_SCALE_MEASURED` when the tissue under RASI, LASI, RPSI and LPSI
was measured in the MRI's body label (`personalize.skin`).  Motion: SCoRE's
residual covariance plus the soft-tissue-artefact term
`personalize.pipeline.motion.MOTION_HIP_STA_COV`.  Both hips are fused at once
(`fuse_hips`), so a functional centre also corrects the registration error the
other hip shares.  Without a functional trial, SCoRE runs on a walk only when
its hip range of motion qualifies (`motion.FUNCTIONAL_HIP_MIN_RANGE_DEG`),
else a published regression is the motion hip (`estimate_hips`).  The scales were calibrated on TRAINING phantom subjects
(`benchmarks/fusion_cache.py` then `benchmarks/fusion_calibration.py`;
validation seeds are never used); the numbers they came from are in
``calibration.json``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from lowerlimb.errors import FitError, InputError
from lowerlimb.estimates import Gaussian

from ..fusion import Fused, fuse_linear
from .joint_estimates import CentreEstimates, JointContext, JointEstimates
from .segment_registration import carried_by_own_markers
from .motion import (DAVIS_HIP_SD, FUNCTIONAL_HIP_MIN_RANGE_DEG, HARRINGTON_SD, PELVIS_CLUSTER, THIGH_MARKERS,
                     davis_tissue_cov, harrington_hip, hip_range_of_motion, motion_hip, pelvis_rear, subject_marker_radius)

__all__ = ["MRI_HIP_COV_SCALE", "MRI_HIP_COV_SCALE_MEASURED", "MRI_HIP_MODEL_SD", "MRI_HIP_MODEL_SD_MEASURED", "MOTION_HIP_MODEL_SD", "FEMUR_LANDMARKS", "fuse_hips", "femur_hip_centre", "estimate_hips", "hip_motion_trial"]

#: variance scale of the registration-propagated MRI hip covariance with prior (estimated) soft tissue, with
#: `MRI_HIP_MODEL_SD`: maximum likelihood of the MRI hip errors of the realistic phantoms (palpated markers, child /
#: adult / obese tissue; benchmarks/realistic_calibration.py, 32 legs of 16 real-anatomy subjects of seed 1000,
#: every marker set and lab; calibration.json)
MRI_HIP_COV_SCALE = 1.5485
#: the same scale with the tissue under all four pelvic markers measured in the MRI's body label (calibration.json
#: ``mri_hip_cov_scale_measured``); the measured sd holds an assumed 2 mm posture term and the 3 mm palpation sd,
#: both absent on the phantoms: use 1.0 on real data until calibrated there
MRI_HIP_COV_SCALE_MEASURED = 0.094
#: model-error sd (m per axis) added to the scaled MRI hip covariance with prior soft tissue (realistic phantoms,
#: benchmarks/realistic_calibration.py; calibration.json)
MRI_HIP_MODEL_SD = 0.0
#: model-error sd (m per axis) added to the MRI hip covariance with the pelvic tissue measured (realistic phantoms'
#: analytic subjects, benchmarks/realistic_calibration.py; calibration.json)
MRI_HIP_MODEL_SD_MEASURED = 0.00152
#: m per axis, model-error sd added to a regression hip's stated covariance (Davis, Harrington: their published
#: errors are on the bony landmarks of their own cohorts; maximum likelihood on the realistic phantoms,
#: benchmarks/realistic_calibration.py; calibration.json)
MOTION_HIP_MODEL_SD = 0.01517


def fuse_hips(reg, hips_scanner: dict, motion: dict, *, mri_scale: float | None = None, model_sd: float = 0.0,
              femur: dict | None = None):
    """Joint Gaussian fusion of both hip centres from one pelvis registration and per-side motion centres.

    Model: z_mri = (h_r, h_l) + e_mri with e_mri ~ N(0, k C₆), C₆ the
    registration-propagated covariance of the two transferred centres
    (`Registration.transfer_points`: C₆[a, b] = J_a Cov(reg) J_bᵀ + δ_ab R C_a Rᵀ,
    the off-diagonal blocks being the shared registration error), k = `mri_scale`;
    z_mot,s = h_s + e_s, e_s ~ N(0, C_s) independent.  The generalised
    least-squares solution (`personalize.fusion.fuse_linear`) minimises
    (z - H h)ᵀ Σ⁻¹ (z - H h) over h = (h_r, h_l).
    k defaults to `MRI_HIP_COV_SCALE`; ``model_sd`` σ adds σ² I to k C₆ (the model-error term calibrated on
    the realistic phantoms, `MRI_HIP_MODEL_SD`).  ``femur``: {side: `Gaussian`} the hip centre as the femur
    registered on its own bony markers carries it (`femur_hip_centre`, lab frame, the registration's covariance,
    scaled and inflated as the pelvis pair's), a further MRI observation z_fem,s = h_s + e_fem,s independent of
    the pelvis registration; the MRI source is then the GLS fusion of the pelvis pair and these.

    Parameters
    ----------
    reg : Registration of the pelvis (scanner -> static lab)
    hips_scanner : {side: `Gaussian` centre (3,) m, (3, 3) m²}, scanner frame
    motion : {side: `Gaussian`}, static lab frame

    Returns
    -------
    mri : {side: `Gaussian`} lab MRI centres (scaled covariance); fused : {side: Fused}
        (names ("mri", "motion"), weights the own-side 3x3 blocks); joint : Fused of the 6-vector
    """
    mri_scale = MRI_HIP_COV_SCALE if mri_scale is None else float(mri_scale)
    sides = [s for s in ("r", "l") if s in hips_scanner]
    n = len(sides)
    Y, C = reg.transfer_points([hips_scanner[s].mean for s in sides], [hips_scanner[s].cov for s in sides])
    ys = dict(zip(sides, Y))
    # + (0.1 mm)² per point (the femoral head centres' detection error on the phantoms): two points alone do not
    # see a rotation about the line through them, so the registration part is singular along that direction
    floor = 1e-8 + float(model_sd) ** 2
    C = mri_scale * C + floor * np.eye(3 * n)
    H = np.eye(3 * n)
    z = np.concatenate([ys[s] for s in sides])
    extra = [(femur[s].mean, mri_scale * femur[s].cov + floor * np.eye(3), H[3 * i:3 * i + 3])
             for i, s in enumerate(sides) if s in (femur or {})]
    if extra:
        both = fuse_linear([(z, C, H)] + extra)
        z, C = both.mean, both.cov
        ys = {s: z[3 * i:3 * i + 3] for i, s in enumerate(sides)}
    obs = [(z, C, H)]
    names = ["mri"]
    for i, s in enumerate(sides):
        obs.append((motion[s].mean, motion[s].cov, H[3 * i:3 * i + 3]))
        names.append(f"motion_{s}")
    joint = fuse_linear(obs, names)
    mri, fused = {}, {}
    for i, s in enumerate(sides):
        b = slice(3 * i, 3 * i + 3)
        mri[s] = Gaussian(ys[s], C[b, b])
        W = np.array([joint.weights[0][b, b], joint.weights[1 + i][b, b]])
        fused[s] = Fused(joint.mean[b], joint.cov[b, b], W, np.trace(W, axis1=1, axis2=2) / 3.0, joint.chi2,
                         joint.dof, joint.p_value, ("mri", "motion"))
    return mri, fused, joint



def _skin_of(est: JointEstimates) -> dict:
    """marker -> (mean, sd) m of the soft tissue measured or estimated under the pelvic markers."""
    out = {}
    for k, v in est.skin.items():
        t, sd = getattr(v, "thickness", None), getattr(v, "sd", None)
        if t is not None and sd is not None and np.isfinite(t) and np.isfinite(sd):
            out[k] = (float(t), float(sd))
    return out


#: the femur's bony-landmark markers (side letter dropped): lateral and medial epicondyle, greater trochanter
FEMUR_LANDMARKS = ("KNE", "MFC", "TRO")


def femur_hip_centre(ctx: JointContext, s: str, est: JointEstimates) -> Gaussian | None:
    """The MRI hip centre carried into the lab by the femur registered on its own bony markers (all of
    `FEMUR_LANDMARKS`; `segment_registration.carried_by_own_markers`), or None: independent of the pelvis
    registration."""
    S = s.upper()
    return carried_by_own_markers(f"femur_{s}", ctx.bones, [f"femur_{s}"], tuple(S + m for m in FEMUR_LANDMARKS),
                                  ctx.static, ctx.meshes,
                                  ctx.joints[f"hip_{s}"].centre, axis=ctx.joint_axis(ctx.joints[f"knee_{s}"]),
                                  tissue_scale=ctx.tissue_scale(est))


def hip_motion_trial(ctx: JointContext, s: str, pelvis_axes, pelvis, thigh):
    """The trial SCoRE is run on for side `s`: the functional trial, else the dynamic trial with the largest hip
    range of motion when it reaches `motion.FUNCTIONAL_HIP_MIN_RANGE_DEG`; (trial, its ranges or None, why not)."""
    if ctx.functional is not None:
        return ctx.functional, None, ""
    best, best_rom = None, None
    for t in ctx.dynamic:
        rom = hip_range_of_motion(ctx.view.static, t, s, pelvis_axes, pelvis=pelvis, thigh=thigh)
        if rom is not None and (best_rom is None or min(rom[k] / v for k, v in FUNCTIONAL_HIP_MIN_RANGE_DEG.items())
                                > min(best_rom[k] / v for k, v in FUNCTIONAL_HIP_MIN_RANGE_DEG.items())):
            best, best_rom = t, rom
    if best_rom is None:
        return None, None, "no trial shows 3 pelvis and 3 thigh markers"
    rom_text = f"flexion-extension {best_rom['flexion']:.0f} deg, ab-adduction {best_rom['abduction']:.0f} deg"
    if all(best_rom[k] >= v for k, v in FUNCTIONAL_HIP_MIN_RANGE_DEG.items()):
        return best, best_rom, rom_text
    need = ", ".join(f"{k} {v:.0f}" for k, v in FUNCTIONAL_HIP_MIN_RANGE_DEG.items())
    return None, best_rom, (f"no functional trial, and the widest hip motion ({Path(best.source).name}: {rom_text}) "
                            f"is below the functional method's minimum ({need} deg)")


def estimate_hips(ctx: JointContext, reg_pelvis, pelvis_axes, est: JointEstimates) -> None:
    """MRI, motion and fused hip centres of every side into `est` (``centres[s]["hip"]``, ``hip_joint``).

    Motion hip: SCoRE on the functional trial; without one, SCoRE on the dynamic trial of widest hip motion only
    when it reaches `motion.FUNCTIONAL_HIP_MIN_RANGE_DEG` (the rule and its sources are there); otherwise a
    published regression: Davis (Plug-in-Gait, sd `motion.DAVIS_HIP_SD`) when the Plug-in-Gait markers are
    there, else Harrington et al. 2007 from the pelvis markers (`motion.harrington_hip`, sd `HARRINGTON_SD`).
    """
    hips_scanner, hip_motion = {}, {}
    view = ctx.view
    pelvis = view.segment_markers("pelvis", PELVIS_CLUSTER)
    for s in ctx.inputs.sides:
        hips_scanner[s] = ctx.joints[f"hip_{s}"].centre
        ctx.say(f"hip {s.upper()}: functional centre")
        thigh = view.segment_markers(f"femur_{s}", tuple(s.upper() + m for m in THIGH_MARKERS))
        trial, rom, why = hip_motion_trial(ctx, s, pelvis_axes, pelvis, thigh)
        try:
            if trial is None:
                raise InputError(ctx.inputs.static.source, why)
            hip_motion[s], _ = motion_hip(view.static, trial, s, pelvis_axes, pelvis=pelvis, thigh=thigh)
            est.sources[f"hip_{s}_motion"] = f"SCoRE on {Path(trial.source).name}" + (
                "" if ctx.functional is not None else f" (no functional trial; hip range {why} qualifies)")
        except (InputError, FitError) as exc:
            if ctx.pig is not None:
                hip_motion[s] = Gaussian.isotropic(np.median(ctx.pig.centres[f"hip_{s}"], axis=0),
                                                   float(np.hypot(DAVIS_HIP_SD, MOTION_HIP_MODEL_SD))).inflated(
                    davis_tissue_cov(ctx.static, pelvis_axes, _skin_of(est)))
                est.sources[f"hip_{s}_motion"] = ("Plug-in-Gait (Davis) regression of the static trial (its sd widened "
                                                  "forward by the soft tissue under the ASIS markers, which it does "
                                                  "not see)")
                used = "Plug-in-Gait regression"
            else:
                hip_motion[s] = harrington_hip(ctx.static, s, pelvis_axes, _skin_of(est),
                                               subject_marker_radius(ctx.inputs)).inflated(MOTION_HIP_MODEL_SD ** 2 * np.eye(3))
                est.sources[f"hip_{s}_motion"] = (
                    f"Harrington et al. 2007 regression of the pelvis markers ({pelvis_rear(ctx.static)[1]}; "
                    f"sd {HARRINGTON_SD * 1e3:.1f} mm per axis after Mantovani et al. 2016, plus the soft tissue's)")
                used = "Harrington regression"
            est.notes.append(f"hip {s.upper()}: no functional hip centre ({exc}); {used} used")
    femur = {}
    for s in ctx.inputs.sides:
        g = femur_hip_centre(ctx, s, est)
        if g is not None:
            femur[s] = g
            est.sources[f"hip_centre_{s}_mri"] = ("MRI hip centre carried by the pelvis registration and by the femur's "
                                                  "own bony markers, fused")
    # both hips at once: their MRI estimates share the pelvis registration error
    mri, fused, est.hip_joint = fuse_hips(reg_pelvis, hips_scanner, hip_motion, mri_scale=est.mri_hip_scale,
                                          model_sd=MRI_HIP_MODEL_SD_MEASURED if ctx.tissue_measured
                                          else MRI_HIP_MODEL_SD, femur=femur)
    for s in ctx.inputs.sides:
        est.centres.setdefault(s, {})["hip"] = CentreEstimates(mri[s], hip_motion[s], fused[s])
