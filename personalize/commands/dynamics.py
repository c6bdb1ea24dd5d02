"""``personalize dynamics MODEL.osim KINEMATICS.mot (--loads GRF.mot LOADS.xml | --c3d TRIAL.c3d) --out DIR``.

Inverse dynamics of a whole trial (`kinematics.gait.inverse_dynamics.trial_inverse_dynamics`):
the coordinates are low-pass filtered (``--cutoff``, 6 Hz; OpenSim's
InverseDynamicsTool filter by default, ``--filter winter`` for Winter's
corrected double pass; ``--cutoff auto``: Winter's residual analysis, median
over the coordinates), differentiated with quintic splines, and the ground
reactions applied at the centre of pressure on the bodies named in the
ExternalLoads file (``--loads``) or on ``calcn_r`` / ``calcn_l`` from the
force plates of a C3D trial (``--c3d``: feet assigned from the markers,
forces filtered at the same cut-off unless ``--no-filter-loads``).  DIR
(staged: nothing is written on error) receives

``inverse_dynamics.sto``
    generalised forces as OpenSim writes them (``*_moment`` N m,
    ``*_force`` N), and ``inverse_dynamics_per_kg.sto`` divided by the model mass;
``joint_powers.sto``
    tau * qd per coordinate (W);
``coordinates_filtered.sto``
    the filtered coordinates, speeds and accelerations (rad, m, /s, /s^2);
``grf.mot`` / ``grf.xml``
    with ``--c3d``: the applied ground reactions in OpenSim's format;
``moments.png``
    hip, knee and ankle moments (N m/kg) against time, right and left;
``report.json``
    inputs, cut-offs, model mass, notes (plate assignment, excluded frames).

A trial without force plates (or whose plates are never loaded) gives kinematics only (``coordinates_filtered.sto``
and the report): joint moments without the ground reactions would be wrong
during stance and are not written.  Frames whose ground reaction cannot be
assigned to one foot (two feet on a plate, a centre of pressure outside its
plate) are NaN in the moment files and listed in the report.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from lowerlimb.errors import InputError

__all__ = ["register", "run_dynamics"]

_JOINTS = (("hip_flexion", "hip_flexion"), ("hip_adduction", "hip_adduction"), ("hip_rotation", "hip_rotation"),
           ("knee_angle", "knee_angle (gait2392: + extension)"), ("ankle_angle", "ankle_angle (+ dorsiflexion)"),
           ("subtalar_angle", "subtalar_angle (+ inversion)"))


def plot_moments(path: Path, result) -> None:
    """Grid of joint moments (N m/kg) against time, right red and left blue."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    from lowerlimb.atomic import atomic_path

    fig = Figure(figsize=(11, 6.5), constrained_layout=True)
    axes = fig.subplots(2, 3, sharex=True).ravel()
    for ax, (stem, title) in zip(axes, _JOINTS):
        for s, colour in (("r", "tab:red"), ("l", "tab:blue")):
            name = f"{stem}_{s}"
            if name in result.coordinates:
                ax.plot(result.time, result.tau_per_kg[:, result.coordinates.index(name)], color=colour, lw=1.2,
                        label=s.upper())
        ax.set_title(f"{title} moment", fontsize=9)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.grid(alpha=0.3)
    for ax in axes[3:]:
        ax.set_xlabel("time (s)")
    for ax in axes[::3]:
        ax.set_ylabel("N m/kg")
    axes[0].legend(fontsize=8)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")


