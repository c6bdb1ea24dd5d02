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

A file that cannot be read correctly is refused (`InputError`) rather than
read in part: a frame count that disagrees with the header (a truncated
file, a header saying 0 frames), a marker label given twice, labels of
several Vicon subjects (``Name:RKNE``) unless one is chosen, an infinite
sample (a NaN is a gap), or a coordinate beyond `MAX_COORDINATE_M` from the
lab origin (no lab is that large; a unit slip such as mm data declared in m
lands there).
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lowerlimb.atomic import atomic_path
from lowerlimb.errors import InputError
from kinematics.io.markers import LENGTH_UNITS as _LENGTH
from kinematics.io.markers import MAX_COORDINATE_M, MAX_RATE_HZ, MarkerTrial, true_runs

__all__ = ["read_c3d", "read_c3d_outputs", "write_c3d", "fill_gaps", "C3DOutputs", "Gap", "GapReport"]

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


def open_c3d(path) -> "object":
    """The ezc3d object of a C3D file, or a one-line `InputError`.

    Guards every reader of C3D files: the parameter section is walked first, the file is
    read once in a forked child (a corrupt file can crash ezc3d), and the frame count must
    agree with the header (a truncated file is refused).
    """
    import ezc3d

    p = Path(path)
    if not p.is_file():
        raise InputError(path, "C3D file not found")
    expected = _header_frames(p)
    _check_parameter_section(p)
    _survives_ezc3d(p)
    try:
        c3d = ezc3d.c3d(os.fspath(p))
    except Exception as exc:  # ezc3d raises bare RuntimeError/IOError for corrupt files
        raise InputError(path, f"not a readable C3D file ({' '.join(str(exc).split())})") from None
    n = int(np.asarray(c3d["data"]["points"]).shape[-1]) if np.asarray(c3d["data"]["points"]).ndim == 3 else 0
    if expected is not None and n != expected:
        raise InputError(path, f"the file holds {n} frames but its header says {expected} (truncated or corrupt file)")
    return c3d


#: longest a C3D file may take to read (a corrupt one can make ezc3d allocate or loop for ever)
READ_TIMEOUT_S = 60.0


def _survives_ezc3d(p: Path) -> None:
    """Refuse a file that crashes ezc3d: it is first read in a forked child process.

    ezc3d (C++) dereferences what a corrupt parameter section points to and
    can take the whole process down with a segmentation fault (found by
    tests/test_fuzz_readers.py); the child costs one fork and one extra parse
    (a few ms for a trial).  Without ``os.fork`` (Windows) the file is read directly.
    """
    import signal
    import time

    import ezc3d

    if not hasattr(os, "fork"):  # pragma: no cover
        return
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: parse, report by exit code (and the error text), never return into the caller's code
        code = 1
        try:
            os.close(r)
            import faulthandler

            faulthandler.disable()  # a crash here is the expected, reported outcome: no dump on stderr
            ezc3d.c3d(os.fspath(p))
            code = 0
        except BaseException as exc:
            code = 3
            try:
                os.write(w, " ".join(str(exc).split())[:300].encode("utf-8", "replace"))
            except BaseException:
                pass
        finally:
            os._exit(code)
    os.close(w)
    deadline = time.monotonic() + READ_TIMEOUT_S
    try:
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            if time.monotonic() > deadline:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                raise InputError(p, f"reading took over {READ_TIMEOUT_S:g} s: corrupt C3D file")
            time.sleep(0.002)
        msg = os.read(r, 400).decode("utf-8", "replace")
    finally:
        os.close(r)
    if os.WIFEXITED(status) and os.WEXITSTATUS(status) == 3:
        raise InputError(p, f"not a readable C3D file ({msg or 'ezc3d refused it'})")
    if os.WIFSIGNALED(status):
        try:
            name = signal.Signals(os.WTERMSIG(status)).name
        except ValueError:
            name = f"signal {os.WTERMSIG(status)}"
        raise InputError(p, f"corrupt C3D file: the C3D reader (ezc3d) crashed on it ({name})")


