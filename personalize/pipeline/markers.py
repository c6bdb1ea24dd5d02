"""The subject's marker set and the trials under internal marker names (the estimators' view of the markers).

Which set (`subject_marker_set`): ``markers.json`` in the subject folder, else
the ``--marker-set`` given (a preset name or a file), else the preset whose
labels fit the static trial best (`kinematics.io.marker_sets.detect_marker_set`;
Vicon ``Subject:`` prefixes ignored).  A set that does not fit the static
trial is refused in one line naming the static file and the missing markers.

The estimators are written for the internal names (Plug-in-Gait and
``landmarks.json``: RASI, RKNE, RMFC, RTTB, ...).  `MarkerView` renames each
marker that sits on a landmark to that landmark's name
(`kinematics.io.marker_sets.canonical_trial`) and gives each segment's
cluster: every marker the set puts on that body plus the Plug-in-Gait
technical markers of the phantoms (`motion.THIGH_MARKERS`, ...) that the
trials show.  The model and the IK keep the lab's own labels.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from kinematics.io.marker_sets import (SPECIAL_SEGMENTS, MarkerSet, canonical_names, canonical_trial,
                                       detect_marker_set, match_marker_set, read_marker_set, resolve_marker_set)
from kinematics.io.markers import MarkerTrial
from lowerlimb.errors import InputError

__all__ = ["MODEL_BODIES", "subject_marker_set", "MarkerView", "marker_view"]

#: bodies a marker set may name (besides ``torso`` and ``ignore``)
MODEL_BODIES = ("pelvis",) + tuple(f"{b}_{s}" for s in ("r", "l") for b in ("femur", "tibia", "talus", "calcn", "toes"))


def _listed(labels, n: int = 12) -> str:
    labels = list(labels)
    return ", ".join(labels[:n]) + (f" and {len(labels) - n} more" if len(labels) > n else "")


def subject_marker_set(folder: Path, static: MarkerTrial, spec=None) -> tuple[MarkerSet, tuple, str]:
    """The marker set of a subject folder, the sides whose markers it has, and where the set came from.

    Parameters
    ----------
    folder : subject folder (its ``markers.json`` wins)
    static : the static trial (its labels choose a preset when nothing is given)
    spec : preset name, markers.json path or `MarkerSet` (``personalize run --marker-set``), or None

    Returns
    -------
    MarkerSet; sides (('r', 'l') subset with every marker of that side visible in `static`); origin text

    Raises
    ------
    InputError : a markers.json naming an unknown body; a set the static trial does not fit (names the static
        file and the missing markers); labels that fit no preset (names the nearest preset's missing markers)
    """
    src = static.source or "static trial"
    path = Path(folder) / "markers.json"
    if path.is_file():
        ms, origin = read_marker_set(path), f"{path.name} of the subject folder"
    elif spec is not None:
        ms = resolve_marker_set(spec)
        origin = f"--marker-set {spec if isinstance(spec, (str, Path)) else ms.name}"
        path = Path(str(spec)) if not isinstance(spec, MarkerSet) else path
    else:
        m = detect_marker_set(static)
        if not m.fits:
            labels = {n.split(":")[-1] for n in static.names}
            absent = [n for n in m.missing if n not in labels]
            unseen = [n for n in m.missing if n in labels]
            what = "; ".join(x for x in (f"lacks {_listed(absent)}" if absent else "",
                                         f"marker(s) {_listed(unseen)} never visible" if unseen else "") if x)
            raise InputError(src, f"the marker labels fit no known marker set: the nearest, {m.marker_set.name!r}: "
                                  f"{what}; describe the lab's set in {path} "
                                  "(label -> segment, landmark) or pass --marker-set FILE|PRESET")
        return m.marker_set, m.sides, f"preset {m.marker_set.name!r}, detected from the labels of {Path(src).name}"
    bad = sorted({v.segment for v in ms.markers.values() if v.segment not in MODEL_BODIES + SPECIAL_SEGMENTS})
    if bad:
        raise InputError(path, f"unknown segment(s) {', '.join(bad)}: use {', '.join(MODEL_BODIES)}, torso or ignore")
    m = match_marker_set(ms, static)
    if not m.fits:
        raise InputError(src, f"markers of the marker set {ms.name!r} ({origin}) missing or never visible: "
                              f"{_listed(m.missing)}")
    return ms, m.sides, f"{ms.name!r} from {origin}"


@dataclass(frozen=True)
class MarkerView:
    """The subject's trials under internal marker names.

    marker_set : the set (None: the labels are Plug-in-Gait's)
    internal : own label -> internal name (static trial's labels)
    static : the static trial renamed; trials : name -> trial renamed
    """

    marker_set: MarkerSet | None
    internal: dict
    static: MarkerTrial
    trials: dict = field(default_factory=dict)

    def label(self, name: str) -> str:
        """The lab's own label of the internal `name` (itself when not renamed)."""
        return next((k for k, v in self.internal.items() if v == name), name)

    def segment_markers(self, body: str, extra=(), dynamic: bool = True) -> tuple:
        """Internal names of a body's cluster: `extra` (internal names, e.g. the Plug-in-Gait table of the body)
        then every marker the set puts on `body` (static-only calibration markers left out when `dynamic`)."""
        out = list(extra)
        if self.marker_set is not None:
            for k, v in self.marker_set.markers.items():
                if v.segment == body and not (dynamic and v.static_only):
                    out.append(self.internal.get(k, canonical_names(self.marker_set, [k])[k]))
        return tuple(dict.fromkeys(out))


def marker_view(inputs) -> MarkerView:
    """`MarkerView` of a `personalize.pipeline.SubjectInputs`."""
    ms = inputs.marker_set
    return MarkerView(ms, canonical_names(ms, inputs.static.names), canonical_trial(inputs.static, ms),
                      {k: canonical_trial(t, ms) for k, t in inputs.trials.items()})
