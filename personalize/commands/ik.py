"""``personalize ik MODEL.osim TRIAL.trc --out RESULT.mot``: marker inverse kinematics.

Runs the engine's IK (kinematics.algorithms.ik.solve_ik) with the marker weights and
coordinate tasks of an optional OpenSim IK setup file and writes

* ``RESULT.mot``: generalized coordinates in OpenSim's format (degrees for
  rotational coordinates, metres for translations, ``inDegrees=yes``);
* ``RESULT_marker_errors.sto`` next to it: per frame ``total_squared_error``
  (m^2, unweighted sum over the markers present),
  ``marker_error_RMS`` and ``marker_error_max`` (m), like OpenSim's IK tool.

Frames where every tracked marker is missing are left out of both files and
reported.  Both files are written atomically.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import typer

from lowerlimb.errors import InputError


def run_ik(model_path: Path, trial_path: Path, out: Path, setup: Optional[Path] = None,
           start: Optional[float] = None, end: Optional[float] = None, limits: str = "clamped",
           quiet: bool = False) -> dict:
    """Library form of the command; returns a summary dict (paths, frames, mean/max RMS in metres)."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from kinematics.algorithms.ik import check_trial_scale, read_ik_setup, solve_ik
    from kinematics.io.opensim_io import load_osim
    from kinematics.io.storage import read_trc, write_mot, write_sto

    console = Console(stderr=True, quiet=quiet)
    if limits not in ("clamped", "all", "none"):
        raise InputError("--limits", f"must be clamped, all or none, not {limits!r}")
    if out.suffix.lower() != ".mot":
        raise InputError(out, "the output file must end in .mot")
    if not trial_path.is_file():
        raise InputError(trial_path, "marker file not found")
    from ..outputs import check_output_file

    check_output_file(out, inputs=[model_path, trial_path, setup])
    check_output_file(out.with_name(out.stem + "_marker_errors.sto"), inputs=[model_path, trial_path, setup])
    model = load_osim(model_path)
    trial = read_trc(trial_path)
    su = read_ik_setup(setup) if setup is not None else None
    t0, t1 = start, end
    if su is not None and su.time_range is not None:
        t0 = su.time_range[0] if t0 is None else t0
        t1 = su.time_range[1] if t1 is None else t1
    if t0 is not None and t1 is not None and t1 < t0:
        raise InputError("--end", f"end time {t1} s is before start time {t0} s")
    if t0 is not None or t1 is not None:
        trial = trial.window(t0, t1)
    weights = None
    ctasks = ()
    if su is not None:
        unknown = [m for m in su.marker_weights if m not in model.marker_names]
        if unknown:
            console.print(f"warning: setup marker tasks not in the model ignored: {', '.join(unknown)}")
        weights = {m: w for m, w in su.marker_weights.items() if m in model.marker_names}
        absent = [m for m in weights if m not in trial.names]
        if absent:
            console.print(f"warning: markers of the setup missing from the trial: {', '.join(absent)}")
        bad = [t.name for t in su.coordinate_tasks if t.name not in model.coordinate_names]
        if bad:
            raise InputError(setup, f"coordinate tasks name coordinates absent from the model: {', '.join(bad)}")
        ctasks = su.coordinate_tasks
        if not any(m in trial.names for m in weights):
            raise InputError(trial_path, "none of the setup's marker tasks is in the trial")
    used = [m for m in (weights or model.marker_names) if m in trial.names]
    if not used:
        raise InputError(trial_path, f"the trial has no marker of the model {model_path.name}")
    check_trial_scale(model, trial, used)
    with Progress(TextColumn("[bold]ik[/bold]"), BarColumn(), TextColumn("{task.completed}/{task.total} frames"),
                  TimeElapsedColumn(), console=console, transient=True) as prog:
        task = prog.add_task("ik", total=trial.n_frames)
        res = solve_ik(model, trial, weights, ctasks, limits=limits,
                       progress=lambda done, total: prog.update(task, completed=done, total=total))
    ok = res.solved
    if not ok.all():
        console.print(f"warning: {int((~ok).sum())} frame(s) with every tracked marker missing were skipped "
                      f"(times {', '.join(f'{t:.4f}' for t in res.time[~ok][:10])}{' ...' if (~ok).sum() > 10 else ''})")
    und = ok & ~res.determined
    if und.any():
        console.print(f"warning: {int(und.sum())} frame(s) have too few markers to determine every coordinate "
                      f"(times {', '.join(f'{t:.4f}' for t in res.time[und][:10])}{' ...' if und.sum() > 10 else ''}); "
                      "their undetermined coordinates keep the previous frame's value")
    rot = [c.name for c in model.coordinates if c.kind == "rotational"]
    write_mot(out, model.coordinate_names, res.time[ok], res.q[ok], in_degrees=True, rotational=rot)
    err_path = out.with_name(out.stem + "_marker_errors.sto")
    sq = np.nansum(res.marker_errors[ok] ** 2, axis=1)
    write_sto(err_path, ["total_squared_error", "marker_error_RMS", "marker_error_max"], res.time[ok],
              np.stack([sq, res.rms[ok], res.max_error[ok]], axis=1),
              header_extra=[f"Marker errors of {out.name}: metres (squared error in m^2), model frame",
                            f"model={model_path.name}", f"trial={trial_path.name}"],
              name="marker_errors")
    summary = {"mot": str(out), "marker_errors": str(err_path), "frames": int(ok.sum()),
               "skipped": int((~ok).sum()), "underdetermined": int(und.sum()), "rms_mean_m": float(np.nanmean(res.rms)),
               "rms_max_m": float(np.nanmax(res.rms)), "max_error_m": float(np.nanmax(res.max_error)),
               "seconds": res.seconds}
    console.print(f"ik: {summary['frames']} frames, marker RMS mean {1e3 * summary['rms_mean_m']:.2f} mm "
                  f"(max {1e3 * summary['rms_max_m']:.2f} mm) -> {out}")
    return summary


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
        run_ik(model, trial, out, setup, start, end, limits, quiet)
