"""``personalize batch MANIFEST.csv --out DIR [--scheduler ADDRESS] [--workers K]``: run a cohort.

MANIFEST is a CSV with columns ``subject`` (output folder name) and ``path``
(its SUBJECT_DIR, relative to the manifest's folder or absolute).  Each subject
runs as one dask task (a local cluster of K single-threaded worker processes by
default, or the cluster at ``--scheduler``); results go to ``DIR/<subject>/``,
published only when the subject succeeded, and ``DIR/batch.csv`` lists
subject, status (ok, error, skipped), seconds, error message and output folder.
Re-running skips subjects whose ``summary.json`` is complete.  Each subject's
job runs in a process of its own: one that crashes (segfault, ``os._exit``, out
of memory) is that subject's error row, retried ``--retries`` times.  Exit code 0
when every subject is ok or skipped, 1 when some failed (see batch.csv), 2 for a
bad manifest, option or --out, 130 / 143 when stopped by SIGINT (Ctrl-C) /
SIGTERM (batch.csv then lists what is done; rerun the same command to resume).
"""
from __future__ import annotations

from pathlib import Path

import typer

from personalize.cohort.records import DEFAULT_JOB


def batch(
    manifest: Path = typer.Argument(..., help="CSV with columns subject,path."),
    out: Path = typer.Option(..., "--out", help="Output folder: DIR/<subject>/ and DIR/batch.csv."),
    scheduler: str = typer.Option("", "--scheduler", help="Address of an existing dask scheduler (tcp://host:8786); default: a local cluster."),
    workers: int = typer.Option(2, "--workers", help="Worker processes of the local cluster (one thread each)."),
    retries: int = typer.Option(2, "--retries", help="Extra attempts of a subject after an unexpected failure."),
    rerun: bool = typer.Option(False, "--rerun", help="Run every subject again, even those already complete."),
    job: str = typer.Option(DEFAULT_JOB, "--job",
                            help="Per-subject function module.function(subject_dir, out) -> summary dict."),
) -> None:
    """Run the per-subject job on every subject of a manifest with dask.distributed."""
    from rich.console import Console

    from lowerlimb.errors import InputError

    from personalize.cohort import run_batch

    if not (0 <= retries <= 10):
        raise InputError("--retries", f"{retries} is outside 0-10")
    console = Console(stderr=True)
    result = run_batch(manifest, out, job=job, scheduler=scheduler or None, workers=workers, retries=retries,
                       resume=not rerun, console=console)
    print_batch(result, console)
    if result.counts["error"]:
        raise typer.Exit(1)


def print_batch(result, console) -> None:
    """Print a `personalize.cohort.BatchResult`'s error rows and counts with rich (also used by ``validate``)."""
    from rich.table import Table

    errors = [r for r in result.results if r.status == "error"]
    if errors:
        t = Table(title="Subjects that failed")
        t.add_column("subject")
        t.add_column("error", overflow="fold")
        for r in errors:
            t.add_row(r.subject, r.error)
        console.print(t)
    c = result.counts
    console.print(f"{c['ok']} ok, {c['error']} error, {c['skipped']} skipped (already complete); "
                  f"table in {result.csv}")


def register(app: typer.Typer) -> None:
    app.command("batch")(batch)
