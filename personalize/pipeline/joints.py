"""Joint estimation: the pelvis registration, then hip, knee, ankle and foot per side (MRI, motion, fused).

Each MRI joint centre and axis reaches the lab frame of the static trial through
its segment's registration, proximal first (`personalize.pipeline.hip`,
`knee`, `foot`): the pelvis from its markers (soft tissue measured in the MRI's
body label where it has one), then femur, shank and foot each from its markers
plus the fused proximal joint centre.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

from kinematics.gait.pig import pelvis_frame
from kinematics.gait.soft_tissue import tissue_scale_prior
from lowerlimb.errors import InputError

from ..fusion import fuse_axis
from ..marker_registration import register_segments
from ..registration import GATE_P, gate_statistic, static_marker_positions
from ..skin import estimated_skin
from .foot import estimate_ankle, estimate_foot_axes
from .hip import MRI_HIP_COV_SCALE, MRI_HIP_COV_SCALE_MEASURED, estimate_hips
from .inputs import PELVIS_MARKERS, SubjectInputs, label_volume
from .joint_estimates import AxisEstimates, JointContext, JointEstimates
from .knee import estimate_knee
from .markers import marker_view
from .motion import pelvis_rear, pig_static

__all__ = ["estimate_joints", "pelvis_skin", "gate_registrations", "gate_segment", "passes_gate", "motion_only",
           "SEGMENT_JOINTS"]


def pelvis_skin(inputs: SubjectInputs, surfaces: dict, landmarks, volume=None) -> dict:
    """Tissue under the pelvic markers (`personalize.skin.measure_pelvis_skin`) when the label volume names a
    body/skin label; {} for bone-only volumes and mesh folders (the population prior is then used).

    `landmarks` : `personalize.landmarks.LandmarkSet`; `volume`: the subject's label volume when already read."""
    from ..io import read_tissue_label
    from ..skin import measure_pelvis_skin

    if "pelvis" not in surfaces or "pelvis" not in landmarks or read_tissue_label(inputs.label_map) is None:
        return {}
    vol = volume if volume is not None else label_volume(inputs)
    if vol is None:
        return {}
    return measure_pelvis_skin(vol, landmarks["pelvis"], surfaces["pelvis"].mesh)


