"""Benchmark: cohort throughput of ``personalize.cohort.run_batch`` with 1 and 2 dask workers.

Job: ``personalize.evaluation.demo.run_demo`` on one phantom per subject (phantom seed =
subject index, ``--voxel`` mm label volume: write the phantom, extract the bone
surfaces, compare with the exact ones).  Each configuration runs the same
``--subjects`` subjects into a fresh output folder on a new LocalCluster of K
single-threaded worker processes.  Reported per K: subjects per minute over the
compute wall time (first submission to last completion; cluster start-up
excluded, reported separately), mean per-subject wall and CPU seconds on the
workers, speed-up over K = 1, and the machine's load average (the machine may
be shared: compare CPU seconds too).

Usage::

    python benchmarks/batch.py [--subjects 4] [--voxel 2.0] [--workers 1 2] [--json benchmarks/results/batch.json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lowerlimb.atomic import write_text  # noqa: E402


def demo_job(subject_dir: Path, out: Path, progress=None) -> dict:
    """Adapter: run ``run_demo`` with the seed and voxel size stored in ``subject_dir/demo.json``."""
    import time as _t

    from personalize.evaluation.demo import run_demo

    spec = json.loads((Path(subject_dir) / "demo.json").read_text())
    c0, w0 = _t.process_time(), _t.perf_counter()
    summary = run_demo(out, seed=int(spec["seed"]), voxel_mm=float(spec["voxel_mm"]), progress=progress)
    return dict(summary, cpu_seconds=_t.process_time() - c0, wall_seconds=_t.perf_counter() - w0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=4)
    ap.add_argument("--voxel", type=float, default=2.0, help="phantom label-volume voxel size, mm")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "batch.json")
    args = ap.parse_args(argv)

    from personalize.cohort import Subject, run_batch

    results = []
    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        tmp = Path(tmp)
        subjects = []
        for i in range(args.subjects):
            d = tmp / "subjects" / f"s{i:02d}"
            d.mkdir(parents=True)
            (d / "demo.json").write_text(json.dumps({"seed": i, "voxel_mm": args.voxel}))
            subjects.append(Subject(f"s{i:02d}", d))
        for k in args.workers:
            load0 = os.getloadavg()[0]
            res = run_batch(subjects, tmp / f"out_k{k}", job=demo_job, workers=k, progress=False)
            summaries = [json.loads((Path(r.output) / "summary.json").read_text()) for r in res.results
                         if r.status == "ok"]
            row = {"workers": k, "subjects": args.subjects, "ok": res.counts["ok"], "errors": res.counts["error"],
                   "subjects_per_minute": res.subjects_per_minute, "compute_wall_s": res.compute_seconds,
                   "total_wall_s": res.wall_seconds, "startup_s": res.wall_seconds - res.compute_seconds,
                   "mean_subject_wall_s": sum(s["wall_seconds"] for s in summaries) / max(1, len(summaries)),
                   "mean_subject_cpu_s": sum(s["cpu_seconds"] for s in summaries) / max(1, len(summaries)),
                   "loadavg_1min_before": load0, "loadavg_1min_after": os.getloadavg()[0]}
            results.append(row)
            print(f"workers={k}: {row['subjects_per_minute']:.2f} subjects/min ({row['ok']} ok, {row['errors']} error; "
                  f"compute {row['compute_wall_s']:.1f} s, start-up {row['startup_s']:.1f} s, "
                  f"per subject {row['mean_subject_wall_s']:.1f} s wall / {row['mean_subject_cpu_s']:.1f} s CPU; "
                  f"load {load0:.1f} -> {row['loadavg_1min_after']:.1f})", flush=True)
    base = next((r for r in results if r["workers"] == 1), None)
    for r in results:
        r["speedup_vs_1_worker"] = r["subjects_per_minute"] / base["subjects_per_minute"] if base else None
    if base:
        for r in results:
            print(f"speed-up with {r['workers']} worker(s): {r['speedup_vs_1_worker']:.2f}x")
    payload = {"benchmark": "batch", "job": "personalize.evaluation.demo.run_demo", "voxel_mm": args.voxel,
               "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
               "results": results}
    write_text(args.json, json.dumps(payload, indent=1) + "\n")
    print(f"wrote {args.json}")
    return 0 if all(r["errors"] == 0 for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
