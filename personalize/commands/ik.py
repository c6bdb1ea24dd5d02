"""``personalize ik MODEL.osim TRIAL.trc --out RESULT.mot``: marker inverse kinematics.

Solves the trial with `personalize.inverse_kinematics.trial_inverse_kinematics`
(marker weights and coordinate tasks of an optional OpenSim IK setup file) and
writes ``RESULT.mot`` (degrees) and ``RESULT_marker_errors.sto`` (m) next to it
(`write_trial_ik`), like OpenSim's IK tool.  Frames where every tracked marker
is missing are left out of both files and reported.  Both files are written
atomically.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("ik")
    def ik(
        model: Path = typer.Argument(..., help="OpenSim model (.osim)"),
        trial: Path = typer.Argument(..., help="marker trajectories (.trc)"),
        out: Path = typer.Option(..., "--out", help="result coordinates (.mot, degrees as OpenSim writes them)"),
        setup: Optional[Path] = typer.Option(None, "--setup", help="OpenSim IK setup (.xml): marker weights, coordinate tasks, time range"),
        start: Optional[float] = typer.Option(None, "--start", help="first time (s)"),
        end: Optional[float] = typer.Option(None, "--end", help="last time (s)"),
        limits: str = typer.Option("clamped", "--limits", help="coordinate ranges to enforce: clamped (OpenSim), all, none"),
        quiet: bool = typer.Option(False, "--quiet", help="no progress or summary on stderr"),
    ) -> None:
        """Inverse kinematics of a marker trial; writes RESULT.mot and RESULT_marker_errors.sto."""
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        from ..inverse_kinematics import check_ik_output, trial_inverse_kinematics, write_trial_ik

        console = Console(stderr=True, quiet=quiet)
        check_ik_output(out, inputs=[model, trial, setup])
        with Progress(TextColumn("[bold]ik[/bold]"), BarColumn(), TextColumn("{task.completed}/{task.total} frames"),
                      TimeElapsedColumn(), console=console, transient=True) as prog:
            task = prog.add_task("ik", total=None)
            res = trial_inverse_kinematics(model, trial, setup=setup, start=start, end=end, limits=limits,
                                           progress=lambda done, total: prog.update(task, completed=done, total=total))
        write_trial_ik(res, out)
        for w in res.warnings:
            console.print(f"warning: {w}")
        console.print(f"lab: {res.lab.describe()}" if res.lab is not None else f"lab: not detected ({res.lab_problem})",
                      markup=False, highlight=False)
        console.print(f"ik: {int(res.solved.sum())} frames, marker RMS mean {1e3 * res.rms_mean:.2f} mm "
                      f"(max {1e3 * res.rms_max:.2f} mm) -> {out}")
