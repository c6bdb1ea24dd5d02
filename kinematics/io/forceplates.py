"""Force platforms of a C3D file: ground reactions in the lab frame, and the foot on each plate.

`read_force_plates` turns the FORCE_PLATFORM group and its analog channels
into, per plate and per frame, the ground reaction acting ON THE SUBJECT, in
the lab frame, SI units:

* ``force`` F (N),
* ``moment`` M_c (N m) about the centre c of the plate's top surface,
* ``cop`` p (m), the centre of pressure on the top surface,
* ``free_moment`` T (N m), the moment about p, along the plate normal n.

Model (plate frame P, rotation R_P from plate to lab, surface centre c):

    F = R_P f,   M_c = R_P (m_o + f x o)            (o: sensor origin -> surface centre)
    p = c + R_P (-m_y / f_z, m_x / f_z, 0),  T = M_c - (p - c) x F   (T || n)

where (f, m_o) are the force and the moment about the sensor origin in P:

* type 1: channels f_x f_y f_z, p_x p_y, T_z (centre of pressure given),
* type 2: f_x f_y f_z m_x m_y m_z,
* type 3 (Kistler, 8 channels f_x12 f_x34 f_y14 f_y23 f_z1..f_z4, ORIGIN = a b az0):
  f = (f_x12 + f_x34, f_y14 + f_y23, sum f_zi),
  m = (b (f_z1 + f_z2 - f_z3 - f_z4), a (f_z2 + f_z3 - f_z1 - f_z4), b (f_x34 - f_x12) + a (f_y14 - f_y23)),
  o = (0, 0, az0),
* type 4: type 2 after the 6x6 ``CAL_MATRIX`` (``CAL_MATRIX[:, :, plate]`` times
  the channel vector, the layout ezc3d uses).

Conventions and checks (the C3D spec leaves several of these to the vendor):

* The plate frame is X = c1 - c2, Z = X x (c1 - c4), Y = Z x X from the
  ``CORNERS`` (as ezc3d and BTK).  ``ORIGIN`` is taken as the sensor
  origin's offset from the surface centre whatever sign the vendor wrote: the
  surface is put ABOVE the sensor origin along the lab vertical (Vicon writes
  +41 mm for Kistler plates, AMTI a negative z; both mean "41 mm below").
* Channel units come from ``ANALOG:UNITS`` (N, kN, N mm, N m, mm, m); the
  analog values are read scaled by ezc3d ((raw - OFFSET) SCALE GEN_SCALE).
* The ground can only push: if the vertical force of the loaded frames
  points down, the plate records the action on the plate and F, M are negated
  (a note says so).
* Zeroing: ``zero="auto"`` subtracts each channel's mean over the
  ``FORCE_PLATFORM:ZERO`` frame range when the file gives a valid one (first
  <= last; Vicon's ``[1, 0]`` asks for none, and Nexus' own ground reactions
  are then not zeroed either); ``zero="start"`` uses the first 0.1 s;
  ``zero="none"`` never zeroes.  A baseline window where the plate carries
  the threshold or more (point-rate average) is not used (note).
* Analog to point frames (``at="points"``): each point frame gets the mean of
  the analog signal over one point period centred on it (a box average, zero
  lag; for 9 analog samples per frame, the 9 centred samples).  The analog time
  base is frame 0 + j / ANALOG:RATE; when the analog samples do not span the
  point frames at the stated ANALOG:RATE (an ANALOG:RATE that is not the
  file's samples-per-frame times POINT:RATE), the file is refused.  The CoP
  is computed after averaging the wrench, never by averaging CoPs.
* Under the load ``threshold`` (N, along the plate normal; tested on the
  point-period average also at the analog rate) the CoP and free moment are
  NaN and ``loaded`` is False.  Loaded frames whose CoP is outside
  the plate outline (by more than 1 cm) are marked in ``cop_outside``.

Which foot stands on each plate: `kinematics.gait.plate_contacts.assign_feet`.

This module is the one place that interprets force platforms; writers of
OpenSim ground-reaction files and the inverse dynamics read `ForcePlates`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from kinematics.io.c3d import open_c3d
from kinematics.io.markers import LENGTH_UNITS as _LENGTH
from kinematics.io.markers import true_runs
from lowerlimb.errors import InputError

__all__ = ["ForcePlate", "ForcePlates", "box_average", "read_force_plates"]

DEFAULT_THRESHOLD_N = 20.0
_COP_TOLERANCE_M = 0.01
_FORCE = {"n": 1.0, "kn": 1e3, "newton": 1.0, "newtons": 1.0}
_MOMENT = {"nmm": 1e-3, "n.mm": 1e-3, "n mm": 1e-3, "nm": 1.0, "n.m": 1.0, "n m": 1.0, "knm": 1e3}

@dataclass(frozen=True)
class ForcePlate:
    """One force platform over the trial, lab frame, SI units.

    Attributes
    ----------
    index : int
        0-based plate number in FORCE_PLATFORM.
    type : int
        C3D platform type (1-4).
    corners : ndarray (4, 3), m
        Surface corners c1..c4 in the lab frame.
    centre : ndarray (3,), m
        Centre of the top surface.
    rotation : ndarray (3, 3)
        Plate frame to lab frame (columns: plate X, Y, Z in the lab).
    normal : ndarray (3,)
        Unit surface normal pointing up (towards the subject).
    force : ndarray (F, 3), N
        Ground reaction force on the subject.
    moment : ndarray (F, 3), N m
        Ground reaction moment about `centre`.
    cop : ndarray (F, 3), m
        Centre of pressure on the surface; NaN when not `loaded`.
    free_moment : ndarray (F, 3), N m
        Moment about the CoP (along `normal`); NaN when not `loaded`.
    loaded : ndarray (F,) bool
        Normal force above the threshold.
    cop_outside : ndarray (F,) bool
        Loaded and CoP more than 1 cm outside the plate outline.
    channels : tuple of str
        Analog channel labels used.
    notes : tuple of str
        What the reader did that a user should know (zeroing, sign flips).
    """

    index: int
    type: int
    corners: np.ndarray
    centre: np.ndarray
    rotation: np.ndarray
    normal: np.ndarray
    force: np.ndarray
    moment: np.ndarray
    cop: np.ndarray
    free_moment: np.ndarray
    loaded: np.ndarray
    cop_outside: np.ndarray
    channels: tuple = ()
    notes: tuple = ()

    @property
    def name(self) -> str:
        return f"plate {self.index + 1}"

    def intervals(self, min_frames: int = 1) -> list[tuple[int, int]]:
        """(start, stop) frame ranges (stop exclusive) where the plate is loaded."""
        return [(a, b) for a, b in true_runs(self.loaded) if b - a >= min_frames]

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether points (..., 3) project inside the plate outline grown by `margin` (m)."""
        local = (np.asarray(points, float) - self.centre) @ self.rotation
        half = np.abs((self.corners - self.centre) @ self.rotation)[:, :2].max(axis=0)
        with np.errstate(invalid="ignore"):
            return np.all(np.abs(local[..., :2]) <= half + margin, axis=-1)

    def height_above(self, points: np.ndarray) -> np.ndarray:
        """Signed height (m) of points (..., 3) above the surface plane."""
        return (np.asarray(points, float) - self.centre) @ self.normal


