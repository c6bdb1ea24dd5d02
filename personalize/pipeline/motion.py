"""Joint estimates from motion capture alone, in the lab frame of the static trial (m, unit vectors).

Marker clusters are referenced to their static positions, so a cluster frame
IS the static lab frame: SCoRE hip centres (pelvis vs thigh clusters, on the
functional trial), SARA knee axes (thigh vs shank clusters, on the other
dynamic trials); the Plug-in-Gait reconstruction of the static trial gives the
knee and ankle centres, the Davis hip and the torsioned-tibia ankle axis
(fall-backs without functional data or medial markers).  Each estimate carries
its covariance (sd) with the soft-tissue-artefact terms below, calibrated on
TRAINING phantoms (values and sources: ``calibration.json``).

Without the Plug-in-Gait markers (`has_pig_markers`) the centres come from
what the markers allow: the knee (ankle) centre is the midpoint of the lateral
and medial epicondyle (malleolus) markers moved in by marker radius + soft
tissue (`condylar_centre`), the knee (ankle) axis the line through them
(`condylar_axis`); the hip without a qualifying functional trial
(`hip_range_of_motion`) is the Harrington et al. (2007) regression of the
pelvis markers (`harrington_hip`).
"""
from __future__ import annotations

import numpy as np

from kinematics.io.markers import MarkerTrial
from lowerlimb.errors import InputError
from lowerlimb.estimates import Gaussian

from .inputs import PELVIS_MARKERS
from .joint_estimates import Direction

__all__ = ["motion_hip", "motion_knee_axis", "pig_static", "has_pig_markers", "MOTION_HIP_STA_COV",
           "MOTION_KNEE_AXIS_SD_DEG", "MOTION_ANKLE_AXIS_SD_DEG", "PIG_ANKLE_AXIS_SD_DEG", "PIG_CENTRE_SD",
           "DAVIS_HIP_SD", "PIG_KNEE_AXIS_SD_DEG", "THIGH_MARKERS", "SHANK_MARKERS", "PELVIS_CLUSTER",
           "hip_range_of_motion", "FUNCTIONAL_HIP_MIN_RANGE_DEG", "harrington_hip", "HARRINGTON_SD",
           "condylar_centre", "condylar_axis", "PALPATION_SD", "CONDYLAR_CENTRE_MODEL_SD", "CONDYLAR_AXIS_SD_DEG",
           "pelvis_rear", "subject_marker_radius", "pelvic_tissue", "davis_tissue_cov"]

#: soft-tissue-artefact covariance of a SCoRE hip centre (m²) in the pelvis axes (anterior, medial, up; left legs
#: mirrored): the second moment about zero of the training legs' SCoRE errors (sds 4.9, 7.2, 10.4 mm;
#: calibration.json ``motion_hip_sta_cov``)
MOTION_HIP_STA_COV = np.array([[23.7, 1.5, -21.4], [1.5, 51.6, 15.0], [-21.4, 15.0, 108.3]]) * 1e-6
#: soft-tissue-artefact sd of a SARA knee axis on skin-marker clusters: the largest per-anatomy Rayleigh maximum
#: likelihood of the realistic phantoms' SARA errors (analytic 10.3, ICL_MRI 4.8, LHDL_CT 3.0 deg; 40 legs of seed
#: 1000; benchmarks/axis_calibration.py, calibration.json)
MOTION_KNEE_AXIS_SD_DEG = 10.26
#: the transmalleolar axis ANK - ANKM of the static trial against the talocrural axis: the largest per-anatomy
#: Rayleigh maximum likelihood (LHDL_CT 10.5, ICL_MRI 5.7 deg, analytic 0.1: its malleolar markers sit on the
#: axis; 40 legs of seed 1000; the palpation value 3 deg had covered 60 %; benchmarks/axis_calibration.py)
MOTION_ANKLE_AXIS_SD_DEG = 10.48
#: Plug-in-Gait torsioned-tibia ankle axis (no medial malleolus marker): assumed sd, not calibrated
PIG_ANKLE_AXIS_SD_DEG = 6.0
#: Plug-in-Gait knee / ankle centre sd (m per axis), calibrated on TRAINING phantoms
#: (benchmarks/knee_ankle_calibration.py, mean Mahalanobis d² = 3; calibration.json)
PIG_CENTRE_SD = {"knee": 0.0051, "ankle": 0.0083}
#: fall-backs without functional data: Davis regression hip centre (errors ~1-3 cm, Leardini et al. 1999),
#: Plug-in-Gait knee axis from the KNE/THI markers
DAVIS_HIP_SD = 0.015
PIG_KNEE_AXIS_SD_DEG = 8.0

