"""Benchmark: inverse dynamics by composed transmission elements against OpenSim (solver and InverseDynamicsTool).

Same model (gait2392 scaled to subject01, muscles switched off), the same N
random states (q uniform within the coordinate ranges, qd ~ N(0, 2^2),
qdd ~ N(0, 5^2), seeded).  Reported: the largest absolute difference (N m or
N), the largest difference relative to the largest |tau| of the state, the
median per-element relative difference, and the wall/CPU time of both (the
engine vectorised over the N states, OpenSim one state at a time; model
loading excluded for both).

Trial part (``--trial``, on by default): subject01_walk1 on subject01_simbody.osim
with its ground reactions and a 6 Hz filter, once through OpenSim's
InverseDynamicsTool (``tool.run()``: reading the files, filtering, splines,
solving; the model constructed beforehand) and once through
`kinematics.gait.inverse_dynamics.trial_inverse_dynamics` (reading the same
files, building the transmission chain, filtering, splines, solving; the
model loaded beforehand), over the
setup's window (0.4-1.6 s, i.e. the 67 IK frames from 0.5 s) and over the
whole span of the ground reactions (0.5-2.5 s, 121 frames).  Reported:
frames per second of both, their ratio, and the largest RMS difference of a
column relative to its peak.  Each timing is the best of ``--repeat`` runs
(the first engine call, paying Python's imports, is not timed).

Usage::

    python benchmarks/dynamics.py [--data ../shared/data] [--n 200] [--repeat 3] [--no-trial]
                                  [--json benchmarks/results/dynamics.json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lowerlimb.atomic import write_text  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PERSONALIZE_SHARED_DATA", REPO.parent / "shared" / "data")))
    ap.add_argument("--n", type=int, default=200, help="number of random states")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "dynamics.json")
    ap.add_argument("--trial", action=argparse.BooleanOptionalAction, default=True,
                    help="also time a whole gait trial against OpenSim's InverseDynamicsTool")
    ap.add_argument("--repeat", type=int, default=5, help="timings per tool (best kept)")
    args = ap.parse_args(argv)
    path = args.data / "opensim_gait2392" / "subject01_simbody_adjusted.osim"
    if not path.is_file():
        print(f"skipped: {path} not found")
        return 0
    try:
        import opensim
    except ImportError:
        print("skipped: the opensim package is not installed")
        return 0
    from kinematics.mechanisms.dynamics import inverse_dynamics, opensim_inverse_dynamics
    from kinematics.io.opensim_io import load_osim
    from kinematics.mechanisms.transmission import TransmissionChain

    model = load_osim(path)
    rng = np.random.default_rng(args.seed)
    q = model.random_q(args.n, rng)
    qd = rng.normal(size=q.shape) * 2.0
    qdd = rng.normal(size=q.shape) * 5.0
    om = opensim.Model(str(path))
    fs = om.getForceSet()
    for i in range(fs.getSize()):
        fs.get(i).set_appliesForce(False)
    t0, c0 = time.perf_counter(), time.process_time()
    ref = opensim_inverse_dynamics(om, model.coordinate_names, q, qd, qdd)
    os_wall, os_cpu = time.perf_counter() - t0, time.process_time() - c0
    chain = TransmissionChain(model)
    t0, c0 = time.perf_counter(), time.process_time()
    tau = inverse_dynamics(model, q, qd, qdd, chain=chain)
    en_wall, en_cpu = time.perf_counter() - t0, time.process_time() - c0
    err = np.abs(tau - ref)
    scale = np.abs(ref).max(axis=1, keepdims=True)
    rel_state = (err / scale).max()
    rel_elem = np.median(err / np.maximum(np.abs(ref), 1e-12))
    report = {
        "model": str(path.name), "states": args.n, "seed": args.seed,
        "max_abs_difference": float(err.max()), "max_difference_relative_to_state_max": float(rel_state),
        "median_elementwise_relative_difference": float(rel_elem),
        "engine": {"seconds": en_wall, "cpu_seconds": en_cpu, "states_per_second": args.n / en_wall},
        "opensim": {"seconds": os_wall, "cpu_seconds": os_cpu, "states_per_second": args.n / os_wall},
        "machine": platform.platform(), "units": "tau in N m (rotational) / N (translational); time in s",
    }
    print(f"{args.n} states: max |tau - tau_OpenSim| = {err.max():.3g} (relative to the state's max |tau|: "
          f"{rel_state:.3g}; median element-wise relative {rel_elem:.3g})")
    print(f"engine {args.n / en_wall:.0f} states/s, OpenSim {args.n / os_wall:.0f} states/s")
    if args.trial:
        report["trial"] = trial_benchmark(args.data / "opensim_gait2392", args.repeat)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_text(args.json, json.dumps(report, indent=2))
    print(f"wrote {args.json}")
    return 0


def trial_benchmark(d: Path, repeat: int) -> dict:
    """Whole-trial inverse dynamics: the engine against OpenSim's InverseDynamicsTool (module docstring)."""
    import tempfile

    import opensim

    from kinematics.io.external_loads import read_external_loads
    from kinematics.gait.inverse_dynamics import trial_inverse_dynamics
    from kinematics.io.opensim_io import load_osim
    from kinematics.io.storage import read_mot, read_sto
    from kinematics.mechanisms.transmission import TransmissionChain

    model_path, ik, grf, xml = (d / n for n in ("subject01_simbody.osim", "subject01_walk1_ik.mot",
                                                  "subject01_walk1_grf.mot", "subject01_walk1_grf.xml"))
    model = load_osim(model_path)
    rot = [c for c, k in zip(model.coordinate_names, tuple(c.kind for c in model.coordinates)) if k == "rotational"]

    def engine(t0, t1):
        tab = read_mot(ik).to_radians(rot)
        loads = read_external_loads(xml, grf)
        return trial_inverse_dynamics(model, tab.time, tab.select(model.coordinate_names), loads, cutoff=6.0,
                                      start=t0, end=t1, chain=TransmissionChain(model))

    engine(0.5, 1.6)  # imports and first-call costs, not timed
    out = {"model": model_path.name, "kinematics": ik.name, "cutoff_hz": 6.0, "windows": []}
    with tempfile.TemporaryDirectory() as tmp:
        for t0, t1 in ((0.4, 1.6), (0.5, 2.5)):
            om = opensim.Model(str(model_path))
            os_best, os_cpu = np.inf, np.inf
            for k in range(repeat):
                tool = opensim.InverseDynamicsTool()
                tool.setModel(om)
                tool.setCoordinatesFileName(str(ik))
                tool.setExternalLoadsFileName(str(xml))
                tool.setLowpassCutoffFrequency(6.0)
                tool.setStartTime(max(t0, 0.5))
                tool.setEndTime(t1)
                ex = opensim.ArrayStr()
                ex.append("muscles")
                tool.setExcludedForces(ex)
                tool.setResultsDir(tmp)
                tool.setOutputGenForceFileName(f"id_{k}.sto")
                c, p = time.perf_counter(), time.process_time()
                tool.run()
                os_best = min(os_best, time.perf_counter() - c)
                os_cpu = min(os_cpu, time.process_time() - p)
            ref = read_sto(Path(tmp) / "id_0.sto")
            en_best, en_cpu = np.inf, np.inf
            for _ in range(repeat):
                c, p = time.perf_counter(), time.process_time()
                res = engine(t0, t1)
                en_best = min(en_best, time.perf_counter() - c)
                en_cpu = min(en_cpu, time.process_time() - p)
            worst, worst_col = 0.0, ""
            for i, lab in enumerate(res.labels):
                r = np.interp(res.time, ref.time, ref.column(lab))
                e = float(np.sqrt(np.mean((res.tau[:, i] - r) ** 2)) / np.abs(r).max())
                if e > worst:
                    worst, worst_col = e, lab
            n = res.time.shape[0]
            row = {"window_s": [t0, t1], "frames": n, "opensim_frames": ref.n_frames,
                   "engine_frames_per_second": n / en_best, "opensim_frames_per_second": ref.n_frames / os_best,
                   "engine_seconds": en_best, "opensim_seconds": os_best,
                   "engine_cpu_seconds": en_cpu, "opensim_cpu_seconds": os_cpu,
                   "speed_ratio": (n / en_best) / (ref.n_frames / os_best),
                   "cpu_speed_ratio": (n / en_cpu) / (ref.n_frames / os_cpu),
                   "max_rms_difference_relative_to_peak": worst, "worst_column": worst_col}
            out["windows"].append(row)
            print(f"trial {t0}-{t1} s ({n} frames): engine {row['engine_frames_per_second']:.0f} frames/s, "
                  f"OpenSim InverseDynamicsTool {row['opensim_frames_per_second']:.0f} frames/s "
                  f"(x{row['speed_ratio']:.1f} wall, x{row['cpu_speed_ratio']:.1f} CPU); largest RMS difference {100 * worst:.4f} % of peak ({worst_col})")
    return out


if __name__ == "__main__":
    raise SystemExit(main())
