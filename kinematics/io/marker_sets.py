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
that are removed after the static trial (CAST).  Optional per set:
``"placement"``, how the knee and ankle markers were put on: ``"palpated"``
(the default for a file: on the bony prominence itself, the epicondyle's or
malleolus's most lateral / medial point, as the IOR and CAST protocols
palpate them) or ``"joint-axis"`` (Plug-in-Gait's protocol, the presets
``pig`` and ``pig-sacr``: the knee and ankle markers on the flexion and
transmalleolar axes, Vicon Plug-in-Gait reference guide).

Presets (`PRESETS`, `preset`):

* ``pig`` -- Vicon Plug-in-Gait lower body (Davis et al. 1991): ASI, PSI, THI
  and TIB wands, KNE, ANK, HEE, TOE;
* ``pig-sacr`` -- the same with one sacral marker SACR instead of RPSI and LPSI;
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

Matching a trial (`match_marker_set`, `detect_marker_set`): a set fits a trial
when the trial shows every pelvis marker of the set and, for at least one
side, every marker the set puts on that side's bodies (``torso`` and
``ignore`` markers are never required); Vicon ``Subject:`` label prefixes are
ignored.  The canonical view (`canonical_names`, `canonical_trial`) renames a
marker with a ``landmark`` to that landmark's name (``RTUB`` -> ``RTTB``,
``R.Knee.Lat`` -> ``RKNE``) and a pelvis marker named like the sacrum
(``V.Sacral``) to ``SACR``, so that estimators written for the internal
(Plug-in-Gait / ``landmarks.json``) names find them.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lowerlimb.errors import InputError

__all__ = ["MarkerDef", "MarkerSet", "PRESETS", "preset", "resolve_marker_set", "read_marker_set",
           "write_marker_set", "SPECIAL_SEGMENTS", "SetMatch", "match_marker_set", "detect_marker_set",
           "canonical_names", "canonical_trial", "LEGACY_LANDMARKS", "PLACEMENTS"]

#: how knee and ankle markers are put on (module docstring)
PLACEMENTS = ("palpated", "joint-axis")
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
    #: "palpated" or "joint-axis" (module docstring)
    placement: str = "palpated"

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
        return MarkerSet(self.name, {k: v for k, v in self.markers.items() if k in keep}, self.placement)

    @property
    def on_joint_axes(self) -> bool:
        """True when the knee and ankle markers sit on the joint axes (Plug-in-Gait's placement)."""
        return self.placement == "joint-axis"

    def to_json(self) -> dict:
        return {"name": self.name, "placement": self.placement,
                "markers": {k: v.to_json() for k, v in self.markers.items()}}


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
    return MarkerSet("pig", _sided(rows), "joint-axis")


def _pig_sacr() -> MarkerSet:
    """Plug-in-Gait with one sacral marker SACR instead of the two PSIS markers (as Plug-in-Gait allows)."""
    pig = _pig().markers
    m = {k: v for k, v in pig.items() if not k.endswith("PSI")}
    m = {"SACR": MarkerDef("pelvis"), **m}
    return MarkerSet("pig-sacr", m, "joint-axis")


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
PRESETS = {"pig": _pig, "pig-sacr": _pig_sacr, "ior": _ior, "cast": _cast, "opensim": _opensim}


def preset(name: str) -> MarkerSet:
    """The preset marker set `name` (``pig``, ``pig-sacr``, ``ior``, ``cast``, ``opensim``)."""
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
    placement = d.get("placement", "palpated")
    if placement not in PLACEMENTS:
        raise InputError(p, f"\"placement\" must be one of {', '.join(PLACEMENTS)}, not {placement!r}")
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
    return MarkerSet(str(d.get("name") or p.stem), out, placement)


def write_marker_set(path: str | os.PathLike, ms: MarkerSet) -> Path:
    """Write `ms` as ``markers.json`` (atomically)."""
    from lowerlimb.atomic import write_text

    return write_text(path, json.dumps(ms.to_json(), indent=1) + "\n")


# --------------------------------------------------------------------------- matching a trial
#: medial markers named as Plug-in-Gait extensions (the analytic phantoms' KNEM, ANKM) -> their landmark, for
#: labels a marker set leaves out
LEGACY_LANDMARKS = {"KNEM": "MFC", "ANKM": "MMA"}


def _bare(label: str) -> str:
    """`label` without a Vicon ``Subject:`` prefix."""
    return str(label).rsplit(":", 1)[-1]


def _side_of(md: MarkerDef) -> str | None:
    return md.segment[-1] if md.segment[-2:] in ("_r", "_l") else None


@dataclass(frozen=True)
class SetMatch:
    """How a marker set fits a trial's labels.

    marker_set : the set; sides : sides ('r', 'l') with every one of their markers visible
    missing : labels the set needs but the trial lacks (the pelvis', then, when no side is complete, each side's)
    found : number of the set's labels the trial shows
    """

    marker_set: MarkerSet
    sides: tuple
    missing: tuple
    found: int

    @property
    def fits(self) -> bool:
        return bool(self.sides) and not any(self.marker_set.segment(m) == "pelvis" for m in self.missing)


