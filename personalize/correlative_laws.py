"""Correlative joint laws fitted to per-frame kinematics files, and their result files.

`fit_joint_law` fits the regression law of Pronost et al. (2010, eq. 1)
between a joint's rotations a (independent) and its translations y
(dependent) over every frame f of every trial,

    y_f = C[:, :k] a_f + C[:, k]      minimising  sum_f |y_f - C[:, :k] a_f - C[:, k]|^2

(`kinematics.mechanisms.correlative_fit.fit_law`), from OpenSim ``.mot`` / ``.sto``
files (e.g. IK with a free joint).  Angles are converted to radians on reading
(``inDegrees=yes``); slopes are in m/rad, constants in m, in the parent frame
of the joint as the input kinematics define it.  The held-out error leaves one
trial out, or contiguous blocks of each trial (``folds``: serially correlated
frames make random folds optimistic).

`write_joint_law` writes, staged (nothing is written on error):

``law.json``
    `law_document`: the law over all trials (joint, dependent, independent,
    coefficients ``[[c1, c2, c3, c4] per dependent]``, units, coefficient
    covariance, fit statistics incl. held-out errors, the data used);
``laws_by_trial.json``
    with ``by_trial``: one law per trial (sub-motion laws);
``coefficients.csv``, ``deviation.csv``, ``fit.csv`` and ``tables.md``
    the seed's Table 1 (coefficients) and Table 2 (average deviation,
    motion / sub-motion specific, mm) forms and the fit statistics;
``deviation.png``
    the seed's Figure 3 form: deviation coloured over the three rotations.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from kinematics.io.storage import Table
from kinematics.mechanisms.correlative import CorrelativeLaw
from personalize.presentation.correlative_tables import TextTable, fit_table
from lowerlimb.errors import InputError

__all__ = ["JointLawFit", "default_columns", "fit_joint_law", "law_document",
           "read_kinematics", "write_joint_law"]

ROTATIONS = ("flexion", "adduction", "rotation")
TRANSLATIONS = ("tx", "ty", "tz")


def default_columns(joint: str) -> tuple[list[str], list[str]]:
    """Column names of a joint in the phantom's truth .mot files.

    ``knee_r`` -> (knee_flexion_r, knee_adduction_r, knee_rotation_r),
    (knee_tx_r, knee_ty_r, knee_tz_r); a joint without side suffix gets
    ``<joint>_flexion`` etc.
    """
    m = re.fullmatch(r"(.+)_([rl])", joint)
    if m:
        base, side = m.groups()
        return [f"{base}_{r}_{side}" for r in ROTATIONS], [f"{base}_{t}_{side}" for t in TRANSLATIONS]
    return [f"{joint}_{r}" for r in ROTATIONS], [f"{joint}_{t}" for t in TRANSLATIONS]


def read_kinematics(path: str | os.PathLike) -> Table:
    """Per-frame coordinates from an OpenSim ``.mot`` or ``.sto`` file (values as in the file)."""
    from kinematics.io.storage import read_mot, read_sto

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".mot":
        return read_mot(path)
    if suffix == ".sto":
        return read_sto(path)
    raise InputError(path, f"unsupported kinematics file type {suffix!r} (expected .mot or .sto)")


def _trial_labels(paths: Sequence[Path]) -> list[str]:
    labels: list[str] = []
    for p in paths:
        lab = p.stem
        k = 2
        while lab in labels:
            lab = f"{p.stem}#{k}"
            k += 1
        labels.append(lab)
    return labels


@dataclass(frozen=True, eq=False)
class JointLawFit:
    """A correlative law fitted to the frames of several trials.

    Attributes
    ----------
    law : CorrelativeLaw, over all trials
    trial_laws : dict trial label -> CorrelativeLaw (sub-motion laws; empty unless fitted by trial)
    independent, dependent : (F, k) and (F, D) data in SI (rad, m), every trial stacked
    groups : (F,) trial label of each frame
    paths : input files, one per trial; labels : their trial labels (file stems, made unique)
    frames : dict label -> frame count
    folds : 0 (leave one trial out) or the contiguous blocks per trial of the held-out error
    """

    law: CorrelativeLaw
    trial_laws: dict
    independent: np.ndarray
    dependent: np.ndarray
    groups: np.ndarray
    paths: tuple[Path, ...]
    labels: tuple[str, ...]
    frames: dict
    folds: int = 0

    @property
    def joint(self) -> str:
        return self.law.joint

    @property
    def lengths(self) -> bool:
        """Whether every dependent is a length (deviations in mm, the deviation figure drawn)."""
        return all(u == "m" for u in self.law.dependent_units)


def fit_joint_law(kinematics: Sequence[str | os.PathLike], *, joint: str = "knee_r",
                  independent: Sequence[str] | None = None, dependent: Sequence[str] | None = None,
                  rotational: Sequence[str] | None = None, by_trial: bool = False, folds: int = 0) -> JointLawFit:
    """Fit a joint's correlative law to kinematics files, one file per trial.

    Parameters
    ----------
    kinematics : ``.mot`` / ``.sto`` files
    joint : joint name; picks the default columns (`default_columns`)
    independent, dependent : column names (default from `joint`)
    rotational : rotational columns (default: guessed from the names,
        `kinematics.io.storage.guess_rotational`)
    by_trial : also fit one law per trial
    folds : 0 (leave one trial out) or >= 2 contiguous blocks per trial for the held-out error

    Returns
    -------
    JointLawFit

    Raises
    ------
    InputError
        No file, a bad joint name, a column both dependent and independent, bad
        `folds`, missing columns or file types, or data that cannot determine the law.
    """
    from kinematics.io.storage import guess_rotational
    from kinematics.mechanisms.correlative_fit import fit_law, fit_laws_by_group

    if not kinematics:
        raise InputError("KINEMATICS", "no kinematics file given")
    if not re.fullmatch(r"[A-Za-z0-9_.\-]+", joint):
        raise InputError("--joint", f"joint name {joint!r} must be letters, digits, '_', '-' or '.'")
    ind_default, dep_default = default_columns(joint)
    ind = list(independent or ind_default)
    dep = list(dependent or dep_default)
    both = [n for n in dep if n in ind]
    if both:
        raise InputError("--dependent", f"{', '.join(both)} listed both as dependent and independent")
    paths = tuple(Path(p) for p in kinematics)
    labels = _trial_labels(paths)
    X, Y, groups, frames = [], [], [], {}
    rot_set = set(rotational or guess_rotational(ind + dep))
    for path, lab in zip(paths, labels):
        tab = read_kinematics(path)
        missing = [n for n in ind + dep if n not in tab.columns]
        if missing:
            hint = "" if independent or dependent else " (use --independent/--dependent to name other columns)"
            raise InputError(path, f"missing columns: {', '.join(missing)}{hint}")
        tab = tab.to_radians(rot_set)
        X.append(tab.select(ind))
        Y.append(tab.select(dep))
        groups += [lab] * tab.n_frames
        frames[lab] = tab.n_frames
    X, Y = np.vstack(X), np.vstack(Y)
    groups = np.asarray(groups)
    iu = ["rad" if n in rot_set else "m" for n in ind]
    du = ["rad" if n in rot_set else "m" for n in dep]
    if folds < 0 or folds == 1:
        raise InputError("--folds", f"{folds} folds: use 0 (leave one trial out) or at least 2")
    if folds:
        cv = np.concatenate([[f"{lab}:{k}" for k in np.arange(frames[lab]) * folds // frames[lab]]
                             for lab in labels])
    else:
        cv = groups if len(labels) > 1 else None
    law = fit_law(X, Y, ind, dep, groups=cv, joint=joint,
                  independent_units=iu, dependent_units=du, source=", ".join(p.name for p in paths))
    trial_laws = fit_laws_by_group(X, Y, groups, ind, dep, joint=joint, independent_units=iu,
                                   dependent_units=du, source=joint) if by_trial else {}
    return JointLawFit(law, trial_laws, X, Y, groups, paths, tuple(labels), frames, folds)


def law_document(fit: JointLawFit) -> dict:
    """The ``law.json`` document: the law's JSON form and the data it was fitted to."""
    doc = fit.law.to_json()
    doc["data"] = {"files": [p.name for p in fit.paths], "frames": fit.frames,
                   "cross_validation": f"{fit.folds} contiguous blocks per trial" if fit.folds else "leave one trial out",
                   "frame": "the joint's parent frame as defined by the input kinematics"}
    return doc


