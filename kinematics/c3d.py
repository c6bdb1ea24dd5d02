"""C3D marker files: reading, writing and gap filling.

Positions are converted at the file boundary from the unit in ``POINT:UNITS``
(usually mm) to metres; invalid samples (negative residual, or all three
coordinates exactly zero, the C3D convention for "not seen") become NaN.

Vicon Nexus also stores model outputs as C3D points: joint angles (degrees),
forces, moments, powers and modelled markers, listed in the parameter groups
named by ``POINT:TYPE_GROUPS`` (``ANGLES``, ``FORCES``...).  Those are not
marker positions; `read_c3d` leaves them out of the `MarkerTrial` and
`read_c3d_outputs` returns them converted to SI (radians, N, N m, W, m).
Segment axis points written by Plug-in-Gait (``PELO``, ``RFEO``...) are plain
points in length units and are read as markers.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .errors import InputError
from .markers import MarkerTrial

__all__ = ["read_c3d", "read_c3d_outputs", "write_c3d", "fill_gaps", "C3DOutputs", "Gap", "GapReport"]

_LENGTH = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "meters": 1.0, "metres": 1.0, "millimeters": 1e-3, "millimetres": 1e-3}
# Output groups written by Nexus and the factor converting their stated unit to SI.
_OUTPUT_GROUPS = {
    "ANGLES": ("ANGLE_UNITS", {"deg": np.pi / 180.0, "rad": 1.0}, "rad"),
    "FORCES": ("FORCE_UNITS", {"N": 1.0, "N/kg": 1.0}, "N"),
    "MOMENTS": ("MOMENT_UNITS", {"Nmm": 1e-3, "Nm": 1.0, "Nmm/kg": 1e-3, "Nm/kg": 1.0}, "N m"),
    "POWERS": ("POWER_UNITS", {"W": 1.0, "W/kg": 1.0}, "W"),
    "MODELED_MARKERS": ("MODELED_MARKER_UNITS", _LENGTH, "m"),
}


def _param(group: dict, name: str, default=None):
    try:
        return group[name]["value"]
    except (KeyError, TypeError):
        return default


def _open(path) -> "object":
    import ezc3d

    p = Path(path)
    if not p.is_file():
        raise InputError(path, "C3D file not found")
    try:
        return ezc3d.c3d(os.fspath(p))
    except Exception as exc:  # ezc3d raises bare RuntimeError/IOError for corrupt files
        raise InputError(path, f"not a readable C3D file ({exc})") from None


def _labels(c3d) -> list[str]:
    point = c3d["parameters"]["POINT"]
    labels = list(_param(point, "LABELS", []))
    # Files with more than 255 points continue the list in LABELS2, LABELS3...
    k = 2
    while f"LABELS{k}" in point:
        labels += list(_param(point, f"LABELS{k}", []))
        k += 1
    n = c3d["data"]["points"].shape[1]
    labels = [str(s).strip() for s in labels[:n]]
    labels += [f"*{i}" for i in range(len(labels), n)]
    return labels


def _output_names(point: dict) -> dict[str, str]:
    """Map point label -> output group name for every Nexus output group present."""
    out: dict[str, str] = {}
    for grp in _OUTPUT_GROUPS:
        for name in _param(point, grp, []) or []:
            out[str(name).strip()] = grp
    return out


def _positions(c3d, path) -> tuple[np.ndarray, float]:
    pts = np.asarray(c3d["data"]["points"], dtype=float)[:3]  # (3, M, F)
    res = np.asarray(c3d["data"]["meta_points"]["residuals"], dtype=float)[0]  # (M, F)
    pos = np.transpose(pts, (2, 1, 0)).copy()  # (F, M, 3)
    invalid = (res.T < 0) | np.all(pos == 0.0, axis=2) | ~np.all(np.isfinite(pos), axis=2)
    pos[invalid] = np.nan
    rate = float(np.ravel(_param(c3d["parameters"]["POINT"], "RATE", [0.0]))[0])
    if not rate > 0:
        raise InputError(path, "POINT:RATE is missing or not positive")
    return pos, rate


def read_c3d(path: str | os.PathLike, *, keep_unlabelled: bool = False) -> MarkerTrial:
    """Read the marker trajectories of a C3D file.

    Parameters
    ----------
    path : path of the ``.c3d`` file.
    keep_unlabelled : bool
        Keep points whose label starts with ``*`` (Nexus' unlabelled
        trajectories); dropped by default.

    Returns
    -------
    MarkerTrial
        Positions (F, M, 3) in metres, NaN where a marker was not seen.
        ``extra`` holds ``subject`` (label prefix, if any), ``first_frame`` and
        ``units_in_file``.

    Raises
    ------
    InputError
        Unreadable file, unknown length unit, no markers.
    """
    c3d = _open(path)
    point = c3d["parameters"]["POINT"]
    unit = str(np.ravel(_param(point, "UNITS", ["mm"]))[0]).strip()
    if unit.lower() not in _LENGTH:
        raise InputError(path, f"unknown POINT:UNITS {unit!r} (expected mm, cm or m)")
    scale = _LENGTH[unit.lower()]
    labels = _labels(c3d)
    outputs = _output_names(point)
    pos, rate = _positions(c3d, path)
    # Nexus prefixes labels with "Subject:" when several subjects share a file.
    names, keep, subject = [], [], None
    for i, lab in enumerate(labels):
        if lab in outputs or lab.split(":")[-1] in outputs:
            continue
        if lab.startswith("*") and not keep_unlabelled:
            continue
        if ":" in lab:
            subject, lab = lab.split(":", 1)
        if not lab or lab in names:
            continue
        names.append(lab)
        keep.append(i)
    if not names:
        raise InputError(path, "no marker trajectories in the file")
    first = int(np.ravel(c3d["header"]["points"].get("first_frame", 0))[0])
    time = (np.arange(pos.shape[0]) + first) / rate
    extra = {"subject": subject, "first_frame": first, "units_in_file": unit}
    return MarkerTrial(tuple(names), pos[:, keep] * scale, rate, time, os.fspath(path), extra)


@dataclass(frozen=True)
class C3DOutputs:
    """Model outputs stored as C3D points (e.g. Vicon Nexus Plug-in-Gait).

    Attributes
    ----------
    values : dict name -> ndarray (F, 3), SI units (rad, N, N m, W, m); NaN gaps
    kind : dict name -> group (``ANGLES``, ``FORCES``, ``MOMENTS``, ``POWERS``, ``MODELED_MARKERS``)
    units : dict name -> SI unit string
    rate : float, Hz
    source : str
    """

    values: dict
    kind: dict
    units: dict
    rate: float
    source: str | None = None

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.values[name]
        except KeyError:
            raise InputError(self.source, f"model output {name!r} is not in the file") from None


def read_c3d_outputs(path: str | os.PathLike) -> C3DOutputs:
    """Read the non-marker points (angles, forces, moments, powers) of a C3D file.

    Angles are returned in radians, moments in N m: the file's ``*_UNITS``
    parameters are honoured and an unknown unit is an `InputError`.
    """
    c3d = _open(path)
    point = c3d["parameters"]["POINT"]
    labels = _labels(c3d)
    groups = _output_names(point)
    pos, rate = _positions(c3d, path)
    values, kind, units = {}, {}, {}
    for i, lab in enumerate(labels):
        name = lab.split(":")[-1]
        grp = groups.get(lab) or groups.get(name)
        if grp is None:
            continue
        unit_param, table, si = _OUTPUT_GROUPS[grp]
        unit = str(np.ravel(_param(point, unit_param, [next(iter(table))]))[0]).strip()
        factor = table.get(unit, table.get(unit.lower()))
        if factor is None:
            raise InputError(path, f"unknown {unit_param} {unit!r} for {name}")
        values[name] = pos[:, i] * factor
        kind[name] = grp
        units[name] = si
    return C3DOutputs(values, kind, units, rate, os.fspath(path))


def write_c3d(path: str | os.PathLike, trial: MarkerTrial, *, outputs: C3DOutputs | None = None) -> Path:
    """Write marker trajectories (and optional angle outputs) to a C3D file, atomically.

    Markers are written in millimetres (``POINT:UNITS = mm``) in the lab frame
    of `trial`; NaN samples are written as zeros with residual -1 (invalid).
    Angle outputs, if given, are written in degrees in the ``POINT:ANGLES`` group.
    """
    import ezc3d

    names = list(trial.names)
    data = [np.asarray(trial.positions, float) * 1e3]
    out_names: list[str] = []
    if outputs is not None:
        for name, v in outputs.values.items():
            if outputs.kind.get(name) != "ANGLES":
                continue
            if v.shape[0] != trial.n_frames:
                raise InputError(path, f"output {name} has {v.shape[0]} frames, markers have {trial.n_frames}")
            data.append(np.degrees(v)[:, None, :])
            out_names.append(name)
    pos = np.concatenate(data, axis=1)  # (F, M, 3)
    valid = np.all(np.isfinite(pos), axis=2)
    pts = np.ones((4, pos.shape[1], pos.shape[0]))
    pts[:3] = np.transpose(np.where(valid[..., None], pos, 0.0), (2, 1, 0))
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(trial.rate)]
    c["parameters"]["POINT"]["LABELS"]["value"] = names + out_names
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c["data"]["points"] = pts
    # ezc3d derives residuals from meta_points; -1 marks an invalid sample.
    res = np.where(valid.T, 0.0, -1.0)[None]
    c["data"]["meta_points"] = {"residuals": res, "camera_masks": np.zeros((7, pos.shape[1], pos.shape[0]), bool)}
    if out_names:
        c.add_parameter("POINT", "ANGLES", out_names)
        c.add_parameter("POINT", "ANGLE_UNITS", ["deg"])
        c.add_parameter("POINT", "TYPE_GROUPS", ["ANGLES", "ANGLE"])
    with atomic_path(path) as tmp:
        c.write(os.fspath(tmp))
    return Path(path)


# --------------------------------------------------------------------------- gaps


@dataclass(frozen=True)
class Gap:
    """One run of consecutive missing samples of one marker."""

    marker: str
    start: float  # s, time of the first missing frame
    end: float  # s, time of the last missing frame
    n_frames: int
    filled: bool
    reason: str  # "filled", "too long", "at trial start/end", "too few valid samples"


@dataclass(frozen=True)
class GapReport:
    """What `fill_gaps` did: every gap found, filled or not."""

    gaps: tuple[Gap, ...]
    max_gap_s: float

    @property
    def unfilled(self) -> tuple[Gap, ...]:
        return tuple(g for g in self.gaps if not g.filled)

    def summary(self) -> str:
        n_f = sum(g.filled for g in self.gaps)
        lines = [f"{n_f} gap(s) up to {self.max_gap_s:g} s filled by cubic spline, {len(self.unfilled)} left as NaN"]
        for g in self.unfilled:
            lines.append(f"  {g.marker}: {g.start:.3f}-{g.end:.3f} s ({g.n_frames} frames) not filled: {g.reason}")
        return "\n".join(lines)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) index pairs of the True runs of a 1-D mask, stop exclusive."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def fill_gaps(trial: MarkerTrial, max_gap_s: float) -> tuple[MarkerTrial, GapReport]:
    """Fill short interior marker gaps by cubic-spline interpolation.

    For each marker, the valid samples (t_k, p_k) define a not-a-knot cubic
    spline s(t) per coordinate; a gap of n frames bounded by valid samples on
    both sides is replaced by s(t) when n / rate <= `max_gap_s`.  Longer gaps,
    gaps touching the first or last frame (that would be extrapolation) and
    markers with fewer than 4 valid samples stay NaN and are reported: no
    data is ever invented outside the measured span.

    Returns
    -------
    (MarkerTrial, GapReport)
    """
    from scipy.interpolate import CubicSpline

    if not max_gap_s >= 0:
        raise InputError("max_gap_s", f"must be >= 0 s, got {max_gap_s}")
    pos = trial.positions.copy()
    t = trial.time
    gaps: list[Gap] = []
    nf = trial.n_frames
    for j, name in enumerate(trial.names):
        missing = ~np.all(np.isfinite(pos[:, j]), axis=1)
        if not missing.any():
            continue
        runs = _runs(missing)
        valid = ~missing
        spline = CubicSpline(t[valid], pos[valid, j], axis=0) if valid.sum() >= 4 else None
        for a, b in runs:
            n = b - a
            if a == 0 or b == nf:
                reason, ok = "at trial start/end", False
            elif spline is None:
                reason, ok = "too few valid samples", False
            elif n / trial.rate > max_gap_s + 1e-12:
                reason, ok = "too long", False
            else:
                pos[a:b, j] = spline(t[a:b])
                reason, ok = "filled", True
            gaps.append(Gap(name, float(t[a]), float(t[b - 1]), int(n), ok, reason))
    out = MarkerTrial(trial.names, pos, trial.rate, trial.time, trial.source, dict(trial.extra))
    return out, GapReport(tuple(gaps), float(max_gap_s))