def _check_parameter_section(p: Path) -> None:
    """Walk the parameter records (C3D spec) and refuse a section whose records leave it or are malformed.

    Each record: name length (int8, 0 ends), group/parameter id (int8), name,
    offset to the next record (int16, 0 ends), then for a parameter its type
    (-1 char, 1 byte, 2 int16, 4 float), dimensions and data, and a
    description.  ezc3d follows such garbage for minutes or into a crash.
    """
    try:
        with open(p, "rb") as f:
            head = f.read(512)
            if len(head) < 512 or head[1] != 0x50 or head[0] < 2:
                return
            start = (head[0] - 1) * 512
            f.seek(start)
            sec = f.read(4)
            if len(sec) < 4:
                return
            n_blocks = sec[2]
            sec += f.read(max(n_blocks, 1) * 512 - 4)
    except OSError:
        return  # reported by the reader
    end = ">" if sec[3] == 86 else "<"
    if n_blocks == 0:
        raise InputError(p, "corrupt C3D parameter section (0 blocks)")
    if len(sec) < n_blocks * 512:
        raise InputError(p, f"truncated C3D file: the parameter section of {n_blocks} blocks is cut short")
    i, n_rec, groups, params = 4, 0, set(), []
    while i + 2 <= len(sec):
        nchar, ident = struct.unpack("bb", sec[i:i + 2])
        if nchar == 0:
            break
        name_end = i + 2 + abs(nchar)
        if name_end + 2 > len(sec):
            raise InputError(p, f"corrupt C3D parameter section: record {n_rec + 1} runs past its end")
        (offset,) = struct.unpack(end + "h", sec[name_end:name_end + 2])
        body = name_end + 2
        if ident < 0:
            groups.add(-ident)
            need = 1
        else:
            if body + 2 > len(sec):
                raise InputError(p, f"corrupt C3D parameter section: record {n_rec + 1} runs past its end")
            ptype, ndims = struct.unpack("bB", sec[body:body + 2])
            if ptype not in (-1, 1, 2, 4) or ndims > 7:
                raise InputError(p, f"corrupt C3D parameter section: record {n_rec + 1} has type {ptype}, "
                                    f"{ndims} dimensions")
            dims = sec[body + 2:body + 2 + ndims]
            size = abs(ptype) * int(np.prod([d for d in dims], dtype=np.int64)) if ndims else abs(ptype)
            need = 2 + ndims + size + 1
            params.append(ident)
        if body + need > len(sec):
            raise InputError(p, f"corrupt C3D parameter section: record {n_rec + 1} runs past its end")
        n_rec += 1
        if offset == 0:
            break
        nxt = name_end + offset
        if offset < 0 or nxt < body + need - 1 or nxt > len(sec):
            raise InputError(p, f"corrupt C3D parameter section: record {n_rec} points outside the section")
        i = nxt
    orphans = sorted(set(params) - groups)
    if orphans:
        raise InputError(p, f"corrupt C3D parameter section: parameters of undefined group(s) {orphans[:5]}")


def _header_frames(p: Path) -> int | None:
    """Frame count the C3D header states (last - first + 1), checked against the file size.

    ezc3d quietly reads what a truncated file still holds (and rewrites its
    own header to match), so the 512-byte header is read here first.  None
    when the header cannot say (over 65535 frames: the 16-bit field saturates).
    """
    try:
        with open(p, "rb") as f:
            head = f.read(512)
            if len(head) < 512 or head[1] != 0x50 or head[0] < 2:
                return None  # ezc3d gives the error for what is not a C3D file
            f.seek((head[0] - 1) * 512)
            ph = f.read(4)
        size = p.stat().st_size
    except OSError as exc:
        raise InputError(p, f"cannot read ({exc.strerror or exc})") from None
    if len(ph) < 4:
        raise InputError(p, "truncated C3D file: the parameter section is missing")
    end = ">" if ph[3] == 86 else "<"  # processor type 84 Intel, 85 DEC (little-endian), 86 MIPS (big-endian)
    n_points, n_analog, first, last = struct.unpack(end + "4H", head[2:10])
    scale = struct.unpack(end + "f", head[12:16])[0] if ph[3] != 85 else -1.0
    data_start = struct.unpack(end + "H", head[16:18])[0]
    if last == 65535:
        return None
    n = last - first + 1
    if n <= 0:
        raise InputError(p, f"the header says {max(n, 0)} frames (first frame {first}, last frame {last})")
    word = 4 if scale < 0 else 2
    need = (data_start - 1) * 512 + n * (4 * n_points + n_analog) * word
    if data_start >= 2 and size < need:
        have = max(size - (data_start - 1) * 512, 0) // max((4 * n_points + n_analog) * word, 1)
        raise InputError(p, f"the file ends after {have} of the {n} frames its header states (truncated file)")
    return n


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
    # NaN is a gap whatever its residual (float C3Ds from some exporters mark gaps so); infinity is corruption
    invalid = (res.T < 0) | np.all(pos == 0.0, axis=2) | np.any(np.isnan(pos), axis=2)
    pos[invalid] = np.nan
    bad = ~invalid & ~np.all(np.isfinite(pos), axis=2)
    if bad.any():
        f, m = (int(v[0]) for v in np.nonzero(bad))
        raise InputError(path, f"{int(bad.sum())} sample(s) marked valid are not finite (first: point {m + 1}, "
                               f"frame {f + 1}): corrupt data")
    try:
        rate = float(np.ravel(_param(c3d["parameters"]["POINT"], "RATE", [0.0]))[0])
    except (TypeError, ValueError, IndexError):
        rate = float("nan")
    if not (0 < rate <= MAX_RATE_HZ):
        raise InputError(path, f"POINT:RATE {rate:g} Hz is missing or outside (0, {MAX_RATE_HZ:g}] Hz")
    return pos, rate