#: Plug-in-Gait and phantom technical markers of the thigh and shank clusters, internal names (side letter added);
#: `markers.MarkerView.segment_markers` adds every marker the marker set puts on the segment
THIGH_MARKERS = ("THI", "KNE", "THIP", "THIA", "MFC", "TRO")
SHANK_MARKERS = ("TIB", "ANK", "MMA", "TIBM1", "TIBM2", "TIBM3", "TTB", "HFB")
PELVIS_CLUSTER = PELVIS_MARKERS + ("SACR",)


def cluster_pose(static: MarkerTrial, trials, names):
    """Cluster poses over the concatenated trials; the cluster frame is the static lab frame."""
    from kinematics.algorithms.segments import rigid_pose

    from ..registration import static_marker_positions

    ref_of = {n: g.mean for n, g in static_marker_positions(static, names).items()}
    use = [n for n in ref_of if all(n in t.names for t in trials)]
    if len(use) < 3:
        return None
    ref = np.array([ref_of[n] for n in use])
    meas = np.concatenate([t.subset(use).positions for t in trials], axis=0)
    return rigid_pose(ref, meas)


def _sta_cov(axes, side: str) -> np.ndarray:
    """`MOTION_HIP_STA_COV` in the lab: A M Σ M Aᵀ (A the pelvis axes, M mirrors y for a left leg)."""
    M = np.diag([1.0, -1.0 if side == "l" else 1.0, 1.0])
    A = np.eye(3) if axes is None else np.asarray(axes, float)
    return A @ M @ MOTION_HIP_STA_COV @ M @ A.T


def motion_hip(static, functional: MarkerTrial, side: str, axes=None, *, pelvis=None, thigh=None):
    """SCoRE hip centre (static lab frame, m) as a `Gaussian`, and the SCoRE estimate itself.

    Cov = SCoRE's residual covariance + the soft-tissue-artefact term
    `MOTION_HIP_STA_COV` (pelvis axes `axes`, 3x3 columns x, y, z; the static
    lab axes if None).  `pelvis`, `thigh`: the clusters' marker names (default
    `PELVIS_CLUSTER`, `THIGH_MARKERS` with the side letter).
    """
    from kinematics.algorithms.functional import score

    S = side.upper()
    P = cluster_pose(static, [functional], PELVIS_CLUSTER if pelvis is None else tuple(pelvis))
    D = cluster_pose(static, [functional], tuple(S + m for m in THIGH_MARKERS) if thigh is None else tuple(thigh))
    if P is None or D is None:
        raise InputError(functional.source, f"SCoRE needs 3 pelvis and 3 {S} thigh markers")
    est = score(P.R, P.t, D.R, D.t)
    return Gaussian(est.proximal, est.cov_proximal + _sta_cov(axes, side)), est


def motion_knee_axis(static, trials, side: str, *, thigh=None, shank=None):
    """SARA knee axis (static lab frame) of the thigh and shank clusters over `trials`.

    sd = √(SARA's direction sd² + `MOTION_KNEE_AXIS_SD_DEG`²).  `thigh`, `shank`: the clusters' marker names
    (default `THIGH_MARKERS`, `SHANK_MARKERS` with the side letter).
    """
    from kinematics.algorithms.functional import sara

    S = side.upper()
    P = cluster_pose(static, trials, tuple(S + m for m in THIGH_MARKERS) if thigh is None else tuple(thigh))
    D = cluster_pose(static, trials, tuple(S + m for m in SHANK_MARKERS) if shank is None else tuple(shank))
    if P is None or D is None:
        raise InputError(static.source, f"SARA needs 3 {S} thigh and 3 {S} shank markers")
    est = sara(P.R, P.t, D.R, D.t)
    return Direction(est.direction_proximal, float(np.hypot(np.degrees(est.direction_sd), MOTION_KNEE_AXIS_SD_DEG)))



