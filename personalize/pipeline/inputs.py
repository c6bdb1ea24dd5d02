"""Inputs of a subject folder: find, read and check them (the first stage of `personalize.pipeline.run_subject`).

A subject folder holds ``labels.nii.gz`` (+ ``label_map.json``) or ``bones/``,
``subject.json``, the static trial (``static.c3d``; any file whose name starts
with ``static``, whatever its case: ``Static.c3d``, ``STATIC.C3D``,
``Static_trial.trc``) and every other ``*.c3d`` / ``*.trc`` (gait, crouch,
functional ``functional_hip*``).  A trial written both as C3D and TRC (same
name) is read from the C3D.  Every trial is read in its lab's axes, the lab
is read from the trials (`personalize.pipeline.lab`) and each trial is
expressed in the internal frame (X the static pose's facing, Y left, Z up, m).
Refused (`InputError`, one line naming the file): no or several static
trials, a missing motion trial, an ambiguous lab, a trial whose rigid pelvis
marker distances differ from the static trial's (another subject), labels
and markers without a common side.  ``subject.json`` may leave out the leg
lengths and knee and ankle widths: they are then measured on the bones
(`kinematics.gait.subject.measure_from_bones`, in `run.read_subject_bones`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinematics.io.markers import MarkerTrial
from lowerlimb.errors import InputError

__all__ = ["SubjectInputs", "find_inputs", "find_trials", "check_same_subject", "check_trial_legs", "TRIAL_LEG_RATIO_TOL",
           "label_volume", "PELVIS_MARKERS", "rigid_pelvis_labels"]

#: the rigid pelvis markers every trial must show
PELVIS_MARKERS = ("RASI", "LASI", "RPSI", "LPSI")


@dataclass(frozen=True)
class SubjectInputs:
    """A subject folder, read and checked.

    folder : Path; bones : labels file or bones/ folder; label_map : Path or None
    static : MarkerTrial; trials : dict name -> MarkerTrial (every dynamic trial, incl. functional)
    functional : name of the hip calibration trial or None
    subject : kinematics.gait.subject.SubjectMeasurements, or None until the bones give the measurements
        subject.json leaves out (`subject_given` holds what it gives)
    truth : dict (truth.json) or None; sides : tuple of sides with both bones and markers
    marker_set : `kinematics.io.marker_sets.MarkerSet` the trials' labels follow (None: Plug-in-Gait names);
        marker_set_source : where it came from (`personalize.pipeline.markers.subject_marker_set`)
    lab : `kinematics.gait.lab_frame.LabFrame` the trials were recorded in (lab coordinates); every trial
        above is expressed in the internal frame, x_internal = lab.internal_from_lab @ x_lab (X the static
        pose's facing, Y left, Z up, m)
    subject_given : what subject.json gives (SI, `kinematics.gait.subject.read_subject_values`)
    subject_sources : measurement -> "subject file" or how the bones gave it (set with the bones)
    """

    folder: Path
    bones: Path
    label_map: Path | None
    static: MarkerTrial
    trials: dict
    functional: str | None
    subject: object
    truth: dict | None
    sides: tuple
    marker_set: object = None
    lab: object = None
    subject_given: dict | None = None
    marker_set_source: str = ""
    subject_sources: dict | None = None


def _pelvis_distances(trial: MarkerTrial, names) -> np.ndarray:
    """Median over frames of every pairwise distance between the markers `names` (m; NaN when never seen together)."""
    d = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            x = np.linalg.norm(trial.marker(a) - trial.marker(b), axis=1)
            x = x[np.isfinite(x)]
            d.append(np.median(x) if x.size else np.nan)
    return np.array(d)


def find_inputs(subject_dir: str | Path, marker_set=None) -> SubjectInputs:
    """Locate and read the inputs of a subject folder (see the module docstring).

    `marker_set` : preset name, markers.json path or `MarkerSet` for a folder without ``markers.json``
    (`personalize.pipeline.markers.subject_marker_set`).

    Raises
    ------
    InputError : one line naming the file and the problem
    """
    from kinematics.gait.subject import read_subject_values, subject_from_values
    from kinematics.io.trials import read_trial

    from ..evaluation.truth import read_truth
    from .lab import read_lab, to_internal
    from .markers import subject_marker_set

    folder = Path(subject_dir)
    if not folder.is_dir():
        raise InputError(folder, "subject folder not found")
    bones = next((folder / n for n in ("labels.nii.gz", "labels.nii", "labels.nrrd") if (folder / n).is_file()), None)
    if bones is None and (folder / "bones").is_dir():
        bones = folder / "bones"
    if bones is None:
        raise InputError(folder, "no bone images: expected labels.nii.gz (with label_map.json) or a bones/ folder of meshes")
    label_map = folder / "label_map.json" if (folder / "label_map.json").is_file() and bones.is_file() else None
    static_path, trial_paths = find_trials(folder)
    if not (folder / "subject.json").is_file():
        raise InputError(folder / "subject.json", "missing: height and mass (and the Plug-in-Gait measurements the "
                                                  "bones cannot give) are required")
    given = read_subject_values(folder / "subject.json")
    subject = subject_from_values(given, folder / "subject.json", missing_ok=True)
    static = read_trial(static_path)
    trials = {p.stem: read_trial(p) for p in trial_paths}
    lab = read_lab(static, trials.values())
    static = to_internal(static, lab)
    trials = {k: to_internal(t, lab) for k, t in trials.items()}
    ms, marker_sides, ms_source = subject_marker_set(folder, static, marker_set)
    check_same_subject(static, trials.values(), ms)
    functional = next((k for k in sorted(trials) if k.lower() == "functional_hip"), None)
    if functional is None:
        functional = next((k for k in sorted(trials) if k.lower().startswith("functional")), None)
    truth = read_truth(folder / "truth.json")
    return SubjectInputs(folder, bones, label_map, static, trials, functional, subject, truth, marker_sides,
                         marker_set=ms, lab=lab, subject_given=given, marker_set_source=ms_source)


def find_trials(folder: Path) -> tuple[Path, list[Path]]:
    """The static trial and the motion trials of a subject folder (module docstring).

    Returns (static path, sorted motion trial paths).  A stem present as both ``.c3d`` and ``.trc``
    is read from the C3D (it is the lab's original; the TRC an export).

    Raises
    ------
    InputError : no static trial, several (listed), or no motion trial
    """
    from kinematics.io.trials import TRIAL_SUFFIXES

    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in TRIAL_SUFFIXES)
    by_stem: dict[str, list[Path]] = {}
    for p in files:
        by_stem.setdefault(p.stem, []).append(p)
    chosen = [next((p for p in ps if p.suffix.lower() == ".c3d"), ps[0]) for ps in by_stem.values()]
    statics = [p for p in chosen if p.stem.lower().startswith("static")]
    if not statics:
        raise InputError(folder / "static.c3d", "missing: the static (standing) trial is required (static.c3d or "
                                                ".trc, any case)")
    if len(statics) > 1:
        raise InputError(folder, f"several static trials ({', '.join(p.name for p in statics)}): keep one")
    motion = sorted(p for p in chosen if p not in statics)
    if not motion:
        raise InputError(folder, f"no motion trial: at least one C3D or TRC besides {statics[0].name} is required")
    return statics[0], motion



def _visible(trial: MarkerTrial, name: str) -> bool:
    return name in trial.names and bool(np.all(np.isfinite(trial.marker(name)), axis=1).any())


def rigid_pelvis_labels(static: MarkerTrial, marker_set=None) -> tuple:
    """The labels of the rigid pelvis markers the trials are compared on: those the marker set puts on the pelvis
    (every ``pelvis`` marker of `marker_set` the static trial has), else `PELVIS_MARKERS`."""
    if marker_set is None:
        return PELVIS_MARKERS
    return tuple(m for m in marker_set.on_segment("pelvis") if m in static.names
                 and not marker_set.markers[m].static_only)


def check_same_subject(static: MarkerTrial, trials, marker_set=None) -> None:
    """Refuse trials that cannot be of the static trial's subject.

    The pelvis markers (`rigid_pelvis_labels`: RASI, LASI, RPSI, LPSI for
    Plug-in-Gait; R.ASIS, L.ASIS, V.Sacral for OpenSim's set) sit on one rigid
    segment: their pairwise distances, medians over the frames, must agree with
    the static trial's within ``max(15 mm, 6 % of the shortest)``; a Vicon
    subject name (label prefix) must be the static's.  The static must show at
    least three pelvis markers, each of them at some frame.

    Raises
    ------
    InputError naming the static trial (a pelvis marker never visible) or the trial at fault.
    """
    src = static.source
    names = rigid_pelvis_labels(static, marker_set)
    missing = [m for m in (PELVIS_MARKERS if marker_set is None else names) if m not in static.names]
    if missing or len(names) < 3:
        raise InputError(src, f"missing markers: {', '.join(missing)}" if missing else
                         f"only {len(names)} pelvis marker(s) ({', '.join(names) or 'none'}): 3 are needed")
    never = [m for m in names if not _visible(static, m)]
    if never:
        raise InputError(src, f"pelvis marker(s) {', '.join(never)} never visible ({static.n_frames} frames, "
                              "no valid sample): the static trial cannot place the pelvis")
    ref = _pelvis_distances(static, names)
    if not np.all(np.isfinite(ref)):
        raise InputError(src, "the pelvis markers are never visible together in one frame")
    for tr in trials:
        missing = [m for m in names if m not in tr.names]
        if missing:
            raise InputError(tr.source, f"pelvis markers {', '.join(missing)} missing")
        s1, s2 = static.extra.get("subject"), tr.extra.get("subject")
        if s1 and s2 and s1 != s2:
            raise InputError(tr.source, f"labelled for subject {s2!r} but the static trial "
                                        f"{Path(src).name} is subject {s1!r}")
        d = _pelvis_distances(tr, names)
        if not np.all(np.isfinite(d)):
            raise InputError(tr.source, "the pelvis markers are never visible together in one frame")
        diff = float(np.max(np.abs(d - ref)))
        if diff > max(0.015, 0.06 * np.min(ref)):
            raise InputError(tr.source, f"pelvis marker distances differ from the static trial {Path(src).name} by "
                                        f"{diff * 1e3:.0f} mm (rigid on one subject): a trial of another subject?")


#: a movement trial's 95th-percentile ASIS-ankle marker distance over the leg length: 0.99-1.00 on mocap_pig
#: (Movement_trial with Test.vsk; the legs straighten at heel strike), refused beyond 1 +- this
TRIAL_LEG_RATIO_TOL = 0.10


def check_trial_legs(subject, trial: MarkerTrial, tol: float = TRIAL_LEG_RATIO_TOL) -> dict:
    """Refuse a movement trial whose legs cannot be the subject file's (no static trial to compare with).

    r = P95(|ASIS - ANK|) / leg length per side must satisfy |r - 1| <= `tol`
    (in walking the leg is straight at heel strike, so the 95th percentile is
    the standing distance).  Returns {side: r}; sides without both markers are skipped.
    """
    ratios = {}
    for side, L in (("R", subject.right_leg_length), ("L", subject.left_leg_length)):
        if f"{side}ASI" not in trial.names or f"{side}ANK" not in trial.names:
            continue
        d = np.linalg.norm(trial.marker(f"{side}ASI") - trial.marker(f"{side}ANK"), axis=1)
        d = d[np.isfinite(d)]
        if d.size < 10:
            continue
        r = float(np.percentile(d, 95) / L)
        ratios[side] = r
        if abs(r - 1.0) > tol:
            raise InputError(trial.source, f"{side} ASIS-ankle marker distance (95th percentile {np.percentile(d, 95) * 1e3:.0f} mm) "
                                           f"does not match the {'right' if side == 'R' else 'left'} leg length "
                                           f"{L * 1e3:.0f} mm of {subject.source or 'the subject file'} (ratio {r:.2f}): "
                                           "a trial of another subject, or the wrong subject file?")
    return ratios



def label_volume(inputs: SubjectInputs):
    """The subject's label volume (`personalize.io.LabelVolume`), or None when the bones are a mesh folder."""
    from ..io import is_label_volume_path, read_label_volume

    src = Path(inputs.bones)
    if not (src.is_file() and is_label_volume_path(src)):
        return None
    return read_label_volume(src, inputs.label_map)
