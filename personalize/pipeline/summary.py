"""What a run of the pipeline found, as one value (`SubjectSummary`) and its one serializer (``summary.json``)."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lowerlimb.atomic import write_text

from .joint_estimates import JointEstimates

__all__ = ["SubjectSummary", "write_summary", "UNITS", "FRAME"]

UNITS = {"centres": "m (mm where named *_mm)", "axes": "unit vectors", "angles": "deg where named *_deg",
         "angle_rmse_deg": "per coordinate, RMSE of the IK angle against the phantom truth over the gait trials, deg",
         "angle_offset_deg": "per coordinate, mean IK - true angle over the gait trials (constant part of the error), deg",
         "ik_rms_mm": "largest over the dynamic trials of the mean per-frame RMS marker error, mm",
         "errors": "worst side; *_mm Euclidean distance, *_deg angle between axes (sign-free)",
         "joints_on_bones": "per joint, distance (mm) of the model's parent- and child-side joint centre, carried "
                            "into its bone's scanner frame, from the MRI joint and (phantoms) the true one"}
FRAME = ("internal frame: X the static pose's facing, Y left, Z up, the lab's origin "
         "(x_internal = lab.internal_from_lab @ x_lab)")


@dataclass
class SubjectSummary:
    """A subject's run: inputs used, joint estimates, fused parameters, IK fits and (phantoms) errors.

    estimates : `JointEstimates`; lengths : segment -> `personalize.parameter_fusion.SegmentLength`
    intercepts : side -> `personalize.pipeline.knee_law.KneeIntercept`
    ik : trial -> `personalize.pipeline.trials.TrialFit`; chain_blend : `trials.chain_blend` (JSON-ready)
    truth : `personalize.evaluation.truth.TruthComparison` or None
    lab : `kinematics.gait.lab_frame.LabFrame.to_json` of the trials' lab
    measurements : Plug-in-Gait measurement -> {"value": m, "source": subject file or how the bones gave it}
    markers : `pipeline.marker_assignment.MarkerAssignment.to_json`: each static marker's body and why
    joints_on_bones : `pipeline.model.joints_on_bones`
    dynamics_setups : `pipeline.dynamics_setups.write_dynamics_setups` (trials with force plates)
    generic : `personalize.generic_comparison.GenericComparison.to_json` (gait2392 scaled to the same markers) or None
    patellofemoral : side -> `personalize.patellofemoral.PatellarTrack.to_json` (the sides with the joint)
    """

    subject: str
    subject_dir: str
    sides: list
    trials: list
    functional_trial: str | None
    dropped_joints: dict
    notes: list
    sources: dict
    estimates: JointEstimates
    lengths: dict = field(default_factory=dict)
    intercepts: dict = field(default_factory=dict)
    ik: dict = field(default_factory=dict)
    chain_blend: dict = field(default_factory=dict)
    truth: object = None
    lab: dict | None = None
    measurements: dict | None = None
    markers: dict | None = None
    joints_on_bones: dict | None = None
    dynamics_setups: dict = field(default_factory=dict)
    generic: dict | None = None
    patellofemoral: dict = field(default_factory=dict)

    @property
    def ik_rms_mm(self) -> float:
        dyn = [v.rms_mean_mm for k, v in self.ik.items() if k != "static"]
        return float(max(dyn)) if dyn else self.ik["static"].rms_mean_mm

    def estimates_json(self) -> dict:
        est, out = self.estimates, {}
        for s in self.sides:
            for jn, e in est.centres[s].items():
                out[f"{jn}_{s}_centre"] = {"mri": e.mri.mean.tolist(), "motion": e.motion.mean.tolist(),
                                           "mri_cov": e.mri.cov.tolist(), "motion_cov": e.motion.cov.tolist(),
                                           "fused": e.fused.summary()}
            for jn, e in est.axes[s].items():
                f = e.fused
                out[f"{jn}_{s}_axis"] = {
                    src: {"direction": np.asarray(d.direction).tolist(), "sd_deg": float(d.sd_deg)}
                    for src, d in (("mri", e.mri), ("motion", e.motion))}
                out[f"{jn}_{s}_axis"]["fused"] = {"direction": f.direction.tolist(), "sd_deg": f.sd_deg,
                                                  "weights": dict(zip(f.names, f.shares.tolist())), "p_value": f.p_value}
        if est.hip_joint is not None:
            hj = est.hip_joint
            out["hips_joint_fusion"] = {
                "state": [f"hip_{s}_{a}" for s in self.sides for a in "xyz"], "mean": hj.mean.tolist(),
                "cov": hj.cov.tolist(), "weights": dict(zip(hj.names, hj.shares.tolist())), "chi2": hj.chi2,
                "dof": hj.dof, "p_value": hj.p_value,
                "method": "generalised least squares of both MRI hips (registration cross-covariance) and each side's motion centre"}
        for s, k in self.intercepts.items():
            out[f"knee_{s}_standing_translation"] = k.summary()
        for k, v in self.lengths.items():
            out[f"{k}_length"] = v.summary()
        return out

    def to_json(self) -> dict:
        """The ``summary.json`` document (SI units unless a key names its unit)."""
        est = self.estimates
        doc = {"subject": self.subject, "subject_dir": self.subject_dir, "sides": list(self.sides), "units": UNITS,
               "frame": FRAME, **({"lab": self.lab} if self.lab is not None else {}),
               **({"subject_measurements": self.measurements} if self.measurements is not None else {}),
               "trials": list(self.trials), "functional_trial": self.functional_trial,
               "dropped_joints": dict(self.dropped_joints), "notes": list(self.notes), "sources": self.sources,
               **({"markers": self.markers} if self.markers is not None else {}),
               **({"joints_on_bones": self.joints_on_bones} if self.joints_on_bones is not None else {}),
               "estimates": self.estimates_json()}
        if est.skin:
            doc["skin_thickness"] = {k: v.summary() for k, v in est.skin.items()}
            if self.truth is not None and self.truth.skin_error_mm:
                doc["skin_thickness_error_mm"] = dict(self.truth.skin_error_mm)
        doc["mri_hip_cov_scale"] = est.mri_hip_scale
        doc["registration"] = {k: {"rms_mm": r.rms * 1e3, "used": list(r.names), "rejected": list(r.rejected),
                                   **({"tissue_scale": r.tissue_scale, "tissue_scale_log_sd": r.tissue_scale_log_sd}
                                      if getattr(r, "tissue_scale", None) is not None else {})}
                               for k, r in est.registrations.items()}
        doc["ik"] = {k: v.summary() for k, v in self.ik.items()}
        doc["chain_blend"] = self.chain_blend
        doc["dynamics_setups"] = self.dynamics_setups
        doc["ik_rms_mm"] = self.ik_rms_mm
        if self.generic is not None:
            doc["generic"] = self.generic
        if self.patellofemoral:
            doc["patellofemoral"] = self.patellofemoral
        if self.truth is not None:
            doc.update(self.truth.to_json())
        return doc


def write_summary(path: Path, summary: SubjectSummary) -> Path:
    """``summary.json``: `SubjectSummary.to_json`."""
    return write_text(path, json.dumps(summary.to_json(), indent=1, default=float) + "\n")