def pig_static(inputs, view=None):
    """Plug-in-Gait reconstruction of the static trial (knee and ankle centres, torsioned tibia), or None when
    neither the static trial nor its internal-name view (`view`, a `markers.MarkerView`) has the Plug-in-Gait
    markers (`has_pig_markers`)."""
    from kinematics.gait.reconstruction import reconstruct

    trial = next((t for t in (inputs.static, getattr(view, "static", None)) if t is not None and has_pig_markers(t)),
                 None)
    if trial is None:
        return None
    return reconstruct(trial, "pig", static=trial, subject=inputs.subject, check_static=False)



def has_pig_markers(trial: MarkerTrial) -> bool:
    """Whether `trial` carries the Plug-in-Gait lower-body markers (`kinematics.gait.pig.LOWER_BODY_MARKERS`, and
    RPSI + LPSI or SACR) that `pig_static` needs."""
    from kinematics.gait.pig import LOWER_BODY_MARKERS

    names = set(trial.names)
    return all(m in names for m in LOWER_BODY_MARKERS) and ("SACR" in names or {"RPSI", "LPSI"} <= names)


def subject_marker_radius(inputs) -> float | None:
    """Marker radius (m) from the subject's marker diameter (subject.json), or None (the default radius)."""
    from lowerlimb.geometry import marker_radius

    d = getattr(inputs.subject, "marker_diameter", None)
    return marker_radius(d) if d else None


def pelvis_rear(static: dict):
    """The pelvis' posterior reference (static lab, m) and what it is: mid-PSIS, else the sacral marker."""
    if "RPSI" in static and "LPSI" in static:
        return 0.5 * (static["RPSI"].mean + static["LPSI"].mean), "mid-PSIS"
    if "SACR" in static:
        return np.asarray(static["SACR"].mean, float), "sacral marker"
    raise InputError("static trial", "the pelvis needs RPSI and LPSI or a sacral marker (SACR, V.Sacral)")


# --------------------------------------------------------------------------- hip without a functional trial
#: the smallest hip ranges of motion (deg; 2.5-97.5 percentile spans of the thigh cluster's rotation in the pelvis
#: cluster) for which a trial's SCoRE hip centre is used.  The functional hip centre's error grows steeply as the
#: range shrinks, most along the axis the motion does not explore: Piazza et al. 2004 (J Biomech 37:349, errors grow
#: as the range falls below about 30 deg), Camomilla et al. 2006 (J Biomech 39:1096, flexion-extension AND
#: ab-adduction amplitudes of the star-arc motion they recommend).  Walking (about 40 deg flexion-extension but
#: about 10-15 deg ab-adduction) does not qualify: SCoRE on a walk put the hips 111-127 mm off (issue #17, point 7)
FUNCTIONAL_HIP_MIN_RANGE_DEG = {"flexion": 30.0, "abduction": 20.0}


def hip_range_of_motion(static: MarkerTrial, trial: MarkerTrial, side: str, axes=None, *, pelvis=None,
                        thigh=None) -> dict | None:
    """Ranges (deg) of the thigh in the pelvis over `trial`: {"flexion": ..., "abduction": ...}, or None
    without 3 pelvis and 3 thigh markers.

    R = R_pelvisᵀ R_thigh (cluster poses, identity in the static pose) in the pelvis axes `axes` (columns x
    forward, y left, z up), Cardan Y-X-Z: flexion about y, ab/adduction about x; each range is the 2.5-97.5
    percentile span over the frames.
    """
    from scipy.spatial.transform import Rotation

    S = side.upper()
    P = cluster_pose(static, [trial], PELVIS_CLUSTER if pelvis is None else tuple(pelvis))
    D = cluster_pose(static, [trial], tuple(S + m for m in THIGH_MARKERS) if thigh is None else tuple(thigh))
    if P is None or D is None:
        return None
    A = np.eye(3) if axes is None else np.asarray(axes, float)
    R = np.einsum("ji,fjk->fik", A, np.einsum("fji,fjk->fik", P.R, D.R)) @ A
    ok = np.all(np.isfinite(R), axis=(1, 2))
    if ok.sum() < 10:
        return None
    ang = np.degrees(Rotation.from_matrix(R[ok]).as_euler("YXZ"))
    span = lambda a: float(np.percentile(a, 97.5) - np.percentile(a, 2.5))  # noqa: E731
    return {"flexion": span(ang[:, 0]), "abduction": span(ang[:, 1])}


