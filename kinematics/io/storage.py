"""OpenSim text files: marker trajectories (TRC) and time tables (MOT, STO).

Formats
-------
TRC
    Tab-separated.  Line 1 ``PathFileType 4 (X/Y/Z) <name>``; line 2 the header
    keys (``DataRate CameraRate NumFrames NumMarkers Units OrigDataRate
    OrigDataStartFrame OrigNumFrames``), line 3 their values; line 4
    ``Frame# Time`` then each marker name followed by two empty fields; line 5
    the ``X1 Y1 Z1 X2 ...`` sub-labels; then (after an optional blank line) one
    row per frame.  An empty field is a gap.  Coordinates are in ``Units``
    (``mm``, ``cm`` or ``m``); `read_trc` converts them to metres.
MOT / STO
    A header of free lines and ``key=value`` lines up to ``endheader``; then a
    tab-separated line of column labels starting with ``time``; then one
    whitespace-separated row of numbers per sample.  ``inDegrees=yes`` means
    the *rotational* columns are in degrees (OpenSim does not say which columns
    are rotational; the model does), translations are always metres.  Without
    an ``inDegrees`` key the values are taken as SI (OpenSim's own default).

Readers refuse what they cannot read correctly: a TRC coordinate beyond
`MAX_COORDINATE_M` (after unit conversion) or infinite, a MOT/STO value beyond
`MAX_TABLE_VALUE` or infinite (an empty field or ``NaN`` is a gap), a data
rate that is not a positive number below 100 kHz.

Inside the project everything is SI (metres, radians, seconds): readers convert
at this boundary, writers convert back to what OpenSim expects and state the
units in the header.  Every write is atomic (`lowerlimb.atomic.atomic_path`).
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from lowerlimb.atomic import write_text
from lowerlimb.errors import InputError
from kinematics.io.markers import MAX_COORDINATE_M, MAX_RATE_HZ, MarkerTrial

__all__ = [
    "TRC_UNITS",
    "read_trc",
    "write_trc",
    "Table",
    "read_mot",
    "read_sto",
    "write_mot",
    "write_sto",
    "guess_rotational",
]

#: largest plausible |value| in a MOT/STO table (degrees, m, N, N m, W of human movement are far below)
MAX_TABLE_VALUE = 1e7

#: Length units a TRC header may declare, as metres per unit.
TRC_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}

_UNIT_ALIASES = {"mm": "mm", "millimeters": "mm", "millimetres": "mm", "cm": "cm", "centimeters": "cm",
                 "centimetres": "cm", "m": "m", "meters": "m", "metres": "m"}

_TRC_KEYS = ("DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units",
             "OrigDataRate", "OrigDataStartFrame", "OrigNumFrames")


def _read_lines(path: str | os.PathLike) -> list[str]:
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "file not found")
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        try:
            text = p.read_text(encoding="latin-1")
        except Exception as exc:  # pragma: no cover - latin-1 decodes any byte
            raise InputError(p, f"cannot read text ({exc})") from None
    except OSError as exc:
        raise InputError(p, f"cannot read ({exc.strerror})") from None
    if "\x00" in text:
        raise InputError(p, "binary file, not a text OpenSim file")
    return text.splitlines()


def _to_float(tok: str, path, line_no: int, what: str) -> float:
    tok = tok.strip()
    if tok == "":
        return math.nan
    try:
        return float(tok)
    except ValueError:
        raise InputError(path, f"line {line_no}: {what} {tok!r} is not a number") from None


# --------------------------------------------------------------------------- TRC
def read_trc(path: str | os.PathLike) -> MarkerTrial:
    """Read an OpenSim/Motion-Lab TRC file into a `MarkerTrial` (metres).

    Parameters
    ----------
    path : path-like
        The ``.trc`` file.

    Returns
    -------
    MarkerTrial
        ``positions`` (F, M, 3) in metres, NaN where a field is empty (gap);
        ``time`` (F,) s from the ``Time`` column; ``rate`` = ``DataRate`` (Hz).
        ``extra`` holds ``frame_numbers`` (F,), ``units`` (the file's unit)
        and ``header`` (the header key/values as strings).

    Raises
    ------
    InputError
        Missing header lines or keys, unknown ``Units``, marker count or frame
        count disagreeing with the header, non-numeric fields, rows longer than
        the header allows, non-increasing time.
    """
    path = Path(path)
    lines = _read_lines(path)
    if len(lines) < 5:
        raise InputError(path, f"TRC file has {len(lines)} lines; the 5 header lines are missing")
    if not lines[0].startswith("PathFileType"):
        raise InputError(path, "not a TRC file (line 1 does not start with 'PathFileType')")
    keys = [k.strip() for k in lines[1].split("\t")]
    vals = [v.strip() for v in lines[2].split("\t")]
    header = {k: v for k, v in zip(keys, vals) if k}
    for key in ("DataRate", "NumFrames", "NumMarkers", "Units"):
        if key not in header:
            raise InputError(path, f"TRC header lacks the {key} field (line 2)")
    units = _UNIT_ALIASES.get(header["Units"].strip().lower(), header["Units"].strip())
    if units not in TRC_UNITS:
        raise InputError(path, f"TRC Units {units!r} unknown (expected one of {', '.join(TRC_UNITS)})")
    scale = TRC_UNITS[units]
    try:
        rate = float(header["DataRate"])
        n_frames_hdr = int(float(header["NumFrames"]))
        n_markers_hdr = int(float(header["NumMarkers"]))
    except ValueError:
        raise InputError(path, "TRC header DataRate/NumFrames/NumMarkers are not numbers") from None
    if not (0 < rate <= MAX_RATE_HZ):
        raise InputError(path, f"TRC DataRate {header['DataRate']!r} must be a positive number up to {MAX_RATE_HZ:g} Hz")

    label_fields = lines[3].split("\t")
    if len(label_fields) < 2 or label_fields[0].strip() != "Frame#" or label_fields[1].strip().lower() != "time":
        raise InputError(path, "TRC line 4 must start with 'Frame#<tab>Time'")
    names = tuple(f.strip() for f in label_fields[2:] if f.strip())
    if len(names) != n_markers_hdr:
        raise InputError(path, f"TRC header says {n_markers_hdr} markers but line 4 names {len(names)}")
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputError(path, f"duplicate marker names {dup}")
    n_cols = 2 + 3 * len(names)

    frames, rows, line_nos = [], [], []
    for i in range(5, len(lines)):
        line = lines[i]
        if not line.strip():
            continue
        toks = line.split("\t")
        if len(toks) > n_cols:
            if any(t.strip() for t in toks[n_cols:]):
                raise InputError(path, f"line {i + 1}: {len(toks)} fields, more than the {n_cols} of {len(names)} markers")
            toks = toks[:n_cols]
        elif len(toks) < n_cols:
            # Some writers drop the empty fields of trailing gaps.
            toks = toks + [""] * (n_cols - len(toks))
        frame = _to_float(toks[0], path, i + 1, "frame number")
        row = [_to_float(t, path, i + 1, "value") for t in toks[1:]]
        frames.append(frame)
        rows.append(row)
        line_nos.append(i + 1)
    if not rows:
        raise InputError(path, "TRC file has no data rows")
    data = np.asarray(rows, dtype=float)
    if len(rows) != n_frames_hdr:
        raise InputError(path, f"TRC header says {n_frames_hdr} frames but the file has {len(rows)} data rows")
    time = data[:, 0]
    if not np.all(np.isfinite(time)):
        raise InputError(path, "TRC Time column has empty or non-numeric entries")
    if len(time) > 1 and np.any(np.diff(time) <= 0):
        k = int(np.argmax(np.diff(time) <= 0))
        raise InputError(path, f"TRC time does not increase at frame {k + 2} ({time[k]} -> {time[k + 1]} s)")
    positions = data[:, 1:].reshape(len(rows), len(names), 3) * scale
    with np.errstate(invalid="ignore"):
        far = np.abs(positions) > MAX_COORDINATE_M
    if far.any():
        f, m, _ = (int(v[0]) for v in np.nonzero(far))
        top = float(np.nanmax(np.abs(positions[np.isfinite(positions)])))
        hint = "corrupt value or wrong Units"
        if units != "mm" and top / scale * 1e-3 <= MAX_COORDINATE_M:
            hint = f"the coordinates look like millimetres (header Units={units}): fix the Units line of the TRC header"
        raise InputError(path, f"line {line_nos[f]}: marker {names[m]} is "
                               f"{float(np.nanmax(np.abs(positions[f, m]))):.3g} m from the lab origin (bound "
                               f"{MAX_COORDINATE_M:g} m): {hint}")
    # A gap is a whole missing marker: a partially empty triplet is also a gap.
    partial = np.isnan(positions).any(axis=2)
    positions[partial] = np.nan
    return MarkerTrial(
        names=names,
        positions=positions,
        rate=rate,
        time=time,
        source=str(path),
        extra={"frame_numbers": np.asarray(frames), "units": units, "header": header},
    )


def _fmt(x: float, spec: str) -> str:
    return "" if not math.isfinite(x) else format(x, spec)


def write_trc(path: str | os.PathLike, trial: MarkerTrial, units: str = "mm") -> Path:
    """Write `trial` (metres) as a TRC file in `units` (``mm``, ``cm`` or ``m``).

    Gaps (NaN) become empty fields; the header records ``Units``, the rate and
    the frame and marker counts.  Frame numbers start at 1.  Atomic.

    Returns
    -------
    Path
        `path`.
    """
    path = Path(path)
    if units not in TRC_UNITS:
        raise InputError(path, f"TRC units {units!r} unknown (expected one of {', '.join(TRC_UNITS)})")
    for n in trial.names:
        if not n or any(c in n for c in "\t\r\n"):
            raise InputError(path, f"marker name {n!r} cannot be written to a TRC file")
    scale = 1.0 / TRC_UNITS[units]
    spec = {"mm": ".6f", "cm": ".7f", "m": ".9f"}[units]
    F, M = trial.positions.shape[:2]
    rate = float(trial.rate)
    out = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "\t".join(_TRC_KEYS),
        f"{rate:.2f}\t{rate:.2f}\t{F}\t{M}\t{units}\t{rate:.2f}\t1\t{F}",
        "\t".join(["Frame#", "Time"] + [f"{n}\t\t" for n in trial.names]).rstrip("\t") + "\t\t",
        "\t\t" + "\t".join(f"X{j + 1}\tY{j + 1}\tZ{j + 1}" for j in range(M)),
        "",
    ]
    pos = trial.positions * scale
    for f in range(F):
        vals = "\t".join(_fmt(v, spec) for v in pos[f].ravel())
        # Trailing tab as OpenSim/Vicon files have: OpenSim drops one trailing empty field.
        out.append(f"{f + 1}\t{trial.time[f]:.6f}\t{vals}\t")
    return write_text(path, "\n".join(out) + "\n")


# --------------------------------------------------------------------- MOT / STO
@dataclass(frozen=True)
class Table:
    """A time table of an OpenSim ``.mot`` / ``.sto`` file, values as in the file.

    Attributes
    ----------
    columns : tuple of str, length C
        Column labels, without ``time``.
    time : ndarray, shape (F,), seconds (or the file's own abscissa)
    values : ndarray, shape (F, C)
        As stored: rotational columns in degrees when `in_degrees`, else radians;
        translations in metres.
    in_degrees : bool
        The file's ``inDegrees`` flag (False when absent).
    source : str or None
        File the table came from (error messages).
    header : dict
        The ``key=value`` header entries (strings) plus ``"name"`` (first line).
    """

    columns: tuple[str, ...]
    time: np.ndarray
    values: np.ndarray
    in_degrees: bool = False
    source: str | None = None
    header: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        vals = np.asarray(self.values, dtype=float)
        t = np.asarray(self.time, dtype=float)
        cols = tuple(self.columns)
        if vals.ndim != 2 or vals.shape != (t.shape[0], len(cols)):
            raise InputError(self.source, f"table values of shape {vals.shape} do not match {t.shape[0]} times x {len(cols)} columns")
        if len(set(cols)) != len(cols):
            dup = sorted({c for c in cols if cols.count(c) > 1})
            raise InputError(self.source, f"duplicate column labels {dup}")
        object.__setattr__(self, "values", vals)
        object.__setattr__(self, "time", t)
        object.__setattr__(self, "columns", cols)

    @property
    def n_frames(self) -> int:
        return self.values.shape[0]

    def index(self, name: str) -> int:
        try:
            return self.columns.index(name)
        except ValueError:
            raise InputError(self.source, f"column {name!r} is missing (columns: {', '.join(self.columns)})") from None

    def column(self, name: str) -> np.ndarray:
        """Values of one column, shape (F,), in the file's units."""
        return self.values[:, self.index(name)]

    def select(self, names: Sequence[str]) -> np.ndarray:
        """Several columns as an array of shape (F, len(names)); one error lists every missing name."""
        missing = [n for n in names if n not in self.columns]
        if missing:
            raise InputError(self.source, f"missing columns: {', '.join(missing)}")
        return self.values[:, [self.columns.index(n) for n in names]]

    def to_radians(self, rotational_names: Iterable[str]) -> "Table":
        """The table in SI units: the listed rotational columns in radians.

        Names absent from the table are ignored (a model's full list of
        rotational coordinates can be passed).  A table already in radians is
        returned unchanged; the result has ``in_degrees=False``.
        """
        if not self.in_degrees:
            return self
        rot = set(rotational_names)
        vals = self.values.copy()
        idx = [j for j, c in enumerate(self.columns) if c in rot]
        vals[:, idx] = np.radians(vals[:, idx])
        header = dict(self.header)
        header["inDegrees"] = "no"
        return Table(self.columns, self.time.copy(), vals, False, self.source, header)


def guess_rotational(names: Iterable[str]) -> set[str]:
    """Columns that look rotational by OpenSim naming conventions.

    A name is translational when it ends in ``_tx``, ``_ty``, ``_tz`` (also
    before a ``_r``/``_l`` side suffix) or names a translation direction
    (``_ant``, ``_sup``, ``_lat`` ...); every other name is taken as
    rotational.  Use the model's coordinate types when a model is available.
    """
    trans = re.compile(r"(^|_)(t[xyz]|trans\w*|ant|sup|lat|med|post|inf|[xyz])(_[rl])?$")
    return {n for n in names if not trans.search(n)}


def _read_table(path: str | os.PathLike, kind: str) -> Table:
    path = Path(path)
    lines = _read_lines(path)
    end = next((i for i, ln in enumerate(lines) if ln.strip().lower() == "endheader"), None)
    if end is None:
        raise InputError(path, f"{kind} file has no 'endheader' line")
    header: dict[str, str] = {}
    for i, ln in enumerate(lines[:end]):
        s = ln.strip()
        if "=" in s:
            k, v = s.split("=", 1)
            header[k.strip()] = v.strip()
        elif i == 0 and s:
            header["name"] = s
    flag = header.get("inDegrees", "no").strip().lower()
    if flag not in ("yes", "no"):
        raise InputError(path, f"inDegrees={header['inDegrees']!r} must be yes or no")
    in_degrees = flag == "yes"

    k = end + 1
    while k < len(lines) and not lines[k].strip():
        k += 1
    if k >= len(lines):
        raise InputError(path, f"{kind} file has no column labels after endheader")
    label_line = lines[k]
    labels = [s.strip() for s in (label_line.split("\t") if "\t" in label_line else label_line.split())]
    labels = [s for s in labels if s]
    if not labels or labels[0].lower() != "time":
        raise InputError(path, f"line {k + 1}: the first column label must be 'time' (got {labels[0] if labels else 'nothing'!r})")
    columns = labels[1:]
    if not columns:
        raise InputError(path, f"{kind} file has a time column only")
    rows = []
    for i in range(k + 1, len(lines)):
        s = lines[i].strip()
        if not s:
            continue
        toks = s.split()
        if len(toks) != len(labels):
            raise InputError(path, f"line {i + 1}: {len(toks)} values for {len(labels)} column labels")
        rows.append([_to_float(t, path, i + 1, "value") for t in toks])
    if not rows:
        raise InputError(path, f"{kind} file has no data rows")
    data = np.asarray(rows, dtype=float)
    if "nRows" in header:
        try:
            n_hdr = int(header["nRows"])
        except ValueError:
            raise InputError(path, f"nRows={header['nRows']!r} is not an integer") from None
        if n_hdr != len(rows):
            raise InputError(path, f"header says nRows={n_hdr} but the file has {len(rows)} data rows")
    if "nColumns" in header:
        try:
            c_hdr = int(header["nColumns"])
        except ValueError:
            raise InputError(path, f"nColumns={header['nColumns']!r} is not an integer") from None
        if c_hdr != len(labels):
            raise InputError(path, f"header says nColumns={c_hdr} but line {k + 1} has {len(labels)} labels")
    time = data[:, 0]
    if not np.all(np.isfinite(time)):
        raise InputError(path, "the time column has non-finite entries")
    with np.errstate(invalid="ignore"):
        far = np.abs(data) > MAX_TABLE_VALUE
    if far.any():
        r, c = (int(v[0]) for v in np.nonzero(far))
        raise InputError(path, f"row {r + 1}, column {labels[c]!r}: value {data[r, c]:.3g} beyond the bound "
                               f"{MAX_TABLE_VALUE:g} (corrupt or not a table of human movement)")
    if len(time) > 1 and np.any(np.diff(time) < 0):
        j = int(np.argmax(np.diff(time) < 0))
        raise InputError(path, f"time decreases at row {j + 2} ({time[j]} -> {time[j + 1]})")
    return Table(tuple(columns), time, data[:, 1:], in_degrees, str(path), header)


def read_mot(path: str | os.PathLike) -> Table:
    """Read an OpenSim ``.mot`` file (e.g. IK coordinates) as a `Table`.

    Values are returned as stored; call ``table.to_radians(names)`` with the
    rotational coordinate names to get SI units.

    Raises
    ------
    InputError
        No ``endheader``, first label not ``time``, ragged rows, non-numeric
        values, ``nRows``/``nColumns`` disagreeing with the data, decreasing time.
    """
    return _read_table(path, "MOT")


def read_sto(path: str | os.PathLike) -> Table:
    """Read an OpenSim ``.sto`` storage file as a `Table` (same parser as `read_mot`)."""
    return _read_table(path, "STO")


def _check_table_args(path, names, time, values):
    names = list(names)
    for n in names:
        if not n or any(c.isspace() for c in n):
            raise InputError(path, f"column label {n!r} must be non-empty without spaces or tabs")
    if len(set(names)) != len(names):
        raise InputError(path, "duplicate column labels")
    if any(n.lower() == "time" for n in names):
        raise InputError(path, "'time' is written automatically; do not pass it as a column")
    time = np.asarray(time, dtype=float).ravel()
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        values = values[:, None]
    if values.shape != (time.shape[0], len(names)):
        raise InputError(path, f"values of shape {values.shape} do not match {time.shape[0]} times x {len(names)} names")
    return names, time, values


def _write_table(path: Path, first_line: str, keys: list[str], free_lines: list[str],
                 names: list[str], time: np.ndarray, values: np.ndarray) -> Path:
    out = [first_line] + keys + free_lines + ["endheader", "\t".join(["time"] + names)]
    for t, row in zip(time, values):
        out.append("\t".join([f"{t:.8f}"] + [repr(float(v)) if not math.isfinite(v) else f"{v:.10g}" for v in row]))
    return write_text(path, "\n".join(out) + "\n")


def write_mot(path: str | os.PathLike, names: Sequence[str], time, values, in_degrees: bool = True,
              rotational: Iterable[str] | None = None, name: str = "Coordinates") -> Path:
    """Write generalized coordinates as an OpenSim ``.mot`` file.

    Parameters
    ----------
    names : sequence of str, length C
        Column labels (coordinate names), without ``time``.
    time : array, shape (F,), seconds
    values : array, shape (F, C)
        SI values: radians for rotational columns, metres otherwise.
    in_degrees : bool
        Write the rotational columns in degrees (``inDegrees=yes``), as
        OpenSim IK does.
    rotational : iterable of str
        The rotational column names.  Required when `in_degrees` is True
        (OpenSim files do not say which columns are angles); see
        `guess_rotational` for a name-based guess.
    name : str
        First header line (OpenSim uses ``Coordinates``).

    Returns
    -------
    Path
        `path`, written atomically.
    """
    path = Path(path)
    names, time, values = _check_table_args(path, names, time, values)
    if in_degrees and rotational is None:
        raise ValueError("write_mot(in_degrees=True) needs the set of rotational column names")
    rot = set(rotational or ())
    unknown = sorted(rot - set(names))
    if unknown:
        raise InputError(path, f"rotational columns {unknown} are not among the names")
    vals = values.copy()
    if in_degrees:
        idx = [j for j, n in enumerate(names) if n in rot]
        vals[:, idx] = np.degrees(vals[:, idx])
    keys = ["version=1", f"nRows={len(time)}", f"nColumns={len(names) + 1}",
            f"inDegrees={'yes' if in_degrees else 'no'}"]
    free = ["", "Units are S.I. units (second, meters, Newtons, ...)",
            "Angles are in degrees." if in_degrees else "Angles are in radians.", ""]
    return _write_table(path, name, keys, free, names, time, vals)


def write_sto(path: str | os.PathLike, names: Sequence[str], time, values,
              header_extra: Mapping[str, object] | Sequence[str] | None = None,
              name: str | None = None, in_degrees: bool = False) -> Path:
    """Write an OpenSim ``.sto`` storage file (values written as given).

    Parameters
    ----------
    names : sequence of str, length C
    time : array, shape (F,)
    values : array, shape (F, C)
        Written unchanged; by default SI (radians, metres) with ``inDegrees=no``.
    header_extra : mapping or sequence of str, optional
        Extra header entries: a mapping is written as ``key=value`` lines, a
        sequence as free text lines (e.g. the frame the values refer to).
    name : str, optional
        First header line; defaults to the file stem.
    in_degrees : bool
        Value of the ``inDegrees`` flag (the caller converted the angles).
    """
    path = Path(path)
    names, time, values = _check_table_args(path, names, time, values)
    keys = ["version=1", f"nRows={len(time)}", f"nColumns={len(names) + 1}",
            f"inDegrees={'yes' if in_degrees else 'no'}"]
    free: list[str] = []
    if header_extra:
        items = (f"{k}={v}" for k, v in header_extra.items()) if isinstance(header_extra, Mapping) else header_extra
        for line in items:
            line = str(line)
            if "\n" in line or "\r" in line or line.strip().lower() == "endheader":
                raise InputError(path, f"header line {line!r} cannot be written")
            key = line.split("=", 1)[0].strip() if "=" in line else None
            if key in ("version", "nRows", "nColumns", "inDegrees", "DataType"):
                raise InputError(path, f"header key {key!r} is written automatically")
            free.append(line)
    free.append("Units are S.I. units (second, meters, Newtons, ...)")
    free.append("Angles are in degrees." if in_degrees else "Angles are in radians.")
    return _write_table(path, name or path.stem, keys, free, names, time, values)
