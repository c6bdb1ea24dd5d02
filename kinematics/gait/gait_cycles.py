r"""Gait events and cycles: foot strikes and toe offs, signals normalised to % of the gait cycle.

Events from force plates: a foot strike is the first frame a plate assigned
to a foot carries the load threshold (``ForcePlates.threshold`` along the
plate normal), the toe off the first frame after that interval without it.
Intervals touching the start or the end of the trial give no strike
(respectively no toe off): the foot was already on the plate, or still is.

Events from kinematics (Zeni et al. 2008, Gait Posture 27:710), for trials
without plates: along the walking direction d (horizontal, the pelvis'
mean displacement)

.. math::

    h(t) = (x_{heel}(t) - x_{sacrum}(t)) \cdot d, \qquad
    o(t) = (x_{toe}(t) - x_{sacrum}(t)) \cdot d,

foot strikes are the maxima of h (the heel furthest in front of the pelvis)
and toe offs the minima of o (the toe furthest behind), peaks at least
``min_interval`` apart and with a prominence of at least ``min_prominence``.
The sacrum is SACR or the mid-point of RPSI and LPSI.

A cycle runs from one foot strike to the next of the same foot; a signal
:math:`s(t)` is resampled at 101 points (0, 1, ..., 100 % of the cycle) by
linear interpolation in time between the strike times.  Cycles with a NaN
inside give NaN at those points; the mean and sd over cycles use the finite
cycles at each point (sd NaN with a single cycle).
"""
from __future__ import annotations

import csv
import itertools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinematics.io.c3d import open_c3d
from lowerlimb.errors import InputError
from kinematics.io.markers import MarkerTrial

__all__ = [
    "N_POINTS",
    "CycleStatistics",
    "GaitCycle",
    "GaitEvent",
    "c3d_events",
    "cycle_statistics",
    "events_from_kinematics",
    "events_from_plates",
    "events_from_vertical_force",
    "gait_cycles",
    "normalise_cycle",
    "walking_direction",
    "write_cycles_csv",
]

N_POINTS = 101


@dataclass(frozen=True)
class GaitEvent:
    """One gait event.

    side : ``"R"`` or ``"L"``; kind : ``"strike"`` or ``"off"``; frame : int (0-based marker frame);
    time : float, s; source : ``"plate N"`` or ``"kinematics"``
    """

    side: str
    kind: str
    frame: int
    time: float
    source: str


@dataclass(frozen=True)
class GaitCycle:
    """One gait cycle of one foot: strike to next strike, with the toe off between (or None)."""

    side: str
    start: GaitEvent
    end: GaitEvent
    off: GaitEvent | None

    @property
    def stance_percent(self) -> float:
        """Toe off as % of the cycle (NaN without a toe off)."""
        if self.off is None:
            return float("nan")
        return 100.0 * (self.off.time - self.start.time) / (self.end.time - self.start.time)


@dataclass(frozen=True)
class CycleStatistics:
    """Mean and sd over cycles of a normalised signal.

    percent : (101,) % cycle; mean, sd : (101, k) in the signal's unit; n_cycles : int;
    cycles : (n_cycles, 101, k) the normalised cycles; stance_percent : (n_cycles,) toe-off %
    """

    percent: np.ndarray
    mean: np.ndarray
    sd: np.ndarray
    n_cycles: int
    cycles: np.ndarray
    stance_percent: np.ndarray


def events_from_plates(plates, contacts) -> list[GaitEvent]:
    """Foot strikes and toe offs of the plate contacts assigned to one foot.

    Parameters
    ----------
    plates : kinematics.io.forceplates.ForcePlates (at the marker frames)
    contacts : list of kinematics.gait.plate_contacts.PlateContact

    Returns
    -------
    list of GaitEvent, ordered by time.  Contacts without a single foot give none.
    """
    ev = []
    n = plates.n_frames
    for c in contacts:
        if c.foot is None or "two feet" in c.flags:
            continue
        src = f"plate {c.plate + 1}"
        if c.start > 0:
            ev.append(GaitEvent(c.foot, "strike", int(c.start), float(plates.time[c.start]), src))
        if c.stop < n:
            ev.append(GaitEvent(c.foot, "off", int(c.stop), float(plates.time[c.stop]), src))
    return sorted(ev, key=lambda e: (e.time, e.side))


