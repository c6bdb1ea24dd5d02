r"""The patellofemoral joint: the patella's path over the femur as the knee flexes, from the subject's bones.

Frame: the femur's knee frame F (origin the knee centre, Z the flexion axis to the subject's right, Y towards
the hip, X anterior).  The patella moves in F's sagittal plane: its pose is a rotation :math:`\alpha` about Z
through its centre :math:`c` (the MRI pose at :math:`\alpha = 0`), then a translation :math:`t = (t_x, t_y, 0)`:

.. math::  x' = R_z(\alpha)(x - c) + c + t .

At each knee flexion :math:`q` the pose solves three equations (Yamaguchi & Zajac 1989's planar patella, with
the subject's surfaces for its contact):

1. the patellar tendon keeps its MRI length, :math:`|A' - T(q)| = L_0` (:math:`A` the patella's apex, :math:`T(q)`
   the tibial tuberosity moved by the model's knee joint);
2. the articular surface keeps its MRI clearance to the femur, :math:`\mathrm{softmin}_i\, s_i = d_0`
   (:math:`s_i` the signed distance of articular vertex :math:`i` along the normal of its nearest femoral vertex;
   soft minimum with :math:`\tau` = `CONTACT_TAU`), so the patella rides on the trochlea and then the condyles;
3. the patella is a frictionless three-force member in moment balance: quadriceps tension along :math:`B' \to Q`
   (:math:`B` the patella's base, :math:`Q` = `QUADRICEPS_POINT` on the anterior femoral shaft), tendon tension
   along :math:`A' \to T`, contact force along the femoral normal :math:`n` at the soft contact point :math:`C`;
   force balance fixes the two tensions per unit contact force, and their moment about :math:`C` must vanish.

Solved with `scipy.optimize.least_squares` (residuals in mm), continued from the MRI pose in steps of `STEP_DEG`
each way (the last two poses extrapolated as the guess, a failed step halved twice).  A knee angle still above
`RESIDUAL_TOL` ends the converged range (the patella has left the surfaces the model knows, e.g. past the notch);
`PatellarTrack` keeps that range only, and a range under `MIN_RANGE_DEG` gives no path.

In the model the path is a CustomJoint femur -> patella whose coordinate is coupled one to one to knee flexion
(as Rajagopal et al. 2016's ``knee_angle_r_beta``): rotation :math:`\alpha(q)` about Z and the translation
:math:`c - R_z(\alpha) c + t` of the joint frame, both splines of :math:`q`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["PatellaGeometry", "PatellarTrack", "patellar_track", "CONTACT_TAU", "QUADRICEPS_POINT",
           "TENDON_RANGE", "STEP_DEG", "RESIDUAL_TOL", "MIN_RANGE_DEG"]

#: m, soft-minimum temperature of the articular clearance (smooth in the pose; about the mesh spacing)
CONTACT_TAU = 0.0007
#: m, knee frame (x anterior, y proximal): where the quadriceps' line of action from the patella's base is aimed,
#: on the anterior femoral shaft 20 cm above the knee (chosen on ICL_MRI, checked on LHDL_CT and TLEM2_MRI)
QUADRICEPS_POINT = (0.02, 0.20)
#: m, plausible patellar tendon lengths (apex to tuberosity); outside, the tuberosity or the patella is not right
TENDON_RANGE = (0.03, 0.09)
#: deg, continuation step of the knee angle
STEP_DEG = 5.0
#: deg, the least converged range above full extension for a path to be used (gait's knee reaches 60-70 deg)
MIN_RANGE_DEG = 45.0
#: residual (mm: tendon length, clearance, moment per unit contact force) above which a knee angle is not converged
RESIDUAL_TOL = 0.5


@dataclass(frozen=True)
class PatellaGeometry:
    """The surfaces and points the path needs, in one frame (any; m).

    femur_vertices, femur_normals : (N, 3) the femur's distal surface (outward normals)
    patella_vertices, patella_normals : (M, 3); patella_centre : (3,); patella_rotation : (3, 3) columns the
    patella's anterior, superior and right axes (`personalize.landmarks.patella`); tuberosity : (3,) the tibial
    tuberosity where the MRI puts it relative to femur and patella (its distance to the apex is the tendon's
    length); tuberosity_on_tibia : (3,) the same point where the tibia is (a model's tibia placement), or None
    """

    femur_vertices: np.ndarray
    femur_normals: np.ndarray
    patella_vertices: np.ndarray
    patella_normals: np.ndarray
    patella_centre: np.ndarray
    patella_rotation: np.ndarray
    tuberosity: np.ndarray
    tuberosity_on_tibia: np.ndarray | None = None


@dataclass(frozen=True)
class PatellarTrack:
    """The patella's path (module docstring), knee frame F.

    flexion : (K,) rad, knee flexion of the samples (converged range, increasing)
    rotation : (K,) rad, :math:`\\alpha` about F's Z (negative: the patella flexes with the knee)
    translation : (K, 2) m, the joint frame's translation :math:`c - R_z(\\alpha) c + t` in F (x, y)
    centre : (3,) m, the patella's centre in F; tendon_length, clearance : m (MRI)
    residual : (K,) max residual (mm / mN m) per sample
    """

    flexion: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    centre: np.ndarray
    tendon_length: float
    clearance: float
    residual: np.ndarray

    @property
    def patellar_flexion_ratio(self) -> float:
        """Patellar flexion per degree of knee flexion over the converged range (slope of a line fit)."""
        return float(-np.polyfit(self.flexion, self.rotation, 1)[0])

    def centre_path(self) -> np.ndarray:
        """(K, 2) m, the patella's centre in F's sagittal plane (x anterior, y proximal) at each sample."""
        return np.array([(_rz(a) @ self.centre)[:2] + t for a, t in zip(self.rotation, self.translation)])

    def to_json(self) -> dict:
        return {"frame": "femur knee frame (origin knee centre, Z flexion axis to the right, Y proximal, X anterior)",
                "flexion_deg": np.degrees(self.flexion).round(2).tolist(),
                "patellar_flexion_deg": (-np.degrees(self.rotation)).round(2).tolist(),
                "translation_mm": (1e3 * self.translation).round(2).tolist(),
                "centre_mm": (1e3 * self.centre).round(2).tolist(),
                "centre_path_mm": (1e3 * self.centre_path()).round(2).tolist(),
                "tendon_length_mm": round(1e3 * self.tendon_length, 2), "clearance_mm": round(1e3 * self.clearance, 2),
                "patellar_flexion_per_knee_flexion": round(self.patellar_flexion_ratio, 3),
                "max_residual": float(np.max(self.residual)), "method": "planar three-force patella on the "
                "subject's femur and patella surfaces, tendon length from the MRI (Yamaguchi & Zajac 1989)"}


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def patellar_track(geometry: PatellaGeometry, frame: tuple, tuberosity_at: Callable[[float], np.ndarray],
                   flexion_range=(-10.0, 120.0), start_deg: float = 0.0) -> PatellarTrack | None:
    """The patella's path over `flexion_range` (deg), or None (implausible tendon length, too short a range).

    Parameters
    ----------
    geometry : `PatellaGeometry` (its frame: that of `frame`)
    frame : (origin (3,), rotation (3, 3)) the knee frame F in the geometry's frame (columns X, Y, Z)
    tuberosity_at : q (rad) -> (3,) the tibial tuberosity in F at knee flexion q (the model's knee joint)
    start_deg : knee flexion at which the MRI pose is the starting guess
    """
    from scipy.optimize import least_squares
    from scipy.spatial import cKDTree

    o, R = (np.asarray(v, float) for v in frame)
    to_f = lambda x: (np.asarray(x, float) - o) @ R          # noqa: E731
    FV, FN = to_f(geometry.femur_vertices), np.asarray(geometry.femur_normals, float) @ R
    PV, PN = to_f(geometry.patella_vertices), np.asarray(geometry.patella_normals, float) @ R
    c = to_f(geometry.patella_centre)
    Rp = R.T @ np.asarray(geometry.patella_rotation, float)
    keep = (np.linalg.norm(FV - c, axis=1) < 0.12)
    FV, FN = FV[keep], FN[keep]
    tree = cKDTree(FV)
    art = PV[(PN @ Rp[:, 0]) < -0.3]                        # facing the femur
    height = (PV - c) @ Rp[:, 1]
    apex, base = PV[np.argmin(height)], PV[np.argmax(height)]
    q_pt = np.array([QUADRICEPS_POINT[0], QUADRICEPS_POINT[1], c[2]])

    def contact(P):
        _, j = tree.query(P)
        s = np.einsum("ij,ij->i", P - FV[j], FN[j])
        m = s.min()
        w = np.exp(-(s - m) / CONTACT_TAU)
        n = (w / w.sum()) @ FN[j]
        return m - CONTACT_TAU * np.log(w.sum()), (w / w.sum()) @ P, n / np.linalg.norm(n)

    L0 = float(np.linalg.norm(apex - to_f(geometry.tuberosity)))
    if not (TENDON_RANGE[0] <= L0 <= TENDON_RANGE[1]):
        return None
    d0 = contact(art)[0]

    def moved(x, P):
        return (P - c) @ _rz(x[0]).T + c + np.array([x[1], x[2], 0.0])

    def residuals(x, T):
        A, B = moved(x, apex), moved(x, base)
        sm, C, n = contact(moved(x, art))
        uq, ut = (q_pt - B) / np.linalg.norm(q_pt - B), (T - A) / np.linalg.norm(T - A)
        fq, ft = np.linalg.solve(np.array([uq[:2], ut[:2]]).T, -n[:2])
        cross = lambda a, b: a[0] * b[1] - a[1] * b[0]      # noqa: E731
        moment = cross(B[:2] - C[:2], fq * uq[:2]) + cross(A[:2] - C[:2], ft * ut[:2])
        return 1e3 * np.array([np.linalg.norm(A - T) - L0, sm - d0, moment])

    def solve(q, x):
        r = least_squares(residuals, x, args=(tuberosity_at(np.radians(q)),), x_scale=[0.1, 0.005, 0.005])
        return r.x, float(np.max(np.abs(r.fun)))

    rows = {}
    for direction in (1.0, -1.0):
        path = [(start_deg, np.zeros(3))]           # (knee angle, pose), the MRI pose as the first guess
        step = STEP_DEG
        while True:
            q0, x0 = path[-1]
            q = q0 + direction * step
            if not (flexion_range[0] - 1e-9 <= q <= flexion_range[1] + 1e-9) or step < STEP_DEG / 4:
                break
            # predictor: the last two poses extrapolated; corrector: least squares; a failed step is halved
            guess = x0 if len(path) < 2 else x0 + (x0 - path[-2][1]) * step / abs(q0 - path[-2][0])
            x, res = solve(q, guess if len(path) > 1 else x0)
            if res > RESIDUAL_TOL:
                step /= 2.0
                continue
            path.append((q, x))
            rows[round(q, 6)] = (x.copy(), res)
            step = STEP_DEG
        if len(path) == 1:
            x, res = solve(start_deg, np.zeros(3))
            if res <= RESIDUAL_TOL:
                rows[round(start_deg, 6)] = (x, res)
    qs = np.array(sorted(rows))
    if len(qs) < 3 or qs[-1] - max(qs[0], 0.0) < MIN_RANGE_DEG:
        return None
    X = np.array([rows[k][0] for k in qs])
    trans = np.array([(c - _rz(a) @ c)[:2] + t for a, t in zip(X[:, 0], X[:, 1:])])
    return PatellarTrack(np.radians(qs), X[:, 0], trans, c, L0, float(d0), np.array([rows[k][1] for k in qs]))