@dataclass(frozen=True)
class ForcePlates:
    """All force platforms of a trial, sampled at `rate`.

    Attributes
    ----------
    plates : tuple of ForcePlate
    rate : float, Hz
        Sampling rate of the arrays (the point rate with ``at="points"``).
    time : ndarray (F,), s
        Same time base as `kinematics.io.c3d.read_c3d` for the file's markers.
    threshold : float, N
    analog_rate, point_rate : float, Hz
    source : str or None
    notes : tuple of str
    """

    plates: tuple
    rate: float
    time: np.ndarray
    threshold: float
    analog_rate: float
    point_rate: float
    source: str | None = None
    notes: tuple = ()

    def __len__(self) -> int:
        return len(self.plates)

    def __iter__(self):
        return iter(self.plates)

    def __getitem__(self, i: int) -> ForcePlate:
        return self.plates[i]

    @property
    def n_frames(self) -> int:
        return self.time.shape[0]

    def rotated(self, R) -> "ForcePlates":
        """The plates in another frame with the same origin, ``x' = R x`` (R a proper rotation, 3x3): corners,
        centre, plate axes, normal, force, moment, centre of pressure and free moment."""
        R = np.asarray(R, float)
        turn = lambda x: np.asarray(x, float) @ R.T  # noqa: E731
        plates = tuple(replace(p, corners=turn(p.corners), centre=turn(p.centre), rotation=R @ p.rotation,
                               normal=turn(p.normal), force=turn(p.force), moment=turn(p.moment), cop=turn(p.cop),
                               free_moment=turn(p.free_moment)) for p in self.plates)
        return replace(self, plates=plates)


