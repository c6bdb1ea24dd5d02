"""A phantom subject's truth and the pipeline's errors against it (frames, centres, axes, joint angles).

A phantom subject folder (`personalize.evaluation.phantom_subject.write_phantom_subject`)
holds ``truth.json`` (scanner frame) and ``truth/static_centres.trc`` (the true static
joint centres in the lab's own axes, as the trials are written); `truth_in_static_lab` maps the
truth to the internal frame the run works in (the trials' lab read by the run,
`SubjectInputs.lab`, x_internal = lab.internal_from_lab @ x_lab: the same map as the trials),
`errors_against_truth` and `angle_errors_against_truth` measure a run against it.  The joint
angles compared (hip, knee, ankle) are relative angles between segments: frame-free.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lowerlimb.errors import InputError
from lowerlimb.geometry import kabsch

__all__ = ["read_truth", "truth_in_static_lab", "errors_against_truth", "angle_errors_against_truth", "TRUTH_ANGLES",
           "chain_angle_errors", "TruthComparison", "compare_with_truth"]


def read_truth(path: Path) -> dict | None:
    """truth.json of a phantom subject (None when absent); `InputError` when it is not what the phantom writes."""
    if not path.is_file():
        return None
    try:
        truth = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(path, f"not readable JSON ({' '.join(str(exc).split())})") from None
    if not isinstance(truth, dict):
        raise InputError(path, f"holds a JSON {type(truth).__name__}, expected an object")
    joints = truth.get("joints")
    if joints is not None:
        J = joints.get("joints") if isinstance(joints, dict) else None
        try:
            ok = isinstance(J, dict) and all(
                isinstance(v, dict) and np.shape(v.get("origin")) == (3,) and np.shape(v.get("rotation")) == (3, 3)
                and np.all(np.isfinite(np.asarray(v.get("origin"), float)))
                and np.all(np.isfinite(np.asarray(v.get("rotation"), float))) for v in J.values())
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise InputError(path, "joints.joints must map each joint to an origin (3) and rotation (3x3)")
    return truth



#: joint -> its centre's marker in a phantom's ``truth/static_centres.trc``
STATIC_CENTRE_MARKERS = {"hip_r": "RHJC", "hip_l": "LHJC", "knee_r": "RKJC", "knee_l": "LKJC", "ankle_r": "RAJC",
                         "ankle_l": "LAJC"}


def true_static_centres(folder, internal_from_lab=None) -> dict | None:
    """True hip/knee/ankle centres of the static trial (``truth/static_centres.trc``, median over frames), or None.

    In the lab's axes, or with `internal_from_lab` (3, 3; `LabFrame.internal_from_lab`, summary.json
    ``lab.internal_from_lab``) in the run's internal frame.
    """
    from kinematics.io.storage import read_trc
    from personalize.pipeline.lab import rotate_points

    path = Path(folder) / "truth" / "static_centres.trc"
    if not path.is_file():
        return None
    cen = read_trc(path)
    out = {k: np.nanmedian(cen.marker(m), axis=0) for k, m in STATIC_CENTRE_MARKERS.items() if m in cen.names}
    if internal_from_lab is not None:
        R = np.asarray(internal_from_lab, float)
        out = {k: rotate_points(R, v) for k, v in out.items()}
    return out


def truth_in_static_lab(inputs) -> dict | None:
    """Phantom truth (joint centres, knee/ankle axes) in the run's internal frame, or None.

    The scanner -> internal map is the rigid fit (Kabsch) of truth.json's hip,
    knee and ankle joint origins onto the true static centres of
    ``truth/static_centres.trc`` (median over frames) mapped by the run's lab
    (`inputs.lab`, as the trials are); its rms is returned.
    """
    tr = inputs.truth
    lab = getattr(inputs, "lab", None)
    R = None if lab is None else lab.internal_from_lab
    centres = true_static_centres(inputs.folder, R) if tr is not None and "joints" in tr else None
    if centres is None:
        return None
    J = tr["joints"]["joints"]
    P, Q = [], []
    for k, c in centres.items():
        if k in J:
            P.append(J[k]["origin"])
            Q.append(c)
    if len(P) < 3:
        return None
    P, Q = np.array(P, float), np.array(Q, float)
    R, t = kabsch(P, Q)
    rms = float(np.sqrt(np.mean(np.sum((P @ R.T + t - Q) ** 2, axis=1))))
    out = {"rms_m": rms, "centres": {}, "axes": {}}
    for k, v in J.items():
        out["centres"][k] = R @ np.asarray(v["origin"], float) + t
        out["axes"][k] = R @ np.asarray(v["rotation"], float)[:, 2]
    return out


def errors_against_truth(est, truth: dict) -> dict:
    """Per side and source: hip/knee/ankle centre errors (mm) and knee/ankle axis errors (deg), plus the worst side.

    `est` : `personalize.pipeline.JointEstimates`; `truth` : `truth_in_static_lab`.
    """
    per_side = {}
    for s in est.centres:
        row = {}
        for jn in ("hip", "knee", "ankle"):
            t = truth["centres"].get(f"{jn}_{s}")
            if t is None:
                continue
            e = est.centres[s][jn]
            row[f"{jn}_centre_mm"] = {"mri": 1e3 * float(np.linalg.norm(e.mri.mean - t)),
                                      "motion": 1e3 * float(np.linalg.norm(e.motion.mean - t)),
                                      "fused": 1e3 * float(np.linalg.norm(e.fused.mean - t))}
        for jn in ("knee", "ankle"):
            t = truth["axes"].get(f"{jn}_{s}")
            if t is None:
                continue
            e = est.axes[s][jn]
            row[f"{jn}_axis_deg"] = {"mri": _angle_deg(e.mri.direction, t), "motion": _angle_deg(e.motion.direction, t),
                                     "fused": _angle_deg(e.fused.direction, t)}
        per_side[s] = row
    worst = {}
    for key in ("hip_centre_mm", "knee_centre_mm", "ankle_centre_mm", "knee_axis_deg", "ankle_axis_deg"):
        rows = [r[key] for r in per_side.values() if key in r]
        if rows:
            worst[key] = {src: max(r[src] for r in rows) for src in ("mri", "motion", "fused")}
    return {"worst": worst, "per_side": per_side}


#: joint angles compared with the phantom truth (both sides)
TRUTH_ANGLES = ("hip_flexion", "hip_adduction", "hip_rotation", "knee_flexion", "ankle_angle")


def angle_errors_against_truth(inputs, ik_results: dict, rotational) -> dict:
    """Joint-angle RMSE (deg) of the personalised model's IK against the phantom's true coordinates.

    For every gait trial with ``truth/<trial>.mot`` (else every non-functional
    dynamic trial), per coordinate of `TRUTH_ANGLES` and side:
    RMSE = √(mean_t (q_IK(t) - q_true(t))²) over the frames of all those trials
    (same coordinate names and conventions; a definitional offset between the
    personalised and the true joint frames counts as error).

    Returns
    -------
    rmse : dict coordinate (e.g. ``knee_flexion_r``) -> RMSE deg (empty when no truth is available)
    offset : dict coordinate -> mean (q_IK - q_true) deg, the constant part of the error (e.g. a
        personalised joint frame whose zero differs from the truth's)
    """
    from kinematics.io.storage import read_mot

    names = [k for k in ik_results if k.startswith("gait")] or [k for k in ik_results if k != "static"
                                                                 and not k.startswith("functional")]
    sq: dict[str, list] = {}
    for k in names:
        path = inputs.folder / "truth" / f"{k}.mot"
        if not path.is_file():
            continue
        tab = read_mot(path)
        res = ik_results[k]
        for c in (f"{a}_{s}" for s in inputs.sides for a in TRUTH_ANGLES):
            if c not in tab.columns or c not in res.coordinates or c not in rotational:
                continue
            qt = tab.values[:, tab.columns.index(c)]
            qt = qt if tab.in_degrees else np.degrees(qt)
            qi = np.degrees(res.q[:, res.coordinates.index(c)])
            qt = np.interp(res.time, tab.time, qt)
            d = qi - qt
            sq.setdefault(c, []).append(d[np.isfinite(d)])
    sq = {c: np.concatenate(v) for c, v in sq.items() if sum(map(len, v))}
    return ({c: float(np.sqrt(np.mean(d**2))) for c, d in sq.items()}, {c: float(np.mean(d)) for c, d in sq.items()})




def chain_angle_errors(inputs, chains: dict) -> dict:
    """RMSE (deg) of each chain's and the blend's Plug-in-Gait angles against the truth of the gait trials.

    `chains` : trial -> {chain name or "blend": reconstruction} (`personalize.pipeline.trials.chain_blend`);
    the truth is ``truth/<trial>_angles.mot``.  Per chain: the RMSE over the frames of each angle, averaged over
    the gait trials (``angle_rmse_deg``) and over the angles (``angle_rmse_deg_mean_over_angles``); {} without truth.
    """
    from kinematics.gait.reconstruction import ANGLE_COLUMNS
    from kinematics.io.storage import read_mot

    rmse: dict = {}
    for name, recs in chains.items():
        tpath = inputs.folder / "truth" / f"{name}_angles.mot"
        if not (name.startswith("gait") and tpath.is_file()):
            continue
        tab = read_mot(tpath)
        tv = tab.values if tab.in_degrees else np.degrees(tab.values)
        for m, r in recs.items():
            d = np.degrees(r.angle_table()) - np.array([np.interp(r.time, tab.time, tv[:, tab.columns.index(c)])
                                                        for c in ANGLE_COLUMNS]).T
            rmse.setdefault(m, []).append(np.sqrt(np.nanmean(d**2, axis=0)))
    if not rmse:
        return {}
    return {"angle_rmse_deg_mean_over_angles": {m: float(np.mean(v)) for m, v in rmse.items()},
            "angle_rmse_deg": {m: dict(zip(ANGLE_COLUMNS, np.mean(v, axis=0).tolist())) for m, v in rmse.items()}}


def _angle_deg(u, v) -> float:
    c = abs(float(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v))))
    return float(np.degrees(np.arccos(min(1.0, c))))


@dataclass(frozen=True)
class TruthComparison:
    """A run measured against its phantom's truth (summary.json's truth fields).

    truth : `truth_in_static_lab`; errors : `errors_against_truth`; angle_rmse_deg, angle_offset_deg :
    `angle_errors_against_truth`; skin_error_mm : marker -> used minus drawn pelvic soft tissue (mm)
    """

    truth: dict
    errors: dict
    angle_rmse_deg: dict
    angle_offset_deg: dict
    skin_error_mm: dict

    def to_json(self) -> dict:
        out = {}
        if self.angle_rmse_deg:
            out["angle_rmse_deg"] = self.angle_rmse_deg
            out["angle_offset_deg"] = self.angle_offset_deg
        out["errors"] = {k: self.errors["worst"][k] for k in ("hip_centre_mm", "knee_axis_deg", "ankle_axis_deg",
                                                              "knee_centre_mm", "ankle_centre_mm") if k in self.errors["worst"]}
        out["errors_per_side"] = self.errors["per_side"]
        out["truth_frame"] = {"scanner_to_static_lab_rms_m": self.truth["rms_m"],
                              "method": "Kabsch fit of truth.json joint origins to truth/static_centres.trc"}
        return out


def compare_with_truth(inputs, truth: dict, est, ik_results: dict, rotational) -> TruthComparison:
    """`TruthComparison` of a run: `personalize.pipeline.SubjectInputs`, its `truth_in_static_lab`, the
    `JointEstimates` and the IK results (trial -> `kinematics.algorithms.ik` result)."""
    ang, off = angle_errors_against_truth(inputs, ik_results, rotational)
    true_skin = ((inputs.truth or {}).get("image") or {}).get("skin", {}).get("sites", {})
    skin = {k: 1e3 * (v.thickness - true_skin[k]["thickness"]) for k, v in est.skin.items() if k in true_skin}
    return TruthComparison(truth, errors_against_truth(est, truth), ang, off, skin)
