"""``personalize markers TRIAL.c3d --method pig|foot-to-hip|blend --subject S --out DIR``: joint centres and angles.

Reconstructs the legs of a marker trial with Plug-in-Gait (hip first),
the seed's foot-to-hip model, or both blended per frame with Gaussian weights
(`kinematics.gait.reconstruction`, `kinematics.gait.chain_blend`) and writes into
DIR (staged: nothing is written on error):

``centres.trc``
    virtual markers RHJC, LHJC, RKJC, LKJC, RAJC, LAJC (lab frame of the trial, mm);
``angles.mot``
    hip_flexion_r, hip_adduction_r, hip_rotation_r, knee_*, ankle_* and ``_l``
    in degrees, Plug-in-Gait sign conventions (compare with Nexus'
    RHipAngles, RKneeAngles, RAnkleAngles: flexion/dorsiflexion, adduction/
    inversion, internal rotation positive on both sides);
``angles.png``
    the angle curves;
``report.json``
    method, notes (calibrations used), marker gaps (filled / left as NaN),
    centre standard deviations (mm), hip centres in the pelvis frame (m);
    for ``blend`` the foot-to-hip chain's weight per segment (median, 10-90 %)
    and each chain's median rigid marker residual per segment (mm).

Marker gaps up to ``--max-gap`` seconds are filled by cubic splines; longer
gaps, and gaps at the trial ends, stay missing (those frames give NaN) and
are reported.  A static trial whose ASIS-ankle marker distances do not
match the subject's leg lengths is refused.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import typer

from lowerlimb.errors import InputError

__all__ = ["run_markers", "register", "read_trial", "plot_angles"]


def read_trial(path: Path, subject_name: Optional[str] = None):
    """MarkerTrial from a .c3d (mm in the file) or .trc file; `subject_name` picks a Vicon subject's labels."""
    from kinematics.io.c3d import read_c3d
    from kinematics.io.storage import read_trc

    p = Path(path)
    if not p.is_file():
        raise InputError(path, "file not found")
    suffix = p.suffix.lower()
    if suffix == ".c3d":
        return read_c3d(p, subject=subject_name)
    if suffix == ".trc":
        return read_trc(p)
    raise InputError(path, f"unsupported marker file type {suffix!r} (expected .c3d or .trc)")


