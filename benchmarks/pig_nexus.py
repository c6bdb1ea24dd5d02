"""Benchmark: Plug-in-Gait against Vicon Nexus, and functional hip centres on star-arc motion.

Part 1 runs `kinematics.gait.pig` on ../shared/data/mocap_pig (pyCGM sample data,
which carries Nexus' own Plug-in-Gait outputs) with the foot offsets
calibrated from the static trial, and reports the mean over frames of
|knee/ankle centre - Nexus femur/tibia origin| (mm) and |angle - Nexus angle|
(degrees, per component) for hip, knee and ankle.

Part 2 simulates a thigh cluster pivoting in a 45-degree star-arc about a
known hip centre relative to a moving pelvis cluster (0.5 mm marker noise,
seeded) and reports the hip-centre error (mm) of the centre transformation
technique, SCoRE and the sphere fit.

Targets (issue K2): centres within 1 mm and angles within 1 degree of Nexus;
functional hip centre errors under 2 mm.

Usage::

    python benchmarks/pig_nexus.py [--json benchmarks/results/pig_nexus.json]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from lowerlimb.atomic import write_text  # noqa: E402


def nexus_comparison(data: Path) -> dict:
    from kinematics.io.c3d import read_c3d, read_c3d_outputs
    from kinematics.gait.pig import plug_in_gait, static_foot_offsets
    from kinematics.gait.subject import read_vsk, validate_static

    sub = read_vsk(data / "Test.vsk")
    static = read_c3d(data / "Static_trial.c3d")
    validate_static(sub, static)
    cal = static_foot_offsets(static, sub)
    out = {"foot_offset_diff_rad": {k: abs(getattr(cal, k) - getattr(sub, k)) for k in (
        "right_static_plantar_flexion", "left_static_plantar_flexion",
        "right_static_rotation_offset", "left_static_rotation_offset")}}
    for name in ("Movement_trial", "Static_trial"):
        trial = read_c3d(data / f"{name}.c3d")
        nexus = read_c3d_outputs(data / f"{name}.c3d")
        res = plug_in_gait(trial, cal)
        rows = {}
        for s, sfx in (("R", "_r"), ("L", "_l")):
            for centre, seg in (("knee", "FEO"), ("ankle", "TIO")):
                e = np.linalg.norm(res.centres[centre + sfx] - trial.marker(s + seg), axis=1)
                rows[f"{centre}{sfx}_centre_mm"] = float(np.nanmean(e) * 1e3)
            for joint, label in (("hip", "HipAngles"), ("knee", "KneeAngles"), ("ankle", "AnkleAngles")):
                d = np.abs((np.degrees(res.angles[joint + sfx] - nexus[s + label]) + 180) % 360 - 180)
                rows[f"{joint}{sfx}_angles_deg"] = [float(v) for v in np.nanmean(d, axis=0)]
        out[name] = rows
    return out


def functional_errors() -> dict:
    from test_functional import HIP_IN_PELVIS, PELVIS_MARKERS, THIGH_MARKERS, simulate

    from kinematics.algorithms.functional import centre_transformation, pivot_sphere_fit, score
    from kinematics.algorithms.segments import rigid_pose

    out = {}
    for seed in range(5):
        pel, thi = simulate(seed=seed)
        P, T = rigid_pose(PELVIS_MARKERS, pel), rigid_pose(THIGH_MARKERS, thi)
        est = {"ctt": centre_transformation(P.R, P.t, T.R, T.t).proximal,
               "score": score(P.R, P.t, T.R, T.t).proximal,
               "sphere": pivot_sphere_fit(P.to_local(thi)).centre}
        for k, v in est.items():
            out.setdefault(k, []).append(float(np.linalg.norm(v - HIP_IN_PELVIS) * 1e3))
    return {k: {"errors_mm": v, "max_mm": max(v)} for k, v in out.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "mocap_pig")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    result = {"units": "mm for centres, degrees for angles (mean over frames of absolute differences)"}
    if args.data.is_dir():
        result["nexus"] = nexus_comparison(args.data)
    else:
        print(f"no Nexus data at {args.data}: skipping part 1")
    result["functional_star_arc_45deg_0.5mm"] = functional_errors()
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        write_text(args.json, text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