def estimate_joints(inputs: SubjectInputs, surfaces: dict, landmarks, joints: dict, say: Callable[[str], None],
                    dropped: dict | None = None, skin: dict | None = None) -> JointEstimates:
    """MRI, motion and fused joint parameters per side (static lab frame); see the module docstring.

    Parameters
    ----------
    surfaces : bone -> `personalize.surfaces.BoneSurface` (scanner frame)
    landmarks : `personalize.landmarks.LandmarkSet` (scanner frame)
    joints : joint name -> `personalize.frames.Joint` (scanner frame), model-error term taken out
        (`Joint.without_model_error`: the MRI covariance scales were calibrated on phantoms)
    dropped : joint name -> why it is missing (for the error message)
    skin : {marker: `personalize.skin.SkinThickness`}; default measured by `pelvis_skin` (empty without a body label)
    """
    view = marker_view(inputs)
    st = view.static
    static = static_marker_positions(st)
    est = JointEstimates()
    sac, _ = pelvis_rear(static)
    pf = pelvis_frame(static["RASI"].mean[None], static["LASI"].mean[None], sac[None])
    est.pelvis = (pf.origin[0], pf.axes[0])
    if skin is None:
        say("measuring the soft tissue over the pelvic landmarks")
        skin = pelvis_skin(inputs, surfaces, landmarks)
    est.skin = dict(skin)
    measured = {k: v for k, v in skin.items() if v.source == "MRI"}
    for v in skin.values():
        if v.note and v.source != "MRI" and "no body/skin label" not in v.note:
            est.notes.append(f"soft tissue under {v.marker}: {v.note}")
    all_measured = all(m in measured for m in PELVIS_MARKERS)
    est.mri_hip_scale = MRI_HIP_COV_SCALE_MEASURED if all_measured else MRI_HIP_COV_SCALE
    meshes = {k: v.mesh for k, v in surfaces.items()}
    say("registering the pelvis")
    sub = inputs.subject
    regs = register_segments(landmarks, st, sides=inputs.sides, segments=("pelvis",), surfaces=meshes,
                             skin_thickness={k: v.thickness for k, v in measured.items()},
                             skin_sd={k: v.sd for k, v in measured.items()},
                             tissue_prior=tissue_scale_prior(getattr(sub, "height", None), getattr(sub, "mass", None),
                                                             getattr(sub, "age", None)),
                             virtual={"pelvis": sacral_landmark(landmarks, static)})
    if "pelvis" not in regs:
        raise InputError(inputs.static.source, "the pelvis could not be registered (needs RASI, LASI, RPSI, LPSI in MRI and markers)")
    est.registrations["pelvis"] = regs["pelvis"]
    est.skin.update(estimated_skin(regs["pelvis"]))
    dynamic = [view.trials[k] for k in sorted(inputs.trials) if k != inputs.functional and not k.startswith("functional")]
    for s in inputs.sides:
        for jn in ("hip", "knee", "ankle"):
            if f"{jn}_{s}" not in joints:
                why = (dropped or {}).get(f"{jn}_{s}", "not detected")
                raise InputError(inputs.bones, f"no {jn}_{s} joint from the MRI bones ({why})")
    ctx = JointContext(inputs, landmarks.bones, joints, static, meshes, pig_static(inputs, view),
                       dynamic or [view.trials[k] for k in sorted(view.trials)],
                       view.trials[inputs.functional] if inputs.functional else None, all_measured, say, view)
    estimate_hips(ctx, regs["pelvis"], est.pelvis[1], est)
    for s in inputs.sides:
        # each segment is gated before the next one is registered on its fused distal joint centre
        hip = est.centres[s]["hip"].fused
        est.registrations[f"femur_{s}"], knee, knee_axis, k_scale = estimate_knee(ctx, s, hip, est.mri_hip_scale, est)
        est.centres[s]["knee"], est.axes[s] = knee, {"knee": knee_axis}
        if not gate_segment(est, f"femur_{s}", say):
            k_scale = 1.0          # the knee anchor is now the motion estimate, not a calibrated MRI one
        reg_t, ankle, ankle_axis, a_scale = estimate_ankle(ctx, s, est.centres[s]["knee"].fused, k_scale, est)
        est.registrations[f"tibia_{s}"] = reg_t
        est.centres[s]["ankle"], est.axes[s]["ankle"] = ankle, ankle_axis
        if not gate_segment(est, f"tibia_{s}", say):
            a_scale = 1.0
        for r in (est.registrations[f"femur_{s}"], reg_t):
            if any(n.startswith(("pig_", "motion_")) for n in r.names):
                est.notes.append(f"{r.segment}: fewer than 3 landmark/marker correspondences; registered with the Plug-in-Gait "
                                 "joint centre (MRI and motion estimates of this segment are correlated)")
        ankle_fused = est.centres[s]["ankle"].fused
        reg_c, est.lines[s] = estimate_foot_axes(ctx, s, ankle_fused, a_scale, reg_t, est)
        est.registrations[f"calcn_{s}"] = reg_c
        if not gate_segment(est, f"calcn_{s}", say) or (reg_c is reg_t and f"tibia_{s}" in est.mri_dropped):
            # the MRI subtalar and mtp axes came through a failed registration: the default axes instead
            foot_joints = {k: v for k, v in ctx.joints.items() if k not in (f"subtalar_{s}", f"mtp_{s}")}
            _, est.lines[s] = estimate_foot_axes(replace(ctx, joints=foot_joints), s, ankle_fused, a_scale, reg_t, est)
    note_inconsistencies(est)
    return est


def sacral_landmark(landmarks, static: dict) -> dict:
    """{"SACR": (scanner point, outward normal)}: a sacral marker over the mid-point of the MRI's PSIS, for marker
    sets without PSIS markers (OpenSim's V.Sacral); {} when the trial has both PSIS or no sacral marker."""
    if "SACR" not in static or ("RPSI" in static and "LPSI" in static) or "pelvis" not in landmarks:
        return {}
    lm = landmarks["pelvis"].landmarks
    if not all(n in lm for n in ("RASI", "LASI", "RPSI", "LPSI")):
        return {}
    p = {n: np.asarray(lm[n].position, float) for n in ("RASI", "LASI", "RPSI", "LPSI")}
    mid_psis = 0.5 * (p["RPSI"] + p["LPSI"])
    lr = p["LASI"] - p["RASI"]
    back = mid_psis - 0.5 * (p["RASI"] + p["LASI"])
    back -= (back @ lr) / (lr @ lr) * lr
    return {"SACR": (mid_psis, back / np.linalg.norm(back))}


#: joints whose MRI estimates a segment's registration carries into the lab (centre and axis; the foot's lines)
SEGMENT_JOINTS = {"femur": ("knee",), "tibia": ("ankle",), "calcn": ("subtalar", "mtp")}


def passes_gate(reg) -> tuple[bool, str]:
    """Whether a registration passes its chi-square gate (`registration.gate_statistic` p >= `GATE_P`), and why not."""
    chi2, dof, p = gate_statistic(reg)
    if p >= GATE_P:
        return True, ""
    return False, (f"{reg.segment} registration of the MRI bones to the static markers fails its chi-square gate "
                   f"(chi2 = {chi2:.1f} on {dof} dof, p = {p:.1g} < {GATE_P:g}; rms {reg.rms * 1e3:.1f} mm"
                   + (f"; outliers {', '.join(reg.rejected)}" if reg.rejected else "") + ")")