def _tables(fit: JointLawFit) -> tuple[TextTable, TextTable, TextTable]:
    """Seed Table 1 (coefficients) and Table 2 (deviation) forms, and the fit statistics."""
    from personalize.presentation.correlative_tables import coefficient_table, deviation_table

    law, trial_laws, X, Y, groups = fit.law, fit.trial_laws, fit.independent, fit.dependent, fit.groups
    by_trial = bool(trial_laws)
    all_laws = {"all trials": law, **trial_laws}
    cells = {}
    for lab in fit.labels:
        sel = groups == lab
        g = float(np.nanmean(law.deviation(X[sel], Y[sel])))
        t = float(np.nanmean(trial_laws[lab].deviation(X[sel], Y[sel]))) if by_trial else None
        cells[lab] = {fit.joint: (g, t)}
    sub = float(np.nanmean(np.concatenate([trial_laws[lab].deviation(X[groups == lab], Y[groups == lab])
                                           for lab in fit.labels]))) if by_trial else None
    cells["all trials"] = {fit.joint: (float(np.nanmean(law.deviation(X, Y))), sub)}
    return (coefficient_table(all_laws), deviation_table(cells, unit="mm" if fit.lengths else "m", digits=2),
            fit_table(all_laws))


def write_joint_law(fit: JointLawFit, out: str | os.PathLike) -> Path:
    """Write law.json, laws_by_trial.json (laws by trial), the tables and deviation.png into ``out``, replacing it whole.

    Check ``out`` first with `personalize.outputs.check_output_dir` (an existing folder is replaced).
    """
    from lowerlimb.json_format import json_text
    from personalize.presentation.correlative_tables import plot_deviation
    from lowerlimb.atomic import inside

    from .outputs import replaced_dir

    law, X, Y = fit.law, fit.independent, fit.dependent
    t1, t2, t3 = _tables(fit)
    with replaced_dir(out) as stage:
        inside(stage, "law.json").write_text(json_text(law_document(fit)) + "\n", encoding="utf-8")
        if fit.trial_laws:
            per = {}
            for lab, tl in fit.trial_laws.items():
                j = tl.to_json()
                j["data"] = {"files": [fit.paths[fit.labels.index(lab)].name], "frames": {lab: fit.frames[lab]}}
                per[lab] = j
            inside(stage, "laws_by_trial.json").write_text(json_text(per) + "\n", encoding="utf-8")
        inside(stage, "coefficients.csv").write_text(t1.to_csv(), encoding="utf-8")
        inside(stage, "deviation.csv").write_text(t2.to_csv(), encoding="utf-8")
        inside(stage, "fit.csv").write_text(t3.to_csv(), encoding="utf-8")
        ind, dep = law.independent, law.dependent
        iu, du = law.independent_units, law.dependent_units
        notes = (f"# Correlative law of {fit.joint}\n\nIndependent: {', '.join(ind)} ({', '.join(iu)}); "
                 f"dependent: {', '.join(dep)} ({', '.join(du)}).\nFiles: {', '.join(p.name for p in fit.paths)}.\n"
                 "Slopes in dependent unit per independent unit, c4 (constant) in the dependent unit; "
                 "± one standard deviation from the regression (frames are serially correlated: "
                 "see the leave-one-trial-out error for prediction).\n\n")
        inside(stage, "tables.md").write_text(notes + t1.to_markdown() + "\n" + t2.to_markdown() + "\n"
                                              + t3.to_markdown(), encoding="utf-8")
        ok = np.isfinite(X).all(axis=1) & np.isfinite(Y).all(axis=1)
        if fit.lengths:
            plot_deviation(inside(stage, "deviation.png"), X[ok], law.deviation(X[ok], Y[ok]), ind,
                           title=f"{fit.joint}: deviation between data and law (seed Figure 3 form)",
                           angle_unit="deg" if all(u == "rad" for u in iu) else "rad")
    return Path(out)
