"""Speed and memory of phantom construction, rasterisation and meshing.

Usage: ``python benchmarks/phantom_speed.py [--out phantom_speed.json] [--meshes]``

Prints wall and CPU seconds (CPU time is the fair number on a shared
machine) and the peak resident memory, and writes them as JSON.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from phantoms import make_phantom  # noqa: E402
from phantoms.imaging import label_volume  # noqa: E402


def _timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="phantom_speed.json")
    ap.add_argument("--meshes", action="store_true", help="also time the reference meshes of every bone")
    args = ap.parse_args()
    res = {}
    ph, w, c = _timed(lambda: make_phantom(seed=0))
    res["make_phantom"] = {"wall_s": w, "cpu_s": c}
    cases = {
        "femur_pelvis_1mm": dict(bones=["femur_r", "pelvis"]),
        "whole_body_1mm": dict(),
        "whole_body_1mm_noise_0.5": dict(noise=0.5),
        "femur_0.5x0.5x2mm": dict(bones=["femur_r"], voxel=(0.5e-3, 0.5e-3, 2e-3)),
    }
    for name, kw in cases.items():
        (lab, _, _), w, c = _timed(lambda kw=kw: label_volume(ph, **kw))
        res[name] = {"wall_s": w, "cpu_s": c, "shape": list(lab.shape), "MB": lab.nbytes / 1e6}
        print(f"{name:28s} wall {w:6.2f} s  cpu {c:6.2f} s  shape {lab.shape}")
        del lab
    if args.meshes:
        for b in ph.bone_names:
            m, w, c = _timed(lambda b=b: ph.mesh(b))
            res[f"mesh_{b}"] = {"wall_s": w, "cpu_s": c, "faces": len(m.faces)}
            print(f"mesh {b:22s} wall {w:6.2f} s  cpu {c:6.2f} s  faces {len(m.faces)}")
    res["peak_rss_MB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS {res['peak_rss_MB']:.0f} MB")
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