def motion_only(e):
    """`CentreEstimates` / `AxisEstimates` `e` with the fused estimate replaced by the motion one (MRI weight 0).

    The sources' agreement (chi2, p) of the original fusion is kept: it says how far the dropped MRI estimate was.
    """
    f = e.fused
    if isinstance(e, AxisEstimates):
        alone = fuse_axis([e.motion.direction], [e.motion.sd_deg], ("motion",))
        sign = 1.0 if float(alone.direction @ f.direction) >= 0 else -1.0
        return replace(e, fused=replace(f, direction=sign * alone.direction, sd_deg=alone.sd_deg, cov=alone.cov,
                                        shares=np.array([0.0, 1.0])))
    d = f.mean.size
    return replace(e, fused=replace(f, mean=np.asarray(e.motion.mean, float).copy(),
                                    cov=np.asarray(e.motion.cov, float).copy(),
                                    weights=np.stack([np.zeros((d, d)), np.eye(d)]), shares=np.array([0.0, 1.0])))


def gate_segment(est: JointEstimates, segment: str, say: Callable[[str], None] | None = None) -> bool:
    """Gate one leg segment's registration; on failure drop its MRI source (fused = motion for the joints it
    carries, `SEGMENT_JOINTS`), say so on `say` and in ``est.notes``.  Returns whether it passed.

    The foot's subtalar and mtp axes have no motion estimate: the caller replaces them by the default axes.
    Idempotent: a segment already dropped (``est.mri_dropped``) is not dropped twice.
    """
    if segment in est.mri_dropped:
        return False
    ok, what = passes_gate(est.registrations[segment])
    if ok:
        return True
    kind, s = segment.rsplit("_", 1)
    carried = SEGMENT_JOINTS.get(kind, ())
    for jn in carried:
        if jn in est.centres.get(s, {}):
            est.centres[s][jn] = motion_only(est.centres[s][jn])
        if jn in est.axes.get(s, {}):
            est.axes[s][jn] = motion_only(est.axes[s][jn])
        if kind != "calcn":
            est.sources[f"{jn}_{s}"] = f"motion only: the MRI source was dropped ({segment} registration failed its gate)"
    msg = (f"{what}: its MRI source is dropped, the {' and '.join(f'{j}_{s}' for j in carried)} "
           + ("axes are the defaults" if kind == "calcn" else "estimates are the motion ones alone")
           + " (wrong bones, a misplaced or mislabelled marker?)")
    est.mri_dropped[segment] = msg
    est.notes.append(f"warning: {msg}")
    if say is not None:
        say(f"warning: {msg}")
    return False


def note_inconsistencies(est: JointEstimates, p_min: float = 0.01) -> None:
    """Say so in ``notes`` when a registration or a fusion fails its χ² test (p < `p_min`).

    A pelvis whose soft tissue is far thicker than the prior, a misplaced marker or an MRI of
    another subject shows up here first; the estimates stay (with inflated covariances), flagged.
    """
    for name, r in est.registrations.items():
        if r.p_value < p_min:
            est.notes.append(f"low confidence: {name} registration residuals {r.rms * 1e3:.1f} mm rms exceed the "
                             f"declared marker/soft-tissue noise (chi2 {r.chi2:.1f} on {r.dof} dof, p = {r.p_value:.1g}); "
                             "its MRI estimates carry an inflated covariance")
    hj = est.hip_joint
    if hj is not None and hj.p_value is not None and hj.p_value < p_min:
        est.notes.append(f"low confidence: MRI and motion hip centres disagree (chi2 {hj.chi2:.1f} on {hj.dof} dof, "
                         f"p = {hj.p_value:.1g}); the fused hip centres are a compromise, check the pelvis markers")
    for kind, per_side in (("axis", est.axes), ("centre", est.centres)):
        for s, joints in per_side.items():
            for jn, e in joints.items():
                if kind == "centre" and jn == "hip" and est.hip_joint is not None:
                    continue  # said once above for both hips
                p = e.fused.p_value
                if p is not None and p < p_min:
                    est.notes.append(f"low confidence: {jn} {kind} ({s}) MRI and motion estimates disagree "
                                     f"(p = {p:.1g}); fused anyway")



def gate_registrations(inputs: SubjectInputs, est: JointEstimates, say: Callable[[str], None] | None = None) -> None:
    """Refuse the subject when the pelvis registration fails its chi-square gate (the MRI bones are another
    person's); drop the MRI source of any other segment failing it (`gate_segment`) not already dropped.

    Raises
    ------
    InputError : naming the bones, the pelvis' chi-square and p-value
    """
    ok, what = passes_gate(est.registrations["pelvis"])
    if not ok:
        raise InputError(inputs.bones, what + ": the bones and the markers are not of the same person?")
    for name in est.registrations:
        if name != "pelvis":
            gate_segment(est, name, say)
