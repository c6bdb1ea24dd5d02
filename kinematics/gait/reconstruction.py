"""Per-method leg reconstruction from marker trials: joint centres, segment poses, angles.

`reconstruct(trial, method, static=..., subject=..., functional=...)` runs

* ``"pig"``: Plug-in-Gait (`kinematics.gait.pig`), hip-first: Davis regression hip
  centres (or, with a functional trial, the SCoRE hip centre of the pelvis
  and thigh marker clusters), chord-function knee and ankle centres, foot
  offsets from the static trial;
* ``"foot-to-hip"``: the seed's foot-first model (`kinematics.gait.foot_to_hip`):
  knee and ankle axes and centres from the foot and shank markers, the hip
  centre by the centre transformation technique, from the functional trial
  when given, else from the trial itself;
* ``"blend"``: both chains, each segment's pose blended frame by frame with
  Gaussian weights from each chain's rigid marker residual on that segment
  (`kinematics.gait.chain_blend`; needs the static trial), angles recomputed from
  the blended segments; ``Reconstruction.weights`` holds the foot-to-hip
  chain's weight per segment and frame.

Both return the same `Reconstruction`: segment frames in the Plug-in-Gait
convention (x anterior, y left, z proximal; ``tibia_r`` aligned with the knee
axis, ``tibia_torsioned_r`` with the ankle axis), centres in the lab, and the
Plug-in-Gait joint angles (flexion, adduction, internal rotation; the ankle
dorsiflexion, inversion, internal rotation), so that the two methods compare
directly with each other and with Nexus' RHipAngles, RKneeAngles, RAnkleAngles.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kinematics.gait.chain_blend import CENTRE_SEGMENT, blend_poses, chain_residuals
from lowerlimb.errors import FitError, InputError
from kinematics.gait.foot_to_hip import (REQUIRED_MARKERS, FootToHipCalibration, calibrate, hip_centre_in_pelvis,
                          knee_ankle_axes, seed_femur_frame)
from kinematics.algorithms.functional import score
from kinematics.io.markers import MarkerTrial
from kinematics.gait.pig import (LOWER_BODY_MARKERS, SegmentPose, chord_centre_jacobians, joint_angles, leg_angles, leg_chain,
                  median_covariance, pelvis_frame, plug_in_gait, sacrum_marker, static_foot_offsets, unit_vectors)
from kinematics.gait.subject import SubjectMeasurements, validate_static

__all__ = ["Reconstruction", "reconstruct", "METHODS", "ANGLE_COLUMNS", "CENTRE_MARKERS", "tibia_fluctuation"]

METHODS = ("pig", "foot-to-hip", "blend")
SIDES = (("R", "_r"), ("L", "_l"))
#: angles.mot columns (degrees in the file)
ANGLE_COLUMNS = tuple(f"{j}_{a}_{s}" for s in ("r", "l") for j in ("hip", "knee", "ankle")
                      for a in ("flexion", "adduction", "rotation"))
#: virtual marker name of each centre
CENTRE_MARKERS = {"hip_r": "RHJC", "hip_l": "LHJC", "knee_r": "RKJC", "knee_l": "LKJC", "ankle_r": "RAJC", "ankle_l": "LAJC"}


@dataclass(frozen=True)
class Reconstruction:
    """Result of one method on one trial (SI units, lab frame).

    method : 'pig' or 'foot-to-hip'
    time : (F,) s
    centres : dict ``hip_r``, ``knee_r``, ``ankle_r``, ``_l`` -> (F, 3) m
    centre_cov : dict name -> (3, 3) m², lab-frame covariance (median over frames)
    segments : dict ``pelvis``, ``femur_r``, ``tibia_r``, ``tibia_torsioned_r``, ``foot_r``, ... -> SegmentPose
    angles : dict ``hip_r``, ``knee_r``, ``ankle_r``, ... -> (F, 3) rad, Plug-in-Gait sign conventions
    hip_in_pelvis : dict side -> kinematics.algorithms.functional.CentreEstimate (functional/CTT hip centres; empty for Davis)
    notes : tuple of str (calibration source, missing calibrations, ...)
    weights : dict segment -> (F,) weight of the foot-to-hip chain (``blend`` only)
    residuals : dict chain (``pig``, ``foot-to-hip``) -> dict segment -> (F,) m (``blend`` only)
    chains : dict chain -> the Reconstruction it blended (``blend`` only)
    """

    method: str
    time: np.ndarray
    centres: dict
    centre_cov: dict
    segments: dict
    angles: dict
    hip_in_pelvis: dict = field(default_factory=dict)
    notes: tuple = ()
    source: str | None = None
    weights: dict = field(default_factory=dict)
    residuals: dict = field(default_factory=dict)
    chains: dict = field(default_factory=dict)

    def angle_table(self) -> np.ndarray:
        """(F, 18) radians in the order of `ANGLE_COLUMNS`."""
        cols = []
        for s in ("r", "l"):
            for j in ("hip", "knee", "ankle"):
                cols.append(self.angles[f"{j}_{s}"])
        return np.concatenate(cols, axis=1)


def _require(trial: MarkerTrial, method: str) -> None:
    if method == "pig":
        need = list(LOWER_BODY_MARKERS)
    elif method == "foot-to-hip":
        need = ["RASI", "LASI"] + [f"{s}{m}" for s, _ in SIDES for m in REQUIRED_MARKERS]
    else:  # functional trial for PiG (SCoRE): the pelvis; thigh clusters are checked when used
        need = ["RASI", "LASI"]
    missing = [m for m in need if m not in trial.names]
    if "SACR" not in trial.names:
        missing += [m for m in ("RPSI", "LPSI") if m not in trial.names]
    if missing:
        raise InputError(trial.source, f"missing markers for {method}: {', '.join(missing)} (SACR may replace RPSI+LPSI)")


def _check_geometry(trial: MarkerTrial) -> None:
    """Refuse trials in the wrong unit or with left/right swapped (mirrored) before any result is made.

    The inter-ASIS marker distance must be 0.15-0.45 m, and the knee markers
    must lie below the pelvis: on the negative side of the pelvis z axis
    (z = x × y with y from RASI to LASI), which flips when the sides are swapped.
    """
    d = np.linalg.norm(trial.marker("RASI") - trial.marker("LASI"), axis=1)
    d = d[np.isfinite(d)]
    if d.size == 0:
        raise InputError(trial.source, "RASI and LASI are never visible together")
    if not 0.15 < float(np.median(d)) < 0.45:
        raise InputError(trial.source, f"inter-ASIS marker distance {np.median(d):.4g} m is implausible "
                                       "(expected 0.15-0.45 m): wrong units in the file?")
    pel = pelvis_frame(trial.marker("RASI"), trial.marker("LASI"), sacrum_marker(trial))
    for s in "RL":
        if f"{s}KNE" not in trial.names:
            continue
        h = pel.to_local(trial.marker(f"{s}KNE"))[:, 2]
        h = h[np.isfinite(h)]
        if h.size and np.median(h) > 0:
            raise InputError(trial.source, f"{s}KNE lies above the pelvis in the pelvis frame: left and right "
                                           "marker labels swapped, or a mirrored (left-handed) lab frame?")


def _frame(origin, z, y_hint) -> SegmentPose:
    z = unit_vectors(z)
    y = unit_vectors(y_hint - np.sum(y_hint * z, -1, keepdims=True) * z)
    return SegmentPose(np.asarray(origin, float), np.stack([np.cross(y, z), y, z], axis=-1))


def _frame_y(origin, y, z_hint) -> SegmentPose:
    """Frame with y exact (a hinge axis) and z the component of z_hint orthogonal to it."""
    z = unit_vectors(z_hint - np.sum(z_hint * y, -1, keepdims=True) * y)
    return SegmentPose(np.asarray(origin, float), np.stack([np.cross(y, z), y, z], axis=-1))


def _foot(trial: MarkerTrial, s: str, tibia_torsioned: SegmentPose) -> SegmentPose:
    """Anatomical foot: origin TOE, z = unit(HEE - TOE), x = unit(y_tibia × z) (Plug-in-Gait's corrected foot)."""
    toe, hee = trial.marker(f"{s}TOE"), trial.marker(f"{s}HEE")
    z = unit_vectors(hee - toe)
    x = unit_vectors(np.cross(tibia_torsioned.axes[..., 1], z))
    return SegmentPose(toe, np.stack([x, np.cross(z, x), z], axis=-1))


def _functional_hips_score(functional: MarkerTrial) -> dict:
    """SCoRE hip centres in the Plug-in-Gait pelvis frame from the pelvis and thigh marker clusters."""
    from kinematics.algorithms.segments import cluster_reference, rigid_pose

    out = {}
    pel = pelvis_frame(functional.marker("RASI"), functional.marker("LASI"), sacrum_marker(functional))
    for s, _ in SIDES:
        thigh = [m for m in (f"{s}THI", f"{s}KNE", f"{s}THIP", f"{s}THIA", f"{s}KNEM") if m in functional.names]
        if len(thigh) < 3:
            raise InputError(functional.source, f"functional hip (SCoRE) needs 3 {s} thigh markers; found {', '.join(thigh) or 'none'}")
        b = functional.subset(thigh).positions
        try:
            ref = cluster_reference(b)
        except FitError as exc:
            raise InputError(functional.source, str(exc)) from None
        D = rigid_pose(ref, b)
        try:
            out[s] = score(pel.axes, pel.origin, D.R, D.t)
        except FitError as exc:
            raise InputError(functional.source, f"{s} functional hip centre: {exc}") from None
    return out


def _pig_with_hips(trial: MarkerTrial, subject: SubjectMeasurements, hips_local: dict) -> tuple[dict, dict, dict]:
    """Plug-in-Gait chain (segments under `kinematics.gait.pig` names) with given hip centres (pelvis frame)
    instead of the Davis regression."""
    pelvis = pelvis_frame(trial.marker("RASI"), trial.marker("LASI"), sacrum_marker(trial))
    legs, centres = leg_chain(trial, subject, {s: pelvis.to_lab(hips_local[s]) for s, _ in SIDES})
    return {"pelvis": pelvis, **legs}, centres, pelvis


def _our_segment_names(pig_segments: dict) -> dict:
    """Plug-in-Gait segments under this module's names: ``tibia`` untorsioned, ``tibia_torsioned`` with torsion."""
    segs = {"pelvis": pig_segments["pelvis"]}
    for _, sfx in SIDES:
        segs[f"femur{sfx}"] = pig_segments[f"femur{sfx}"]
        segs[f"tibia{sfx}"] = pig_segments[f"tibia_untorsioned{sfx}"]
        segs[f"tibia_torsioned{sfx}"] = pig_segments[f"tibia{sfx}"]
        if f"foot{sfx}" in pig_segments:
            segs[f"foot{sfx}"] = pig_segments[f"foot{sfx}"]
    return segs


def _chord_cov(trial, subject, s, centres, pelvis, cov_hip_pelvis, h: float = 1e-4) -> dict:
    """Lab covariances of the hip, knee and ankle centres from the functional hip covariance.

    Cov(hip) = R_p C R_pᵀ per frame; the knee and ankle inherit it through the
    chord functions: Cov(knee) = J_k Cov(hip) J_kᵀ, J_k = ∂knee/∂hip (central
    differences), likewise the ankle through ∂ankle/∂knee; median over frames.
    """
    sfx = "_r" if s == "R" else "_l"
    Jk, Ja = chord_centre_jacobians(trial, subject, s, centres[f"hip{sfx}"], centres[f"knee{sfx}"], h)
    R = pelvis.axes
    c_hip = R @ cov_hip_pelvis @ np.swapaxes(R, 1, 2)
    c_knee = Jk @ c_hip @ np.swapaxes(Jk, 1, 2)
    c_ankle = Ja @ c_knee @ np.swapaxes(Ja, 1, 2)
    return {f"hip{sfx}": median_covariance(c_hip), f"knee{sfx}": median_covariance(c_knee), f"ankle{sfx}": median_covariance(c_ankle)}


def _reconstruct_pig(trial, subject, static, functional, notes, hip_est=None) -> Reconstruction:
    if static is not None:
        subject = static_foot_offsets(static, subject)
    if functional is None:
        res = plug_in_gait(trial, subject)
        segs = _our_segment_names(res.segments)
        notes += list(res.notes)
        return Reconstruction("pig", trial.time, res.centres, res.centre_cov, segs, res.angles, {}, tuple(notes), trial.source)
    if hip_est is None:
        hip_est = _functional_hips_score(functional)
    pig_segs, centres, pelvis = _pig_with_hips(trial, subject, {s: e.proximal for s, e in hip_est.items()})
    angles, pig_notes = leg_angles(trial, subject, pig_segs, centres, "no static trial")
    notes += pig_notes
    segs = _our_segment_names(pig_segs)
    cov = {}
    for s, _ in SIDES:
        cov.update(_chord_cov(trial, subject, s, centres, pelvis, hip_est[s].cov_proximal))
    notes.append("hip centres: SCoRE on the functional trial (pelvis and thigh clusters)")
    return Reconstruction("pig", trial.time, centres, cov, segs, angles, {s: e for s, e in hip_est.items()},
                          tuple(notes), trial.source)


def _shanks(trial: MarkerTrial, cal: FootToHipCalibration) -> dict:
    M = trial.marker
    return {s: knee_ankle_axes(M(f"{s}KNE"), M(f"{s}ANK"), M(f"{s}HEE"), M(f"{s}TOE"), cal.d_knee[s], cal.d_ankle[s], s,
                               cal.foot_offset[s], cal.axis_rotation[s]) for s, _ in SIDES}


def _ctt_hips(trial: MarkerTrial, cal: FootToHipCalibration, planar: bool = True) -> dict:
    pelvis = pelvis_frame(trial.marker("RASI"), trial.marker("LASI"), sacrum_marker(trial))
    out = {}
    for s, sh in _shanks(trial, cal).items():
        fem = seed_femur_frame(sh.knee, sh.knee_axis, trial.marker(f"{s}THI"), s)
        try:
            out[s] = hip_centre_in_pelvis(pelvis, fem, planar)
        except FitError as exc:
            raise InputError(trial.source, f"{s} hip centre cannot be found from this trial ({exc}); "
                                           "give a functional hip trial") from None
    return out


def _shank_cov(trial: MarkerTrial, cal: FootToHipCalibration, s: str, sd: float, n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """First-order covariance of the knee and ankle centres from isotropic marker noise `sd` (m)."""
    names = [f"{s}KNE", f"{s}ANK", f"{s}HEE", f"{s}TOE"]
    X = np.stack([trial.marker(m) for m in names], axis=1)
    ok = np.flatnonzero(np.all(np.isfinite(X), axis=(1, 2)))
    if ok.size == 0:
        return np.full((3, 3), np.nan), np.full((3, 3), np.nan)
    idx = ok[np.linspace(0, ok.size - 1, min(n, ok.size)).astype(int)]
    X = X[idx]
    h = 1e-5
    Jk = np.zeros((len(idx), 3, 12))
    Ja = np.zeros((len(idx), 3, 12))
    for j in range(12):
        dX = np.zeros_like(X)
        dX[:, j // 3, j % 3] = h
        p = knee_ankle_axes(*(X + dX).transpose(1, 0, 2), cal.d_knee[s], cal.d_ankle[s], s, cal.foot_offset[s], cal.axis_rotation[s])
        m = knee_ankle_axes(*(X - dX).transpose(1, 0, 2), cal.d_knee[s], cal.d_ankle[s], s, cal.foot_offset[s], cal.axis_rotation[s])
        Jk[:, :, j] = (p.knee - m.knee) / (2 * h)
        Ja[:, :, j] = (p.ankle - m.ankle) / (2 * h)
    return (median_covariance(sd**2 * Jk @ np.swapaxes(Jk, 1, 2)), median_covariance(sd**2 * Ja @ np.swapaxes(Ja, 1, 2)))


def _reconstruct_f2h(trial, subject, static, functional, notes, marker_sd, hip_est=None) -> Reconstruction:
    cal = calibrate(subject, static)
    notes.append(f"foot-to-hip calibration: {cal.source}")
    if hip_est is None:
        # a functional (star-arc) trial shows hip abduction, which makes the out-of-plane coordinate observable
        hip_est = _ctt_hips(functional if functional is not None else trial, cal, planar=functional is None)
        notes.append("hip centres: centre transformation technique on "
                     + ("the functional trial (3-D)" if functional is not None
                        else "this trial, in the thigh-shank plane (eq. 30; no functional trial given)"))
    pelvis = pelvis_frame(trial.marker("RASI"), trial.marker("LASI"), sacrum_marker(trial))
    segs = {"pelvis": pelvis}
    centres, cov, angles = {}, {}, {}
    for (s, sfx), sh in zip(SIDES, _shanks(trial, cal).values()):
        hip = pelvis.to_lab(hip_est[s].proximal)
        left = -sh.knee_axis if s == "R" else sh.knee_axis
        aleft = -sh.ankle_axis if s == "R" else sh.ankle_axis
        # revolute knee (the seed's model): femur and tibia share the knee axis as their y axis;
        # the femur's long axis points to the femur-fixed hip centre of eq. (37)
        seed_femur = seed_femur_frame(sh.knee, sh.knee_axis, trial.marker(f"{s}THI"), s)
        hip_f = seed_femur.to_lab(hip_est[s].distal)
        segs[f"femur{sfx}"] = _frame_y(sh.knee, left, hip_f - sh.knee)
        segs[f"tibia{sfx}"] = _frame_y(sh.ankle, left, sh.knee - sh.ankle)
        segs[f"tibia_torsioned{sfx}"] = _frame(sh.ankle, sh.knee - sh.ankle, aleft)
        segs[f"foot{sfx}"] = _foot(trial, s, segs[f"tibia_torsioned{sfx}"])
        centres.update({f"hip{sfx}": hip, f"knee{sfx}": sh.knee, f"ankle{sfx}": sh.ankle})
        angles[f"hip{sfx}"] = joint_angles(pelvis, segs[f"femur{sfx}"], "hip", s)
        angles[f"knee{sfx}"] = joint_angles(segs[f"femur{sfx}"], segs[f"tibia{sfx}"], "knee", s)
        angles[f"ankle{sfx}"] = joint_angles(segs[f"tibia_torsioned{sfx}"], segs[f"foot{sfx}"], "ankle", s)
        R = pelvis.axes
        cov[f"hip{sfx}"] = median_covariance(R @ hip_est[s].cov_proximal @ np.swapaxes(R, 1, 2))
        cov[f"knee{sfx}"], cov[f"ankle{sfx}"] = _shank_cov(trial, cal, s, marker_sd)
    return Reconstruction("foot-to-hip", trial.time, centres, cov, segs, angles, hip_est, tuple(notes), trial.source)


def _fill_residual(r: np.ndarray, pose: SegmentPose) -> np.ndarray:
    """A frame whose pose exists but whose segment markers are hidden takes the chain's median residual."""
    ok_pose = np.all(np.isfinite(pose.axes), axis=(1, 2)) & np.all(np.isfinite(pose.origin), axis=1)
    fill = float(np.nanmedian(r)) if np.isfinite(r).any() else 1.0
    return np.where(np.isfinite(r), r, np.where(ok_pose, fill, np.nan))


def _reconstruct_blend(trial, subject, static, functional, notes, marker_sd) -> Reconstruction:
    if static is None:
        raise InputError("--static", "the blended chains need the static trial (each chain's markers in its "
                                     "segment frames are taken from it)")
    a = _reconstruct_pig(trial, subject, static, functional, [])
    b = _reconstruct_f2h(trial, subject, static, functional, [], marker_sd)
    a0 = _reconstruct_pig(static, subject, static, functional, [], hip_est=a.hip_in_pelvis or None)
    b0 = _reconstruct_f2h(static, subject, static, functional, [], marker_sd, hip_est=b.hip_in_pelvis)
    ra = chain_residuals(a.segments, trial, a0.segments, static)
    rb = chain_residuals(b.segments, trial, b0.segments, static)
    segs, weights = {}, {}
    for name, pa in a.segments.items():
        pb = b.segments.get(name)
        if pb is None:
            segs[name] = pa
            continue
        bl = blend_poses(pa, pb, _fill_residual(ra[name], pa), _fill_residual(rb[name], pb))
        segs[name], weights[name] = bl.as_segment_pose(), bl.weight_b
    centres, cov, angles = {}, {}, {}
    for s, sfx in SIDES:
        for j, seg in CENTRE_SEGMENT.items():
            w = weights[f"{seg}{sfx}"][:, None]
            ca, cb = a.centres[f"{j}{sfx}"], b.centres[f"{j}{sfx}"]
            centres[f"{j}{sfx}"] = np.where(np.isfinite(ca) & np.isfinite(cb), (1 - w) * ca + w * cb,
                                            np.where(np.isfinite(ca), ca, cb))
            wm = float(np.nanmedian(w)) if np.isfinite(w).any() else 0.5
            cov[f"{j}{sfx}"] = (1 - wm) ** 2 * a.centre_cov[f"{j}{sfx}"] + wm**2 * b.centre_cov[f"{j}{sfx}"]
        angles[f"hip{sfx}"] = joint_angles(segs["pelvis"], segs[f"femur{sfx}"], "hip", s)
        angles[f"knee{sfx}"] = joint_angles(segs[f"femur{sfx}"], segs[f"tibia{sfx}"], "knee", s)
        angles[f"ankle{sfx}"] = joint_angles(segs[f"tibia_torsioned{sfx}"], segs[f"foot{sfx}"], "ankle", s)
    med = ", ".join(f"{k} {np.nanmedian(v):.2f}" for k, v in weights.items() if np.isfinite(v).any())
    notes += [f"pig: {n}" for n in a.notes] + [f"foot-to-hip: {n}" for n in b.notes]
    notes.append(f"blend: per-frame Gaussian weights from each chain's rigid marker residual; median foot-to-hip "
                 f"weight per segment: {med}")
    return Reconstruction("blend", trial.time, centres, cov, segs, angles, a.hip_in_pelvis, tuple(notes), trial.source,
                          weights, {"pig": ra, "foot-to-hip": rb}, {"pig": a, "foot-to-hip": b})


def reconstruct(trial: MarkerTrial, method: str = "pig", *, static: MarkerTrial | None = None,
                subject: SubjectMeasurements, functional: MarkerTrial | None = None,
                marker_sd: float = 0.001, check_static: bool = True) -> Reconstruction:
    """Joint centres, segment frames and Plug-in-Gait joint angles of a marker trial.

    Parameters
    ----------
    trial : MarkerTrial (lab frame, metres, Z up)
    method : 'pig', 'foot-to-hip' or 'blend' (both, blended per frame; needs `static`)
    static : static trial of the same subject (foot offsets, foot-to-hip calibration, leg-length check)
    subject : SubjectMeasurements (leg lengths, knee/ankle widths, marker diameter, tibial torsion)
    functional : hip calibration trial (star-arc); PiG: SCoRE hip centres of the thigh clusters,
        foot-to-hip: the centre transformation on its eq. (29) femur frames
    marker_sd : m, marker noise assumed for the foot-to-hip knee/ankle covariances
    check_static : refuse a static trial whose ASIS-ankle distances do not match the leg lengths

    Returns
    -------
    Reconstruction
    """
    if method not in METHODS:
        raise InputError("--method", f"unknown method {method!r} (pig, foot-to-hip or blend)")
    for m in (("pig", "foot-to-hip") if method == "blend" else (method,)):
        _require(trial, m)
    _check_geometry(trial)
    notes: list[str] = []
    if static is not None:
        for m in (("pig", "foot-to-hip") if method == "blend" else (method,)):
            _require(static, m)
        _check_geometry(static)
        if check_static:
            validate_static(subject, static)
    if functional is not None:
        _require(functional, "functional" if method == "pig" else "foot-to-hip")
        _check_geometry(functional)
    if method == "pig":
        return _reconstruct_pig(trial, subject, static, functional, notes)
    if method == "blend":
        return _reconstruct_blend(trial, subject, static, functional, notes, marker_sd)
    return _reconstruct_f2h(trial, subject, static, functional, notes, marker_sd)


def tibia_fluctuation(tibia: SegmentPose, markers: np.ndarray) -> np.ndarray:
    """Average position fluctuation of markers relative to a tibia frame (the seed's Fig. 20).

    For each marker, its path p_f in the frame and the mean position p̄: the
    mean over frames of |p_f - p̄|.  markers (F, M, 3) lab -> (M,) m.
    """
    local = np.einsum("fji,fmj->fmi", tibia.axes, markers - tibia.origin[:, None])
    ok = np.all(np.isfinite(local), axis=(1, 2))
    local = local[ok]
    return np.mean(np.linalg.norm(local - local.mean(axis=0), axis=2), axis=0)
