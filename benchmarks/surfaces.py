"""Benchmark: label volume -> all bone surfaces and point clouds.

A full two-sided lower-body phantom label volume (`phantoms`) is written as
NIfTI at 1 mm and 0.5 mm isotropic voxels; a fresh Python process then reads it
with `personalize.surfaces.load_bones` and builds every bone's point cloud.
Reported per resolution: wall time (read + extract + point clouds, imports
excluded), CPU time (the honest figure on a shared machine), peak resident
memory of that process (ru_maxrss, imports included) and, from a second
untimed run, the tracemalloc peak (numpy/Python allocations of the pipeline).
Surface accuracy is asserted by tests/test_surfaces.py, not measured here.

Target (issue F1): <= 5 s and <= 2 GB at 1 mm on a 2-core machine.

Usage::

    python benchmarks/surfaces.py [--voxels 1.0 0.5] [--json benchmarks/results/surfaces.json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


# --------------------------------------------------------------------------- child: the timed part
def _child(volume: str, traced: bool) -> None:
    import tracemalloc

    from personalize.surfaces import load_bones
    import open3d  # noqa: F401  heavy imports happen before the clock starts
    import skimage.measure  # noqa: F401
    import nibabel  # noqa: F401

    if traced:  # tracemalloc slows numpy-heavy code a lot: a separate, untimed run
        tracemalloc.start()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    bones = load_bones(volume, workers=2)
    n_points = {k: int(len(b.points)) for k, b in bones.items()}  # every point cloud is built
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    traced_peak = tracemalloc.get_traced_memory()[1] if traced else None
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB
    result = {"wall_s": wall, "cpu_s": cpu, "load_average_1min": os.getloadavg()[0], "peak_rss_bytes": maxrss, "tracemalloc_peak_bytes": traced_peak,
              "bones": len(bones), "points": int(sum(n_points.values())),
              "faces": int(sum(len(b.mesh.faces) for b in bones.values()))}
    print(json.dumps(result))


# --------------------------------------------------------------------------- parent
def _make_volume(voxel_mm: float, folder: Path) -> tuple[Path, str]:
    """Write the phantom label volume (uint8 NIfTI, mm); returns (nifti, description)."""
    try:
        from phantoms import make_phantom
        from phantoms.imaging import label_volume
    except ImportError:
        return _make_standin(voxel_mm, folder)
    import nibabel as nib
    import numpy as np

    from lowerlimb.atomic import write_text

    ph = make_phantom(seed=0, placement="identity")  # both sides, axis-aligned: the tightest volume
    # partial-volume supersampling is slow at 0.5 mm and changes nothing about the work measured
    supersample = voxel_mm >= 1.0
    labels, affine_mm, label_map = label_volume(ph, voxel=(voxel_mm * 1e-3,) * 3, supersample=supersample)
    labels = labels.astype(np.uint8)  # 15 labels: the usual uint8 segmentation
    img = nib.Nifti1Image(labels, affine_mm)
    img.header.set_xyzt_units("mm")
    nii = folder / "labels.nii.gz"
    nib.save(img, str(nii))
    write_text(folder / "label_map.json", json.dumps(label_map))
    return nii, (f"phantoms.make_phantom(seed=0, placement='identity'), both sides, "
                       f"phantoms.imaging.label_volume(supersample={supersample})")


def _make_standin(voxel_mm: float, folder: Path) -> tuple[Path, str]:
    """Analytic two-sided lower body (capsules/ellipsoids) when `phantoms` is not installed."""
    import nibabel as nib
    import numpy as np

    from lowerlimb.bones import DEFAULT_LABEL_MAP

    h = voxel_mm
    shape = tuple(int(round(e / h)) for e in (420.0, 260.0, 1000.0))
    labels = np.zeros(shape, np.uint8)
    aff = np.diag([h, h, h, 1.0])
    aff[:3, 3] = [-210.0, -130.0, -950.0]

    def capsule(name, a, b, r):
        a, b = np.asarray(a, float), np.asarray(b, float)
        lo = np.floor((np.minimum(a, b) - r - aff[:3, 3]) / h).astype(int)
        hi = np.ceil((np.maximum(a, b) + r - aff[:3, 3]) / h).astype(int) + 1
        lo, hi = np.maximum(lo, 0), np.minimum(hi, shape)
        g = np.stack(np.meshgrid(*[np.arange(l, u) * h + aff[k, 3] for k, (l, u) in enumerate(zip(lo, hi))],
                                 indexing="ij"), -1)
        ab = b - a
        t = np.clip(((g - a) @ ab) / (ab @ ab), 0, 1)
        d = np.linalg.norm(g - (a + t[..., None] * ab), axis=-1)
        sub = labels[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        sub[(d < r) & (sub == 0)] = DEFAULT_LABEL_MAP[name]

    capsule("pelvis", [-110, 0, 0], [110, 0, 0], 45)
    for s, sign in (("r", -1), ("l", 1)):
        x = sign * 90
        capsule(f"femur_{s}", [x, 0, -40], [x, 10, -470], 16)
        capsule(f"patella_{s}", [x, 45, -470], [x, 45, -500], 16)
        capsule(f"tibia_{s}", [x, 0, -500], [x, 0, -860], 15)
        capsule(f"fibula_{s}", [x + sign * 35, -5, -520], [x + sign * 35, -5, -850], 7)
        capsule(f"talus_{s}", [x, 0, -880], [x, 30, -880], 18)
        capsule(f"calcn_{s}", [x, -40, -915], [x, 80, -910], 22)
        capsule(f"toes_{s}", [x, 110, -930], [x, 130, -930], 12)
    nii = folder / "labels.nii.gz"
    img = nib.Nifti1Image(labels, aff)
    img.header.set_xyzt_units("mm")
    nib.save(img, str(nii))
    return nii, "analytic stand-in (phantoms not importable)"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxels", type=float, nargs="+", default=[1.0, 0.5], help="isotropic voxel sizes, mm")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "surfaces.json")
    ap.add_argument("--child", nargs=2, metavar=("VOLUME", "TRACED"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        _child(args.child[0], args.child[1] == "1")
        return 0
    from lowerlimb.atomic import write_text

    report = {"benchmark": "surfaces: label volume -> all point clouds", "units": {"wall_s": "s", "memory": "bytes"},
              "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
              "target": {"voxel_mm": 1.0, "wall_s": 5.0, "peak_rss_bytes": 2 * 1024**3}, "runs": []}
    for vox in args.voxels:
        with tempfile.TemporaryDirectory(prefix="bench_surfaces_") as tmp:
            t0 = time.perf_counter()
            nii, what = _make_volume(vox, Path(tmp))
            gen = time.perf_counter() - t0
            import nibabel as nib

            shape = nib.load(str(nii)).shape
            runs = []
            for traced in ("0", "1"):
                proc = subprocess.run([sys.executable, __file__, "--child", str(nii), traced],
                                      capture_output=True, text=True, cwd=str(REPO))
                if proc.returncode != 0:
                    print(proc.stderr, file=sys.stderr)
                    return 1
                runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
            res = runs[0]
            res["tracemalloc_peak_bytes"] = runs[1]["tracemalloc_peak_bytes"]
        res.update({"voxel_mm": vox, "volume_shape": list(shape), "phantom": what, "generation_s": gen})
        report["runs"].append(res)
        line = (f"{vox:g} mm: {res['bones']} bones, volume {shape}, {res['wall_s']:.2f} s wall "
                f"({res['cpu_s']:.2f} s CPU, load {res['load_average_1min']:.1f} on {os.cpu_count()} cores), "
                f"peak RSS {res['peak_rss_bytes'] / 2**20:.0f} MiB, tracemalloc peak "
                f"{res['tracemalloc_peak_bytes'] / 2**20:.0f} MiB, {res['points']} points")
        if vox == 1.0:
            mem_ok = res["peak_rss_bytes"] <= 2 * 1024**3
            res["target_met"] = {"wall": res["wall_s"] <= 5.0 and mem_ok, "cpu": res["cpu_s"] <= 5.0 and mem_ok}
            line += (f"  [target <= 5 s, <= 2 GB: wall {'met' if res['target_met']['wall'] else 'NOT met'}, "
                     f"CPU {'met' if res['target_met']['cpu'] else 'NOT met'}"
                     f"{' (machine loaded: wall time inflated)' if res['load_average_1min'] > os.cpu_count() else ''}]")
        print(line, flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_text(args.json, json.dumps(report, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
