"""``personalize scale STATIC --model GENERIC.osim --setup SETUP.xml [--marker-set MARKERS.xml] --out DIR``.

Scales a generic OpenSim model to the subject of a static trial as OpenSim's ScaleTool does
(`personalize.scaling.scale_model`: segment scale factors from the setup's marker pairs, masses to the subject's,
markers placed on the static pose) and writes DIR (`write_scaled_model`): scaled_model.osim, scale.json (scale
factors per body, measurements, masses, marker RMS / max), static_pose.mot and static_ground.trc.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("scale")
    def scale(
        static: Path = typer.Argument(..., help="static trial (.c3d or .trc), any lab orientation"),
        model: Path = typer.Option(..., "--model", help="generic OpenSim model (.osim)"),
        setup: Path = typer.Option(..., "--setup", help="OpenSim Scale setup (.xml): marker pairs per body, "
                                                        "manual scales, time ranges, mass, placement IK tasks"),
        out: Path = typer.Option(..., "--out", help="output folder"),
        marker_set: Optional[Path] = typer.Option(None, "--marker-set",
                                                  help="OpenSim MarkerSet (.xml) replacing or adding to the "
                                                       "model's markers (default: the model's own)"),
        mass: Optional[float] = typer.Option(None, "--mass", help="subject mass (kg); overrides the setup's"),
        start: Optional[float] = typer.Option(None, "--start", help="first time (s), overrides the setup's ranges"),
        end: Optional[float] = typer.Option(None, "--end", help="last time (s), overrides the setup's ranges"),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out folder whole."),
        quiet: bool = typer.Option(False, "--quiet", help="no summary on stderr"),
    ) -> None:
        """Scale a generic OpenSim model from a static trial (OpenSim ScaleTool's method)."""
        from rich.console import Console

        from ..outputs import check_output_dir
        from ..scaling import scale_model, write_scaled_model

        console = Console(stderr=True, quiet=quiet)
        check_output_dir(out, inputs=[static, model, setup, marker_set], overwrite=overwrite)
        res = scale_model(static, model, setup=setup, marker_set=marker_set, mass=mass, start=start, end=end)
        write_scaled_model(res, out)
        for w in res.warnings:
            console.print(f"warning: {w}", markup=False, highlight=False)
        console.print(f"lab: {res.lab.describe()}", markup=False, highlight=False)
        for m in res.measurements:
            console.print(f"measurement {m.name}: {m.factor:.4f} ({', '.join(m.bodies)})", markup=False,
                          highlight=False)
        for b, f in res.manual.items():
            console.print(f"manual scale {b}: {' '.join(f'{v:.4f}' for v in f)}", markup=False, highlight=False)
        console.print(f"mass {res.mass_generic:.2f} -> {res.mass_scaled:.2f} kg; static-pose marker RMS "
                      f"{1e3 * res.marker_rms:.2f} mm (max {1e3 * res.marker_max:.2f} mm, {res.worst_marker}) "
                      f"-> {out}", markup=False, highlight=False)
