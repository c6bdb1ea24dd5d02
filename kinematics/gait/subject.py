"""Subject measurements for marker-based models (Plug-in-Gait and friends).

Read from a Vicon ``.vsk`` (XML, parsed with defusedxml; lengths in mm,
angles in radians, mass in kg) or a JSON file (SI units: metres, radians, kg).
Everything inside is SI.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np

from lowerlimb.errors import InputError
from lowerlimb.geometry import DEFAULT_MARKER_DIAMETER
from kinematics.io.markers import MarkerTrial

__all__ = ["SubjectMeasurements", "read_subject", "read_subject_values", "subject_from_values", "read_vsk",
           "validate_static", "BONE_MEASURABLE", "measure_from_bones"]


@dataclass(frozen=True)
class SubjectMeasurements:
    """Anthropometric measurements of one subject (SI units).

    Attributes
    ----------
    left_leg_length, right_leg_length : float, m
        ASIS to medial malleolus, through the knee.
    left_knee_width, right_knee_width, left_ankle_width, right_ankle_width : float, m
        Medio-lateral widths across the joint (calliper).
    inter_asis_distance : float or None, m
        None (or 0 in a vsk) means "measure from the ASIS markers".
    marker_diameter : float, m
    height : float or None, m
    mass : float or None, kg
    left_asis_trochanter, right_asis_trochanter : float or None, m
        None means Plug-in-Gait's regression 0.1288 * leg length - 0.04856 m.
    left_tibial_torsion, right_tibial_torsion : float, rad
    left_thigh_rotation, right_thigh_rotation, left_shank_rotation, right_shank_rotation : float, rad
    left_static_plantar_flexion, right_static_plantar_flexion, left_static_rotation_offset,
    right_static_rotation_offset : float or None, rad
        Foot offsets found by a static trial (None: not calibrated yet).
    source : str or None
    """

    left_leg_length: float
    right_leg_length: float
    left_knee_width: float
    right_knee_width: float
    left_ankle_width: float
    right_ankle_width: float
    inter_asis_distance: float | None = None
    marker_diameter: float = DEFAULT_MARKER_DIAMETER
    height: float | None = None
    mass: float | None = None
    left_asis_trochanter: float | None = None
    right_asis_trochanter: float | None = None
    left_tibial_torsion: float = 0.0
    right_tibial_torsion: float = 0.0
    left_thigh_rotation: float = 0.0
    right_thigh_rotation: float = 0.0
    left_shank_rotation: float = 0.0
    right_shank_rotation: float = 0.0
    left_static_plantar_flexion: float | None = None
    right_static_plantar_flexion: float | None = None
    left_static_rotation_offset: float | None = None
    right_static_rotation_offset: float | None = None
    source: str | None = None

    def __post_init__(self):
        for name in ("left_leg_length", "right_leg_length", "left_knee_width", "right_knee_width",
                     "left_ankle_width", "right_ankle_width", "marker_diameter"):
            v = getattr(self, name)
            if v is None or not math.isfinite(v) or v <= 0:
                raise InputError(self.source, f"{name} must be a positive length in metres, got {v}")
        # A leg length of 866 given as metres is a unit slip (mm); refuse it.
        for name in ("left_leg_length", "right_leg_length"):
            v = getattr(self, name)
            if not 0.3 < v < 1.5:
                raise InputError(self.source, f"{name} = {v:g} m is implausible (expected 0.3-1.5 m; mm given as m?)")
        for name in ("left_knee_width", "right_knee_width", "left_ankle_width", "right_ankle_width"):
            v = getattr(self, name)
            if not 0.02 < v < 0.3:
                raise InputError(self.source, f"{name} = {v:g} m is implausible (expected 0.02-0.3 m)")
        if self.inter_asis_distance is not None and not 0.1 < self.inter_asis_distance < 0.5:
            raise InputError(self.source, f"inter_asis_distance = {self.inter_asis_distance:g} m is implausible")

    def side(self, side: str) -> dict:
        """Measurements of one side (``'R'`` or ``'L'``) without the side prefix."""
        p = {"R": "right_", "L": "left_"}[side.upper()[0]]
        return {f.name[len(p):]: getattr(self, f.name) for f in fields(self) if f.name.startswith(p)}

    @property
    def mean_leg_length(self) -> float:
        return 0.5 * (self.left_leg_length + self.right_leg_length)

    def with_static_offsets(self, **kw) -> "SubjectMeasurements":
        return replace(self, **kw)

    def to_json(self) -> str:
        """JSON text (SI units; the key ``units`` says so)."""
        d = asdict(self)
        d.pop("source")
        return json.dumps({"units": "m, rad, kg", **d}, indent=2)


# vsk StaticParameter name -> (field, factor to SI)
_VSK = {
    "LeftLegLength": ("left_leg_length", 1e-3),
    "RightLegLength": ("right_leg_length", 1e-3),
    "LeftKneeWidth": ("left_knee_width", 1e-3),
    "RightKneeWidth": ("right_knee_width", 1e-3),
    "LeftAnkleWidth": ("left_ankle_width", 1e-3),
    "RightAnkleWidth": ("right_ankle_width", 1e-3),
    "InterAsisDistance": ("inter_asis_distance", 1e-3),
    "MarkerDiameter": ("marker_diameter", 1e-3),
    "Height": ("height", 1e-3),
    "Bodymass": ("mass", 1.0),
    "LeftAsisTrocanterDistance": ("left_asis_trochanter", 1e-3),
    "RightAsisTrocanterDistance": ("right_asis_trochanter", 1e-3),
    "LeftTibialTorsion": ("left_tibial_torsion", 1.0),
    "RightTibialTorsion": ("right_tibial_torsion", 1.0),
    "LeftThighRotation": ("left_thigh_rotation", 1.0),
    "RightThighRotation": ("right_thigh_rotation", 1.0),
    "LeftShankRotation": ("left_shank_rotation", 1.0),
    "RightShankRotation": ("right_shank_rotation", 1.0),
    "LeftStaticPlantFlex": ("left_static_plantar_flexion", 1.0),
    "RightStaticPlantFlex": ("right_static_plantar_flexion", 1.0),
    "LeftStaticRotOff": ("left_static_rotation_offset", 1.0),
    "RightStaticRotOff": ("right_static_rotation_offset", 1.0),
}
_REQUIRED = ("left_leg_length", "right_leg_length", "left_knee_width", "right_knee_width",
             "left_ankle_width", "right_ankle_width")


#: the measurements a segmented bone set gives when the subject file leaves them out (`measure_from_bones`)
BONE_MEASURABLE = _REQUIRED


def read_vsk(path: str | os.PathLike) -> SubjectMeasurements:
    """Read subject measurements from a Vicon ``.vsk`` file.

    Lengths in the vsk are millimetres, angles radians, mass kg.  Empty
    values (no ``VALUE`` attribute) take the defaults; an ``InterAsisDistance``
    of 0 means "measure from the markers" (None here).
    """
    return subject_from_values(_vsk_values(path), path)


def _vsk_values(path) -> dict:
    """The vsk's measurements as SI values keyed by `SubjectMeasurements` field (only those it gives)."""
    from defusedxml import ElementTree as ET

    p = Path(path)
    if not p.is_file():
        raise InputError(path, "subject file not found")
    try:
        root = ET.parse(os.fspath(p)).getroot()
    except Exception as exc:
        raise InputError(path, f"not a readable vsk/XML file ({exc})") from None
    values: dict = {}
    for el in root.iter():
        if el.tag not in ("StaticParameter", "Parameter"):
            continue
        name = el.get("NAME")
        if name not in _VSK or el.get("VALUE") in (None, ""):
            continue
        key, factor = _VSK[name]
        try:
            values[key] = float(el.get("VALUE")) * factor
        except ValueError:
            raise InputError(path, f"parameter {name} has a non-numeric value {el.get('VALUE')!r}") from None
    if values.get("inter_asis_distance") == 0.0:
        values["inter_asis_distance"] = None
    for k in ("left_asis_trochanter", "right_asis_trochanter"):
        if values.get(k) == 0.0:
            values[k] = None
    return values