# --------------------------------------------------------------------------- helpers


def _param(group: dict, name: str, default=None):
    try:
        return group[name]["value"]
    except (KeyError, TypeError):
        return default


def box_average(samples: np.ndarray, analog_rate: float, point_rate: float, n_frames: int) -> np.ndarray:
    """Mean of an analog signal over one point period centred on each point frame.

    Analog sample j is at time j / analog_rate, point frame k at k / point_rate
    (both from the first point frame).  Frame k gets

        (1 / T) * integral over [t_k - T/2, t_k + T/2] of x(t) dt,   T = 1 / point_rate,

    with x piecewise constant over each analog sample (sample j covering
    [t_j - 1/(2 f_a), t_j + 1/(2 f_a)]); windows are clipped at the record's ends.
    For an odd integer ratio r this is the mean of the r centred samples; any
    ratio (integer or not) is handled the same way.

    Parameters
    ----------
    samples : ndarray (N, ...) at `analog_rate`
    n_frames : int
        Number of point frames wanted.

    Returns
    -------
    ndarray (n_frames, ...)
    """
    x = np.asarray(samples, float)
    n = x.shape[0]
    edges = (np.arange(n + 1) - 0.5) / analog_rate
    cum = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0) / analog_rate])
    t = np.arange(n_frames) / point_rate
    lo = np.clip(t - 0.5 / point_rate, edges[0], edges[-1])
    hi = np.clip(t + 0.5 / point_rate, edges[0], edges[-1])
    flat = cum.reshape(n + 1, -1)
    c_lo = np.stack([np.interp(lo, edges, flat[:, i]) for i in range(flat.shape[1])], axis=1)
    c_hi = np.stack([np.interp(hi, edges, flat[:, i]) for i in range(flat.shape[1])], axis=1)
    width = np.maximum(hi - lo, 1e-12)[:, None]
    return ((c_hi - c_lo) / width).reshape((n_frames,) + x.shape[1:])


def _moving_average(x: np.ndarray, n: int) -> np.ndarray:
    """Centred moving average over `n` samples (edges: the available samples)."""
    if n <= 1:
        return x
    from scipy.ndimage import uniform_filter1d

    return uniform_filter1d(x, size=n, mode="nearest")


def _unit_factor(unit: str, table: dict, path, label: str) -> float:
    u = unit.strip().lower().replace("·", " ")
    if u in table:
        return table[u]
    raise InputError(path, f"analog channel {label!r} has unit {unit!r}, expected one of {sorted(table)}")


def _plate_frame(corners: np.ndarray) -> np.ndarray:
    x = corners[0] - corners[1]
    y = corners[0] - corners[3]
    z = np.cross(x, y)
    y = np.cross(z, x)
    return np.column_stack([x / np.linalg.norm(x), y / np.linalg.norm(y), z / np.linalg.norm(z)])


# --------------------------------------------------------------------------- reader