def events_from_vertical_force(time: np.ndarray, vertical: np.ndarray, side: str, *, threshold: float = 20.0,
                               source: str = "force") -> list[GaitEvent]:
    """Foot strikes (first sample at or over `threshold` N) and toe offs (first sample under it) of one
    foot's vertical ground reaction `vertical` (F,) N sampled at `time` (F,) s, e.g. an OpenSim
    ground-reaction ``.mot`` column.  ``frame`` is the sample index."""
    vertical = np.asarray(vertical, float)
    on = np.nan_to_num(vertical, nan=0.0) >= threshold
    d = np.diff(on.astype(int))
    ev = [GaitEvent(side, "strike", int(i + 1), float(time[i + 1]), source) for i in np.flatnonzero(d == 1)]
    ev += [GaitEvent(side, "off", int(i + 1), float(time[i + 1]), source) for i in np.flatnonzero(d == -1)]
    return sorted(ev, key=lambda e: e.time)


def c3d_events(path: str | os.PathLike) -> list[GaitEvent]:
    """Gait events stored in a C3D's EVENT group (as Vicon Nexus writes them); [] when there are none.

    ``EVENT:CONTEXTS`` "Right"/"Left", ``EVENT:LABELS`` "Foot Strike"/"Foot Off", ``EVENT:TIMES``
    (2, n) minutes and seconds from the start of the capture (0 s at its frame 1).  The event's
    time is in `kinematics.io.c3d.read_c3d`'s time base (which starts at the trial's first frame
    / POINT:RATE), its frame the 0-based index of the nearest marker frame of the trial.
    """
    c = open_c3d(path)
    grp = c["parameters"].get("EVENT", {})
    rate = float(np.ravel(c["parameters"]["POINT"]["RATE"]["value"])[0])
    first = int(np.ravel(c["header"]["points"].get("first_frame", 0))[0])
    used = int(np.ravel(grp.get("USED", {}).get("value", [0]) or [0])[0])
    if used == 0:
        return []
    try:
        times = np.asarray(grp["TIMES"]["value"], float).reshape(2, -1)
        labels = [str(v).strip().lower() for v in grp["LABELS"]["value"]]
        contexts = [str(v).strip().lower() for v in grp["CONTEXTS"]["value"]]
    except (KeyError, ValueError) as exc:
        raise InputError(path, f"EVENT group without readable TIMES, LABELS and CONTEXTS ({exc})") from None
    if min(times.shape[1], len(labels), len(contexts)) < used:
        raise InputError(path, f"EVENT:USED is {used} but TIMES/LABELS/CONTEXTS hold {times.shape[1]}/"
                               f"{len(labels)}/{len(contexts)} events")
    ev = []
    for k in range(used):
        t = float(times[0, k] * 60.0 + times[1, k])
        side = {"right": "R", "left": "L"}.get(contexts[k])
        kind = {"foot strike": "strike", "foot off": "off"}.get(labels[k])
        if side and kind:
            ev.append(GaitEvent(side, kind, int(round(t * rate)) - first, t, "c3d"))
    return sorted(ev, key=lambda e: e.time)


def _sacrum(trial: MarkerTrial, name: str | None = None) -> np.ndarray:
    if name is not None:
        trial.require([name])
        return trial.marker(name)
    if "SACR" in trial.names:
        return trial.marker("SACR")
    if "RPSI" in trial.names and "LPSI" in trial.names:
        return 0.5 * (trial.marker("RPSI") + trial.marker("LPSI"))
    raise InputError(trial.source, "no SACR or RPSI/LPSI markers: cannot find gait events from kinematics")