#: Harrington et al. (2007, J Biomech 40:595) single-variable regression of the hip centre on pelvic width PW and
#: depth PD (mm), in the pelvis frame at the mid-ASIS (x anterior, y superior, z lateral): x = -0.24 PD - 9.9,
#: y = -0.30 PW - 10.9, z = 0.33 PW + 7.3
HARRINGTON = {"x": (-0.24, -9.9), "y": (-0.30, -10.9), "z": (0.33, 7.3)}
#: per-axis sd of the regression (m): 3-D error 12.3 +- 5.9 mm on 67 pelvic CTs (Mantovani, Ng & Lamontagne 2016,
#: Gait Posture 44:48), i.e. sqrt((12.3² + 5.9²) / 3) per axis
HARRINGTON_SD = float(np.sqrt((12.3**2 + 5.9**2) / 3.0)) * 1e-3


def pelvic_tissue(static: dict, skin: dict | None = None) -> tuple[tuple[float, float], tuple[float, float]]:
    """(mean, sd) m of the soft tissue under the anterior (RASI, LASI) and the posterior (RPSI, LPSI, else SACR)
    pelvic markers: `skin` {marker: (mean, sd)} where given (measured or estimated), else the site prior
    (`personalize.registration.skin_prior`); means averaged, variances averaged."""
    from ..registration import skin_prior

    def tissue(name):
        v = (skin or {}).get(name)
        return tuple(v) if v is not None else skin_prior(name)

    out = []
    for names in (("RASI", "LASI"), ("RPSI", "LPSI") if "RPSI" in static and "LPSI" in static else ("SACR", "SACR")):
        t = [tissue(n) for n in names]
        out.append((float(np.mean([a for a, _ in t])), float(np.sqrt(np.mean([b ** 2 for _, b in t])))))
    return out[0], out[1]


def davis_tissue_cov(static: dict, axes, skin: dict | None = None) -> np.ndarray:
    """Covariance (3, 3) m² the soft tissue under the ASIS markers adds to the Davis (Plug-in-Gait) hip centre.

    Davis et al. (1991) fitted the regression on radiographs, from the bony spines, and Plug-in-Gait moves the
    ASIS markers in by the marker radius only: tissue of thickness t_A under them carries the pelvis origin, and
    the centre placed from it, t_A forward along the pelvis x axis.  The mean is left as Plug-in-Gait gives it
    (the baseline users compare with Nexus); the unmodelled shift enters as variance, (t̄_A² + σ_A²) x xᵀ
    (`pelvic_tissue`), so that an obese subject's Davis centre, several centimetres forward, is not fused as if it
    were an adult's.
    """
    (tA_m, tA_sd), _ = pelvic_tissue(static, skin)
    x = np.asarray(axes, float)[:, 0]
    return (tA_m ** 2 + tA_sd ** 2) * np.outer(x, x)