def match_marker_set(ms: MarkerSet, trial) -> SetMatch:
    """`SetMatch` of `ms` on `trial` (a `kinematics.io.markers.MarkerTrial`; a marker counts when it has a finite frame)."""
    seen = set()
    for i, n in enumerate(trial.names):
        if np.isfinite(trial.positions[:, i]).all(axis=1).any():
            seen.add(_bare(n))
    need = {k: v for k, v in ms.markers.items() if v.segment not in SPECIAL_SEGMENTS}
    pelvis = [k for k, v in need.items() if v.segment == "pelvis" and k not in seen]
    per_side = {s: [k for k, v in need.items() if _side_of(v) == s and k not in seen] for s in ("r", "l")}
    has = {s: any(_side_of(v) == s for v in need.values()) for s in ("r", "l")}
    sides = tuple(s for s in ("r", "l") if has[s] and not per_side[s])
    missing = tuple(pelvis + ([] if sides else [k for s in ("r", "l") if has[s] for k in per_side[s]]))
    return SetMatch(ms, sides, missing, sum(k in seen for k in ms.markers))


def detect_marker_set(trial, candidates=None) -> SetMatch:
    """The preset (or one of `candidates`, `MarkerSet`s) that fits `trial` best.

    Among the sets that fit (`SetMatch.fits`), the one showing the most of its labels; ties go to the smaller
    set (fewer labels unaccounted for).  When none fits, the one missing the fewest markers (its `SetMatch`
    says what is missing).
    """
    sets = list(candidates) if candidates is not None else [b() for b in PRESETS.values()]
    matches = [match_marker_set(ms, trial) for ms in sets]
    fitting = [m for m in matches if m.fits]
    if fitting:
        return max(fitting, key=lambda m: (m.found, -len(m.marker_set.markers)))
    return min(matches, key=lambda m: (len(m.missing), -m.found))


def canonical_names(ms: MarkerSet | None, labels) -> dict:
    """label -> internal name: the set's ``landmark`` for markers that have one, ``SACR`` for a sacral pelvis marker
    without one (label containing ``SAC``), `LEGACY_LANDMARKS` for labels the set leaves out, Plug-in-Gait's
    THI / TIB / TOE for a renamed Plug-in-Gait set (`_pig_roles`), else the label.

    A name already used by another label is never taken (the label then keeps its own name).
    """
    labels = list(labels)
    taken = set(labels)
    out = {}
    for lab in labels:
        md = ms.markers.get(lab) if ms is not None else None
        new = None
        if md is not None and md.landmark:
            new = md.landmark
        elif md is not None and md.segment == "pelvis" and "SAC" in lab.upper():
            new = "SACR"
        elif md is None and len(lab) > 1 and lab[0] in "RL" and lab[1:] in LEGACY_LANDMARKS:
            new = lab[0] + LEGACY_LANDMARKS[lab[1:]]
        if new is None or new == lab or new in taken:
            out[lab] = lab
        else:
            out[lab] = new
            taken.add(new)
    for lab, new in _pig_roles(ms, labels).items():
        if out.get(lab) == lab and new not in taken:
            out[lab] = new
            taken.add(new)
    return out


#: Plug-in-Gait's technical (non-landmark) markers and the body each rides on
_PIG_ROLES = (("THI", "femur"), ("TIB", "tibia"), ("TOE", "calcn"))


def _pig_roles(ms: MarkerSet | None, labels) -> dict:
    """A lab's own labels for Plug-in-Gait's THI, TIB and TOE, where its set makes them unambiguous.

    A side whose femur, tibia and calcaneus each carry exactly one marker without a ``landmark`` (dynamic,
    in `labels`) is a Plug-in-Gait set under other names (thigh wand, shank wand, toe marker): those three take
    the Plug-in-Gait names, so its static reconstruction can run.  Sides with clusters or several skin markers
    on a body get nothing (the roles would be guesses).
    """
    if ms is None:
        return {}
    labels = set(labels)
    out = {}
    for S, s in (("R", "r"), ("L", "l")):
        picked = {}
        for role, body in _PIG_ROLES:
            free = [k for k, v in ms.markers.items() if v.segment == f"{body}_{s}" and not v.landmark
                    and not v.static_only and k in labels]
            if len(free) != 1:
                break
            picked[free[0]] = f"{S}{role}"
        else:
            out.update(picked)
    return out


def canonical_trial(trial, ms: MarkerSet | None):
    """`trial` with its labels renamed by `canonical_names` (same positions, same source)."""
    from .markers import MarkerTrial

    names = canonical_names(ms, trial.names)
    return MarkerTrial(tuple(names[n] for n in trial.names), trial.positions, trial.rate, trial.time, trial.source,
                       trial.extra)
