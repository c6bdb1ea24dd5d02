"""The single-subject pipeline: MRI + motion capture -> fused personalised model (`run_subject`).

Stages, and the values that pass between them (every estimate in SI units
with its covariance, `lowerlimb.estimates.Gaussian`):

1. **inputs** (`inputs.find_inputs` -> `SubjectInputs`): ``labels.nii.gz`` (+
   ``label_map.json``) or ``bones/``, ``static.c3d``, ``subject.json`` and every
   other ``*.c3d``; trials of another subject and labels and markers without a
   common side are refused (`InputError`);
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
from .inputs import SubjectInputs, check_same_subject, check_trial_legs, find_inputs
from .joint_estimates import JointEstimates
from .joints import estimate_joints
from .run import run_subject
from .summary import SubjectSummary

__all__ = ["run_subject", "SubjectInputs", "find_inputs", "check_same_subject", "check_trial_legs",
           "estimate_joints", "JointEstimates", "SubjectSummary"]