def subject_from_values(values: dict, path, *, missing_ok: bool = False) -> SubjectMeasurements | None:
    """`SubjectMeasurements` of `values` (`read_subject_values`); None when `missing_ok` and only
    `BONE_MEASURABLE` ones are missing (they are then measured on the bones, `measure_from_bones`).

    Raises
    ------
    InputError : a required measurement missing (naming every one), or a value out of range
    """
    missing = [k for k in _REQUIRED if k not in values]
    if missing and missing_ok and set(missing) <= set(BONE_MEASURABLE):
        return None
    if missing:
        if Path(path).suffix.lower() == ".vsk":
            missing = [n for n, (k, _) in _VSK.items() if k in missing]
        raise InputError(path, f"missing subject measurements: {', '.join(missing)}")
    try:
        return SubjectMeasurements(**values, source=os.fspath(path))
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"bad measurement value ({exc})") from None


def read_subject(path: str | os.PathLike) -> SubjectMeasurements:
    """Read subject measurements from a ``.vsk`` (Vicon, mm) or ``.json`` (SI) file."""
    return subject_from_values(read_subject_values(path), path)


def read_subject_values(path: str | os.PathLike) -> dict:
    """The measurements a ``.vsk`` (Vicon, mm) or ``.json`` (SI) subject file gives, SI, keyed by
    `SubjectMeasurements` field; only those present (none required here: `subject_from_values` checks)."""
    p = Path(path)
    if p.suffix.lower() == ".vsk":
        return _vsk_values(p)
    if p.suffix.lower() != ".json":
        raise InputError(path, "subject measurements must be a .vsk or .json file")
    if not p.is_file():
        raise InputError(path, "subject file not found")
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None
    if not isinstance(d, dict):
        raise InputError(path, "expected a JSON object of measurements")
    d.pop("units", None)
    known = {f.name for f in fields(SubjectMeasurements)} - {"source"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise InputError(path, f"unknown measurement(s): {', '.join(unknown)}")
    try:
        return {k: (None if v is None else float(v)) for k, v in d.items()}
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"bad measurement value ({exc})") from None


