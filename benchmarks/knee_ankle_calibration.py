"""Calibration of the knee and ankle error models: the knee-law intercept and the knee/ankle centre covariances.

On TRAINING phantom subjects (``personalize.evaluation.phantom_set.draw_subjects`` with the
training seed 1000; validation seeds are never used): run the pipeline
(`personalize.pipeline.run_subject`), then IK of the gait and crouch trials on
the personalised model with free knee translations, fit the flexion law
t = s * flexion + c per side (`kinematics.mechanisms.correlative_fit.fit_law`) and evaluate it
at the standing knee flexion.  The phantom's true standing translation is 0,
so the result is the estimate's error; its rms per axis is
`personalize.parameter_fusion.MOTION_KNEE_TRANSLATION_SD`.  The fit's own
(formal) sd is printed next to it.

The same runs give the knee and ankle centre error models: per leg the
Mahalanobis distance d² = eᵀ C⁻¹ e of each source's centre (MRI registered,
motion Plug-in-Gait) against the phantom truth in the static lab
(`personalize.evaluation.truth.truth_in_static_lab`); an honest covariance has
mean d² = 3, so mean d² / 3 is the factor the claimed covariance is off by
(`personalize.pipeline.knee.MRI_KNEE_CENTRE_COV_SCALE`, `personalize.pipeline.foot.MRI_ANKLE_CENTRE_COV_SCALE`, `personalize.pipeline.motion.PIG_CENTRE_SD`).

Usage::

    python benchmarks/knee_ankle_calibration.py [--subjects 8] [--folders DIR_WITH_SUBJECT_DIRS]
        [--work /tmp/knee_ankle_calibration] [--json benchmarks/results/knee_ankle_calibration.json]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def standing_translation(subject_dir: Path, out: Path) -> dict:
    from kinematics.io.storage import read_trc
    from kinematics.mechanisms.correlative_fit import fit_law
    from kinematics.algorithms.ik import solve_ik
    from kinematics.io.opensim_io import load_osim
    from personalize.pipeline import run_subject

    if not (out / "model.osim").is_file():
        run_subject(subject_dir, out)
    m = load_osim(out / "model.osim").with_couplings(None)
    q_st = json.loads((out / "model.json").read_text())["standing_q"]
    # the run's TRC copies of the trials are in the model's ground (the C3Ds are in the lab)
    kin = out / "kinematics"
    trials = [read_trc(t) for t in sorted(kin.glob("gait_*[0-9].trc")) + sorted(kin.glob("crouch_*[0-9].trc"))]
    res = [solve_ik(m, tr) for tr in trials]
    rows = {}
    for s in ("r", "l"):
        A = np.concatenate([r.q[:, [m.coordinate_index(f"knee_{n}_{s}") for n in ("flexion", "adduction", "rotation")]]
                            for r in res])
        D = np.concatenate([r.q[:, [m.coordinate_index(f"knee_{n}_{s}") for n in ("tx", "ty", "tz")]] for r in res])
        f = fit_law(A[:, :1], D, (f"knee_flexion_{s}",), (f"knee_tx_{s}", f"knee_ty_{s}", f"knee_tz_{s}"),
                    joint=f"knee_{s}")
        q = np.array([[q_st[f"knee_flexion_{s}"]]])
        rows[s] = {"translation_m": f.predict(q)[0].tolist(), "formal_sd_m": f.predict_sd(q)[0].tolist()}
    return rows


def centre_calibration(pairs) -> dict:
    """Mean Mahalanobis d² of the MRI, motion and fused knee/ankle centres of the runs (see the module docstring)."""
    from personalize.evaluation.truth import truth_in_static_lab
    from personalize.pipeline import find_inputs

    rows = {j: {src: [] for src in ("mri", "motion", "fused")} for j in ("knee", "ankle")}
    for subject_dir, run in pairs:
        s = json.loads((run / "summary.json").read_text())
        tr = truth_in_static_lab(find_inputs(subject_dir))
        for side in s["sides"]:
            for j in rows:
                e = s["estimates"][f"{j}_{side}_centre"]
                t = np.asarray(tr["centres"][f"{j}_{side}"])
                for src in ("mri", "motion", "fused"):
                    m, C = ((e["fused"]["mean"], e["fused"]["cov"]) if src == "fused" else (e[src], e[f"{src}_cov"]))
                    d = np.asarray(m, float) - t
                    C = np.asarray(C, float)
                    rows[j][src].append((float(d @ np.linalg.solve(C, d)), float(np.linalg.norm(d)),
                                         float(np.sqrt(np.trace(C)))))
    out = {}
    for j, r in rows.items():
        for src, v in r.items():
            v = np.array(v)
            out[f"{j}_{src}"] = {"legs": len(v), "mean_d2": float(v[:, 0].mean()), "cov_scale": float(v[:, 0].mean() / 3),
                                 "error_median_mm": float(np.median(v[:, 1]) * 1e3),
                                 "claimed_rms_median_mm": float(np.median(v[:, 2]) * 1e3)}
            o = out[f"{j}_{src}"]
            print(f"{j} centre, {src:6s}: mean d2 {o['mean_d2']:.2f} (honest: 3) -> covariance scale {o['cov_scale']:.3f}; "
                  f"error median {o['error_median_mm']:.2f} mm, claimed sqrt(tr C) median {o['claimed_rms_median_mm']:.2f} mm")
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=8)
    ap.add_argument("--folders", type=Path, default=None, help="existing training subject folders (phantom_001, ...)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/knee_ankle_calibration"))
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "knee_ankle_calibration.json")
    a = ap.parse_args(argv)
    from lowerlimb.atomic import write_text
    from personalize.evaluation.phantom_set import draw_subjects, ensure_phantom_subject

    specs = draw_subjects(a.subjects, 1000)
    out, errs, sds = {}, [], []
    for spec in specs:
        d = (a.folders / spec.subject) if a.folders is not None else ensure_phantom_subject(a.work / "subjects" / spec.subject, spec)
        r = standing_translation(Path(d), a.work / "runs" / spec.subject)
        out[spec.subject] = r
        for s, v in r.items():
            errs.append(v["translation_m"])
            sds.append(v["formal_sd_m"])
            print(f"{spec.subject} {s}: standing translation (tx, ty, tz) "
                  + " ".join(f"{1e3 * x:+.2f}" for x in v["translation_m"]) + " mm, formal sd "
                  + " ".join(f"{1e3 * x:.3f}" for x in v["formal_sd_m"]) + " mm", flush=True)
    centres = centre_calibration([(Path(a.folders / sp.subject) if a.folders is not None else a.work / "subjects" / sp.subject,
                                   a.work / "runs" / sp.subject) for sp in specs])
    e = np.array(errs)
    summary = {"legs": len(e), "rms_mm": (np.sqrt(np.mean(e**2, axis=0)) * 1e3).tolist(),
               "mean_mm": (e.mean(axis=0) * 1e3).tolist(), "formal_sd_median_mm": (np.median(sds, axis=0) * 1e3).tolist()}
    print(f"{len(e)} legs: rms (tx, ty, tz) " + " / ".join(f"{x:.2f}" for x in summary["rms_mm"]) + " mm; formal sd "
          + " / ".join(f"{x:.3f}" for x in summary["formal_sd_median_mm"]) + " mm (median)")
    write_text(a.json, json.dumps({"units": "m (per leg), mm (summary)", "truth": "0 (phantom laws vanish standing)",
                                   "subjects": out, "summary": summary, "centres": centres}, indent=1) + "\n")
    return summary


if __name__ == "__main__":
    main()
