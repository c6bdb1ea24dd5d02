"""Marker inverse kinematics of a trial on an OpenSim model, and its result files.

`trial_inverse_kinematics` reads the model (``.osim``), the trial (``.trc``)
and an optional OpenSim IK setup (marker weights, coordinate tasks, time
range) and solves the trial with `kinematics.algorithms.ik.solve_ik`, which
minimises per frame f

    E(q) = sum_m w_m |x_m(q) - y_m,f|^2 + sum_c w_c (q_c - qbar_c)^2

over the markers present (OpenSim's IK objective).  `write_trial_ik` writes
what OpenSim's IK tool writes:

``RESULT.mot``
    generalized coordinates (degrees for rotational coordinates, metres for
    translations, ``inDegrees=yes``);
``RESULT_marker_errors.sto``
    per frame ``total_squared_error`` (m^2, unweighted sum over the markers
    present), ``marker_error_RMS`` and ``marker_error_max`` (m), as OpenSim's
    IK tool writes them, then one column per marker (|model - measured|, m);
    `write_marker_errors`, also used by ``personalize run``.

Frames where every tracked marker is missing are left out of both files.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from kinematics.algorithms.ik import IKResult
from kinematics.gait.lab_frame import LabFrame
from lowerlimb.errors import InputError

__all__ = ["LIMITS", "TrialIK", "check_ik_output", "marker_errors_path", "trial_inverse_kinematics",
           "write_marker_errors", "write_trial_ik"]

LIMITS = ("clamped", "all", "none")


@dataclass(frozen=True, eq=False)
class TrialIK:
    """IK solution of a trial on a model.

    Attributes
    ----------
    ik : IKResult
        the engine's per-frame solution (q in rad / m, marker errors in m)
    coordinates : tuple of str (n_q), the model's coordinate names
    rotational : tuple of str, the coordinates in degrees in the .mot file (OpenSim's Rotational ones,
        `kinematics.io.opensim_io.degree_coordinates`)
    model_name, trial_name : file names of the inputs (stated in the output headers)
    warnings : tuple of str, setup tasks ignored, skipped or underdetermined frames
    lab : LabFrame or None, the trial's vertical and progression read from its markers
        (`kinematics.gait.lab_frame.detect_lab`); None when they do not tell it, `lab_problem` says why
    lab_problem : str, why the lab could not be read ('' when `lab` is set)
    """

    ik: IKResult
    coordinates: tuple[str, ...]
    rotational: tuple[str, ...]
    model_name: str
    trial_name: str
    warnings: tuple[str, ...] = ()
    lab: LabFrame | None = None
    lab_problem: str = ""

    @property
    def solved(self) -> np.ndarray:
        """(F,) bool: frames with at least one tracked marker (written to the files)."""
        return self.ik.solved

    @property
    def underdetermined(self) -> np.ndarray:
        """(F,) bool: solved frames whose markers do not determine every coordinate."""
        return self.ik.solved & ~self.ik.determined

    @property
    def rms_mean(self) -> float:
        """Mean over the frames of the per-frame marker RMS (m)."""
        return float(np.nanmean(self.ik.rms))

    @property
    def rms_max(self) -> float:
        """Largest per-frame marker RMS (m)."""
        return float(np.nanmax(self.ik.rms))


def marker_errors_path(out: str | os.PathLike) -> Path:
    """``RESULT_marker_errors.sto`` beside ``RESULT.mot``."""
    out = Path(out)
    return out.with_name(out.stem + "_marker_errors.sto")


def check_ik_output(out: str | os.PathLike, inputs: Iterable = ()) -> None:
    """Check before any work that ``out`` (a ``.mot`` file) and its marker-error file can be written.

    Raises
    ------
    InputError
        `out` does not end in ``.mot``, is a folder or an input, or its folder cannot be written.
    """
    from .outputs import check_output_file

    out = Path(out)
    if out.suffix.lower() != ".mot":
        raise InputError(out, "the output file must end in .mot")
    inputs = list(inputs)
    check_output_file(out, inputs=inputs)
    check_output_file(marker_errors_path(out), inputs=inputs)


def _times(time: np.ndarray, sel: np.ndarray) -> str:
    return f"{', '.join(f'{t:.4f}' for t in time[sel][:10])}{' ...' if sel.sum() > 10 else ''}"


def trial_inverse_kinematics(model_path: str | os.PathLike, trial_path: str | os.PathLike, *,
                             setup: str | os.PathLike | None = None, start: float | None = None,
                             end: float | None = None, limits: str = "clamped",
                             progress: Callable[[int, int], None] | None = None) -> TrialIK:
    """Inverse kinematics of a marker trial on an OpenSim model.

    Parameters
    ----------
    model_path : OpenSim model (``.osim``)
    trial_path : marker trajectories (``.trc``), the model's ground frame
    setup : OpenSim IK setup (``.xml``), optional: marker weights, coordinate
        tasks and time range (``start`` / ``end`` take precedence)
    start, end : time window (s), optional
    limits : {'clamped', 'all', 'none'}, coordinate ranges enforced
    progress : called as ``progress(frames_done, frames_total)``

    Returns
    -------
    TrialIK

    Raises
    ------
    InputError
        Unknown `limits`, missing or unreadable files, a window ending before
        it starts, setup tasks naming absent coordinates, a trial without any
        marker of the model or in the wrong unit (`check_trial_scale`).
    """
    from kinematics.algorithms.ik import check_trial_scale, solve_ik
    from kinematics.gait.lab_frame import detect_lab
    from kinematics.io.ik_setup import read_ik_setup
    from kinematics.io.opensim_io import load_osim
    from kinematics.io.storage import read_trc

    if limits not in LIMITS:
        raise InputError("--limits", f"must be clamped, all or none, not {limits!r}")
    model_path, trial_path = Path(model_path), Path(trial_path)
    if not trial_path.is_file():
        raise InputError(trial_path, "marker file not found")
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
    warnings: list[str] = []
    weights = None
    ctasks: Sequence = ()
    if su is not None:
        unknown = [m for m in su.marker_weights if m not in model.marker_names]
        if unknown:
            warnings.append(f"setup marker tasks not in the model ignored: {', '.join(unknown)}")
        weights = {m: w for m, w in su.marker_weights.items() if m in model.marker_names}
        absent = [m for m in weights if m not in trial.names]
        if absent:
            warnings.append(f"markers of the setup missing from the trial: {', '.join(absent)}")
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
    res = solve_ik(model, trial, weights, ctasks, limits=limits, progress=progress)
    ok = res.solved
    if not ok.all():
        warnings.append(f"{int((~ok).sum())} frame(s) with every tracked marker missing were skipped "
                        f"(times {_times(res.time, ~ok)})")
    und = ok & ~res.determined
    if und.any():
        names = f" ({', '.join(res.undetermined_coordinates)})" if res.undetermined_coordinates else ""
        warnings.append(f"{int(und.sum())} frame(s) have too few markers to determine every coordinate{names} "
                        f"(times {_times(res.time, und)}); their undetermined coordinates keep the previous "
                        "frame's value")
    from kinematics.io.opensim_io import degree_coordinates

    rot = tuple(degree_coordinates(model))      # OpenSim's Rotational ones; a coupled patella coordinate in radians
    try:
        lab, lab_problem = detect_lab(None, [trial]), ""
    except InputError as exc:
        lab, lab_problem = None, str(exc)
    return TrialIK(res, tuple(model.coordinate_names), rot, model_path.name, trial_path.name, tuple(warnings),
                   lab, lab_problem)


def write_trial_ik(result: TrialIK, out: str | os.PathLike) -> tuple[Path, Path]:
    """Write ``out`` (``.mot``, degrees) and ``<stem>_marker_errors.sto`` (m) of the solved frames.

    Returns
    -------
    (mot_path, marker_errors_path)
    """
    from kinematics.io.storage import write_mot

    out = Path(out)
    res, ok = result.ik, result.ik.solved
    write_mot(out, result.coordinates, res.time[ok], res.q[ok], in_degrees=True, rotational=result.rotational)
    err_path = write_marker_errors(marker_errors_path(out), res, ok,
                                   header=[f"Marker errors of {out.name}", f"model={result.model_name}",
                                           f"trial={result.trial_name}"])
    return out, err_path


def write_marker_errors(path: str | os.PathLike, ik: IKResult, frames=None, *, header: Sequence[str] = ()) -> Path:
    """Write an IK's marker errors as ``.sto``: OpenSim's three columns, then one per marker (m).

    Parameters
    ----------
    path : the ``.sto`` file (written atomically)
    ik : IKResult
    frames : boolean mask or indices of the frames to write (default: all)
    header : extra header lines (the units and frame line is always written)
    """
    from kinematics.io.storage import write_sto

    sel = slice(None) if frames is None else frames
    err = ik.marker_errors[sel]
    with np.errstate(invalid="ignore"):
        sq = np.nansum(err ** 2, axis=1)
    values = np.column_stack([sq, ik.rms[sel], ik.max_error[sel], err])
    return write_sto(path, ["total_squared_error", "marker_error_RMS", "marker_error_max", *ik.markers],
                     ik.time[sel], values,
                     header_extra=["units: m (total_squared_error m^2); |model - measured| in the model frame",
                                   *header], name="marker_errors")