def read_force_plates(path: str | os.PathLike, *, threshold: float = DEFAULT_THRESHOLD_N, zero: str = "auto",
                      at: str = "points", up=(0.0, 0.0, 1.0)) -> ForcePlates:
    """Read every force platform of a C3D file (see the module docstring for the model).

    Parameters
    ----------
    path : path of the ``.c3d`` file.
    threshold : float, N
        Normal force under which a plate is unloaded (CoP NaN).  Default 20 N.
    zero : {"auto", "start", "none"}
        Baseline removal (module docstring).
    at : {"points", "analog"}
        Sample the outputs at the point (marker) frames, box-averaged, or keep
        the analog rate.
    up : 3-vector
        The lab's vertical (C3D labs: +Z).

    Returns
    -------
    ForcePlates
        Empty `plates` when the file has no force platform (a note says so).

    Raises
    ------
    InputError
        Unreadable file, a platform type other than 1-4, missing channels or
        calibration matrix, unknown units, an ANALOG:RATE inconsistent with the
        stored samples.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(path, "C3D file not found")
    if zero not in ("auto", "start", "none"):
        raise InputError("zero", f"must be 'auto', 'start' or 'none', got {zero!r}")
    if at not in ("points", "analog"):
        raise InputError("at", f"must be 'points' or 'analog', got {at!r}")
    c3d = open_c3d(p)
    params = c3d["parameters"]
    point = params["POINT"]
    point_rate = float(np.ravel(_param(point, "RATE", [0.0]))[0])
    if not point_rate > 0:
        raise InputError(path, "POINT:RATE is missing or not positive")
    n_frames = int(c3d["data"]["points"].shape[2])
    first = int(np.ravel(c3d["header"]["points"].get("first_frame", 0))[0])
    up = np.asarray(up, float) / np.linalg.norm(up)
    fp = params.get("FORCE_PLATFORM", {})
    n_used = int(np.ravel(_param(fp, "USED", [0]) if fp else [0])[0]) if fp else 0
    analogs = np.asarray(c3d["data"]["analogs"], float)[0] if c3d["data"]["analogs"].size else np.zeros((0, 0))
    analog_param = params.get("ANALOG", {})
    analog_rate = float(np.ravel(_param(analog_param, "RATE", [0.0]) if analog_param else [0.0])[0] or 0.0)
    point_time = (np.arange(n_frames) + first) / point_rate
    if n_used == 0 or analogs.size == 0:
        return ForcePlates((), point_rate, point_time, float(threshold), analog_rate, point_rate, os.fspath(path),
                           ("no force platform in the file: kinematics only",))
    n_analog = analogs.shape[1]
    if not analog_rate > 0:
        raise InputError(path, "ANALOG:RATE is missing or not positive")
    # The analog record must span the point frames at the stated rate (C3D stores an integer
    # number of analog samples per point frame; a rate that disagrees means a wrong parameter).
    per_frame = n_analog / n_frames if n_frames else 0.0
    if abs(per_frame * point_rate - analog_rate) > 1e-6 * analog_rate:
        raise InputError(path, f"ANALOG:RATE {analog_rate:g} Hz is not the stored {per_frame:g} analog samples per "
                               f"point frame x POINT:RATE {point_rate:g} Hz: the analog time base is ambiguous")
    labels = [str(s).strip() for s in (_param(analog_param, "LABELS", []) or [])]
    units = [str(s).strip() for s in (_param(analog_param, "UNITS", []) or [])]
    length_unit = str(np.ravel(_param(point, "UNITS", ["mm"]))[0]).strip().lower()
    if length_unit not in _LENGTH:
        raise InputError(path, f"unknown POINT:UNITS {length_unit!r}")
    lscale = _LENGTH[length_unit]
    types = np.ravel(_param(fp, "TYPE", [])).astype(int)
    channel = np.asarray(_param(fp, "CHANNEL", []), dtype=int)
    corners_all = np.asarray(_param(fp, "CORNERS", []), float)
    origin_all = np.asarray(_param(fp, "ORIGIN", []), float)
    cal_all = np.asarray(_param(fp, "CAL_MATRIX", []), float)
    zero_range = np.ravel(_param(fp, "ZERO", [0, 0])).astype(int)
    if types.size < n_used or channel.ndim != 2 or channel.shape[1] < n_used:
        raise InputError(path, f"FORCE_PLATFORM:TYPE/CHANNEL do not describe {n_used} plates")
    if corners_all.ndim != 3 or corners_all.shape[2] < n_used or origin_all.ndim != 2 or origin_all.shape[1] < n_used:
        raise InputError(path, f"FORCE_PLATFORM:CORNERS/ORIGIN do not describe {n_used} plates")

    if at == "points":
        rate = point_rate
        time = point_time
    else:
        rate = analog_rate
        time = (first + np.arange(n_analog) / per_frame) / point_rate
    plates = []
    for k in range(n_used):
        ptype = int(types[k])
        if ptype not in (1, 2, 3, 4):
            raise InputError(path, f"force plate {k + 1} has type {ptype}; types 1-4 are supported")
        n_ch = 8 if ptype == 3 else 6
        if channel.shape[0] < n_ch:
            raise InputError(path, f"force plate {k + 1} (type {ptype}) needs {n_ch} channels in FORCE_PLATFORM:CHANNEL")
        idx = channel[:n_ch, k] - 1
        if np.any(idx < 0) or np.any(idx >= analogs.shape[0]):
            raise InputError(path, f"force plate {k + 1} refers to analog channels {idx + 1} outside the {analogs.shape[0]} stored")
        raw = analogs[idx].T.copy()  # (N, n_ch)
        ch_labels = tuple(labels[i] if i < len(labels) else f"channel {i + 1}" for i in idx)
        ch_units = [units[i] if i < len(units) else "" for i in idx]
        notes: list[str] = []
        scale = np.ones(n_ch)
        for j in range(n_ch):
            if ptype == 1 and j in (3, 4):
                kind = _LENGTH
            elif ptype == 1 and j == 5 or ptype in (2, 4) and j >= 3:
                kind = _MOMENT
            else:
                kind = _FORCE
            if ch_units[j]:
                scale[j] = _unit_factor(ch_units[j], kind, path, ch_labels[j])
            else:
                scale[j] = 1.0 if kind is _FORCE else lscale  # N, N x point unit, point unit
                notes.append(f"channel {ch_labels[j]} has no unit; taken as N / N {length_unit} / {length_unit}")
        bad = ~np.isfinite(raw)
        if bad.any():   # a gap in a plate channel would read as no load (or a NaN wrench) mid-stance
            i, j = np.argwhere(bad)[0]
            raise InputError(path, f"force plate {k + 1}: channel {ch_labels[j]} has {int(bad[:, j].sum())} "
                                   f"non-finite sample(s) (first at analog sample {i + 1})")
        if ptype == 4:
            if cal_all.ndim != 3 or cal_all.shape[2] <= k or cal_all.shape[0] < 6 or cal_all.shape[1] < 6:
                raise InputError(path, f"force plate {k + 1} is type 4 but FORCE_PLATFORM:CAL_MATRIX has no 6x6 matrix for it")
            raw = raw @ cal_all[:6, :6, k].T
        raw = raw * scale
        corners = corners_all[:3, :4, k].T * lscale
        if not np.all(np.isfinite(corners)) or min(np.linalg.norm(corners[0] - corners[1]),
                                                   np.linalg.norm(corners[0] - corners[3])) < 0.01:
            raise InputError(path, f"force plate {k + 1}: FORCE_PLATFORM:CORNERS do not span a plate "
                                   "(edges under 1 cm or not finite)")
        centre = corners.mean(axis=0)
        rot = _plate_frame(corners)
        origin = origin_all[:3, k] * lscale
        # The surface is above the sensor origin: o (sensor origin -> surface centre) points up.
        o = np.array([0.0, 0.0, origin[2]]) if ptype in (1, 3) else origin.copy()
        if (rot @ o) @ up < 0:
            o = -o
        # Baseline from the analog record (frame numbers of ZERO are 1-based point frames).
        if zero != "none" and ptype != 1:
            raw, note = _zero(raw, zero_range if zero == "auto" else None, per_frame, point_rate, threshold,
                              ptype, origin)
            if note:
                notes.append(note)
        if at == "points":
            samples = box_average(raw, analog_rate, point_rate, n_frames)
        else:
            samples = raw
        f, m = _wrench(samples, ptype, origin, o)
        force = f @ rot.T
        moment = m @ rot.T
        normal = rot[:, 2] if rot[:, 2] @ up > 0 else -rot[:, 2]
        fn = force @ normal
        big = np.abs(fn) > threshold
        if big.any() and np.median(fn[big]) < 0:
            force, moment = -force, -moment
            fn = -fn
            notes.append("channels give the force on the plate; negated to the reaction on the subject")
        # Load detection on the point-period average (at the analog rate, raw noise of 10-20 N would
        # otherwise cut a stance into hundreds of pieces): the same frames as the point-rate output.
        fn_detect = fn if at == "points" else _moving_average(fn, round(per_frame))
        loaded = fn_detect > threshold
        # CoP on the surface plane: M_c = (p - c) x F + T n  with (p - c) . n = 0.
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.cross(normal, moment) / fn[:, None]
        r -= np.outer(r @ normal, normal)
        cop = centre + r
        free = moment - np.cross(r, force)
        free = np.outer(free @ normal, normal)
        no_cop = ~(loaded & (fn > threshold))  # a noise dip under the threshold inside a contact: no CoP
        cop[no_cop] = np.nan
        free[no_cop] = np.nan
        plate = ForcePlate(k, ptype, corners, centre, rot, normal, force, moment, cop, free, loaded,
                           np.zeros(len(loaded), bool), ch_labels, tuple(notes))
        has_cop = ~no_cop
        outside = has_cop & ~plate.contains(np.where(has_cop[:, None], cop, centre), margin=_COP_TOLERANCE_M)
        if outside.any():
            object.__setattr__(plate, "cop_outside", outside)
            object.__setattr__(plate, "notes", plate.notes + (
                f"CoP outside the plate in {int(outside.sum())} of {int(loaded.sum())} loaded frames",))
        plates.append(plate)
    return ForcePlates(tuple(plates), rate, time, float(threshold), analog_rate, point_rate, os.fspath(path))


def _zero(raw, zero_range, per_frame, point_rate, threshold, ptype, origin):
    """Subtract each channel's mean over an unloaded baseline window; (raw, note).

    `zero_range` None: the first 0.1 s; else the 1-based point frames of
    FORCE_PLATFORM:ZERO (no zeroing when that range is empty).
    """
    n = raw.shape[0]
    spf = round(per_frame)
    if zero_range is None:
        m = max(round(0.1 * point_rate), 1) * spf
        win, what = slice(0, min(m, n)), "the first 0.1 s"
    else:
        a, b = (int(zero_range[0]), int(zero_range[1])) if np.size(zero_range) >= 2 else (0, 0)
        if not (a >= 1 and b >= a):
            return raw, None
        if b * spf > n:
            return raw, f"FORCE_PLATFORM:ZERO frames {a}-{b} exceed the record: not zeroed"
        win, what = slice((a - 1) * spf, b * spf), f"FORCE_PLATFORM:ZERO frames {a}-{b}"
    seg = raw[win]
    nb = max(seg.shape[0] // spf, 1)
    blocks = seg[: nb * spf].reshape(nb, -1, seg.shape[1]).mean(axis=1) if seg.shape[0] >= spf else seg.mean(0)[None]
    f, _ = _wrench(blocks, ptype, origin, np.zeros(3))
    if np.max(np.linalg.norm(f, axis=1)) >= threshold:
        return raw, f"loaded during {what}: not zeroed"
    base = seg.mean(axis=0)
    off = np.linalg.norm(_wrench(base[None], ptype, origin, np.zeros(3))[0])
    return raw - base, f"zeroed on {what} (force offset {off:.1f} N)"


def _wrench(ch: np.ndarray, ptype: int, origin: np.ndarray, o: np.ndarray):
    """Force and moment about the surface centre, plate frame, from channels (N, n_ch) in SI."""
    if ptype == 3:
        a, b = origin[0], origin[1]
        fx12, fx34, fy14, fy23, fz1, fz2, fz3, fz4 = ch.T
        f = np.column_stack([fx12 + fx34, fy14 + fy23, fz1 + fz2 + fz3 + fz4])
        m = np.column_stack([b * (fz1 + fz2 - fz3 - fz4), a * (fz2 + fz3 - fz1 - fz4),
                             b * (fx34 - fx12) + a * (fy14 - fy23)])
    elif ptype == 1:
        f = ch[:, :3]
        cop = np.column_stack([ch[:, 3], ch[:, 4], np.zeros(len(ch))])
        m = np.cross(cop, f) + np.column_stack([np.zeros((len(ch), 2)), ch[:, 5]])
        return f, m  # type 1 gives the CoP relative to the surface centre directly
    else:
        f = ch[:, :3]
        m = ch[:, 3:6]
    return f, m + np.cross(f, o)