def harrington_hip(static: dict, side: str, axes, skin: dict | None = None, marker_radius: float | None = None,
                   palpation: bool = True):
    """Hip centre (static lab, m) by the Harrington et al. (2007) regression of the pelvis markers, as a `Gaussian`.

    The markers are moved in to the bone first: the mid-ASIS back by t_ASIS + r, the mid-PSIS (or the sacral
    marker) forward by t_PSIS + r (t the soft tissue: `skin` {marker: (mean, sd) m}, else the site prior
    `personalize.registration.skin_prior`; r the marker radius), so PW = |RASI - LASI| and PD = the
    anterior distance mid-ASIS - mid-PSIS are the bony ones the regression was fitted on.

    Cov = A diag(σ²) Aᵀ + J Σ_t Jᵀ + Σ_p: σ = `HARRINGTON_SD` per axis (the regression's error on bony landmarks);
    the tissue uncertainty through x_hip = o - (t_A + r) - 0.24 (PD - t_A - t_P - 2 r): ∂x/∂t_A = -0.76,
    ∂x/∂t_P = +0.24 (pelvis x axis); with `palpation`, Σ_p the markers' palpation (`PALPATION_SD` of ASI and
    PSI per axis, p_A, p_P) through the pelvis frame: the origin (p_A² / 2) I, and its rotations about z and x
    (sd √2 p_A / PW) and about y (sd √((p_A² + p_P²) / 2) / PD), each moving the centre by ω × (c - o).
    """
    from lowerlimb.geometry import DEFAULT_MARKER_RADIUS

    r = DEFAULT_MARKER_RADIUS if marker_radius is None else float(marker_radius)
    A = np.asarray(axes, float)
    x, y, z = A[:, 0], A[:, 1], A[:, 2]
    rear, _ = pelvis_rear(static)
    (tA_m, tA_sd), (tP_m, tP_sd) = pelvic_tissue(static, skin)
    o = 0.5 * (static["RASI"].mean + static["LASI"].mean)
    pw = float(np.linalg.norm(static["RASI"].mean - static["LASI"].mean))
    pd = float((o - rear) @ x) - (tA_m + tP_m + 2 * r)
    o_bone = o - (tA_m + r) * x
    (ax_, bx), (ay, by), (az, bz) = HARRINGTON["x"], HARRINGTON["y"], HARRINGTON["z"]
    lateral = -y if side == "r" else y
    c = o_bone + 1e-3 * ((ax_ * pd * 1e3 + bx) * x + (ay * pw * 1e3 + by) * z + (az * pw * 1e3 + bz) * lateral)
    cov = HARRINGTON_SD**2 * np.eye(3) + ((0.76 * tA_sd) ** 2 + (0.24 * tP_sd) ** 2) * np.outer(x, x)
    if palpation:
        pA, pP = PALPATION_SD["ASI"], PALPATION_SD["PSI"]
        d = c - o
        cov = cov + 0.5 * pA**2 * np.eye(3)
        for w, sd in ((z, np.sqrt(2.0) * pA / pw), (x, np.sqrt(2.0) * pA / pw),
                      (y, np.sqrt(0.5 * (pA**2 + pP**2)) / max(pd, 0.05))):
            v = np.cross(w, d)
            cov = cov + sd**2 * np.outer(v, v)
    return Gaussian(c, cov)


# --------------------------------------------------------------------------- knee and ankle from condyle markers
#: per-axis sd (m) of a palpated marker's position in the skin plane, by landmark: 10 mm rms (2-D) at the femoral
#: epicondyles, 5 mm at the malleoli, 8 and 10 mm at the anterior and posterior iliac spines, after the
#: inter-examiner dispersions of Della Croce, Cappozzo & Kerrigan 1999 (Med Biol Eng Comput 37:155; rms 6-21 mm,
#: largest at the epicondyles)
PALPATION_SD = {"KNE": 0.010 / np.sqrt(2.0), "MFC": 0.010 / np.sqrt(2.0), "ANK": 0.005 / np.sqrt(2.0),
                "MMA": 0.005 / np.sqrt(2.0), "ASI": 0.008 / np.sqrt(2.0), "PSI": 0.010 / np.sqrt(2.0)}
