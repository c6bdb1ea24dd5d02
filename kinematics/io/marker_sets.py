"""Marker sets as data: which segment each marker label rides on and which bony landmark it sits on.

One description serves the phantoms (which place the markers) and the pipeline
(which reads them back).  File form, ``markers.json``::

    {"name": "ior",
     "markers": {"RTUB": {"segment": "tibia_r", "landmark": "RTTB"},
                 "RSHN": {"segment": "tibia_r"},
                 "C7":   {"segment": "torso"}}}

``segment`` is a body of the model (``pelvis``, ``femur_r``, ``tibia_r``,
``talus_r``, ``calcn_r``, ``toes_r`` and ``_l`` twins), or ``torso``, or
``ignore``; ``landmark`` (optional) is the bony landmark under the marker in the
names ``landmarks.json`` uses (``RASI``, ``RPSI``, ``RTRO``, ``RKNE``, ``RMFC``,
``RTTB``, ``RHFB``, ``RANK``, ``RMMA``, ``RHEE``, ``RD1M``, ``RD5M``, ...).
Optional per marker: ``"static_only": true`` for anatomical calibration markers
that are removed after the static trial (CAST).

Presets (`PRESETS`, `preset`):

* ``pig`` -- Vicon Plug-in-Gait lower body (Davis et al. 1991): ASI, PSI, THI
  and TIB wands, KNE, ANK, HEE, TOE;
* ``ior`` -- a bony-landmark set as hospital gait labs use it (after the IOR
  foot and lower-limb protocol, Leardini et al. 2007, Gait Posture 25:453):
  ASI, PSI, TRO, KNE, MFC, TUB, HFB, SHN (lateral shank skin marker), ANK, MMA,
  HEE and LCA (calcaneus, posterior and lateral), P1M, P5M, D1M, D5M; no wands;
* ``cast`` -- CAST (Cappozzo et al. 1995, Clin Biomech 10:171): four-marker
  rigid clusters on thigh (TH1-TH4) and shank (SH1-SH4), pelvis ASI/PSI, foot
  HEE/D1M/D5M, and the anatomical markers TRO, KNE, MFC, TUB, HFB, ANK, MMA in
  the static trial only;
* ``opensim`` -- OpenSim gait2392's names (``gait2392_Scale_MarkerSet.xml``):
  ``R.ASIS``, ``V.Sacral``, ``R.Thigh.Upper``, ``R.Knee.Lat``, ... (the torso
  markers Sternum, R/L.Acromium, Top.Head ride on ``torso``).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from lowerlimb.errors import InputError

__all__ = ["MarkerDef", "MarkerSet", "PRESETS", "preset", "resolve_marker_set", "read_marker_set",
           "write_marker_set", "SPECIAL_SEGMENTS"]

#: segments that are not bodies of a lower-limb model
SPECIAL_SEGMENTS = ("torso", "ignore")


@dataclass(frozen=True)
class MarkerDef:
    """One marker: the segment it moves with, the bony landmark under it (or None), static-only flag."""

    segment: str
    landmark: str | None = None
    static_only: bool = False

    def to_json(self) -> dict:
        d: dict = {"segment": self.segment}
        if self.landmark:
            d["landmark"] = self.landmark
        if self.static_only:
            d["static_only"] = True
        return d


@dataclass(frozen=True)
class MarkerSet:
    """A named marker set: label -> `MarkerDef` (insertion order kept)."""

    name: str
    markers: dict = field(default_factory=dict)

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(self.markers)

    def segment(self, label: str) -> str:
        return self.markers[label].segment

    def landmark(self, label: str) -> str | None:
        return self.markers[label].landmark

    def dynamic_labels(self) -> tuple[str, ...]:
        """Labels present in the dynamic trials (static-only calibration markers left out)."""
        return tuple(k for k, v in self.markers.items() if not v.static_only)

    def on_segment(self, segment: str) -> tuple[str, ...]:
        return tuple(k for k, v in self.markers.items() if v.segment == segment)

    def subset(self, labels) -> "MarkerSet":
        keep = set(labels)
        return MarkerSet(self.name, {k: v for k, v in self.markers.items() if k in keep})

    def to_json(self) -> dict:
        return {"name": self.name, "markers": {k: v.to_json() for k, v in self.markers.items()}}


# --------------------------------------------------------------------------- presets
def _sided(rows, prefix="{S}") -> dict:
    """rows: (label pattern, segment base, landmark base or None, static_only) -> both sides' MarkerDefs."""
    out = {}
    for S, s in (("R", "r"), ("L", "l")):
        for label, seg, lm, static_only in rows:
            segment = seg if seg in ("pelvis",) + SPECIAL_SEGMENTS else f"{seg}_{s}"
            out[label.format(S=S)] = MarkerDef(segment, None if lm is None else f"{S}{lm}", static_only)
    return out


def _pig() -> MarkerSet:
    rows = [("{S}ASI", "pelvis", "ASI", False), ("{S}PSI", "pelvis", "PSI", False),
            ("{S}THI", "femur", None, False), ("{S}KNE", "femur", "KNE", False),
            ("{S}TIB", "tibia", None, False), ("{S}ANK", "tibia", "ANK", False),
            ("{S}HEE", "calcn", "HEE", False), ("{S}TOE", "calcn", None, False)]
    return MarkerSet("pig", _sided(rows))


