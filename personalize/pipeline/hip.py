"""The hip centres: MRI (pelvis registration) and motion (SCoRE, else Davis), fused jointly for both sides.

MRI: the hip centre's error is the pelvis registration's (the femoral head
centre itself is found to ~0.1 mm); the registration's propagated covariance
(per-site soft-tissue prior sd, `kinematics.gait.soft_tissue`: ASIS 9.7 ± 7.0 mm,
PSIS 19.6 ± 10.9 mm; marker placement sd; landmark covariances) keeps its
structure and its cross-covariance between the two hips (one shared
registration) and is scaled by `MRI_HIP_COV_SCALE`, or by
`MRI_HIP_COV_SCALE_MEASURED` when the tissue under RASI, LASI, RPSI and LPSI
was measured in the MRI's body label (`personalize.skin`).  Motion: SCoRE's
residual covariance plus the soft-tissue-artefact term
`personalize.pipeline.motion.MOTION_HIP_STA_COV`.  Both hips are fused at once
(`fuse_hips`), so a functional centre also corrects the registration error the
other hip shares.  The scales were calibrated on TRAINING phantom subjects
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
from .motion import DAVIS_HIP_SD, motion_hip

__all__ = ["MRI_HIP_COV_SCALE", "MRI_HIP_COV_SCALE_MEASURED", "MRI_HIP_MODEL_SD", "fuse_hips", "estimate_hips"]

#: variance scale of the registration-propagated MRI hip covariance: mean Mahalanobis d² = 3 on 24 TRAINING
#: phantom subjects (48 legs; calibration.json ``mri_hip_cov_scale``); the phantoms' pelvis markers sit exactly
#: (no palpation error), so use 1.0 where palpation errors are real
MRI_HIP_COV_SCALE = 0.43
#: the same scale with the tissue under all four pelvic markers measured in the MRI's body label (calibration.json
#: ``mri_hip_cov_scale_measured``); the measured sd holds an assumed 2 mm posture term and the 3 mm palpation sd,
#: both absent on the phantoms: use 1.0 on real data until calibrated there
MRI_HIP_COV_SCALE_MEASURED = 0.094
#: model-error sd (m per axis) added to the scaled MRI hip covariance with prior soft tissue (realistic phantoms,
#: benchmarks/realistic_calibration.py; calibration.json)
MRI_HIP_MODEL_SD = 0.0


def fuse_hips(reg, hips_scanner: dict, motion: dict, *, mri_scale: float | None = None, model_sd: float = 0.0):
    """Joint Gaussian fusion of both hip centres from one pelvis registration and per-side motion centres.

    Model: z_mri = (h_r, h_l) + e_mri with e_mri ~ N(0, k C₆), C₆ the
    registration-propagated covariance of the two transferred centres
    (`Registration.transfer_points`: C₆[a, b] = J_a Cov(reg) J_bᵀ + δ_ab R C_a Rᵀ,
    the off-diagonal blocks being the shared registration error), k = `mri_scale`;
    z_mot,s = h_s + e_s, e_s ~ N(0, C_s) independent.  The generalised
    least-squares solution (`personalize.fusion.fuse_linear`) minimises
    (z - H h)ᵀ Σ⁻¹ (z - H h) over h = (h_r, h_l).
    k defaults to `MRI_HIP_COV_SCALE`; ``model_sd`` σ adds σ² I to k C₆ (the model-error term calibrated on
    the realistic phantoms, `MRI_HIP_MODEL_SD`).

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
    C = mri_scale * C + (1e-8 + float(model_sd) ** 2) * np.eye(3 * n)
    H = np.eye(3 * n)
    obs = [(np.concatenate([ys[s] for s in sides]), C, H)]
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



def estimate_hips(ctx: JointContext, reg_pelvis, pelvis_axes, est: JointEstimates) -> None:
    """MRI, motion and fused hip centres of every side into `est` (``centres[s]["hip"]``, ``hip_joint``)."""
    hips_scanner, hip_motion = {}, {}
    trial = ctx.functional if ctx.functional is not None else ctx.dynamic[0]
    for s in ctx.inputs.sides:
        hips_scanner[s] = ctx.joints[f"hip_{s}"].centre
        ctx.say(f"hip {s.upper()}: functional centre")
        try:
            hip_motion[s], _ = motion_hip(ctx.inputs.static, trial, s, pelvis_axes)
            est.sources[f"hip_{s}_motion"] = f"SCoRE on {Path(trial.source).name}" + (
                "" if ctx.functional is not None else " (no functional trial)")
        except (InputError, FitError) as exc:
            hip_motion[s] = Gaussian.isotropic(np.median(ctx.pig.centres[f"hip_{s}"], axis=0), DAVIS_HIP_SD)
            est.sources[f"hip_{s}_motion"] = "Plug-in-Gait (Davis) regression of the static trial"
            est.notes.append(f"hip {s.upper()}: no functional hip centre ({exc}); Plug-in-Gait regression used")
    # both hips at once: their MRI estimates share the pelvis registration error
    mri, fused, est.hip_joint = fuse_hips(reg_pelvis, hips_scanner, hip_motion, mri_scale=est.mri_hip_scale,
                                          model_sd=0.0 if ctx.tissue_measured else MRI_HIP_MODEL_SD)
    for s in ctx.inputs.sides:
        est.centres.setdefault(s, {})["hip"] = CentreEstimates(mri[s], hip_motion[s], fused[s])
