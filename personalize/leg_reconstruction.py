"""Joint centres and Plug-in-Gait joint angles of a marker trial, checked against the subject, and their files.

`reconstruct_legs` reads the trial (and the optional static and functional
trials, ``.c3d`` or ``.trc``), refuses files that cannot be of the subject
(pelvis marker distances against the static, else the legs against the
subject file), fills marker gaps up to ``max_gap`` seconds by cubic splines
(`kinematics.io.c3d.fill_gaps`; longer gaps and gaps at the trial ends stay
missing and give NaN) and reconstructs the legs with Plug-in-Gait, the seed's
foot-to-hip model, or both blended per frame with Gaussian weights
(`kinematics.gait.reconstruction.reconstruct`).

`write_leg_reconstruction` writes, staged (nothing is written on error):

``centres.trc``
    virtual markers RHJC, LHJC, RKJC, LKJC, RAJC, LAJC (lab frame of the trial, mm);
``angles.mot``
    hip_flexion_r, hip_adduction_r, hip_rotation_r, knee_*, ankle_* and ``_l``
    in degrees, Plug-in-Gait sign conventions (compare with Nexus'
    RHipAngles, RKneeAngles, RAnkleAngles: flexion/dorsiflexion, adduction/
    inversion, internal rotation positive on both sides);
``angles.png``
    the angle curves (optional);
``report.json``
    `leg_report`: method, notes (calibrations used), marker gaps (filled / left
    as NaN), centre standard deviations (mm), hip centres in the pelvis frame
    (m); for ``blend`` the foot-to-hip chain's weight per segment (median,
    10-90 %) and each chain's median rigid marker residual per segment (mm).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinematics.gait.lab_frame import LabFrame
from kinematics.gait.reconstruction import Reconstruction
from kinematics.io.markers import MarkerTrial
from lowerlimb.errors import InputError

__all__ = ["LegReconstruction", "leg_report", "reconstruct_legs", "write_leg_reconstruction"]

MAX_GAP_S = 2.0


@dataclass(frozen=True, eq=False)
class LegReconstruction:
    """Reconstruction of the legs of one trial.

    Attributes
    ----------
    reconstruction : Reconstruction, centres (F, 3) m and angles (F, 3) rad per joint, lab frame
    trial : MarkerTrial, the gap-filled movement trial (its time base is the outputs')
    inputs : dict ``trial``, ``static``, ``functional``, ``subject`` -> path as given (or None)
    notes : tuple of str, unfilled gaps and the reconstruction's notes (calibrations used)
    gaps : tuple of dict, every marker gap found (trial, marker, start_s, end_s, frames, filled, reason)
    lab : LabFrame or None, the lab's vertical and progression read from the static and the trial
        (`kinematics.gait.lab_frame.detect_lab`); None when they do not tell it, `lab_problem` says why
    lab_problem : str, why the lab could not be read ('' when `lab` is set)
    """

    reconstruction: Reconstruction
    trial: MarkerTrial
    inputs: dict
    notes: tuple[str, ...]
    gaps: tuple[dict, ...]
    lab: LabFrame | None = None
    lab_problem: str = ""

    @property
    def method(self) -> str:
        return self.reconstruction.method

    @property
    def frames(self) -> int:
        """Frames of the trial."""
        return int(self.trial.n_frames)

    @property
    def valid_frames(self) -> int:
        """Frames with every angle reconstructed."""
        return int(np.sum(np.all(np.isfinite(self.reconstruction.angle_table()), axis=1)))


def _filled(trial: MarkerTrial, max_gap: float, label: str, notes: list, gap_log: list) -> MarkerTrial:
    from kinematics.io.c3d import fill_gaps

    filled, report = fill_gaps(trial, max_gap)
    for g in report.gaps:
        gap_log.append({"trial": label, "marker": g.marker, "start_s": g.start, "end_s": g.end,
                        "frames": g.n_frames, "filled": g.filled, "reason": g.reason})
    if report.unfilled:
        notes.append(f"{label}: {len(report.unfilled)} marker gap(s) not filled (outputs needing them are NaN there): "
                     + "; ".join(f"{g.marker} {g.start:.2f}-{g.end:.2f} s ({g.reason})" for g in report.unfilled))
    return filled


def reconstruct_legs(trial: str | os.PathLike, *, method: str, subject: str | os.PathLike | None,
                     static: str | os.PathLike | None = None, functional: str | os.PathLike | None = None,
                     max_gap: float = 0.1, subject_name: str | None = None) -> LegReconstruction:
    """Joint centres and angles of a marker trial.

    Parameters
    ----------
    trial : movement trial (``.c3d`` in mm, or ``.trc``)
    method : 'pig' (Plug-in-Gait, hip first), 'foot-to-hip' (the seed's model) or
        'blend' (both, per-frame Gaussian weights; needs `static`)
    subject : subject measurements (``.vsk`` or ``.json``: leg lengths, knee and ankle widths)
    static : static trial: foot offsets, foot-to-hip calibration, leg-length check
    functional : hip calibration trial (star-arc) for functional hip centres
    max_gap : longest marker gap filled by a cubic spline (s), 0-2 s
    subject_name : Vicon subject whose markers to read when a C3D holds several

    Returns
    -------
    LegReconstruction

    Raises
    ------
    InputError
        Unknown method, no subject file, `max_gap` outside 0-2 s, unreadable files,
        files of another subject, or no frame reconstructed.
    """
    from kinematics.gait.reconstruction import METHODS, reconstruct
    from kinematics.gait.subject import read_subject, validate_static
    from kinematics.io.trials import read_trial

    from .pipeline.inputs import check_same_subject, check_trial_legs

    if method not in METHODS:
        raise InputError("--method", f"{method!r} is not one of {', '.join(METHODS)}")
    if subject is None:
        raise InputError("--subject", "subject measurements are needed (.vsk or .json: leg lengths, knee and ankle widths)")
    if not (0.0 <= max_gap <= MAX_GAP_S):
        raise InputError("--max-gap", f"{max_gap} s is outside 0-2 s")
    subj = read_subject(subject)
    paths = {"trial": trial, "static": static, "functional": functional}
    raw = {k: read_trial(p, subject_name) for k, p in paths.items() if p is not None}
    # every file of one subject: pelvis marker distances against the static (as `run` checks), else the legs
    # against the subject file (the static itself is checked against it in `reconstruct`)
    if "static" in raw and all(m in raw["static"].names for m in ("RASI", "LASI", "RPSI", "LPSI")):
        if all(m in raw["static"].names for m in ("RANK", "LANK")):
            validate_static(subj, raw["static"])    # the static against the subject file first
        check_same_subject(raw["static"], [v for k, v in raw.items() if k != "static"])
    else:
        check_trial_legs(subj, raw["trial"])
    notes: list[str] = []
    gap_log: list[dict] = []
    filled = {k: _filled(raw[k], max_gap, Path(paths[k]).name, notes, gap_log) for k in raw}
    rec = reconstruct(filled["trial"], method, static=filled.get("static"), subject=subj,
                      functional=filled.get("functional"))
    if np.all(~np.isfinite(rec.angle_table())):
        raise InputError(trial, "no frame could be reconstructed (markers missing in every frame?)")
    inputs = {"trial": trial, "static": static, "functional": functional, "subject": subject}
    lab, lab_problem = _lab(filled.get("static"), filled["trial"])
    return LegReconstruction(rec, filled["trial"], inputs, tuple(notes) + tuple(rec.notes), tuple(gap_log),
                             lab, lab_problem)


def _lab(static: MarkerTrial | None, trial: MarkerTrial) -> tuple[LabFrame | None, str]:
    """The lab read from the data, or None and the one-line reason (reported, not yet enforced)."""
    from kinematics.gait.lab_frame import detect_lab

    try:
        return detect_lab(static, [trial]), ""
    except InputError as exc:
        return None, str(exc)


def _sd(cov) -> list[float]:
    return [float(v) for v in np.sqrt(np.clip(np.diag(cov), 0, None))]


def leg_report(result: LegReconstruction) -> dict:
    """The ``report.json`` document (JSON types; units stated in it)."""
    rec = result.reconstruction
    report = {
        "method": rec.method,
        **{k: None if result.inputs[k] is None else str(result.inputs[k]) for k in ("trial", "static", "functional")},
        "subject": str(result.inputs["subject"]),
        "units": {"centres": "mm (centres.trc)", "angles": "deg (angles.mot)", "centre_sd": "mm", "hip_in_pelvis": "m"},
        "frame": "lab frame of the trial; segment axes x anterior, y left, z proximal (Plug-in-Gait)",
        "notes": list(result.notes), "gaps": list(result.gaps),
        "centre_sd_mm": {k: [v * 1e3 for v in _sd(c)] for k, c in rec.centre_cov.items()},
        "hip_in_pelvis": {s: {"position": [float(v) for v in e.proximal], "sd": _sd(e.cov_proximal),
                              "rms_m": float(e.rms), "frames": int(e.n_frames)} for s, e in rec.hip_in_pelvis.items()},
        "valid_frames": result.valid_frames, "frames": result.frames,
    }
    if rec.weights:
        # blend: the foot-to-hip chain's per-frame weight per segment (median and 10-90 % range)
        report["chain_weights_foot_to_hip"] = {
            k: {"median": float(np.nanmedian(w)), "p10": float(np.nanpercentile(w, 10)), "p90": float(np.nanpercentile(w, 90))}
            for k, w in rec.weights.items() if np.isfinite(w).any()}
        report["chain_residual_mm_median"] = {
            c: {k: float(np.nanmedian(r) * 1e3) for k, r in res.items() if np.isfinite(r).any()}
            for c, res in rec.residuals.items()}
    return report


def write_leg_reconstruction(result: LegReconstruction, out: str | os.PathLike, *, plot: bool = True) -> Path:
    """Write centres.trc, angles.mot, angles.png (``plot``) and report.json into ``out``, replacing it whole.

    Check ``out`` first with `personalize.outputs.check_output_dir` (an existing folder is replaced).
    """
    from kinematics.gait.reconstruction import ANGLE_COLUMNS, CENTRE_MARKERS
    from kinematics.io.storage import write_mot, write_trc
    from lowerlimb.json_format import json_text
    from lowerlimb.atomic import inside, write_text

    from .outputs import replaced_dir
    from .presentation.trial_curves import plot_angles

    rec, tr = result.reconstruction, result.trial
    with replaced_dir(out) as stage:
        names = tuple(CENTRE_MARKERS[k] for k in CENTRE_MARKERS)
        pos = np.stack([rec.centres[k] for k in CENTRE_MARKERS], axis=1)
        write_trc(inside(stage, "centres.trc"), MarkerTrial(names, pos, tr.rate, tr.time, "centres.trc"))
        write_mot(inside(stage, "angles.mot"), ANGLE_COLUMNS, tr.time, rec.angle_table(), rotational=ANGLE_COLUMNS,
                  name=f"JointAngles_{rec.method}")
        if plot:
            plot_angles(inside(stage, "angles.png"), tr.time, rec.angles)
        write_text(inside(stage, "report.json"), json_text(leg_report(result)) + "\n")
    return Path(out)
