"""Calibration: error of the motion estimate of the knee's standing translation (the knee-law intercept).

On TRAINING phantom subjects (``personalize.validate.draw_subjects`` with the
training seed 1000; validation seeds are never used): run the pipeline
(`personalize.pipeline.run_subject`), then IK of the gait and crouch trials on
the personalised model with free knee translations, fit the flexion law
t = s * flexion + c per side (`kinematics.correlative.fit_law`) and evaluate it
at the standing knee flexion.  The phantom's true standing translation is 0,
so the result is the estimate's error; its rms per axis is
`personalize.parameter_fusion.MOTION_KNEE_TRANSLATION_SD`.  The fit's own
(formal) sd is printed next to it.

Usage::

    python benchmarks/knee_intercept_calibration.py [--subjects 8] [--folders DIR_WITH_SUBJECT_DIRS]
        [--work /tmp/knee_intercept] [--json benchmarks/results/knee_intercept_calibration.json]
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
    from kinematics.c3d import read_c3d
    from kinematics.correlative import fit_law
    from kinematics.ik import solve_ik
    from kinematics.opensim_io import load_osim
    from personalize.pipeline import run_subject

    if not (out / "model.osim").is_file():
        run_subject(subject_dir, out)
    m = load_osim(out / "model.osim").with_couplings(None)
    q_st = json.loads((out / "model.json").read_text())["standing_q"]
    trials = [read_c3d(t) for t in sorted(subject_dir.glob("gait_*.c3d")) + sorted(subject_dir.glob("crouch_*.c3d"))]
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


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=8)
    ap.add_argument("--folders", type=Path, default=None, help="existing training subject folders (phantom_001, ...)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/knee_intercept"))
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "knee_intercept_calibration.json")
    a = ap.parse_args(argv)
    from kinematics.atomic import write_text
    from personalize.validate import draw_subjects, ensure_phantom_subject

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
    e = np.array(errs)
    summary = {"legs": len(e), "rms_mm": (np.sqrt(np.mean(e**2, axis=0)) * 1e3).tolist(),
               "mean_mm": (e.mean(axis=0) * 1e3).tolist(), "formal_sd_median_mm": (np.median(sds, axis=0) * 1e3).tolist()}
    print(f"{len(e)} legs: rms (tx, ty, tz) " + " / ".join(f"{x:.2f}" for x in summary["rms_mm"]) + " mm; formal sd "
          + " / ".join(f"{x:.3f}" for x in summary["formal_sd_median_mm"]) + " mm (median)")
    write_text(a.json, json.dumps({"units": "m (per leg), mm (summary)", "truth": "0 (phantom laws vanish standing)",
                                   "subjects": out, "summary": summary}, indent=1) + "\n")
    return summary


if __name__ == "__main__":
    main()