def walking_direction(trial: MarkerTrial, up=(0.0, 0.0, 1.0), sacrum: str | None = None,
                      heel: str = "{s}HEE") -> np.ndarray:
    """Unit horizontal walking direction (3,).

    Overground: the pelvis' displacement over the trial.  On a treadmill (the
    pelvis travels less than 0.2 m): the main horizontal axis of the heels'
    motion relative to the sacrum, pointing the way the heels move fast (swing)
    rather than slowly (stance: the median heel velocity along it is backwards).
    """
    s = _sacrum(trial, sacrum)
    up = np.asarray(up, float)
    ok = np.all(np.isfinite(s), axis=1)
    if ok.sum() < 2:
        raise InputError(trial.source, "sacrum markers visible in fewer than 2 frames")
    d = s[ok][-1] - s[ok][0]
    d = d - (d @ up) * up
    if np.linalg.norm(d) >= 0.2:
        return d / np.linalg.norm(d)
    rel = [trial.marker(heel.format(s=side)) - s for side in "RL" if heel.format(s=side) in trial.names]
    if not rel:
        raise InputError(trial.source, "the pelvis does not travel and no heel markers: no walking direction")
    rel = np.concatenate(rel)
    rel = rel[np.all(np.isfinite(rel), axis=1)]
    rel = rel - np.outer(rel @ up, up)
    _, _, vt = np.linalg.svd(rel - rel.mean(0), full_matrices=False)
    d = vt[0] - (vt[0] @ up) * up
    d /= np.linalg.norm(d)
    vel = np.concatenate([np.diff((trial.marker(heel.format(s=side)) - s) @ d) for side in "RL"
                          if heel.format(s=side) in trial.names])
    if np.nanmedian(vel) > 0:
        d = -d
    return d


def events_from_kinematics(trial: MarkerTrial, *, heel: str = "{s}HEE", toe: str = "{s}TOE",
                           sacrum: str | None = None, min_interval: float = 0.4, min_prominence: float = 0.05,
                           up=(0.0, 0.0, 1.0)) -> list[GaitEvent]:
    """Zeni et al. (2008) foot strikes and toe offs from heel, toe and sacrum markers.

    Parameters
    ----------
    trial : MarkerTrial (m)
    heel, toe : marker name patterns (``{s}`` = ``R``/``L``)
    sacrum : marker name of the sacrum (default SACR, else the RPSI/LPSI mid-point)
    up : lab vertical (C3D: +Z; OpenSim: +Y)
    min_interval : float, s, least time between two events of the same kind and foot
    min_prominence : float, m, least prominence of a peak of h or o

    Returns
    -------
    list of GaitEvent (source ``"kinematics"``), ordered by time.
    """
    from scipy.signal import find_peaks

    up = np.asarray(up, float)
    d = walking_direction(trial, up, sacrum, heel)
    sac = _sacrum(trial, sacrum)
    ev = []
    dist = max(int(round(min_interval * trial.rate)), 1)
    for s in "RL":
        names = (heel.format(s=s), toe.format(s=s))
        trial.require(list(names))
        for name, kind, sign in ((names[0], "strike", 1.0), (names[1], "off", -1.0)):
            x = sign * ((trial.marker(name) - sac) @ d)
            ok = np.isfinite(x)
            if ok.sum() < 3:
                continue
            xi = np.interp(np.arange(len(x)), np.flatnonzero(ok), x[ok])
            peaks, _ = find_peaks(xi, distance=dist, prominence=min_prominence)
            for p in peaks:
                if ok[p] and 0 < p < len(x) - 1:
                    ev.append(GaitEvent(s, kind, int(p), float(trial.time[p]), "kinematics"))
    return sorted(ev, key=lambda e: (e.time, e.side))


def gait_cycles(events: list[GaitEvent], side: str) -> list[GaitCycle]:
    """Cycles of `side`: consecutive foot strikes, each with the first toe off between them.

    A pair of strikes with two toe offs of that foot, or two strikes of the
    other foot, between them spans more than one stride (a strike was missed,
    e.g. a foot between two plates): it is not a cycle and is left out.
    """
    strikes = [e for e in events if e.side == side and e.kind == "strike"]
    offs = [e for e in events if e.side == side and e.kind == "off"]
    other = [e for e in events if e.side != side and e.kind == "strike"]
    out = []
    for a, b in itertools.pairwise(strikes):
        between = [o for o in offs if a.time < o.time < b.time]
        if len(between) > 1 or sum(a.time < o.time < b.time for o in other) > 1:
            continue
        out.append(GaitCycle(side, a, b, between[0] if between else None))
    return out