def run_dynamics(model_path: Path, kinematics: Path, out: Path, *, loads: Optional[tuple] = None,
                 c3d: Optional[Path] = None, cutoff: float | str = 6.0, method: str = "opensim",
                 filter_loads: Optional[bool] = None, start: Optional[float] = None, end: Optional[float] = None,
                 plot: bool = True, overwrite: bool = False, quiet: bool = False) -> dict:
    """Library form of the command; returns the report dict."""
    from rich.console import Console

    from kinematics.io.external_loads import read_external_loads, write_external_loads
    from kinematics.gait.inverse_dynamics import (loads_from_c3d, trial_inverse_dynamics,
                                             write_inverse_dynamics, write_joint_powers)
    from kinematics.io.opensim_io import load_osim
    from kinematics.io.storage import read_mot, write_sto

    from ..outputs import check_output_dir, replaced_dir

    console = Console(stderr=True, quiet=quiet)
    if (loads is None) == (c3d is None):
        raise InputError("--loads/--c3d", "give exactly one source of ground reactions: --loads GRF.mot LOADS.xml or --c3d TRIAL.c3d")
    if method not in ("opensim", "winter"):
        raise InputError("--filter", f"must be opensim or winter, not {method!r}")
    auto = str(cutoff).strip().lower() == "auto"
    if not auto:
        try:
            cutoff = float(cutoff)
        except ValueError:
            raise InputError("--cutoff", f"must be a frequency in Hz or 'auto', got {cutoff!r}") from None
        if not cutoff > 0:
            raise InputError("--cutoff", f"must be a positive frequency in Hz, got {cutoff}")
    inputs = [model_path, kinematics] + (list(loads) if loads else [c3d])
    for p in inputs:
        if not Path(p).is_file():
            raise InputError(p, "file not found")
    check_output_dir(out, inputs=inputs, overwrite=overwrite)
    model = load_osim(model_path)
    kinds = tuple(c.kind for c in model.coordinates)
    tab = read_mot(kinematics).to_radians([c for c, k in zip(model.coordinate_names, kinds) if k == "rotational"])
    q = tab.select(model.coordinate_names)
    notes: list[str] = []
    per_coordinate = None
    if auto:
        from kinematics.gait.filtering import choose_cutoff

        cutoff, per = choose_cutoff(q, 1.0 / float(np.mean(np.diff(tab.time))))
        per_coordinate = {c: (None if not np.isfinite(v) else float(v)) for c, v in zip(model.coordinate_names, per)}
        notes.append(f"cut-off {cutoff:.2f} Hz by Winter's residual analysis (median over the coordinates)")
    exclude: tuple = ()
    if loads is not None:
        grf, xml = loads
        ext = read_external_loads(xml, grf)
        load_cut = cutoff if filter_loads else None
        contacts = []
    else:
        tl = loads_from_c3d(c3d, model)
        ext, exclude, contacts = list(tl.loads), tl.exclude, list(tl.contacts)
        notes += list(tl.notes)
        load_cut = None if filter_loads is False else cutoff
    try:
        res = trial_inverse_dynamics(model, tab.time, q, ext, cutoff=cutoff, method=method, load_cutoff=load_cut,
                                     start=start, end=end, exclude=exclude)
    except InputError as exc:
        if exc.source in ("coordinates", "time range"):
            raise InputError(kinematics, exc.problem) from None  # name the file, not the argument
        raise
    notes += list(res.notes)
    kinematics_only = not ext
    report = {
        "model": str(model_path), "kinematics": str(kinematics),
        "loads": [str(p) for p in loads] if loads else None, "c3d": str(c3d) if c3d else None,
        "cutoff_hz": cutoff, "cutoff_per_coordinate_hz": per_coordinate, "filter": method, "load_cutoff_hz": load_cut,
        "frames": int(res.time.shape[0]), "time_s": [float(res.time[0]), float(res.time[-1])],
        "model_mass_kg": res.mass, "bodies_loaded": list(res.loads),
        "contacts": [{"plate": c.plate + 1, "start_s": c.start_time, "end_s": c.end_time, "foot": c.foot,
                      "cop_to_foot_m": c.cop_distance, "flags": list(c.flags)} for c in contacts],
        "excluded_intervals_s": [[a, b, why] for a, b, why in exclude],
        "kinematics_only": kinematics_only, "notes": notes,
        "units": "moments N m (rotational) / N (translational); powers W; per-kg files divided by the model mass; "
                 "coordinates rad / m",
    }
    with replaced_dir(out) as stage:
        cols = ([f"{c}" for c in res.coordinates] + [f"{c}_u" for c in res.coordinates]
                + [f"{c}_udot" for c in res.coordinates])
        write_sto(stage / "coordinates_filtered.sto", cols, res.time, np.hstack([res.q, res.qd, res.qdd]),
                  name="coordinates_filtered",
                  header_extra=[f"Coordinates low-pass filtered at {cutoff:g} Hz ({method});",
                                "q rad or m, u = dq/dt, udot = d2q/dt2; model coordinates"])
        if not kinematics_only:
            write_inverse_dynamics(stage / "inverse_dynamics.sto", res)
            write_inverse_dynamics(stage / "inverse_dynamics_per_kg.sto", res, per_kg=True)
            write_joint_powers(stage / "joint_powers.sto", res)
            if c3d is not None:
                write_external_loads(stage, "grf", ext, frame="model ground")
            if plot:
                plot_moments(stage / "moments.png", res)
        (stage / "report.json").write_text(json.dumps(report, indent=2, default=float), encoding="utf-8")
    if kinematics_only:
        console.print("dynamics: no ground reactions (no force plate, or none loaded): kinematics only "
                      f"(filtered coordinates), no joint moments -> {out}")
    else:
        ex = f", {len(exclude)} interval(s) excluded" if exclude else ""
        console.print(f"dynamics: {res.time.shape[0]} frames {res.time[0]:.3f}-{res.time[-1]:.3f} s, "
                      f"loads on {', '.join(res.loads)}{ex} -> {out}")
    for n in notes:
        if "CoP outside" in n or "two feet" in n or "not computed" in n or "not applied" in n:
            console.print(f"note: {n}")
    return report


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
        run_dynamics(model, kinematics, out, loads=loads, c3d=c3d, cutoff=cutoff, method=method,
                     filter_loads=filter_loads, start=start, end=end, plot=plot, overwrite=overwrite, quiet=quiet)