def plot_angles(path: Path, time: np.ndarray, angles: dict) -> None:
    """3 x 3 grid (hip, knee, ankle x three components) of the right (red) and left (blue) angles, degrees."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 8), constrained_layout=True)
    axes = fig.subplots(3, 3, sharex=True)
    comps = {"hip": ("flexion", "adduction", "internal rotation"), "knee": ("flexion", "adduction", "internal rotation"),
             "ankle": ("dorsiflexion", "inversion", "internal rotation")}
    for i, j in enumerate(("hip", "knee", "ankle")):
        for k in range(3):
            ax = axes[i, k]
            for s, colour in (("r", "tab:red"), ("l", "tab:blue")):
                ax.plot(time, np.degrees(angles[f"{j}_{s}"][:, k]), color=colour, lw=1.2, label=s.upper())
            ax.set_title(f"{j} {comps[j][k]}", fontsize=9)
            ax.ticklabel_format(axis="y", useOffset=False, style="plain")
            lo, hi = ax.get_ylim()
            if hi - lo < 2.0:          # a component fixed by the model (e.g. a hinge knee): show it flat
                mid = 0.5 * (lo + hi)
                ax.set_ylim(mid - 1.0, mid + 1.0)
            ax.grid(alpha=0.3)
            if k == 0:
                ax.set_ylabel("deg")
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=8)
    with_path = Path(path)
    from lowerlimb.atomic import atomic_path

    with atomic_path(with_path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")


def _gaps(trial, max_gap: float, label: str, notes: list, gap_log: list):
    from kinematics.io.c3d import fill_gaps

    filled, report = fill_gaps(trial, max_gap)
    for g in report.gaps:
        gap_log.append({"trial": label, "marker": g.marker, "start_s": g.start, "end_s": g.end,
                        "frames": g.n_frames, "filled": g.filled, "reason": g.reason})
    if report.unfilled:
        notes.append(f"{label}: {len(report.unfilled)} marker gap(s) not filled (outputs needing them are NaN there): "
                     + "; ".join(f"{g.marker} {g.start:.2f}-{g.end:.2f} s ({g.reason})" for g in report.unfilled))
    return filled


def run_markers(trial: Path, *, method: str, out: Path, subject: Optional[Path] = None, static: Optional[Path] = None,
                functional: Optional[Path] = None, max_gap: float = 0.1, plot: bool = True,
                overwrite: bool = False, subject_name: Optional[str] = None) -> dict:
    """Run the command; returns the report dict."""
    from lowerlimb.atomic import inside, write_text

    from ..outputs import check_output_dir, replaced_dir
    from kinematics.mechanisms.correlative import json_text
    from kinematics.io.markers import MarkerTrial
    from kinematics.gait.reconstruction import ANGLE_COLUMNS, CENTRE_MARKERS, METHODS, reconstruct
    from kinematics.io.storage import write_mot, write_trc
    from kinematics.gait.subject import read_subject

    if method not in METHODS:
        raise InputError("--method", f"{method!r} is not one of {', '.join(METHODS)}")
    if subject is None:
        raise InputError("--subject", "subject measurements are needed (.vsk or .json: leg lengths, knee and ankle widths)")
    if not (0.0 <= max_gap <= 2.0):
        raise InputError("--max-gap", f"{max_gap} s is outside 0-2 s")
    check_output_dir(out, inputs=[trial, subject, static, functional], overwrite=overwrite)
    subj = read_subject(subject)
    notes: list[str] = []
    gap_log: list[dict] = []
    from ..pipeline import check_same_subject, check_trial_legs

    raw = {k: read_trial(p, subject_name) for k, p in (("trial", trial), ("static", static), ("functional", functional))
           if p is not None}
    # every file of one subject: pelvis marker distances against the static (as `run` checks), else the legs
    # against the subject file (the static itself is checked against it in `reconstruct`)
    if "static" in raw and all(m in raw["static"].names for m in ("RASI", "LASI", "RPSI", "LPSI")):
        if all(m in raw["static"].names for m in ("RANK", "LANK")):
            from kinematics.gait.subject import validate_static

            validate_static(subj, raw["static"])    # the static against the subject file first
        check_same_subject(raw["static"], [v for k, v in raw.items() if k != "static"])
    else:
        check_trial_legs(subj, raw["trial"])
    tr = _gaps(raw["trial"], max_gap, Path(trial).name, notes, gap_log)
    st = _gaps(raw["static"], max_gap, Path(static).name, notes, gap_log) if static is not None else None
    fu = _gaps(raw["functional"], max_gap, Path(functional).name, notes, gap_log) if functional is not None else None
    rec = reconstruct(tr, method, static=st, subject=subj, functional=fu)
    if np.all(~np.isfinite(rec.angle_table())):
        raise InputError(trial, "no frame could be reconstructed (markers missing in every frame?)")
    report = {
        "method": method, "trial": str(trial), "static": None if static is None else str(static),
        "functional": None if functional is None else str(functional), "subject": str(subject),
        "units": {"centres": "mm (centres.trc)", "angles": "deg (angles.mot)", "centre_sd": "mm", "hip_in_pelvis": "m"},
        "frame": "lab frame of the trial; segment axes x anterior, y left, z proximal (Plug-in-Gait)",
        "notes": list(notes) + list(rec.notes), "gaps": gap_log,
        "centre_sd_mm": {k: [float(v) for v in np.sqrt(np.clip(np.diag(c), 0, None)) * 1e3] for k, c in rec.centre_cov.items()},
        "hip_in_pelvis": {s: {"position": [float(v) for v in e.proximal],
                              "sd": [float(v) for v in np.sqrt(np.clip(np.diag(e.cov_proximal), 0, None))],
                              "rms_m": float(e.rms), "frames": int(e.n_frames)} for s, e in rec.hip_in_pelvis.items()},
        "valid_frames": int(np.sum(np.all(np.isfinite(rec.angle_table()), axis=1))), "frames": int(tr.n_frames),
    }
    if rec.weights:
        # blend: the foot-to-hip chain's per-frame weight per segment (median and 10-90 % range)
        report["chain_weights_foot_to_hip"] = {
            k: {"median": float(np.nanmedian(w)), "p10": float(np.nanpercentile(w, 10)), "p90": float(np.nanpercentile(w, 90))}
            for k, w in rec.weights.items() if np.isfinite(w).any()}
        report["chain_residual_mm_median"] = {
            c: {k: float(np.nanmedian(r) * 1e3) for k, r in res.items() if np.isfinite(r).any()}
            for c, res in rec.residuals.items()}
    with replaced_dir(out) as stage:
        names = tuple(CENTRE_MARKERS[k] for k in CENTRE_MARKERS)
        pos = np.stack([rec.centres[k] for k in CENTRE_MARKERS], axis=1)
        write_trc(inside(stage, "centres.trc"), MarkerTrial(names, pos, tr.rate, tr.time, "centres.trc"))
        write_mot(inside(stage, "angles.mot"), ANGLE_COLUMNS, tr.time, rec.angle_table(), rotational=ANGLE_COLUMNS,
                  name=f"JointAngles_{method}")
        if plot:
            plot_angles(inside(stage, "angles.png"), tr.time, rec.angles)
        write_text(inside(stage, "report.json"), json_text(report) + "\n")
    return report


def register(app: typer.Typer) -> None:
    @app.command("markers")
    def markers_cmd(
        trial: Path = typer.Argument(..., help="Marker trial (.c3d in mm, or .trc)."),
        method: str = typer.Option(..., "--method", help="pig (Plug-in-Gait, hip first), foot-to-hip (the seed's model) or blend (both, per-frame Gaussian weights; needs --static)."),
        out: Path = typer.Option(..., "--out", help="Output folder: centres.trc, angles.mot, angles.png, report.json."),
        subject: Optional[Path] = typer.Option(None, "--subject", help="Subject measurements (.vsk or .json, SI)."),
        static: Optional[Path] = typer.Option(None, "--static", help="Static trial: foot offsets, foot-to-hip calibration, leg-length check."),
        functional: Optional[Path] = typer.Option(None, "--functional", help="Hip calibration trial (star-arc) for functional hip centres."),
        max_gap: float = typer.Option(0.1, "--max-gap", help="Fill marker gaps up to this many seconds (cubic spline); longer ones stay missing."),
        no_plot: bool = typer.Option(False, "--no-plot", help="Skip angles.png."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out folder whole."),
        subject_name: Optional[str] = typer.Option(None, "--subject-name", help="Vicon subject whose markers to read when a C3D holds several (Name:RKNE labels)."),
    ) -> None:
        """Joint centres and Plug-in-Gait joint angles of a marker trial (pig or foot-to-hip)."""
        rep = run_markers(trial, method=method, out=out, subject=subject, static=static, functional=functional,
                          max_gap=max_gap, plot=not no_plot, overwrite=overwrite, subject_name=subject_name)
        for n in rep["notes"]:
            typer.echo(f"note: {n}", err=True)
        typer.echo(f"{method}: {rep['valid_frames']}/{rep['frames']} frames reconstructed; wrote centres.trc, "
                   f"angles.mot{'' if no_plot else ', angles.png'}, report.json to {out}")