def measure_from_bones(values: dict, points: dict, *, source=None) -> tuple[SubjectMeasurements, dict]:
    r"""Subject measurements with the `BONE_MEASURABLE` values a subject file left out taken from the bones.

    Plug-in-Gait's measurements are taken on the skin (Vicon's Plug-in-Gait manual: leg length ASIS to
    medial malleolus through the knee with a tape, knee and ankle widths across the epicondyles and the
    malleoli with a calliper).  From segmented bones (landmark positions, m, one common frame):

    .. math::

        L = \lVert a - k \rVert + \lVert k - m \rVert, \qquad
        w_{knee} = \lVert e_l - e_m \rVert + 2 t_{KNE}, \qquad
        w_{ankle} = \lVert l - m \rVert + 2 t_{ANK}

    with a the ASIS, k the knee joint centre, m and l the medial and lateral malleoli, e_l and e_m the
    lateral and medial epicondyles and t the population soft-tissue thickness over the site
    (`kinematics.gait.soft_tissue`; 5 and 3 mm).  The leg length is bony (the tape's skin offsets at the
    ASIS and malleolus lie mostly across the leg).  A side without the bones takes the other side's value.
    Values given in `values` always win.

    Parameters
    ----------
    values : dict, `read_subject_values`
    points : dict name -> (3,) position, m: ``RASI``, ``LASI``, ``RKJC``/``LKJC`` (knee centres), ``RKNE``,
        ``RMFC``, ``RANK``, ``RMMA`` and the left ones (any may be missing)
    source : the subject file, for messages

    Returns
    -------
    (SubjectMeasurements, sources) with sources field -> "subject.json" or how it was measured (and its value)

    Raises
    ------
    InputError : a measurement neither given nor measurable (naming it and the missing landmarks)
    """
    from .soft_tissue import tissue_prior

    def dist(*names):
        p = [points.get(n) for n in names]
        if any(x is None or not np.all(np.isfinite(x)) for x in p):
            return None
        return float(sum(np.linalg.norm(np.asarray(a, float) - np.asarray(b, float)) for a, b in zip(p, p[1:])))

    rules = {"leg_length": (("{S}ASI", "{S}KJC", "{S}MMA"), 0.0, "ASIS - knee centre - medial malleolus (bones)"),
             "knee_width": (("{S}KNE", "{S}MFC"), 2 * tissue_prior("KNE").mean,
                            "lateral - medial epicondyle (bones) + 2 x {t:.0f} mm tissue prior"),
             "ankle_width": (("{S}ANK", "{S}MMA"), 2 * tissue_prior("ANK").mean,
                             "lateral - medial malleolus (bones) + 2 x {t:.0f} mm tissue prior")}
    out = dict(values)
    sources = {k: "subject file" for k in BONE_MEASURABLE if k in values}
    measured: dict = {}
    for what, (names, add, how) in rules.items():
        for side, S in (("right", "R"), ("left", "L")):
            d = dist(*(n.format(S=S) for n in names))
            if d is not None:
                measured[f"{side}_{what}"] = (d + add, how.format(t=500 * add))
    for key in BONE_MEASURABLE:
        if key in out:
            continue
        side, what = key.split("_", 1)
        other = f"{'left' if side == 'right' else 'right'}_{what}"
        if key in measured:
            out[key], how = measured[key]
        elif other in measured:
            out[key], how = measured[other]
            how = f"{how}, the {other.split('_')[0]} side's (no {side} bones)"
        else:
            names = {n.format(S=S) for n in rules[what][0] for S in "RL"}
            lack = sorted(n for n in names if dist(n, n) is None)
            raise InputError(source, f"{key} is neither given nor measurable: the bones lack {' / '.join(lack)}")
        sources[key] = f"{how}: {out[key] * 1e3:.1f} mm"
    return subject_from_values(out, source or "subject file"), sources


