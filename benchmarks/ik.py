"""Benchmark: the engine's marker IK against OpenSim's InverseKinematicsSolver, side by side.

Same model (gait2392 scaled to subject01), same trial (subject01_walk1.trc over
the setup's time range), same marker weights and coordinate tasks
(subject01_Setup_IK.xml) and the setup's accuracy (OpenSim: optimizer
accuracy; engine: ``tolerance`` on the largest coordinate step, rad or m).
Each solver runs ``--repeat`` times in this process, alternating; the best wall
time counts (model loading excluded for both; OpenSim's assemble + track loop,
the engine's ``solve_ik``; wall and process CPU time, the latter being robust
to other jobs on a shared machine).  Reported: frames per second, mean and max
per-frame marker RMS (m), the weighted objective, and the largest coordinate
difference between the two solutions.

Target (issue K1): engine frames per second >= 5 x OpenSim's, at equal or
lower mean marker RMS.

Usage::

    python benchmarks/ik.py [--data ../shared/data] [--repeat 3] [--json benchmarks/results/ik.json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

# Small dense algebra: one BLAS thread is fastest and keeps the comparison single-core like OpenSim's solver.
for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lowerlimb.atomic import write_text  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PERSONALIZE_SHARED_DATA", REPO.parent / "shared" / "data")))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--block", type=int, default=16, help="frames admitted per iteration into the engine's pipelined window")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "ik.json")
    args = ap.parse_args(argv)
    d = args.data / "opensim_gait2392"
    if not d.is_dir():
        print(f"skipped: {d} not found")
        return 0
    try:
        import opensim  # noqa: F401
    except ImportError:
        print("skipped: the opensim package is not installed")
        return 0
    from kinematics.algorithms.ik import solve_ik
    from kinematics.io.ik_setup import read_ik_setup
    from kinematics.io.opensim_io import load_osim, opensim_inverse_kinematics
    from kinematics.io.storage import read_trc

    model_path, trc = d / "subject01_simbody_adjusted.osim", d / "subject01_walk1.trc"
    su = read_ik_setup(d / "subject01_Setup_IK.xml")
    model = load_osim(model_path)
    trial = read_trc(trc).window(*su.time_range)
    n = trial.n_frames
    os_times, en_times, os_cpu, en_cpu = [], [], [], []
    ref = res = None
    for _ in range(args.repeat):
        ref = opensim_inverse_kinematics(model_path, trc, su.marker_weights, su.coordinate_tasks, su.time_range,
                                         su.accuracy)
        os_times.append(ref["seconds"])
        os_cpu.append(ref["cpu_seconds"])
        t0, c0 = time.perf_counter(), time.process_time()
        res = solve_ik(model, trial, su.marker_weights, su.coordinate_tasks, tolerance=su.accuracy, block=args.block)
        en_times.append(time.perf_counter() - t0)
        en_cpu.append(time.process_time() - c0)
    order = [ref["coordinates"].index(c) for c in model.coordinate_names]
    dq = np.abs(res.q - ref["q"][:, order])
    rot = model.rotational
    # Weighted objective of OpenSim's solution evaluated with the engine (same formula as the engine's cost).
    from kinematics.algorithms.fk import marker_positions

    use = list(res.markers)
    w = np.array([su.marker_weights[m] for m in use])
    y = trial.positions[:, [trial.names.index(m) for m in use]]
    q_os = ref["q"][:, order]
    e_os = np.nansum(w * np.sum((marker_positions(model, q_os, use) - y) ** 2, -1), 1)
    ci = [model.coordinate_index(t.name) for t in su.coordinate_tasks]
    cw = np.array([t.weight for t in su.coordinate_tasks])
    ct = np.array([model.coordinates[i].default if t.value is None else t.value for t, i in zip(su.coordinate_tasks, ci)])
    e_os += ((q_os[:, ci] - ct) ** 2 * cw).sum(1)
    fps_os, fps_en = n / min(os_times), n / min(en_times)
    cfps_os, cfps_en = n / min(os_cpu), n / min(en_cpu)
    report = {
        "benchmark": "ik",
        "model": str(model_path.name), "trial": str(trc.name), "frames": n, "time_range_s": list(su.time_range),
        "markers": len(use), "coordinates": model.n_q, "accuracy": su.accuracy,
        "opensim": {"fps": fps_os, "fps_cpu": cfps_os, "seconds_best": min(os_times), "seconds_all": os_times,
                    "cpu_seconds_all": os_cpu,
                    "rms_mean_m": float(ref["rms"].mean()), "rms_max_m": float(ref["rms"].max()),
                    "objective_mean": float(e_os.mean())},
        "engine": {"fps": fps_en, "fps_cpu": cfps_en, "seconds_best": min(en_times), "seconds_all": en_times,
                   "cpu_seconds_all": en_cpu, "block": args.block,
                   "rms_mean_m": float(np.nanmean(res.rms)), "rms_max_m": float(np.nanmax(res.rms)),
                   "objective_mean": float(np.nanmean(res.cost)), "iterations_mean": float(res.iterations.mean())},
        "speedup": fps_en / fps_os,
        "speedup_cpu": cfps_en / cfps_os,
        "target_speedup": 5.0,
        "max_abs_coordinate_difference": {"deg": float(np.degrees(dq[:, rot]).max()), "m": float(dq[:, ~rot].max())},
        "max_rms_excess_m": float((res.rms - ref["rms"]).max()),
        "machine": {"python": platform.python_version(), "cpu_count": os.cpu_count(), "platform": platform.platform()},
        "units": "seconds, metres, degrees",
    }
    report["meets_target"] = bool(report["speedup"] >= 5.0 and report["engine"]["rms_mean_m"] <= report["opensim"]["rms_mean_m"] + 1e-9)
    print(f"frames {n}: OpenSim {fps_os:.0f} fps (RMS mean {1e3 * ref['rms'].mean():.4f} mm), "
          f"engine {fps_en:.0f} fps (RMS mean {1e3 * np.nanmean(res.rms):.4f} mm), speedup x{report['speedup']:.1f} "
          f"wall / x{report['speedup_cpu']:.1f} CPU time; "
          f"max coordinate difference {report['max_abs_coordinate_difference']['deg']:.3f} deg / "
          f"{1e3 * report['max_abs_coordinate_difference']['m']:.3f} mm")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_text(args.json, json.dumps(report, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
