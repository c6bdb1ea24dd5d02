"""``personalize validate --subjects N --seed S --out DIR [--scheduler ADDRESS]``: validation on phantoms.

Draws N phantom subjects (random anatomy, MRI resolution, segmentation noise,
soft-tissue artefact, marker noise), runs the per-subject job on each as one
dask task and writes ``DIR/metrics.csv`` (one row per subject: the draws and
every error against truth) and ``DIR/report.html`` (statistics and
distributions).  Re-running with the same N and seed resumes.  Exit code 1
when some subject failed (listed in the report), 2 for bad options.

``--realistic`` runs the realistic set instead (`personalize.evaluation.validate.run_realistic_validation`:
real and analytic anatomy, four marker sets, both lab orientations, three body builds, files
named and recorded as labs do); a subject today's pipeline refuses is a row of ``metrics.csv``
with its one-line reason, so the run exits 0 once every row is written.
"""
from __future__ import annotations

from pathlib import Path

import typer


def validate(
    subjects: int = typer.Option(20, "--subjects", help="Number of phantom subjects."),
    seed: int = typer.Option(0, "--seed", help="Master seed of the random draws."),
    out: Path = typer.Option(..., "--out", help="Output folder."),
    scheduler: str = typer.Option("", "--scheduler", help="Address of an existing dask scheduler; default: a local cluster."),
    workers: int = typer.Option(2, "--workers", help="Worker processes of the local cluster."),
    motion: bool = typer.Option(True, "--motion/--no-motion", help="Also write and use the motion-capture trials."),
    job: str = typer.Option("", "--job", help="Per-subject function module.function (default: the full pipeline)."),
    realistic: bool = typer.Option(False, "--realistic", help="The realistic set: analytic, ICL-MRI and LHDL-CT "
                                   "anatomy, four marker sets, z-up and y-up labs, child/adult/obese tissue, half "
                                   "without a functional trial, label volumes and mesh folders."),
    data: Path = typer.Option(None, "--data", help="Root of the real data (bones/, reference_models/) for --realistic; "
                                                   "default ../shared/data."),
    palpation: bool = typer.Option(True, "--palpation/--no-palpation", help="--realistic: bony markers misplaced as "
                                   "palpation misplaces them (default), or exactly on their landmarks (an ablation: "
                                   "what the palpation error costs)."),
) -> None:
    """Run the pipeline on random phantom subjects and summarise its errors against truth."""
    from rich.console import Console

    from personalize.commands.batch import print_batch
    from personalize.evaluation.validate import run_realistic_validation, run_validation

    console = Console(stderr=True)
    if realistic:
        res = run_realistic_validation(subjects, seed, out, data_root=data, scheduler=scheduler or None,
                                       workers=workers, job=job or None, console=console, palpation=palpation)
        print_batch(res.batch, console)
        console.print(f"metrics: {res.metrics_csv}\nreport:  {res.report}")
        return
    res = run_validation(subjects, seed, out, scheduler=scheduler or None, workers=workers, job=job or None,
                         motion=motion, console=console)
    print_batch(res.batch, console)
    console.print(f"metrics: {res.metrics_csv}\nreport:  {res.report}")
    if res.batch.counts["error"]:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    app.command("validate")(validate)
