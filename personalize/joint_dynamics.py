"""Inverse dynamics of a whole trial from an OpenSim model, its coordinates and the ground reactions.

`trial_joint_dynamics` reads the model (``.osim``) and the coordinates
(``.mot``) and solves the equations of motion for the generalised forces,

    tau = M(q) qdd + c(q, qd) - g(q) - sum_b J_b(q)^T w_b

(`kinematics.gait.inverse_dynamics.trial_inverse_dynamics`): the coordinates
are low-pass filtered (``cutoff``, 6 Hz; OpenSim's InverseDynamicsTool filter
by default, ``method='winter'`` for Winter's corrected double pass;
``cutoff='auto'``: Winter's residual analysis, median over the coordinates),
differentiated with quintic splines, and the ground reactions w_b applied at
the centre of pressure on the bodies named in an ExternalLoads file
(``loads``) or on ``calcn_r`` / ``calcn_l`` from the force plates of a C3D
trial (``c3d``: feet assigned from the markers, forces filtered at the same
cut-off unless ``filter_loads=False``).

A trial without force plates (or whose plates are never loaded) gives
kinematics only: joint moments without the ground reactions would be wrong
during stance and are not written.  Frames whose ground reaction cannot be
assigned to one foot (two feet on a plate, a centre of pressure outside its
plate) are NaN in the moment files and listed in the report.

`write_joint_dynamics` writes, staged (nothing is written on error):

``inverse_dynamics.sto`` / ``inverse_dynamics_per_kg.sto``
    generalised forces as OpenSim writes them (``*_moment`` N m, ``*_force`` N),
    and divided by the model mass;
``joint_powers.sto``
    tau * qd per coordinate (W);
``coordinates_filtered.sto``
    the filtered coordinates, speeds and accelerations (rad, m, /s, /s^2);
``grf.mot`` / ``grf.xml``
    from a C3D: the applied ground reactions in OpenSim's format;
``moments.png``
    hip, knee and ankle moments (N m/kg) against time, right and left;
``report.json``
    `dynamics_report`: inputs, cut-offs, model mass, notes (plate assignment, excluded frames).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from kinematics.gait.inverse_dynamics import InverseDynamicsResult
from lowerlimb.errors import InputError

__all__ = ["FILTERS", "JointDynamics", "dynamics_report", "trial_joint_dynamics", "write_joint_dynamics"]

FILTERS = ("opensim", "winter")


@dataclass(frozen=True, eq=False)
class JointDynamics:
    """Inverse dynamics of a trial and what it was computed from.

    Attributes
    ----------
    result : InverseDynamicsResult, generalised forces (F, n_q) N m / N, filtered q, qd, qdd
    loads : tuple of ExternalLoad, the ground reactions applied (empty: kinematics only)
    inputs : dict ``model``, ``kinematics``, ``loads`` (GRF.mot, LOADS.xml), ``c3d`` -> path (or None)
    cutoff : coordinate cut-off (Hz); cutoff_per_coordinate : Winter's choice per coordinate (``auto``)
    method : 'opensim' or 'winter'; load_cutoff : cut-off of the forces (Hz) or None (unfiltered)
    contacts : force-plate contacts assigned to a foot (C3D); exclude : (start s, end s, reason) intervals
    notes : tuple of str
    """

    result: InverseDynamicsResult
    loads: tuple
    inputs: dict
    cutoff: float
    cutoff_per_coordinate: Optional[dict]
    method: str
    load_cutoff: Optional[float]
    contacts: tuple = ()
    exclude: tuple = ()
    notes: tuple[str, ...] = ()

    @property
    def kinematics_only(self) -> bool:
        """No ground reaction applied: no joint moments are published."""
        return not self.loads


def _cutoff(cutoff) -> float | None:
    """The cut-off in Hz, or None for ``auto``."""
    if str(cutoff).strip().lower() == "auto":
        return None
    try:
        value = float(cutoff)
    except ValueError:
        raise InputError("--cutoff", f"must be a frequency in Hz or 'auto', got {cutoff!r}") from None
    if not value > 0:
        raise InputError("--cutoff", f"must be a positive frequency in Hz, got {value}")
    return value


def trial_joint_dynamics(model_path: str | os.PathLike, kinematics: str | os.PathLike, *,
                         loads: Optional[tuple] = None, c3d: str | os.PathLike | None = None,
                         cutoff: float | str = 6.0, method: str = "opensim", filter_loads: Optional[bool] = None,
                         start: Optional[float] = None, end: Optional[float] = None) -> JointDynamics:
    """Joint moments of a trial (inverse dynamics with the ground reactions).

    Parameters
    ----------
    model_path : OpenSim model (``.osim``)
    kinematics : coordinates (``.mot``, e.g. an IK result)
    loads : (GRF.mot, LOADS.xml), OpenSim external loads; or
    c3d : C3D trial with force plates and foot markers (exactly one of `loads`, `c3d`)
    cutoff : low-pass cut-off of the coordinates (Hz) or ``'auto'``
    method : {'opensim', 'winter'}, the filter
    filter_loads : filter the forces at the cut-off (default: yes for `c3d`, no for `loads`)
    start, end : time window (s)

    Returns
    -------
    JointDynamics

    Raises
    ------
    InputError
        Not exactly one load source, an unknown filter, a bad cut-off, missing
        or unreadable files, kinematics not uniformly sampled, no common time.
    """
    from kinematics.gait.inverse_dynamics import loads_from_c3d, trial_inverse_dynamics
    from kinematics.io.external_loads import read_external_loads
    from kinematics.io.opensim_io import degree_coordinates, load_osim
    from kinematics.io.storage import read_mot

    if (loads is None) == (c3d is None):
        raise InputError("--loads/--c3d", "give exactly one source of ground reactions: --loads GRF.mot LOADS.xml or --c3d TRIAL.c3d")
    if method not in FILTERS:
        raise InputError("--filter", f"must be opensim or winter, not {method!r}")
    fixed = _cutoff(cutoff)
    for p in [model_path, kinematics] + (list(loads) if loads else [c3d]):
        if not Path(p).is_file():
            raise InputError(p, "file not found")
    model = load_osim(model_path)
    tab = read_mot(kinematics).to_radians(degree_coordinates(model))
    q = tab.select(model.coordinate_names)
    notes: list[str] = []
    per_coordinate = None
    bad = ~np.all(np.isfinite(q), axis=1)
    if bad.any():
        raise InputError(kinematics, f"{int(bad.sum())} frame(s) with non-finite coordinates (first at "
                                     f"t = {tab.time[np.argmax(bad)]:.4f} s): the IK left them unsolved")
    if fixed is None:
        from kinematics.gait.filtering import choose_cutoff

        fixed, per = choose_cutoff(q, 1.0 / float(np.mean(np.diff(tab.time))), method=method)
        per_coordinate = {c: (None if not np.isfinite(v) else float(v)) for c, v in zip(model.coordinate_names, per)}
        notes.append(f"cut-off {fixed:.2f} Hz by Winter's residual analysis of the {method} filter (median over the coordinates)")
    exclude: tuple = ()
    contacts: tuple = ()
    if loads is not None:
        grf, xml = loads
        ext = read_external_loads(xml, grf)
        load_cut = fixed if filter_loads else None
    else:
        tl = loads_from_c3d(c3d, model)
        ext, exclude, contacts = list(tl.loads), tl.exclude, tuple(tl.contacts)
        notes += list(tl.notes)
        load_cut = None if filter_loads is False else fixed
    try:
        res = trial_inverse_dynamics(model, tab.time, q, ext, cutoff=fixed, method=method, load_cutoff=load_cut,
                                     start=start, end=end, exclude=exclude)
    except InputError as exc:
        if exc.source in ("coordinates", "time range"):
            raise InputError(kinematics, exc.problem) from None  # name the file, not the argument
        raise
    notes += list(res.notes)
    inputs = {"model": model_path, "kinematics": kinematics, "loads": loads, "c3d": c3d}
    return JointDynamics(res, tuple(ext), inputs, fixed, per_coordinate, method, load_cut, contacts,
                         tuple(exclude), tuple(notes))


def dynamics_report(d: JointDynamics) -> dict:
    """The ``report.json`` document (JSON types; units stated in it)."""
    res, inp = d.result, d.inputs
    return {
        "model": str(inp["model"]), "kinematics": str(inp["kinematics"]),
        "loads": [str(p) for p in inp["loads"]] if inp["loads"] else None, "c3d": str(inp["c3d"]) if inp["c3d"] else None,
        "cutoff_hz": d.cutoff, "cutoff_per_coordinate_hz": d.cutoff_per_coordinate, "filter": d.method,
        "load_cutoff_hz": d.load_cutoff,
        "frames": int(res.time.shape[0]), "time_s": [float(res.time[0]), float(res.time[-1])],
        "model_mass_kg": res.mass, "bodies_loaded": list(res.loads),
        "contacts": [{"plate": c.plate + 1, "start_s": c.start_time, "end_s": c.end_time, "foot": c.foot,
                      "cop_to_foot_m": c.cop_distance, "flags": list(c.flags)} for c in d.contacts],
        "excluded_intervals_s": [[a, b, why] for a, b, why in d.exclude],
        "kinematics_only": d.kinematics_only, "notes": list(d.notes),
        "units": "moments N m (rotational) / N (translational); powers W; per-kg files divided by the model mass; "
                 "coordinates rad / m",
    }


def write_joint_dynamics(d: JointDynamics, out: str | os.PathLike, *, plot: bool = True) -> Path:
    """Write the result files (module docstring) into ``out``, replacing it whole.

    Check ``out`` first with `personalize.outputs.check_output_dir` (an existing folder is replaced).
    """
    from kinematics.gait.inverse_dynamics import write_inverse_dynamics, write_joint_powers
    from kinematics.io.external_loads import write_external_loads
    from kinematics.io.storage import write_sto

    from .outputs import replaced_dir
    from .presentation.trial_curves import plot_moments

    res = d.result
    with replaced_dir(out) as stage:
        cols = ([f"{c}" for c in res.coordinates] + [f"{c}_u" for c in res.coordinates]
                + [f"{c}_udot" for c in res.coordinates])
        write_sto(stage / "coordinates_filtered.sto", cols, res.time, np.hstack([res.q, res.qd, res.qdd]),
                  name="coordinates_filtered",
                  header_extra=[f"Coordinates low-pass filtered at {d.cutoff:g} Hz ({d.method});",
                                "q rad or m, u = dq/dt, udot = d2q/dt2; model coordinates"])
        if not d.kinematics_only:
            write_inverse_dynamics(stage / "inverse_dynamics.sto", res)
            write_inverse_dynamics(stage / "inverse_dynamics_per_kg.sto", res, per_kg=True)
            write_joint_powers(stage / "joint_powers.sto", res)
            if d.inputs["c3d"] is not None:
                write_external_loads(stage, "grf", list(d.loads), frame="model ground")
            if plot:
                plot_moments(stage / "moments.png", res)
        (stage / "report.json").write_text(json.dumps(dynamics_report(d), indent=2, default=float), encoding="utf-8")
    return Path(out)
