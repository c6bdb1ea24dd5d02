"""Benchmark: marker-based reconstruction (Plug-in-Gait vs foot-to-hip) on motion phantoms.

Part 1 (speed, issue K2): frames per second of `kinematics.gait.reconstruction.reconstruct`
for each method on a 10-minute gait trial at 100 Hz (60 000 frames), best of 3.

Part 2 (the seed's validation claims, Tändl et al. 2010 section 5, reproduced
on phantoms with soft-tissue artefact and 0.5 mm noise; seeds 0..N-1, both
legs, gait): the average position fluctuation (mm) of RTIBM1, RTIBM2 (tibia-
fixed) and RANKM relative to each method's tibia frame, and the RMSE (deg)
of the knee adduction and rotation angles against the phantom truth.

Part 3: functional hip-centre error (mm, mean over frames, both hips) of the
centre transformation technique, SCoRE and the sphere fit on the thigh
cluster (RTHI, RKNE, RTHIP, RTHIA) vs the pelvis markers, and of the
foot-to-hip hip centre (centre transformation on its eq. 29 femur frames),
for star-arc ranges 20, 30 and 45 degrees, with and without artefact.

Usage::

    python benchmarks/markers.py [--seeds 5] [--json benchmarks/results/markers.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lowerlimb.atomic import write_text  # noqa: E402


def speed() -> dict:
    from kinematics.gait.reconstruction import reconstruct
    from phantoms import make_phantom
    from phantoms.motion import make_trials

    ph = make_phantom(0)
    t0 = time.perf_counter()
    sk, trials, _ = make_trials(ph, 0, rate=100.0, gait_trials=1, gait_cycles=600.0 / 1.1, crouch_angles=(),
                                functional_ranges=(), static_duration=2.0)
    gen = time.perf_counter() - t0
    static, gait = trials[0].markers, trials[1].markers
    out = {"frames": int(gait.n_frames), "rate_hz": gait.rate, "phantom_generation_s": gen}
    for m in ("pig", "foot-to-hip"):
        best = np.inf
        for _ in range(3):
            t = time.perf_counter()
            reconstruct(gait, m, static=static, subject=sk.subject)
            best = min(best, time.perf_counter() - t)
        out[m] = {"seconds": best, "frames_per_second": gait.n_frames / best}
    return out


def claims(n_seeds: int) -> dict:
    from kinematics.gait.reconstruction import reconstruct, tibia_fluctuation
    from phantoms import make_phantom
    from phantoms.motion import make_trials

    fl = {m: [] for m in ("pig", "foot-to-hip")}
    rm = {m: [] for m in ("pig", "foot-to-hip")}
    for seed in range(n_seeds):
        sk, trials, _ = make_trials(make_phantom(seed), seed, rate=100.0, gait_trials=2, gait_cycles=2.0,
                                    crouch_angles=(), functional_ranges=())
        static = trials[0].markers
        for tr in trials[1:]:
            truth = sk.angles(sk.state(tr.q))
            for m in fl:
                rec = reconstruct(tr.markers, m, static=static, subject=sk.subject)
                for s in "RL":
                    mk = np.stack([tr.markers.marker(f"{s}{n}") for n in ("TIBM1", "TIBM2", "ANKM")], axis=1)
                    fl[m].append(tibia_fluctuation(rec.segments[f"tibia_{s.lower()}"], mk))
                    d = np.degrees(rec.angles[f"knee_{s.lower()}"] - truth[f"knee_{s.lower()}"])
                    rm[m].append(np.sqrt(np.nanmean(d**2, axis=0)))
    out = {}
    for m in fl:
        f = np.array(fl[m]) * 1e3
        r = np.array(rm[m])
        out[m] = {"fluctuation_mm": dict(zip(("RTIBM1", "RTIBM2", "RANKM"), map(float, f.mean(axis=0)))),
                  "knee_rmse_deg": dict(zip(("flexion", "adduction", "rotation"), map(float, r.mean(axis=0)))),
                  "knee_rmse_deg_worst_leg": dict(zip(("flexion", "adduction", "rotation"), map(float, r.max(axis=0))))}
    out["legs"] = len(fl["pig"])
    return out


def functional(n_seeds: int) -> dict:
    from kinematics.algorithms.functional import joint_centre_from_clusters
    from kinematics.gait.reconstruction import reconstruct
    from phantoms import make_phantom
    from phantoms.motion import make_trials

    rows: dict = {}
    for sta in (False, True):
        for seed in range(n_seeds):
            sk, trials, _ = make_trials(make_phantom(seed), seed, rate=100.0, gait_trials=0, crouch_angles=(),
                                        functional_ranges=(20, 30, 45), sta=sta)
            static = trials[0].markers
            for tr in trials[1:]:
                truth = sk.centres_lab(sk.state(tr.q))
                key = f"{'with' if sta else 'without'}_sta_{int(tr.meta['range_deg'])}deg"
                r = rows.setdefault(key, {"ctt": [], "score": [], "sphere": [], "foot-to-hip": []})
                for s in "RL":
                    for meth in ("ctt", "score", "sphere"):
                        _, lab = joint_centre_from_clusters(tr.markers, ["RASI", "LASI", "RPSI", "LPSI"],
                                                            [f"{s}THI", f"{s}KNE", f"{s}THIP", f"{s}THIA"], meth)
                        r[meth].append(np.nanmean(np.linalg.norm(lab - truth[f"hip_{s.lower()}"], axis=1)))
                rec = reconstruct(tr.markers, "foot-to-hip", static=static, subject=sk.subject, functional=tr.markers)
                for s in "rl":
                    r["foot-to-hip"].append(np.nanmean(np.linalg.norm(rec.centres[f"hip_{s}"] - truth[f"hip_{s}"], axis=1)))
    return {k: {m: float(np.mean(v) * 1e3) for m, v in r.items()} for k, r in rows.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "markers.json")
    a = ap.parse_args(argv)
    res = {"speed": speed()}
    sp = res["speed"]
    print(f"speed ({sp['frames']} frames at {sp['rate_hz']:g} Hz):")
    for m in ("pig", "foot-to-hip"):
        print(f"  {m:12s} {sp[m]['frames_per_second']:12.0f} frames/s ({sp[m]['seconds']:.2f} s)")
    res["seed_claims"] = c = claims(a.seeds)
    print(f"seed claims ({c['legs']} legs, gait with STA):")
    for m in ("pig", "foot-to-hip"):
        f, r = c[m]["fluctuation_mm"], c[m]["knee_rmse_deg"]
        print(f"  {m:12s} fluctuation mm " + " ".join(f"{k} {v:.1f}" for k, v in f.items())
              + f" | knee RMSE deg flex {r['flexion']:.1f} add {r['adduction']:.1f} rot {r['rotation']:.1f}")
    res["functional_hip_mm"] = fh = functional(a.seeds)
    print("functional hip centre error (mm):")
    for k, v in fh.items():
        print(f"  {k:22s} " + " ".join(f"{m} {e:.1f}" for m, e in v.items()))
    a.json.parent.mkdir(parents=True, exist_ok=True)
    write_text(a.json, json.dumps(res, indent=2) + "\n")
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
