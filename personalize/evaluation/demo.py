"""The built-in demonstration: the main job on a phantom subject, errors against its truth.

`run_demo` is what ``personalize demo`` and ``make demo`` call.  Stage by stage it
(1) builds a phantom subject and writes it like a user's subject folder
(``labels.nii.gz``, ``meshes/``, ``truth.json``), (2) extracts the bone surfaces
from the label volume and measures them against the exact phantom surfaces,
and (3) when landmark detection is available, detects landmarks and joints and
compares them key by key with the truth, (4) writes the phantom's motion trials
(static, gait, crouch and functional C3Ds, ``subject.json``, ``truth/``) so that the
folder is a complete SUBJECT_DIR, and runs the single-subject pipeline on it
(`personalize.pipeline.run_subject`: registration, fusion, personalised model,
IK of every trial) into ``model/``, reporting the errors of the MRI-only, the
motion-only and the fused joint estimates against the truth.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from lowerlimb.atomic import inside, staged_dir, write_text

#: bones whose surfaces the demo measures (the ones the accuracy targets name)
DEMO_SURFACE_BONES = ("pelvis", "femur_r", "tibia_r", "femur_l", "tibia_l")


def surface_error(extracted, exact) -> dict:
    """Mean/max distance (mm) and volume error (%) of an extracted bone (`personalize.surfaces`) vs its exact mesh (m)."""
    from personalize.surfaces import surface_distance

    d = surface_distance(extracted.mesh, exact, n=20000, seed=0)
    volume = abs(exact.volume)
    return {"mean_abs_distance_mm": d["mean"] * 1e3, "max_distance_mm": d["max"] * 1e3,
            "volume_error_pct": 100.0 * (extracted.volume - volume) / volume}


def surface_errors(ph, surfaces: dict, bones=DEMO_SURFACE_BONES) -> dict:
    """`surface_error` of each extracted bone of `bones` against the phantom's exact surface."""
    return {b: surface_error(surfaces[b], ph.mesh(b)) for b in bones if b in surfaces}


def run_demo(out: str | Path, seed: int = 0, voxel_mm: float = 1.0,
             progress: Callable[[str], None] | None = None, pipeline: bool = True, short: bool = False,
             overwrite: bool = False) -> dict:
    """Run the demonstration into `out` and return its summary (also written to ``out/demo.json``).

    Parameters
    ----------
    out : path
        Output folder: ``subject/`` (the phantom subject), ``model/`` (the pipeline's
        results) and ``demo.json``, each published only when complete.
    seed : int
        Phantom seed (anatomy, placement).
    voxel_mm : float
        Isotropic voxel size of the phantom label volume, millimetres.
    pipeline : bool
        Also write the motion trials and run `personalize.pipeline.run_subject`
        (outputs in ``out/model/``, errors in ``summary["pipeline"]``).
    short : bool
        Short motion trials (one gait cycle, one crouch, a short star-arc).
    overwrite : bool
        Replace a non-empty `out` that is not an earlier demo (one with ``demo.json``
        is always replaced).  `out` is replaced whole; on error it keeps its old content.
    """
    from personalize.outputs import check_output_dir, fresh_dir

    say = progress or (lambda msg: None)
    out = Path(out)
    check_output_dir(out, overwrite=overwrite or (out / "demo.json").is_file())
    with fresh_dir(out):
        return _run_demo(out, ph_seed=seed, voxel_mm=voxel_mm, say=say, pipeline=pipeline, short=short)


def _run_demo(out: Path, *, ph_seed: int, voxel_mm: float, say, pipeline: bool, short: bool) -> dict:
    from phantoms import make_phantom
    from phantoms.subject import write_subject

    from personalize.evaluation.phantom_subject import SHORT_TRIALS
    from personalize.pipeline import run_subject
    from personalize.surfaces import load_bones

    seed = ph_seed
    say(f"building phantom (seed {seed})")
    ph = make_phantom(seed=seed)
    # the subject folder is published first so that the pipeline (and its report) see its final path
    subject = inside(out, "subject")
    with staged_dir(subject) as stage:
        write_subject(stage, ph, voxel=(voxel_mm * 1e-3,) * 3, seed=seed, motion=pipeline,
                      trials=SHORT_TRIALS if short else None, progress=say)
    say("extracting surfaces from labels.nii.gz")
    surfaces = load_bones(subject / "labels.nii.gz", subject / "label_map.json", progress=lambda b: say(f"surface {b}"))
    summary = {
        "units": {"distance": "mm", "volume": "%"},
        "seed": seed,
        "voxel_mm": [voxel_mm] * 3,
        "surfaces": surface_errors(ph, surfaces),
    }
    if pipeline:
        res = run_subject(subject, inside(out, "model"), progress=lambda m: say(f"pipeline: {m}"))
        summary["pipeline"] = {"errors": res.get("errors", {}), "ik_rms_mm": res["ik_rms_mm"],
                               "frame": res["frame"], "ik": res["ik"], "sources": res["sources"]}
    write_text(inside(out, "demo.json"), json.dumps(summary, indent=1) + "\n")
    return summary
