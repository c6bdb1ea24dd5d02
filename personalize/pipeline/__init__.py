"""The single-subject pipeline: MRI + motion capture -> fused personalised model (`run_subject`).

Stages, and the values that pass between them (every estimate in SI units
with its covariance, `lowerlimb.estimates.Gaussian`):

1. **inputs** (`inputs.find_inputs` -> `SubjectInputs`): ``labels.nii.gz`` (+
   ``label_map.json``) or ``bones/``, the static trial (``static.c3d``/``.trc``,
   any case), ``subject.json`` and every other ``*.c3d``/``*.trc``; the lab read
   from the trials and every trial expressed in the internal frame (X the static
   pose's facing, Y left, Z up; `lab`); trials of another subject, an ambiguous
   lab and labels and markers without a common side are refused (`InputError`);
2. **bones** (`personalize.bone_set.analyse_bones` -> `BoneSet`): bone surfaces,
   landmarks (`personalize.landmarks.LandmarkSet`) and joint frames
   (`personalize.frames.Joint`) in the scanner frame, the same stage as
   ``personalize bones``;
3. **joints** (`joints.estimate_joints` -> `JointEstimates`): the pelvis
   registered to its markers (soft tissue measured in the MRI's body label
   where it has one, `personalize.skin`), then per side hip (`hip`), knee
   (`knee`), ankle, subtalar and mtp (`foot`): each segment registered from its
   markers plus the fused proximal joint centre, its MRI centres and axes
   carried to the lab with their covariance, fused with the motion estimates
   (`motion`: SCoRE, SARA, Plug-in-Gait) as Gaussians (`personalize.fusion`);
   thigh and shank lengths fused too (`personalize.parameter_fusion`);
4. **model** (`run.build_model` -> `personalize.model_builder.PersonalModel`):
   built from the fused parameters (their covariances kept in ``model.json``),
   the knee law's flexion slopes fitted from IK with free knee translations when
   physiological and its intercept fused (`knee_law`);
5. **kinematics** (`trials`): IK of every trial and the blended hip-first and
   foot-first chains;
6. **summary** (`summary.SubjectSummary` -> ``summary.json``) and
   ``report.html`` (`personalize.presentation.subject_report`); for phantom
   subjects the errors against the truth (`personalize.evaluation.truth`).

Frames: every estimate is compared in the lab frame of the static trial (X
forward, Y left, Z up, metres).  The covariance scales of the MRI and motion
sources were calibrated on TRAINING phantom subjects (mean Mahalanobis d² = 3);
each constant sits with the estimator it parametrises (`hip`, `knee`, `foot`,
`motion`) and the numbers it came from are in ``calibration.json``.
"""
import importlib

# resolved on first use (PEP 562): importing one stage (e.g. `inputs` for `personalize markers`) does not load
# the whole pipeline with fusion, registration and scipy.stats
_EXPORTS = {"run_subject": "run", "SubjectInputs": "inputs", "find_inputs": "inputs",
            "check_same_subject": "inputs", "check_trial_legs": "inputs", "estimate_joints": "joints",
            "JointEstimates": "joint_estimates", "SubjectSummary": "summary"}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
