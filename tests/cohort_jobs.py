"""Small per-subject jobs for the cohort tests (module-level so that dask workers import them by name)."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np


def label_volume_job(subject_dir: Path, out: Path, progress=None) -> dict:
    """Bone volumes from the label volume (voxel count x voxel volume) and from the exact meshes, ml."""
    import trimesh

    from lowerlimb.atomic import write_text
    from personalize.io import read_label_volume

    vol = read_label_volume(Path(subject_dir) / "labels.nii.gz")  # InputError for a corrupt file
    voxel_ml = abs(np.linalg.det(vol.affine_m[:3, :3])) * 1e6
    rows = {}
    for bone, label in vol.label_map.items():
        mesh = trimesh.load(Path(subject_dir) / "meshes" / f"{bone}.ply", force="mesh")
        rows[bone] = {"labels_ml": float(np.count_nonzero(vol.labels == label) * voxel_ml),
                      "mesh_ml": float(abs(mesh.volume) * 1e-3)}  # mesh in mm^3
    write_text(Path(out) / "volumes.json", json.dumps({"units": "ml", "bones": rows}) + "\n")
    return {"volumes_ml": rows, "worker_pid": os.getpid(), **environment_job(subject_dir, out)}


def crash_once_job(subject_dir: Path, out: Path, progress=None) -> dict:
    """Kill the worker process on the first attempt (marker file), succeed on the retry."""
    marker = Path(subject_dir) / "crashed.marker"
    if not marker.exists():
        marker.write_text(str(os.getpid()))
        os._exit(1)
    return {"crashed_pid": int(marker.read_text()), "worker_pid": os.getpid()}


def flaky_job(subject_dir: Path, out: Path, progress=None) -> dict:
    """Raise an unexpected OSError on the first attempt only."""
    marker = Path(subject_dir) / "flaky.marker"
    if not marker.exists():
        marker.write_text("1")
        raise OSError("transient failure")
    return {"attempts": 2}


def bug_job(subject_dir: Path, out: Path, progress=None) -> dict:
    """Always raise an unexpected error; counts its attempts in a file."""
    counter = Path(subject_dir) / "bug.count"
    n = int(counter.read_text()) + 1 if counter.exists() else 1
    counter.write_text(str(n))
    (Path(out) / "partial.txt").write_text("must never be published")
    raise RuntimeError("a bug in the job")


def environment_job(subject_dir: Path, out: Path, progress=None) -> dict:
    """Report the worker's thread and allocator environment."""
    keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "MALLOC_TRIM_THRESHOLD_")
    return {"env": {k: os.environ.get(k) for k in keys}}


def fault_job(subject_dir: Path, out: Path, progress=None) -> dict:
    """The fault named in ``subject_dir/fault.txt`` ("exit": os._exit(3); "segv": a null-pointer read), else
    `label_volume_job` (an InputError for corrupt labels)."""
    fault_file = Path(subject_dir) / "fault.txt"
    fault = fault_file.read_text().strip() if fault_file.exists() else ""
    (Path(out) / "partial.txt").write_text("must never be published")
    if fault == "exit":
        os._exit(3)
    if fault == "segv":
        import ctypes

        ctypes.string_at(0)
    (Path(out) / "partial.txt").unlink()
    return label_volume_job(subject_dir, out)


def segv_or_env_job(subject_dir: Path, out: Path, progress=None) -> dict:
    """Segfault when ``subject_dir/fault.txt`` says "segv", else `environment_job`."""
    if (Path(subject_dir) / "fault.txt").exists():
        import ctypes

        ctypes.string_at(0)
    return environment_job(subject_dir, out)


def sleep_job(subject_dir: Path, out: Path, progress=None) -> dict:
    """Sleep ``COHORT_SLEEP`` seconds (a subject that takes a while), then succeed."""
    import time

    time.sleep(float(os.environ.get("COHORT_SLEEP", "1")))
    (Path(out) / "done.txt").write_text("done")
    return {"slept": float(os.environ.get("COHORT_SLEEP", "1"))}
