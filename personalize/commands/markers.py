"""``personalize markers TRIAL.c3d --method pig|foot-to-hip|blend --subject S --out DIR``: joint centres and angles.

Reconstructs the legs of a marker trial (`personalize.leg_reconstruction.reconstruct_legs`:
Plug-in-Gait, the seed's foot-to-hip model, or both blended per frame) and
writes centres.trc (mm), angles.mot (degrees, Plug-in-Gait conventions),
angles.png and report.json into DIR, staged (`write_leg_reconstruction`).
Marker gaps up to ``--max-gap`` seconds are filled by cubic splines; longer
gaps stay missing and are reported.  A static trial whose ASIS-ankle marker
distances do not match the subject's leg lengths is refused.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("markers")
    def markers_cmd(
        trial: Path = typer.Argument(..., help="Marker trial (.c3d in mm, or .trc)."),
        method: str = typer.Option(..., "--method", help="pig (Plug-in-Gait, hip first), foot-to-hip (the seed's model) or blend (both, per-frame Gaussian weights; needs --static)."),
        out: Path = typer.Option(..., "--out", help="Output folder: centres.trc, angles.mot, angles.png, report.json."),
        subject: Optional[Path] = typer.Option(None, "--subject", help="Subject measurements (.vsk or .json, SI)."),
        static: Optional[Path] = typer.Option(None, "--static", help="Static trial: foot offsets, foot-to-hip calibration, leg-length check."),
        functional: Optional[Path] = typer.Option(None, "--functional", help="Hip calibration trial (star-arc) for functional hip centres."),
        max_gap: float = typer.Option(0.1, "--max-gap", help="Fill marker gaps up to this many seconds (cubic spline); longer ones stay missing."),
        no_plot: bool = typer.Option(False, "--no-plot", help="Skip angles.png."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out folder whole."),
        subject_name: Optional[str] = typer.Option(None, "--subject-name", help="Vicon subject whose markers to read when a C3D holds several (Name:RKNE labels)."),
    ) -> None:
        """Joint centres and Plug-in-Gait joint angles of a marker trial (pig or foot-to-hip)."""
        from ..leg_reconstruction import reconstruct_legs, write_leg_reconstruction
        from ..outputs import check_output_dir

        check_output_dir(out, inputs=[trial, subject, static, functional], overwrite=overwrite)
        res = reconstruct_legs(trial, method=method, subject=subject, static=static, functional=functional,
                               max_gap=max_gap, subject_name=subject_name)
        write_leg_reconstruction(res, out, plot=not no_plot)
        for n in res.notes:
            typer.echo(f"note: {n}", err=True)
        typer.echo(f"lab: {res.lab.describe()}" if res.lab is not None else f"lab: not detected ({res.lab_problem})",
                   err=True)
        typer.echo(f"{method}: {res.valid_frames}/{res.frames} frames reconstructed; wrote centres.trc, "
                   f"angles.mot{'' if no_plot else ', angles.png'}, report.json to {out}")