def normalise_cycle(signal: np.ndarray, time: np.ndarray, cycle: GaitCycle, n: int = N_POINTS) -> np.ndarray:
    """Signal (F, ...) over one cycle, linearly resampled at `n` points from strike to strike: (n, ...)."""
    signal = np.asarray(signal, float)
    t = np.linspace(cycle.start.time, cycle.end.time, n)
    flat = signal.reshape(len(signal), -1)
    out = np.empty((n, flat.shape[1]))
    for k in range(flat.shape[1]):
        out[:, k] = np.interp(t, time, flat[:, k])
        # interpolation must not bridge NaN samples
        bad = ~np.isfinite(flat[:, k])
        if bad.any():
            idx = np.searchsorted(time, t).clip(1, len(time) - 1)
            out[bad[idx] | bad[idx - 1], k] = np.nan
    return out.reshape((n,) + signal.shape[1:])


def cycle_statistics(signal: np.ndarray, time: np.ndarray, cycles: list[GaitCycle], n: int = N_POINTS) -> CycleStatistics:
    """Mean and sd over `cycles` of `signal` (F,) or (F, k), each cycle resampled at `n` points."""
    signal = np.asarray(signal, float)
    if signal.ndim == 1:
        signal = signal[:, None]
    if not cycles:
        raise InputError(None, "no complete gait cycle (two foot strikes of the same foot) in the trial")
    c = np.stack([normalise_cycle(signal, time, cy, n) for cy in cycles])
    with np.errstate(invalid="ignore"), __import__("warnings").catch_warnings():
        __import__("warnings").simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(c, axis=0)
        sd = np.nanstd(c, axis=0, ddof=1) if len(cycles) > 1 else np.full_like(mean, np.nan)
    return CycleStatistics(np.linspace(0.0, 100.0, n), mean, sd, len(cycles), c,
                           np.array([cy.stance_percent for cy in cycles]))


def write_cycles_csv(path: str | os.PathLike, stats: dict, units: dict, *, note: str = "") -> Path:
    """Write normalised cycles as CSV: one row per % cycle, columns ``<name>_<side>_<component>_mean/_sd``.

    Parameters
    ----------
    stats : dict (name, side) -> CycleStatistics, e.g. ``("knee_angle", "R")``; components are
        named x, y, z (Plug-in-Gait's sagittal, frontal, transverse) or by index
    units : dict name -> unit string, written in the header comment
    """
    from lowerlimb.atomic import write_text

    names = sorted(stats, key=lambda k: (k[0], k[1]))
    header, cols = ["percent_cycle"], []
    for name, side in names:
        st = stats[(name, side)]
        comps = "xyz" if st.mean.shape[1] == 3 else [str(i) for i in range(st.mean.shape[1])]
        for k, comp in enumerate(comps):
            header += [f"{name}_{side}_{comp}_mean", f"{name}_{side}_{comp}_sd"]
            cols += [st.mean[:, k], st.sd[:, k]]
    first = stats[names[0]]
    lines = [f"# gait cycles normalised to % cycle (0 = foot strike, 100 = next strike of the same foot); "
             f"units: {', '.join(f'{k} {v}' for k, v in sorted(units.items()))}; components x/y/z = sagittal/frontal/"
             f"transverse (Plug-in-Gait); cycles: {', '.join(f'{n} {s} {stats[(n, s)].n_cycles}' for n, s in names)}"
             + (f"; {note}" if note else "")]
    import io

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for i in range(len(first.percent)):
        w.writerow([f"{first.percent[i]:g}"] + [("" if not np.isfinite(c[i]) else f"{c[i]:.6g}") for c in cols])
    return write_text(path, lines[0] + "\n" + buf.getvalue())