def _corrupt_parameters(path, exc: Exception) -> InputError:
    return InputError(path, f"corrupt C3D parameters ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})")


def read_c3d(path: str | os.PathLike, *, keep_unlabelled: bool = False, subject: str | None = None) -> MarkerTrial:
    """Read the marker trajectories of a C3D file.

    Parameters
    ----------
    path : path of the ``.c3d`` file.
    keep_unlabelled : bool
        Keep points whose label starts with ``*`` (Nexus' unlabelled
        trajectories); dropped by default.
    subject : str, optional
        The Vicon subject whose markers to read when labels carry several
        subject prefixes (``Name:RKNE``); required then.

    Returns
    -------
    MarkerTrial
        Positions (F, M, 3) in metres, NaN where a marker was not seen.
        ``extra`` holds ``subject`` (label prefix, if any), ``first_frame`` and
        ``units_in_file``.

    Raises
    ------
    InputError
        Unreadable or truncated file, frame count disagreeing with the header,
        unknown length unit, no markers, a duplicated label, several subjects
        without `subject`, non-finite valid samples, coordinates beyond
        `MAX_COORDINATE_M`.
    """
    c3d = open_c3d(path)
    try:
        return _trial_from_c3d(c3d, path, keep_unlabelled, subject)
    except InputError:
        raise
    except (IndexError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise _corrupt_parameters(path, exc) from None


def _trial_from_c3d(c3d, path, keep_unlabelled: bool, subject: str | None) -> MarkerTrial:
    point = c3d["parameters"]["POINT"]
    unit = str(np.ravel(_param(point, "UNITS", ["mm"]))[0]).strip()
    if unit.lower() not in _LENGTH:
        raise InputError(path, f"unknown POINT:UNITS {unit!r} (expected mm, cm or m)")
    scale = _LENGTH[unit.lower()]
    labels = _labels(c3d)
    outputs = _output_names(point)
    pos, rate = _positions(c3d, path)
    # Nexus prefixes labels with "Subject:" when several subjects share a file.
    cand = []
    for i, lab in enumerate(labels):
        if lab in outputs or lab.split(":")[-1] in outputs:
            continue
        if lab.startswith("*") and not keep_unlabelled:
            continue
        prefix, _, name = lab.rpartition(":")
        if name:
            cand.append((i, prefix or None, name))
    prefixes = sorted({p for _, p, _ in cand if p})
    if subject is not None:
        if subject not in prefixes:
            raise InputError(path, f"no markers of subject {subject!r} (subjects in the file: "
                                   f"{', '.join(prefixes) or 'none named'})")
        cand = [c for c in cand if c[1] == subject]
    elif len(prefixes) > 1:
        raise InputError(path, f"markers of {len(prefixes)} subjects ({', '.join(prefixes)}): choose one "
                               "(--subject-name / read_c3d(subject=...))")
    names, keep, seen = [], [], {}
    for i, prefix, name in cand:
        if name in seen:
            raise InputError(path, f"marker label {name!r} is given twice (points {seen[name] + 1} and {i + 1}): "
                                   "which trajectory is the marker is unknown")
        seen[name] = i
        names.append(name)
        keep.append(i)
    if not names:
        raise InputError(path, "no marker trajectories in the file")
    subject = subject if subject is not None else (prefixes[0] if prefixes else None)
    first = int(np.ravel(c3d["header"]["points"].get("first_frame", 0))[0])
    time = (np.arange(pos.shape[0]) + first) / rate
    extra = {"subject": subject, "first_frame": first, "units_in_file": unit}
    xyz = pos[:, keep] * scale
    with np.errstate(invalid="ignore"):
        far = np.abs(xyz) > MAX_COORDINATE_M
    if far.any():
        f, m, _ = (int(v[0]) for v in np.nonzero(far))
        raise InputError(path, f"marker {names[m]} at frame {f + 1} is {float(np.nanmax(np.abs(xyz[f, m]))):.3g} m from "
                               f"the lab origin (bound {MAX_COORDINATE_M:g} m): corrupt data or wrong POINT:UNITS")
    return MarkerTrial(tuple(names), xyz, rate, time, os.fspath(path), extra)


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
    c3d = open_c3d(path)
    try:
        return _outputs_from_c3d(c3d, path)
    except InputError:
        raise
    except (IndexError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise _corrupt_parameters(path, exc) from None


def _outputs_from_c3d(c3d, path) -> C3DOutputs:
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
        runs = true_runs(missing)
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
