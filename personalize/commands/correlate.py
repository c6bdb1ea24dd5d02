"""``personalize correlate KINEMATICS... --joint knee_r --out DIR``: correlative joint laws.

Fits the regression law of Pronost et al. (2010, eq. 1) between a joint's
rotations (independent) and its translations (dependent) from per-frame
kinematics (OpenSim ``.mot`` / ``.sto``, e.g. IK with a free joint), and
writes into DIR (staged: nothing is written on error):

``law.json``
    the law over all trials (schema: joint, dependent, independent,
    coefficients ``[[c1, c2, c3, c4] per dependent]``, units, coefficient
    covariance, fit statistics incl. leave-one-trial-out errors);
``laws_by_trial.json``
    with ``--by-trial``: one law per trial (sub-motion laws);
``coefficients.csv``, ``deviation.csv``, ``fit.csv`` and ``tables.md``
    the seed's Table 1 (coefficients) and Table 2 (average deviation,
    motion / sub-motion specific, mm) forms and the fit statistics;
``deviation.png``
    the seed's Figure 3 form: deviation coloured over the three rotations.

Angles are converted to radians on reading (``inDegrees=yes``); slopes are
in m/rad, constants in m, in the parent frame of the joint as the input
kinematics define it.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer

from lowerlimb.atomic import inside
from kinematics.mechanisms.correlative import (CorrelativeLaw, TextTable, coefficient_table, deviation_table, fit_law,
                                    fit_laws_by_group, json_text, plot_deviation)
from kinematics.io.storage import Table, guess_rotational, read_mot, read_sto

from lowerlimb.errors import InputError
from ..outputs import check_output_dir, replaced_dir

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


def _names(text: Optional[str], option: str) -> Optional[list[str]]:
    if text is None:
        return None
    names = [t.strip() for t in text.split(",") if t.strip()]
    if not names:
        raise InputError(option, "empty column list")
    if len(set(names)) != len(names):
        raise InputError(option, "a column is listed twice")
    return names


def _read(path: Path) -> Table:
    suffix = path.suffix.lower()
    if suffix == ".mot":
        return read_mot(path)
    if suffix == ".sto":
        return read_sto(path)
    raise InputError(path, f"unsupported kinematics file type {suffix!r} (expected .mot or .sto)")


def _trial_labels(paths: list[Path]) -> list[str]:
    labels = []
    for p in paths:
        lab = p.stem
        k = 2
        while lab in labels:
            lab = f"{p.stem}#{k}"
            k += 1
        labels.append(lab)
    return labels


def _fmt(x, scale=1.0, digits=3):
    return "-" if x is None or not np.isfinite(x) else f"{x * scale:.{digits}f}"


def fit_table(laws: dict[str, CorrelativeLaw]) -> TextTable:
    """Fit statistics per law and dependent (lengths in mm, angles in rad)."""
    rows = []
    for name, law in laws.items():
        f = law.fit
        for d, dn in enumerate(law.dependent):
            s = 1e3 if law.dependent_units[d] == "m" else 1.0
            u = "mm" if s == 1e3 else law.dependent_units[d]
            loto = None if f.loto_rms is None else f.loto_rms[d]
            rows.append((name, dn, u, _fmt(f.r2[d], 1, 4), _fmt(f.rms[d], s), _fmt(f.max_abs[d], s),
                         "yes" if f.seed_criterion[d] else "no", _fmt(loto, s), str(f.n_frames),
                         f"{f.condition:.3g}"))
    header = ("law", "dependent", "unit", "R2", "rms", "max_abs", "seed criterion", "held-out rms",
              "frames", "condition")
    return TextTable(header, tuple(rows), "Fit statistics (seed criterion: max|MC - E| < min|E|; held-out: "
                                          "leave-one-trial-out, or contiguous blocks with --folds)")


def run_correlate(kinematics: list[Path], out: Path, *, joint: str = "knee_r", independent: Optional[str] = None,
                  dependent: Optional[str] = None, rotational: Optional[str] = None, by_trial: bool = False,
                  folds: int = 0, quiet: bool = False, overwrite: bool = False) -> dict:
    """Library form of the command; returns the law.json content."""
    if not kinematics:
        raise InputError("KINEMATICS", "no kinematics file given")
    if not re.fullmatch(r"[A-Za-z0-9_.\-]+", joint):
        raise InputError("--joint", f"joint name {joint!r} must be letters, digits, '_', '-' or '.'")
    ind_default, dep_default = default_columns(joint)
    ind = _names(independent, "--independent") or ind_default
    dep = _names(dependent, "--dependent") or dep_default
    both = [n for n in dep if n in ind]
    if both:
        raise InputError("--dependent", f"{', '.join(both)} listed both as dependent and independent")
    paths = [Path(p) for p in kinematics]
    check_output_dir(out, inputs=paths, overwrite=overwrite)
    labels = _trial_labels(paths)

    X, Y, groups, frames = [], [], [], {}
    rot_set = set(_names(rotational, "--rotational") or guess_rotational(ind + dep))
    for path, lab in zip(paths, labels):
        tab = _read(path)
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
        # Blocked cross-validation: contiguous blocks of each trial are held out in turn
        # (serially correlated frames make random folds optimistic).
        cv = np.concatenate([[f"{lab}:{k}" for k in np.arange(frames[lab]) * folds // frames[lab]]
                             for lab in labels])
    else:
        cv = groups if len(labels) > 1 else None
    law = fit_law(X, Y, ind, dep, groups=cv, joint=joint,
                  independent_units=iu, dependent_units=du, source=", ".join(p.name for p in paths))
    trial_laws = fit_laws_by_group(X, Y, groups, ind, dep, joint=joint, independent_units=iu,
                                   dependent_units=du, source=joint) if by_trial else {}

    law_json = law.to_json()
    law_json["data"] = {"files": [p.name for p in paths], "frames": frames,
                        "cross_validation": f"{folds} contiguous blocks per trial" if folds else "leave one trial out",
                        "frame": "the joint's parent frame as defined by the input kinematics"}

    # Tables (seed Table 1 and Table 2 forms) and the fit statistics.
    all_laws = {"all trials": law, **trial_laws}
    t1 = coefficient_table(all_laws)
    lengths = all(u == "m" for u in du)
    cells = {}
    for lab in labels:
        sel = groups == lab
        g = float(np.nanmean(law.deviation(X[sel], Y[sel])))
        t = float(np.nanmean(trial_laws[lab].deviation(X[sel], Y[sel]))) if by_trial else None
        cells[lab] = {joint: (g, t)}
    if by_trial:
        sub = float(np.nanmean(np.concatenate([trial_laws[lab].deviation(X[groups == lab], Y[groups == lab])
                                               for lab in labels])))
    else:
        sub = None
    cells["all trials"] = {joint: (float(np.nanmean(law.deviation(X, Y))), sub)}
    t2 = deviation_table(cells, unit="mm" if lengths else "m", digits=2)
    t3 = fit_table(all_laws)

    with replaced_dir(out) as stage:
        (inside(stage, "law.json")).write_text(json_text(law_json) + "\n", encoding="utf-8")
        if by_trial:
            per = {}
            for lab, tl in trial_laws.items():
                j = tl.to_json()
                j["data"] = {"files": [paths[labels.index(lab)].name], "frames": {lab: frames[lab]}}
                per[lab] = j
            inside(stage, "laws_by_trial.json").write_text(json_text(per) + "\n", encoding="utf-8")
        inside(stage, "coefficients.csv").write_text(t1.to_csv(), encoding="utf-8")
        inside(stage, "deviation.csv").write_text(t2.to_csv(), encoding="utf-8")
        inside(stage, "fit.csv").write_text(t3.to_csv(), encoding="utf-8")
        notes = (f"# Correlative law of {joint}\n\nIndependent: {', '.join(ind)} ({', '.join(iu)}); "
                 f"dependent: {', '.join(dep)} ({', '.join(du)}).\nFiles: {', '.join(p.name for p in paths)}.\n"
                 "Slopes in dependent unit per independent unit, c4 (constant) in the dependent unit; "
                 "± one standard deviation from the regression (frames are serially correlated: "
                 "see the leave-one-trial-out error for prediction).\n\n")
        inside(stage, "tables.md").write_text(notes + t1.to_markdown() + "\n" + t2.to_markdown() + "\n"
                                              + t3.to_markdown(), encoding="utf-8")
        ok = np.isfinite(X).all(axis=1) & np.isfinite(Y).all(axis=1)
        if lengths:
            plot_deviation(inside(stage, "deviation.png"), X[ok], law.deviation(X[ok], Y[ok]), ind,
                           title=f"{joint}: deviation between data and law (seed Figure 3 form)",
                           angle_unit="deg" if all(u == "rad" for u in iu) else "rad")
    if not quiet:
        from rich.console import Console
        from rich.table import Table as RichTable

        rt = RichTable(title=f"{joint} law over {len(labels)} trial(s), {law.fit.n_frames} frames")
        for h in ("dependent", "R2", "rms (mm)", "max (mm)", "seed criterion"):
            rt.add_column(h)
        for d, dn in enumerate(dep):
            s = 1e3 if du[d] == "m" else 1.0
            rt.add_row(dn, _fmt(law.fit.r2[d], 1, 4), _fmt(law.fit.rms[d], s), _fmt(law.fit.max_abs[d], s),
                       "yes" if law.fit.seed_criterion[d] else "no")
        Console(stderr=True).print(rt)
        if not law.fit.well_conditioned:
            Console(stderr=True).print(f"[yellow]warning: design condition number {law.fit.condition:.3g}: "
                                       "the rotations are nearly collinear, coefficients poorly determined")
    return law_json


def register(app: typer.Typer) -> None:
    @app.command("correlate")
    def correlate_cmd(
        kinematics: List[Path] = typer.Argument(..., help="Per-frame joint kinematics (.mot/.sto), one file per trial."),
        joint: str = typer.Option("knee_r", "--joint", help="Joint name; picks <joint>_flexion/adduction/rotation and _tx/_ty/_tz columns (side suffix kept last)."),
        out: Path = typer.Option(..., "--out", help="Output folder: law.json, tables, deviation.png."),
        independent: Optional[str] = typer.Option(None, "--independent", help="Comma-separated independent columns (default from --joint)."),
        dependent: Optional[str] = typer.Option(None, "--dependent", help="Comma-separated dependent columns (default from --joint)."),
        rotational: Optional[str] = typer.Option(None, "--rotational", help="Comma-separated rotational columns (default: guessed from names; translations end in _tx/_ty/_tz)."),
        by_trial: bool = typer.Option(False, "--by-trial", help="Also fit one law per trial (sub-motion laws)."),
        folds: int = typer.Option(0, "--folds", help="Held-out error from N contiguous blocks per trial instead of leave-one-trial-out (useful with one trial)."),
        quiet: bool = typer.Option(False, "--quiet", help="No summary table."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out folder whole."),
    ) -> None:
        """Correlative joint law (Pronost 2010): translations as linear functions of the rotations."""
        law = run_correlate(kinematics, out, joint=joint, independent=independent, dependent=dependent,
                            rotational=rotational, by_trial=by_trial, folds=folds, quiet=quiet,
                            overwrite=overwrite)
        fit = law["fit"]
        typer.echo(f"wrote law.json (R2 {', '.join(_fmt(v, 1, 3) for v in fit['r2'])}; "
                   f"mean deviation {_fmt(fit['mean_deviation'], 1e3, 2)} mm) and tables to {out}")
