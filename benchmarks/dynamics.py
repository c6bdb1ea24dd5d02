"""Benchmark: inverse dynamics by composed transmission elements against OpenSim's InverseDynamicsSolver.

Same model (gait2392 scaled to subject01, muscles switched off), the same N
random states (q uniform within the coordinate ranges, qd ~ N(0, 2^2),
qdd ~ N(0, 5^2), seeded).  Reported: the largest absolute difference (N m or
N), the largest difference relative to the largest |tau| of the state, the
median per-element relative difference, and the wall/CPU time of both (the
engine vectorised over the N states, OpenSim one state at a time; model
loading excluded for both).

Usage::

    python benchmarks/dynamics.py [--data ../shared/data] [--n 200] [--json benchmarks/results/dynamics.json]
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

from kinematics.atomic import write_text  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PERSONALIZE_SHARED_DATA", REPO.parent / "shared" / "data")))
    ap.add_argument("--n", type=int, default=200, help="number of random states")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "dynamics.json")
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
    from kinematics.dynamics import inverse_dynamics, opensim_inverse_dynamics
    from kinematics.opensim_io import load_osim
    from kinematics.transmission import TransmissionChain

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
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_text(args.json, json.dumps(report, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
