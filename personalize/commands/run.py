"""``personalize run SUBJECT_DIR --out DIR``: the whole pipeline on one subject.

SUBJECT_DIR holds ``labels.nii.gz`` (+ ``label_map.json``) or ``bones/``,
``static.c3d``, any number of trial C3Ds (``functional_hip*.c3d`` calibrates
the hip centres), ``subject.json`` and, for a marker set other than a preset the
labels fit, ``markers.json`` (or ``--marker-set FILE|PRESET``); the folder `personalize phantom`
writes is itself a valid SUBJECT_DIR.  Writes model.osim, model.json,
meshes/ (at most 20,000 faces per bone unless --full-meshes), muscles.json (``--muscles``), landmarks.json, joints.json,
kinematics/<trial>.mot (+ marker errors, TRC and IK setup; trials with force plates: ground reactions,
ID and static-optimisation setups, reserve_actuators.xml), generic/ (gait2392 scaled to the same markers, its IK of
every trial; ``--generic``), report.html and summary.json; when the subject is refused, only
report.html stating the error (exit code 2 with a one-line message).  --out is
checked before any work (`personalize.outputs`): an existing non-empty folder
is refused unless --overwrite, which replaces it whole.  Progress: step N of
about M, elapsed and remaining time (plain lines when stderr is not a terminal).
"""
from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("run")
    def run(
        subject_dir: Path = typer.Argument(..., help="Subject folder (labels.nii.gz or bones/, static.c3d, trials, subject.json)."),
        out: Path = typer.Option(..., "--out", "-o", help="Output folder (published only when the run succeeds)."),
        report: bool = typer.Option(True, "--report/--no-report", help="Write report.html."),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress display."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out folder whole."),
        marker_set: str = typer.Option(None, "--marker-set", help="The trials' marker set when the subject folder has "
                                       "no markers.json: a markers.json file or a preset (pig, ior, cast, opensim); "
                                       "default: the preset the static trial's labels fit."),
        full_meshes: bool = typer.Option(False, "--full-meshes", help="Write the bone meshes at full resolution "
                                         "(default: each decimated to at most 20,000 faces, its error in model.json)."),
        muscles: str = typer.Option(None, "--muscles", help="none or gait2392: gait2392's 86 leg muscles carried onto "
                                    "the subject's bones (default: gait2392 when the generic model is found and the "
                                    "bones allow it)."),
        gait2392: Path = typer.Option(None, "--gait2392", help="The generic gait2392_thelen2003muscle.osim (with its "
                                      "Geometry/ folder) of opensim-models; default: $PERSONALIZE_GAIT2392, else the "
                                      "shared data folder."),
        generic: bool = typer.Option(None, "--generic/--no-generic", help="Compare with gait2392 scaled to the same "
                                     "markers (OpenSim's ScaleTool) and tracked by the same IK: generic/ and "
                                     "summary.json's generic (default: when gait2392 is found and --muscles is not "
                                     "none)."),
        patella: str = typer.Option("fixed", "--patella", help="fixed (the patella rides on the femur) or joint (a "
                                    "patellofemoral joint whose path comes from the subject's femur, patella and "
                                    "tibial tuberosity; OpenSim's IK and ID reproduce personalize's on it)."),
    ) -> None:
        """Personalised model from MRI and motion capture: fused joints, model.osim, IK of every trial, report."""
        from rich.console import Console

        from ..pipeline import run_subject
        from ..progress import StepProgress

        console = Console(stderr=True, quiet=quiet)
        with StepProgress("run", expected_steps(subject_dir), console) as prog:
            summary = run_subject(subject_dir, out, report=report, progress=prog, overwrite=overwrite,
                                  marker_set=marker_set, full_meshes=full_meshes, muscles=muscles,
                                  gait2392=gait2392, generic=generic, patella=patella)
        if not quiet:
            _print_summary(summary, out, Console())


def expected_steps(subject_dir: Path) -> int:
    """About how many progress messages `run_subject` gives: per bone (surface, landmarks), per trial (IK, knee law)."""
    import json

    d = Path(subject_dir)
    try:
        if (d / "label_map.json").is_file():
            n_bones = len(json.loads((d / "label_map.json").read_text(encoding="utf-8")))
        elif (d / "bones").is_dir():
            n_bones = sum(1 for p in (d / "bones").iterdir() if p.suffix.lower() in (".ply", ".stl", ".obj", ".vtp"))
        else:
            n_bones = 13
        n_trials = sum(1 for p in d.glob("*.c3d") if p.name != "static.c3d")
    except (OSError, ValueError, TypeError):
        n_bones, n_trials = 13, 4
    return 2 * n_bones + 2 * n_trials + 14


def _print_summary(summary: dict, out: Path, console) -> None:
    from rich.table import Table

    ik = summary.get("ik", {})
    t = Table(title=f"{summary['subject']}: IK marker residuals (personalised model)")
    for c in ("trial", "mean RMS (mm)", "max RMS (mm)", "frames"):
        t.add_column(c, justify="left" if c == "trial" else "right")
    for k, v in ik.items():
        t.add_row(k, f"{v['rms_mean_mm']:.2f}", f"{v['rms_max_mm']:.2f}", str(v["frames"]))
    console.print(t)
    if "errors" in summary:
        console.print(errors_table(summary["errors"]))
    if summary.get("generic"):
        console.print(generic_table(summary["generic"]))
    console.print(f"model.osim, report.html, summary.json in {out}/")


def generic_table(generic: dict):
    """rich Table: the personalised model against gait2392 scaled to the same markers (summary.json's generic)."""
    from rich.table import Table

    truth = generic.get("truth") or {}
    t = Table(title="Personalised model against scaled gait2392 (static pose; truth errors on a phantom)")
    for c in ("joint", "centre distance (mm)") + (("error personalised (mm)", "error generic (mm)") if truth else ()):
        t.add_column(c, justify="left" if c == "joint" else "right")
    err = truth.get("centre_error_mm", {})
    for j, v in generic["centres"].items():
        e = err.get(j)
        t.add_row(j, f"{v['distance_mm']:.1f}", *((f"{e['personalised']:.1f}", f"{e['generic']:.1f}") if e else
                                                  (("-", "-") if truth else ())))
    return t


def errors_table(errors: dict):
    """rich Table of per-source errors against the truth (worst side)."""
    from rich.table import Table

    t = Table(title="Errors against the phantom truth (worst side, static-trial lab frame)")
    for c in ("quantity", "MRI", "motion", "fused"):
        t.add_column(c, justify="left" if c == "quantity" else "right")
    for k, v in errors.items():
        t.add_row(k, *(f"{v[s]:.2f}" for s in ("mri", "motion", "fused")))
    return t
