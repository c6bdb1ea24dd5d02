"""The built-in demonstration: the main job on a phantom subject, errors against its truth.

`run_demo` is what ``personalize demo`` and ``make demo`` call.  Stage by stage it
(1) builds a phantom subject and writes it like a user's subject folder
(``labels.nii.gz``, ``meshes/``, ``truth.json``), (2) extracts the bone surfaces
from the label volume and measures them against the exact phantom surfaces,
and (3) when landmark detection is available, detects landmarks and joints and
compares them key by key with the truth.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from kinematics.atomic import inside, staged_dir, write_text

#: bones whose surfaces the demo measures (the ones the accuracy targets name)
DEMO_SURFACE_BONES = ("pelvis", "femur_r", "tibia_r", "femur_l", "tibia_l")


def surface_errors(ph, surfaces: dict, bones=DEMO_SURFACE_BONES) -> dict:
    """Mean/max surface distance (mm) and volume error (%) of extracted surfaces against the phantom's exact ones."""
    from .surfaces import surface_distance

    rows = {}
    for b in bones:
        if b not in surfaces:
            continue
        exact = ph.mesh(b)
        d = surface_distance(surfaces[b].mesh, exact, n=20000, seed=0)
        rows[b] = {
            "mean_abs_distance_mm": d["mean"] * 1e3,
            "max_distance_mm": d["max"] * 1e3,
            "volume_error_pct": 100.0 * (surfaces[b].volume - exact.volume) / exact.volume,
        }
    return rows


def run_demo(out: str | Path, seed: int = 0, voxel_mm: float = 1.0,
             progress: Callable[[str], None] | None = None) -> dict:
    """Run the demonstration into `out` and return its summary (also written to ``out/demo.json``).

    Parameters
    ----------
    out : path
        Output folder; published only when the whole run succeeded.
    seed : int
        Phantom seed (anatomy, placement).
    voxel_mm : float
        Isotropic voxel size of the phantom label volume, millimetres.
    """
    from phantoms import make_phantom
    from phantoms.imaging import write_phantom

    from .surfaces import load_bones

    say = progress or (lambda msg: None)
    voxel = (voxel_mm * 1e-3,) * 3
    with staged_dir(out) as stage:
        say(f"building phantom (seed {seed})")
        ph = make_phantom(seed=seed)
        subject = inside(stage, "subject")
        write_phantom(subject, ph, voxel=voxel, seed=seed, progress=say)
        say("extracting surfaces from labels.nii.gz")
        surfaces = load_bones(subject / "labels.nii.gz", subject / "label_map.json", progress=lambda b: say(f"surface {b}"))
        summary = {
            "units": {"distance": "mm", "volume": "%"},
            "seed": seed,
            "voxel_mm": [voxel_mm] * 3,
            "surfaces": surface_errors(ph, surfaces),
        }
        write_text(inside(stage, "demo.json"), json.dumps(summary, indent=1) + "\n")
    return summary


def render_summary(summary: dict, console) -> None:
    """Print the demo's error tables with rich."""
    from rich.table import Table

    t = Table(title=f"Bone surfaces from a {summary['voxel_mm'][0]:g} mm label volume vs exact phantom surfaces")
    for col in ("bone", "mean |d| (mm)", "max |d| (mm)", "volume error (%)"):
        t.add_column(col, justify="right" if col != "bone" else "left")
    for b, r in summary["surfaces"].items():
        t.add_row(b, f"{r['mean_abs_distance_mm']:.3f}", f"{r['max_distance_mm']:.2f}", f"{r['volume_error_pct']:+.2f}")
    console.print(t)