#: isotropic sd (m) of the distance between the epicondyle (malleolus) midpoint and the joint centre of a model
#: (the flexion axis passes near, not through, the prominences; the most prominent malleolar points lie above the
#: talocrural axis).  Chosen on realistic subject 002 (ICL_MRI bones, ior set): per-axis rms error of the midpoints
#: 8.1 mm (knee) and 10.1 mm (ankle), minus the palpation and tissue terms above; checked on 003, 005, 006, 009
#: (ICL_MRI and LHDL_CT bones, ior, cast and opensim sets, 8 legs): 6.9 and 8.6 mm.  The malleolar midpoint lies on
#: average 9 mm posterior of and 9 mm above the expert's ankle centre there: a bias this sd covers, not corrected.
#: Not from a published source
CONDYLAR_CENTRE_MODEL_SD = {"knee": 0.006, "ankle": 0.010}
#: angle (deg) between the transepicondylar (transmalleolar) line and the knee flexion (talocrural) axis on top of
#: the palpation: a few degrees (Churchill et al. 1998, Clin Orthop 356:111: transepicondylar vs flexion axis;
#: Inman 1976 for the ankle): assumed, not calibrated
CONDYLAR_AXIS_SD_DEG = {"knee": 4.0, "ankle": 4.0}
#: lateral / medial landmark pairs of each joint
CONDYLES = {"knee": ("KNE", "MFC"), "ankle": ("ANK", "MMA")}


def condylar_centre(static: dict, joint: str, side: str, skin: dict | None = None,
                    marker_radius: float | None = None) -> Gaussian:
    """Knee (ankle) centre: the midpoint of the lateral and medial epicondyle (malleolus) markers moved in along
    their line by marker radius + soft tissue (static lab, m), as a `Gaussian`.

    c = ½ [(m_l - (t_l + r) u) + (m_m + (t_m + r) u)], u = unit(m_l - m_m); t the tissue (`skin` {marker: (mean,
    sd)}, else `personalize.registration.skin_prior`).  Cov = ¼ (C_l + C_m) + ¼ (sd_l² + sd_m²) u uᵀ
    + ¼ (p_l² + p_m²) (I - u uᵀ) + s² I, with C the markers' static covariances, p `PALPATION_SD` in the skin
    plane and s `CONDYLAR_CENTRE_MODEL_SD`.
    """
    from lowerlimb.geometry import DEFAULT_MARKER_RADIUS

    from ..registration import skin_prior

    S = side.upper()
    lat, med = (S + n for n in CONDYLES[joint])
    missing = [n for n in (lat, med) if n not in static]
    if missing:
        raise InputError("static trial", f"{joint} centre needs the {' and '.join(missing)} marker(s)")
    r = DEFAULT_MARKER_RADIUS if marker_radius is None else float(marker_radius)
    ml, mm = static[lat], static[med]
    u = ml.mean - mm.mean
    u = u / np.linalg.norm(u)
    tl = tuple((skin or {}).get(lat) or skin_prior(lat))
    tm = tuple((skin or {}).get(med) or skin_prior(med))
    c = 0.5 * ((ml.mean - (tl[0] + r) * u) + (mm.mean + (tm[0] + r) * u))
    P = np.eye(3) - np.outer(u, u)
    pl, pm = (PALPATION_SD[n] for n in CONDYLES[joint])
    cov = (0.25 * (ml.cov + mm.cov) + 0.25 * (tl[1] ** 2 + tm[1] ** 2) * np.outer(u, u)
           + 0.25 * (pl**2 + pm**2) * P + CONDYLAR_CENTRE_MODEL_SD[joint] ** 2 * np.eye(3))
    return Gaussian(c, cov)


def condylar_axis(static: dict, joint: str, side: str) -> Direction:
    """Knee (ankle) axis: the line through the lateral and medial epicondyle (malleolus) markers, lateral minus
    medial, sd = √(atan(√(p_l² + p_m²) / width)² + `CONDYLAR_AXIS_SD_DEG`²)."""
    S = side.upper()
    lat, med = (S + n for n in CONDYLES[joint])
    missing = [n for n in (lat, med) if n not in static]
    if missing:
        raise InputError("static trial", f"{joint} axis needs the {' and '.join(missing)} marker(s)")
    d = static[lat].mean - static[med].mean
    pl, pm = (PALPATION_SD[n] for n in CONDYLES[joint])
    sd = np.degrees(np.arctan(np.hypot(pl, pm) / max(np.linalg.norm(d), 1e-3)))
    return Direction(d, float(np.hypot(sd, CONDYLAR_AXIS_SD_DEG[joint])))
