"""External loads as OpenSim files: the ground-reaction ``.mot`` and its ExternalLoads ``.xml``.

Layout (as OpenSim's example ``subject01_walk1_grf.mot``): per load a prefix
``P`` (``""``, ``"1_"``, ...) and the columns

    P ground_force_vx vy vz   (N, ground frame)
    P ground_force_px py pz   (m, ground frame: the centre of pressure)
    P ground_torque_x y z     (N m, ground frame: the free moment about the CoP)

(all force/point columns first, then the torques), and an ``ExternalLoads``
XML naming, per load, the body it is applied to and the three identifiers;
force and point expressed in ``ground``.  Frames where a load is absent
carry zeros (what OpenSim expects; a zero force at any point is no load).

Lab frames differ from OpenSim's ground (Y up): `ExternalLoad.rotated`
re-expresses a load, e.g. ``LAB_TO_OPENSIM`` for a Z-up C3D lab (x forward
kept, Z up -> Y up).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lowerlimb.atomic import write_text
from lowerlimb.errors import InputError
from kinematics.io.storage import read_mot, write_sto

__all__ = [
    "LAB_TO_OPENSIM",
    "axis_permutation",
    "z_up_from",
    "ExternalLoad",
    "loads_from_plates",
    "read_external_loads",
    "write_external_loads",
]

#: Rotation from a Z-up C3D lab (X forward, Z up) to OpenSim's ground (X forward, Y up, Z right).
LAB_TO_OPENSIM = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class ExternalLoad:
    """One external force on one body over time, ground frame, SI.

    Attributes
    ----------
    name : str
    body : str
        Body the load is applied to (e.g. ``calcn_r``).
    time : ndarray (F,), s
    force : ndarray (F, 3), N
    point : ndarray (F, 3), m
        Point of application (CoP) in ground.
    torque : ndarray (F, 3), N m
        Free moment about `point`.
    """

    name: str
    body: str
    time: np.ndarray
    force: np.ndarray
    point: np.ndarray
    torque: np.ndarray

    def at(self, times) -> ExternalLoad:
        """The load linearly interpolated at `times` (zero outside the data's span)."""
        t = np.asarray(times, float)

        def interp(a):
            return np.column_stack([np.interp(t, self.time, a[:, i], left=0.0, right=0.0) for i in range(3)])

        return ExternalLoad(self.name, self.body, t, interp(self.force), interp(self.point), interp(self.torque))


def _read_data(path):
    """The .mot as a `kinematics.io.storage.Table`, numeric block converted by numpy in one call.

    Ground-reaction files are sampled at the analog rate (tens of thousands of
    values); any irregularity (ragged rows, bad numbers, a header that
    disagrees) falls back to `read_mot`, which names the problem.
    """
    from kinematics.io.storage import Table

    try:
        text = Path(path).read_text(encoding="utf-8", errors="strict")
        lines = text.splitlines()
        end = next(i for i, ln in enumerate(lines) if ln.strip().lower() == "endheader")
        header = {}
        for ln in lines[:end]:
            if "=" in ln:
                k, v = ln.split("=", 1)
                header[k.strip()] = v.strip()
        k = end + 1
        while not lines[k].strip():
            k += 1
        labels = [x for x in (lines[k].split("\t") if "\t" in lines[k] else lines[k].split()) if x.strip()]
        labels = [x.strip() for x in labels]
        rows = [ln for ln in lines[k + 1:] if ln.strip()]
        if any(len(r.split()) != len(labels) for r in rows):
            raise ValueError("ragged")
        data = np.array(" ".join(rows).split(), dtype=float).reshape(len(rows), len(labels))
        ok = (labels[0].lower() == "time" and data.shape[1] == len(labels) and np.all(np.isfinite(data[:, 0]))
              and np.all(np.diff(data[:, 0]) >= 0) and int(header.get("nRows", data.shape[0])) == data.shape[0]
              and int(header.get("nColumns", len(labels))) == len(labels)
              and header.get("inDegrees", "no").lower() in ("yes", "no"))
        if ok:
            return Table(tuple(labels[1:]), data[:, 0], data[:, 1:], header.get("inDegrees", "no").lower() == "yes",
                         str(path), header)
    except (OSError, ValueError, StopIteration, IndexError, UnicodeDecodeError):
        pass
    return read_mot(path)


def _text(el, tag: str, path) -> str:
    child = el.find(tag)
    if child is None or child.text is None or not child.text.strip():
        raise InputError(path, f"ExternalForce {el.get('name')!r} has no <{tag}>")
    return child.text.strip()


def read_external_loads(xml_path: str | os.PathLike, mot_path: str | os.PathLike | None = None) -> list[ExternalLoad]:
    """Read an OpenSim ExternalLoads ``.xml`` and its data ``.mot`` (the xml's ``<datafile>`` by default).

    Only forces and points expressed in ``ground`` are accepted (the layout
    OpenSim's tools and this project write); another frame is an InputError,
    as are missing columns and disabled-only files.
    """
    from kinematics.io.opensim_io import read_xml

    xml_path = Path(xml_path)
    root = read_xml(xml_path, "ExternalLoads file not found", "not an ExternalLoads XML file")
    el = root if root.tag == "ExternalLoads" else root.find("ExternalLoads")
    if el is None:
        raise InputError(xml_path, "no <ExternalLoads> element")
    if mot_path is None:
        df = el.find("datafile")
        if df is None or not (df.text or "").strip():
            raise InputError(xml_path, "no <datafile>; give the ground-reaction .mot explicitly")
        mot_path = xml_path.parent / df.text.strip()
        if not Path(mot_path).is_file():
            raise InputError(xml_path, f"its datafile {df.text.strip()!r} is not next to it")
    table = _read_data(mot_path)
    loads = []
    for f in el.iter("ExternalForce"):
        dis = f.find("isDisabled")
        if dis is not None and (dis.text or "").strip().lower() == "true":
            continue
        ap = f.find("appliesForce")
        if ap is not None and (ap.text or "").strip().lower() == "false":
            continue
        body = _text(f, "applied_to_body", xml_path)
        for tag in ("force_expressed_in_body", "point_expressed_in_body"):
            child = f.find(tag)
            frame = (child.text or "ground").strip() if child is not None else "ground"
            if frame != "ground":
                raise InputError(xml_path, f"ExternalForce {f.get('name')!r}: {tag} {frame!r}; only 'ground' is supported")
        fid = _text(f, "force_identifier", xml_path)
        pid = _text(f, "point_identifier", xml_path)
        tid_el = f.find("torque_identifier")
        tid = (tid_el.text or "").strip() if tid_el is not None else ""
        force = table.select([fid + c for c in "xyz"])
        point = table.select([pid + c for c in "xyz"])
        torque = table.select([tid + c for c in "xyz"]) if tid else np.zeros_like(force)
        for ident, values in ((fid, force), (pid, point), (tid, torque)):
            bad = np.argwhere(~np.isfinite(values))
            if len(bad):   # a gap in a load cannot be interpolated into a force: refuse, do not guess
                row, col = bad[0]
                raise InputError(mot_path, f"column {ident + 'xyz'[col]!r} is not finite at row {row + 1} "
                                           f"(t = {table.time[row]:.4f} s); {len(bad)} such value(s)")
        loads.append(ExternalLoad(f.get("name") or fid, body, table.time.copy(), force, point, torque))
    if not loads:
        raise InputError(xml_path, "no enabled ExternalForce")
    return loads


def write_external_loads(directory: str | os.PathLike, stem: str, loads: Sequence[ExternalLoad],
                         frame: str = "ground") -> tuple[Path, Path]:
    """Write ``<stem>.mot`` (ground reactions) and ``<stem>.xml`` (ExternalLoads) into `directory`.

    All loads must share one time base.  The .mot header states the units
    and the frame; the .xml refers to the .mot by name.
    """
    loads = list(loads)
    if not loads:
        raise InputError(directory, "no load to write")
    t = loads[0].time
    for ld in loads[1:]:
        if ld.time.shape != t.shape or not np.allclose(ld.time, t):
            raise InputError(directory, f"load {ld.name!r} has another time base than {loads[0].name!r}")
    prefixes = [("" if i == 0 else f"{i}_") for i in range(len(loads))]
    names, cols = [], []
    for p, ld in zip(prefixes, loads):
        names += [f"{p}ground_force_v{c}" for c in "xyz"] + [f"{p}ground_force_p{c}" for c in "xyz"]
        cols += [np.nan_to_num(ld.force), np.nan_to_num(ld.point)]
    for p, ld in zip(prefixes, loads):
        names += [f"{p}ground_torque_{c}" for c in "xyz"]
        cols.append(np.nan_to_num(ld.torque))
    directory = Path(directory)
    mot = directory / f"{stem}.mot"
    xml = directory / f"{stem}.xml"
    bodies = ", ".join(f"{p or '(no prefix)'} -> {ld.body}" for p, ld in zip(prefixes, loads))
    write_sto(mot, names, t, np.hstack(cols), name=mot.name,
              header_extra=[f"Ground reactions on the subject, expressed in {frame} (OpenSim: Y up);",
                            "force N, point (centre of pressure) m, torque (free moment about the point) N m;",
                            f"zeros where a load is absent. Loads: {bodies}"])
    forces = []
    for i, (p, ld) in enumerate(zip(prefixes, loads)):
        forces.append(f"""\t\t\t<ExternalForce name="{_xml_escape(ld.name or f'ExternalForce_{i + 1}')}">
\t\t\t\t<applied_to_body>{_xml_escape(ld.body)}</applied_to_body>
\t\t\t\t<force_expressed_in_body>ground</force_expressed_in_body>
\t\t\t\t<point_expressed_in_body>ground</point_expressed_in_body>
\t\t\t\t<force_identifier>{p}ground_force_v</force_identifier>
\t\t\t\t<point_identifier>{p}ground_force_p</point_identifier>
\t\t\t\t<torque_identifier>{p}ground_torque_</torque_identifier>
\t\t\t\t<data_source_name>{_xml_escape(mot.name)}</data_source_name>
\t\t\t</ExternalForce>""")
    text = f"""<?xml version="1.0" encoding="UTF-8"?>
<!-- Ground reactions on the subject: force N and centre of pressure m in ground ({frame}), free torque N m. -->
<OpenSimDocument Version="40000">
\t<ExternalLoads name="{_xml_escape(stem)}">
\t\t<objects>
{chr(10).join(forces)}
\t\t</objects>
\t\t<groups />
\t\t<datafile>{_xml_escape(mot.name)}</datafile>
\t</ExternalLoads>
</OpenSimDocument>
"""
    write_text(xml, text)
    return mot, xml


def _extend(plate, a: int, b: int, others) -> tuple[int, int]:
    """Grow a loaded interval [a, b) over the adjacent frames still above the plate's noise.

    The noise level is the unloaded frames' median normal force plus three
    robust standard deviations (at least 2 N); the interval never grows into
    another interval of the same plate.
    """
    fn = plate.force @ plate.normal
    free = ~plate.loaded
    if free.sum() >= 10:
        base = float(np.median(fn[free]))
        sd = 1.4826 * float(np.median(np.abs(fn[free] - base)))
    else:
        base, sd = 0.0, 0.0
    level = base + max(3.0 * sd, 2.0)
    lo = max([s for _, s in others if s <= a], default=0)
    hi = min([s for s, _ in others if s >= b], default=len(fn))
    while a > lo and fn[a - 1] > level:
        a -= 1
    while b < hi and fn[b] > level:
        b += 1
    return a, b


def _xml_escape(s: str) -> str:
    return str(s).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")


def z_up_from(up) -> np.ndarray:
    """A proper rotation (a signed permutation) taking the lab vertical `up` (a signed lab axis) to +Z; the
    identity for +Z, else keeping the first lab axis that is horizontal."""
    u = np.asarray(up, float)
    return axis_permutation(u, np.array([0.0, 0.0, 1.0]))


def axis_permutation(up_from: np.ndarray, up_to: np.ndarray) -> np.ndarray:
    """The signed permutation R (det +1) with ``R @ up_from = up_to`` that maps the first horizontal axis of
    the source frame to the first horizontal axis of the target (X to X when both have X horizontal).

    Raises InputError when a vertical is not along a signed axis.
    """
    out = []
    for u in (np.asarray(up_from, float), np.asarray(up_to, float)):
        k = int(np.argmax(np.abs(u)))
        if not np.isclose(abs(u[k]), np.linalg.norm(u), atol=1e-6):
            raise InputError("vertical", f"{u.tolist()} is not along a signed axis")
        e = np.zeros(3)
        e[k] = np.sign(u[k])
        h = np.eye(3)[0 if k != 0 else 1]
        out.append(np.column_stack([h, e, np.cross(h, e)]))
    A, B = out
    return B @ A.T


def loads_from_plates(plates, contacts, bodies=None, rotation=LAB_TO_OPENSIM,
                      up=(0.0, 0.0, 1.0)) -> tuple[list[ExternalLoad], list[str]]:
    """One ExternalLoad per foot from the plates' usable contacts (`kinematics.gait.plate_contacts.assign_feet`).

    Each foot's load is the sum, frame by frame, of the plate wrenches of the
    intervals assigned to it (a foot on two plates at once gets the resultant
    force at the combined CoP).  Each interval is grown over the adjacent
    frames whose normal force is still above the plate's noise (strike and
    push-off under the CoP threshold carry load too); there the point is the
    plate centre and the torque carries the moment, so the wrench is exact.  Intervals that are not usable (two feet,
    CoP outside the plate, no foot) are left out and reported.

    Parameters
    ----------
    bodies : dict side -> body name; default ``{"R": "calcn_r", "L": "calcn_l"}``.
    rotation : (3, 3), lab to the output ground frame.
    up : the lab's vertical (a signed lab axis, `kinematics.gait.lab_frame.LabFrame.up`); the centre of
        pressure is solved on the horizontal plane of the plates, so a lab that is not Z up is first turned Z up.

    Returns
    -------
    (loads, notes)
    """
    bodies = bodies or {"R": "calcn_r", "L": "calcn_l"}
    R = np.asarray(rotation, float)
    Q = z_up_from(up)
    if not np.array_equal(Q, np.eye(3)):
        plates, R = plates.rotated(Q), R @ Q.T
    n = plates.n_frames
    notes = []
    acc = {}
    spans = {}
    for c in contacts:
        if not c.usable:
            notes.append(f"not applied: {c.describe()}")
            continue
        p = plates[c.plate]
        a, b = _extend(p, c.start, c.stop, [(d.start, d.stop) for d in contacts if d.plate == c.plate and d is not c])
        spans.setdefault(c.foot, []).append((a, b, c.plate))
        F = np.zeros((n, 3))
        M = np.zeros((n, 3))
        sl = slice(a, b)
        F[sl] = p.force[sl]
        M[sl] = p.moment[sl] + np.cross(p.centre, p.force[sl])  # moment about the lab origin
        f0, m0 = acc.get(c.foot, (np.zeros((n, 3)), np.zeros((n, 3))))
        acc[c.foot] = (f0 + F, m0 + M)
    loads = []
    # the CoP of the written file is only defined under load; the wrench (F, M) is applied whole
    for side in sorted(acc, key=lambda s: ("R", "L").index(s) if s in ("R", "L") else 2):
        F, M = acc[side]
        nrm = np.array([0.0, 0.0, 1.0])
        fn = F @ nrm
        on = np.zeros(n, bool)
        # point on the horizontal plane of the loaded plates' surface: z from the plates, (x, y) from the moment
        z = np.zeros(n)
        for a, b, k in spans[side]:
            z[a:b] = plates[k].centre[2]
            on[a:b] = True
        on &= np.abs(fn) > 1e-9
        P = np.zeros((n, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            # M_O = P x F + T n with P_z = z: solve the horizontal components
            P[:, 0] = (-M[:, 1] + z * F[:, 0]) / fn
            P[:, 1] = (M[:, 0] + z * F[:, 1]) / fn
        P[:, 2] = z
        T = M - np.cross(P, F)
        T[:, :2] = 0.0
        P[~on] = 0.0
        T[~on] = 0.0
        F[~on] = 0.0
        weak = on & (fn < plates.threshold)  # below the threshold the CoP is unreliable: put it at the plate
        if weak.any():
            for a, b, k in spans[side]:
                sel = weak.copy()
                sel[:a] = False
                sel[b:] = False
                P[sel] = plates[k].centre
                T[sel] = (M[sel] - np.cross(P[sel], F[sel]))
        loads.append(ExternalLoad(f"{side}_ground_reaction", bodies.get(side, side), plates.time.copy(),
                                  F @ R.T, P @ R.T, T @ R.T))
    return loads, notes
