"""Cache the per-leg MRI-only and motion-only hip estimates of phantom subjects (fusion calibration data).

For each phantom subject drawn like ``personalize validate`` (`personalize.evaluation.phantom_set.draw_subjects`
with a TRAINING master seed, disjoint from the validation seeds) this runs the pipeline
only up to the joint estimates (surfaces, landmarks, pelvis registration, SCoRE/SARA;
no model, no IK) and stores per subject, in the static-trial lab frame (m, m²):

* the pelvis registration (R, t, 6x6 covariance of (ω, δ), pivot) and the scanner
  hip centres with their own covariance (so both MRI hips' joint 6x6 covariance can
  be recomputed);
* per side: the MRI hip (x, C), the SCoRE hip (x, raw C from its residuals, C with
  the pipeline's floor), the cluster poses of the functional trial (npz) so other
  SCoRE covariances can be computed offline, the knee axes (MRI, motion) and the truth;
* the pelvis anatomical frame of the static markers;
* the soft tissue used under the pelvic markers (measured in the body/skin label or prior,
  `personalize.skin`) and the MRI hip covariance scale in force.

Usage::

    python benchmarks/fusion_cache.py --subjects 24 --seed 1000 --out /tmp/p1_cache
    python benchmarks/fusion_cache.py --folders VALIDATION_OUT/subjects --out /tmp/p1_valcache   # held-out check
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def cache_subject(d: Path, out_json: Path, say=print) -> dict:
    from personalize.bone_set import read_bone_set
    from personalize.evaluation.truth import truth_in_static_lab
    from personalize.pipeline import estimate_joints, find_inputs, foot, hip, knee, motion
    from personalize.pipeline.markers import marker_view
    from personalize.pipeline.motion import PELVIS_CLUSTER, THIGH_MARKERS, cluster_pose
    from kinematics.algorithms.functional import score

    t0 = time.perf_counter()
    inputs = find_inputs(d)
    t1 = time.perf_counter()
    bones = read_bone_set(inputs.bones, inputs.label_map)
    joints = {k: j.without_model_error() for k, j in bones.joints.items()}
    t2 = time.perf_counter()
    est = estimate_joints(inputs, bones.surfaces, bones.landmarks, joints, lambda m: None, bones.dropped)
    truth = truth_in_static_lab(inputs)
    t3 = time.perf_counter()
    reg = est.registrations["pelvis"]
    rec = {"subject": d.name, "units": "m, m^2, rad", "frame": "static-trial lab",
           "pelvis_origin": est.pelvis[0].tolist(), "pelvis_axes": est.pelvis[1].tolist(),
           "reg": {"R": reg.R.tolist(), "t": reg.t.tolist(), "cov": reg.cov.tolist(), "centre": reg.centre.tolist(),
                   "names": list(reg.names), "chi2": reg.chi2, "dof": reg.dof, "inflation": reg.inflation},
           "seconds": {"surfaces": t1 - t0, "landmarks": t2 - t1, "estimates": t3 - t2}, "sides": {},
           # the pipeline constants in force: the cached covariances / sds hold them
           "skin": {k: v.summary() for k, v in est.skin.items()}, "mri_hip_scale": est.mri_hip_scale,
           "constants": {"MRI_HIP_COV_SCALE": hip.MRI_HIP_COV_SCALE, "MRI_HIP_COV_SCALE_MEASURED": hip.MRI_HIP_COV_SCALE_MEASURED,
                         "MRI_KNEE_AXIS_SD_SCALE": knee.MRI_KNEE_AXIS_SD_SCALE,
                         "MOTION_KNEE_AXIS_SD_DEG": motion.MOTION_KNEE_AXIS_SD_DEG,
                         "MRI_ANKLE_AXIS_SD_SCALE": foot.MRI_ANKLE_AXIS_SD_SCALE,
                         "MOTION_ANKLE_AXIS_SD_DEG": motion.MOTION_ANKLE_AXIS_SD_DEG}}
    view = marker_view(inputs)          # the trials under internal names (RKNEM -> RMFC), as the pipeline sees them
    fun = view.trials[inputs.functional]
    poses = {}
    for s in est.centres:
        S = s.upper()
        h = est.centres[s]["hip"]
        P = cluster_pose(view.static, [fun], view.segment_markers("pelvis", PELVIS_CLUSTER))
        D = cluster_pose(view.static, [fun], view.segment_markers(f"femur_{s}", tuple(S + m for m in THIGH_MARKERS)))
        sc = score(P.R, P.t, D.R, D.t)
        poses.update({f"{s}_PR": P.R, f"{s}_Pt": P.t, f"{s}_DR": D.R, f"{s}_Dt": D.t})
        ka = est.axes[s]["knee"]
        aa = est.axes[s]["ankle"]
        rec["sides"][s] = {
            "hip_scanner": joints[f"hip_{s}"].origin.tolist(), "hip_scanner_cov": joints[f"hip_{s}"].origin_cov.tolist(),
            "mri": [h.mri.mean.tolist(), h.mri.cov.tolist()],
            "motion": [h.motion.mean.tolist(), h.motion.cov.tolist()],
            "score": [sc.proximal.tolist(), sc.cov_proximal.tolist(), sc.rms, sc.n_frames],
            "truth": truth["centres"][f"hip_{s}"].tolist(),
            "knee_axis": {"mri": [np.asarray(ka.mri.direction).tolist(), float(ka.mri.sd_deg)],
                          "motion": [np.asarray(ka.motion.direction).tolist(), float(ka.motion.sd_deg)],
                          "truth": truth["axes"][f"knee_{s}"].tolist()},
            "ankle_axis": {"mri": [np.asarray(aa.mri.direction).tolist(), float(aa.mri.sd_deg)],
                           "motion": [np.asarray(aa.motion.direction).tolist(), float(aa.motion.sd_deg)],
                           "truth": truth["axes"][f"ankle_{s}"].tolist()},
        }
    np.savez_compressed(out_json.with_suffix(".npz"), **poses)
    out_json.write_text(json.dumps(rec, indent=1) + "\n")
    say(f"{d.name}: surfaces {t1 - t0:.0f} s, landmarks {t2 - t1:.0f} s, estimates {t3 - t2:.0f} s")
    return rec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=12)
    ap.add_argument("--seed", type=int, default=1000, help="TRAINING master seed (not a validation seed)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/p1_cache"))
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--folders", type=Path, default=None,
                    help="cache existing phantom subject folders (e.g. a validation run's subjects/) instead of drawing")
    a = ap.parse_args(argv)
    from personalize.evaluation.phantom_set import SPEC, draw_subjects, ensure_phantom_subject

    a.out.mkdir(parents=True, exist_ok=True)
    if a.folders is not None:
        for d in sorted(p for p in a.folders.iterdir() if (p / "generated.json").is_file()):
            oj = a.out / f"{d.name}.json"
            if not oj.is_file():
                cache_subject(d, oj)
        return
    for spec in draw_subjects(a.first + a.subjects, a.seed)[a.first:]:
        d = a.out / "subjects" / spec.subject
        oj = a.out / f"{spec.subject}.json"
        if oj.is_file():
            continue
        d.mkdir(parents=True, exist_ok=True)
        (d / SPEC).write_text(json.dumps(spec.to_json(), indent=1) + "\n")
        t0 = time.perf_counter()
        ensure_phantom_subject(d, spec)
        print(f"{spec.subject}: phantom {time.perf_counter() - t0:.0f} s", flush=True)
        cache_subject(d, oj)


if __name__ == "__main__":
    main()