def validate_static(subject: SubjectMeasurements, static: MarkerTrial, *, tolerance: float = 0.08) -> dict:
    """Check that a static trial belongs to the measured subject.

    In quiet standing the ASIS-to-lateral-malleolus marker distance d is close
    to the measured leg length L (ASIS to medial malleolus); the check is
    |median(d) / L - 1| <= `tolerance` for both sides.

    Returns
    -------
    dict side -> ratio median(d) / L

    Raises
    ------
    InputError
        Markers missing, or a leg-length mismatch (another subject's static
        trial, or measurements in the wrong unit).
    """
    static.require(["RASI", "LASI", "RANK", "LANK"])
    ratios = {}
    for side, L in (("R", subject.right_leg_length), ("L", subject.left_leg_length)):
        d = np.linalg.norm(static.marker(f"{side}ASI") - static.marker(f"{side}ANK"), axis=1)
        d = d[np.isfinite(d)]
        if d.size == 0:
            raise InputError(static.source, f"{side}ASI or {side}ANK never visible in the static trial")
        ratio = float(np.median(d) / L)
        ratios[side] = ratio
        if abs(ratio - 1.0) > tolerance:
            raise InputError(
                static.source,
                f"{side} ASIS-ankle marker distance {np.median(d) * 1e3:.0f} mm does not match the measured "
                f"{'right' if side == 'R' else 'left'} leg length {L * 1e3:.0f} mm of {subject.source or 'the subject'} "
                f"(ratio {ratio:.2f}): static trial of another subject, or wrong measurements?",
            )
    return ratios
