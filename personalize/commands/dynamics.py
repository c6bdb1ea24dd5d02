"""``personalize dynamics MODEL.osim KINEMATICS.mot (--loads GRF.mot LOADS.xml | --c3d TRIAL.c3d) --out DIR``.

Inverse dynamics of a whole trial (`personalize.joint_dynamics.trial_joint_dynamics`):
coordinates low-pass filtered (``--cutoff``, 6 Hz or ``auto``; ``--filter``
opensim or winter), ground reactions from an ExternalLoads file or from the
force plates of a C3D trial.  DIR (staged, `write_joint_dynamics`) receives
inverse_dynamics.sto (N m, N), inverse_dynamics_per_kg.sto, joint_powers.sto
(W), coordinates_filtered.sto, grf.mot/grf.xml (``--c3d``), moments.png and
report.json.  A trial without loaded force plates gives kinematics only.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

_NOTED = ("CoP outside", "two feet", "not computed", "not applied")


def register(app: typer.Typer) -> None:
    @app.command("dynamics")
    def dynamics(
        model: Path = typer.Argument(..., help="OpenSim model (.osim)"),
        kinematics: Path = typer.Argument(..., help="coordinates (.mot, e.g. an IK result)"),
        out: Path = typer.Option(..., "--out", help="output folder"),
        loads: Optional[tuple[Path, Path]] = typer.Option(None, "--loads", help="GRF.mot LOADS.xml (OpenSim external loads)"),
        c3d: Optional[Path] = typer.Option(None, "--c3d", help="C3D trial with force plates and foot markers"),
        cutoff: str = typer.Option("6", "--cutoff", help="low-pass cut-off of coordinates (and C3D forces), Hz, or 'auto' (Winter's residual analysis)"),
        method: str = typer.Option("opensim", "--filter", help="opensim (InverseDynamicsTool) or winter"),
        filter_loads: Optional[bool] = typer.Option(None, "--filter-loads/--no-filter-loads",
                                                    help="filter the forces at the cut-off (default: yes for --c3d, no for --loads)"),
        start: Optional[float] = typer.Option(None, "--start", help="first time (s)"),
        end: Optional[float] = typer.Option(None, "--end", help="last time (s)"),
        plot: bool = typer.Option(True, "--plot/--no-plot", help="draw moments.png"),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out folder whole."),
        quiet: bool = typer.Option(False, "--quiet", help="no summary on stderr"),
    ) -> None:
        """Joint moments and powers of a trial (inverse dynamics with ground reactions)."""
        from rich.console import Console

        from ..joint_dynamics import trial_joint_dynamics, write_joint_dynamics
        from ..outputs import check_output_dir

        console = Console(stderr=True, quiet=quiet)
        check_output_dir(out, inputs=[model, kinematics, *(loads or ()), c3d], overwrite=overwrite)
        d = trial_joint_dynamics(model, kinematics, loads=loads, c3d=c3d, cutoff=cutoff, method=method,
                                 filter_loads=filter_loads, start=start, end=end)
        write_joint_dynamics(d, out, plot=plot)
        t = d.result.time
        if d.kinematics_only:
            why = (f"{len(d.contacts)} plate contact(s), none applicable to one foot (see the notes)" if d.contacts
                   else "no force plate, or none loaded")
            console.print(f"dynamics: no ground reactions ({why}): kinematics only "
                          f"(filtered coordinates), no joint moments -> {out}")
        else:
            ex = f", {len(d.exclude)} interval(s) excluded" if d.exclude else ""
            console.print(f"dynamics: {t.shape[0]} frames {t[0]:.3f}-{t[-1]:.3f} s, "
                          f"loads on {', '.join(d.result.loads)}{ex} -> {out}")
        for n in d.notes:
            if any(k in n for k in _NOTED):
                console.print(f"note: {n}")