def _ior() -> MarkerSet:
    rows = [("{S}ASI", "pelvis", "ASI", False), ("{S}PSI", "pelvis", "PSI", False),
            ("{S}TRO", "femur", "TRO", False), ("{S}KNE", "femur", "KNE", False), ("{S}MFC", "femur", "MFC", False),
            ("{S}TUB", "tibia", "TTB", False), ("{S}HFB", "tibia", "HFB", False), ("{S}SHN", "tibia", None, False),
            ("{S}ANK", "tibia", "ANK", False), ("{S}MMA", "tibia", "MMA", False),
            ("{S}HEE", "calcn", "HEE", False), ("{S}LCA", "calcn", None, False),
            ("{S}P1M", "calcn", None, False), ("{S}P5M", "calcn", None, False),
            ("{S}D1M", "calcn", "D1M", False), ("{S}D5M", "calcn", "D5M", False)]
    return MarkerSet("ior", _sided(rows))


def _cast() -> MarkerSet:
    rows = [("{S}ASI", "pelvis", "ASI", False), ("{S}PSI", "pelvis", "PSI", False)]
    rows += [(f"{{S}}TH{i}", "femur", None, False) for i in range(1, 5)]
    rows += [(f"{{S}}SH{i}", "tibia", None, False) for i in range(1, 5)]
    rows += [("{S}HEE", "calcn", "HEE", False), ("{S}D1M", "calcn", "D1M", False), ("{S}D5M", "calcn", "D5M", False)]
    rows += [("{S}TRO", "femur", "TRO", True), ("{S}KNE", "femur", "KNE", True), ("{S}MFC", "femur", "MFC", True),
             ("{S}TUB", "tibia", "TTB", True), ("{S}HFB", "tibia", "HFB", True),
             ("{S}ANK", "tibia", "ANK", True), ("{S}MMA", "tibia", "MMA", True)]
    return MarkerSet("cast", _sided(rows))


def _opensim() -> MarkerSet:
    m = {"Sternum": MarkerDef("torso"), "R.Acromium": MarkerDef("torso"), "L.Acromium": MarkerDef("torso"),
         "Top.Head": MarkerDef("torso"), "R.ASIS": MarkerDef("pelvis", "RASI"), "L.ASIS": MarkerDef("pelvis", "LASI"),
         "V.Sacral": MarkerDef("pelvis")}
    for S, s in (("R", "r"), ("L", "l")):
        for n, seg, lm in (("Thigh.Upper", "femur", None), ("Thigh.Front", "femur", None), ("Thigh.Rear", "femur", None),
                           ("Knee.Lat", "femur", "KNE"), ("Knee.Med", "femur", "MFC"),
                           ("Shank.Upper", "tibia", None), ("Shank.Front", "tibia", None), ("Shank.Rear", "tibia", None),
                           ("Ankle.Lat", "tibia", "ANK"), ("Ankle.Med", "tibia", "MMA"), ("Heel", "calcn", "HEE"),
                           ("Midfoot.Sup", "calcn", None), ("Midfoot.Lat", "calcn", None),
                           ("Toe.Lat", "calcn", "D5M"), ("Toe.Med", "calcn", "D1M"), ("Toe.Tip", "calcn", None)):
            m[f"{S}.{n}"] = MarkerDef(f"{seg}_{s}", None if lm is None else f"{S}{lm}")
    return MarkerSet("opensim", m)


#: preset name -> builder
PRESETS = {"pig": _pig, "ior": _ior, "cast": _cast, "opensim": _opensim}


def preset(name: str) -> MarkerSet:
    """The preset marker set `name` (``pig``, ``ior``, ``cast``, ``opensim``)."""
    key = str(name).strip().lower()
    if key not in PRESETS:
        raise InputError("--marker-set", f"{name!r} is not a preset ({', '.join(PRESETS)}) nor a markers.json file")
    return PRESETS[key]()


def resolve_marker_set(spec: str | os.PathLike | MarkerSet) -> MarkerSet:
    """A `MarkerSet` from a preset name, a ``markers.json`` path, or a `MarkerSet` (returned as is)."""
    if isinstance(spec, MarkerSet):
        return spec
    text = os.fspath(spec)
    if text.strip().lower() in PRESETS:
        return preset(text)
    p = Path(text)
    if p.suffix.lower() == ".json" or p.exists():
        return read_marker_set(p)
    return preset(text)


# --------------------------------------------------------------------------- file boundary
def read_marker_set(path: str | os.PathLike) -> MarkerSet:
    """Read a ``markers.json`` (see the module docstring); one-line `InputError` on any problem."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "marker-set file not found")
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(p, f"not valid JSON ({exc})") from None
    if not isinstance(d, dict) or not isinstance(d.get("markers"), dict) or not d["markers"]:
        raise InputError(p, 'expected {"name": ..., "markers": {LABEL: {"segment": ...}, ...}} with at least one marker')
    out = {}
    for label, v in d["markers"].items():
        if isinstance(v, str):
            v = {"segment": v}
        if not isinstance(v, dict) or not isinstance(v.get("segment"), str) or not v["segment"].strip():
            raise InputError(p, f"marker {label!r}: needs a \"segment\" (a body name, torso or ignore)")
        unknown = sorted(set(v) - {"segment", "landmark", "static_only"})
        if unknown:
            raise InputError(p, f"marker {label!r}: unknown key(s) {', '.join(unknown)}")
        lm = v.get("landmark")
        if lm is not None and not isinstance(lm, str):
            raise InputError(p, f"marker {label!r}: \"landmark\" must be a landmark name")
        out[str(label)] = MarkerDef(v["segment"].strip(), lm or None, bool(v.get("static_only", False)))
    return MarkerSet(str(d.get("name") or p.stem), out)


def write_marker_set(path: str | os.PathLike, ms: MarkerSet) -> Path:
    """Write `ms` as ``markers.json`` (atomically)."""
    from lowerlimb.atomic import write_text

    return write_text(path, json.dumps(ms.to_json(), indent=1) + "\n")
