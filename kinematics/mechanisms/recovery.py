"""Correlative mechanisms recovered from marker motion (Pronost et al. 2010, section 4.3).

Three mechanisms whose kinematics are linear laws between joint coordinates:

helical joint (screw and bolt)
    ``T = alpha R + c``: the bolt's translation T along the screw axis is
    linear in its rotation R about that axis; ``alpha`` (m/rad) is the thread
    pitch (lead per turn ``2 pi alpha``), ``c`` the root location.
gear pair (transmission)
    ``R_b = beta R_a``: ``beta`` is the gear ratio (negative for external
    gears on parallel axes, ``-z_a / z_b``).
bow compass with a wheel
    one input, the wheel rotation R on its threaded rod::

        R_leg1 = a1 R,  R_leg2 = a2 R,  R_rod = a3 R,  T = a4 R + a5

    (three transmissions and one helical joint).  With this model, inverse
    kinematics on the distance between the leg tips has one unknown (R) and a
    closed-form solution (`BowCompass.solve_leg_distance`).

All are recovered without prior knowledge of axis directions: body poses come
from the markers (Kabsch, `scipy.spatial.transform.Rotation.align_vectors`),
relative rotations give the axes (principal direction of the incremental
rotation vectors) and unwrapped angles, and the laws are fitted by
`kinematics.mechanisms.correlative_fit.fit_law`.  Positions in metres, angles in radians.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.mechanisms.correlative import CorrelativeLaw
from kinematics.mechanisms.correlative_fit import fit_law
from lowerlimb.errors import FitError, InputError
from kinematics.algorithms.functional import relative_pose

__all__ = [
    "body_poses",
    "relative_poses",
    "RotationAboutAxis",
    "rotation_about_axis",
    "HelicalFit",
    "fit_helical",
    "GearFit",
    "fit_gear_pair",
    "BowCompass",
    "CompassFit",
    "fit_bow_compass",
]


def _markers(x, name) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim != 3 or a.shape[2] != 3:
        raise InputError(name, f"marker array must have shape (F, M, 3), got {a.shape}")
    if a.shape[1] < 3:
        raise InputError(name, f"{a.shape[1]} markers: a rigid body needs at least 3")
    return a


def body_poses(markers, reference: int | np.ndarray = 0, name: str = "body"):
    """Rigid poses of a marker cluster relative to a reference configuration.

    Model (per frame f, markers m)::

        x_fm = R_f x_ref,m + t_f + e_fm,     min_{R_f, t_f} sum_m |R_f x_ref,m + t_f - x_fm|^2

    solved by the Kabsch algorithm on the centred markers.  Frames with missing
    markers use the markers present (at least 3).

    Parameters
    ----------
    markers : array (F, M, 3), metres
    reference : int or array (M, 3)
        Frame index of the reference configuration, or the configuration itself.

    Returns
    -------
    R : (F, 3, 3), t : (F, 3), rms : (F,) fit residual RMS (m)
    """
    X = _markers(markers, name)
    ref = X[int(reference)] if np.ndim(reference) == 0 else np.asarray(reference, dtype=float)
    if ref.shape != X.shape[1:] or not np.all(np.isfinite(ref)):
        raise InputError(name, "reference configuration must be complete (M, 3)")
    F = X.shape[0]
    R = np.empty((F, 3, 3))
    t = np.empty((F, 3))
    rms = np.empty(F)
    for f in range(F):
        ok = np.isfinite(X[f]).all(axis=1)
        if ok.sum() < 3:
            raise FitError(f"{name}: frame {f} has {ok.sum()} markers; 3 needed for a pose")
        a, b = X[f, ok], ref[ok]
        ca, cb = a.mean(axis=0), b.mean(axis=0)
        if np.linalg.matrix_rank(b - cb, tol=1e-6) < 2:
            raise FitError(f"{name}: markers of frame {f} are collinear; the pose is undetermined")
        rot, _ = Rotation.align_vectors(a - ca, b - cb)
        R[f] = rot.as_matrix()
        t[f] = ca - R[f] @ cb
        rms[f] = math.sqrt(np.mean(np.sum((b @ R[f].T + t[f] - a) ** 2, axis=1)))
    return R, t, rms


def relative_poses(parent_R, parent_t, child_R, child_t):
    """Child poses expressed in the parent's reference frame: ``P^-1 C`` (`kinematics.algorithms.functional.relative_pose`)."""
    return relative_pose(parent_R, parent_t, child_R, child_t)


@dataclass(frozen=True)
class RotationAboutAxis:
    """Angles of a rotation about a fixed axis.

    Attributes
    ----------
    axis : (3,) unit vector (sign chosen so that the last angle is >= 0 unless given)
    angles : (F,) radians, unwrapped, 0 at the reference
    off_axis : (F,) radians, RMS of the rotation-vector increments orthogonal to the axis
    point : (3,) point on the axis closest to the origin of the parent frame (m), or NaN
    """

    axis: np.ndarray
    angles: np.ndarray
    off_axis: float
    point: np.ndarray


def _principal_axis(R, inc) -> np.ndarray:
    """Axis = principal direction of rotation vectors.

    Without wrap-around (every rotation from the first frame below 3/4 pi) the
    rotation vectors of all frames are used.  Otherwise increments over a
    stride k: a slow rotation turns less per frame than the pose noise, so the stride k
    grows until the increments are large (95th percentile of k x the one-frame
    increment below pi/2, so that no k-frame increment wraps past pi).
    """
    step = np.linalg.norm(inc, axis=1)
    if step.max() < 1e-12:
        raise FitError("the body does not rotate: no axis to find")
    total = Rotation.from_matrix(R @ R[0].T).as_rotvec()
    if np.linalg.norm(total, axis=1).max() < 0.75 * math.pi:
        # No wrap-around: every frame's rotation from the first one is an
        # independent sample of theta_f n + e0 (best conditioned for small
        # motions); centring removes e0, the error of the first frame's pose.
        _, s, vt = np.linalg.svd(total - total.mean(axis=0), full_matrices=False)
        if s[0] < 1e-9:
            raise FitError("the body does not rotate: no axis to find")
        return vt[0]
    k = int(np.clip(math.floor((math.pi / 2) / max(np.percentile(step, 95), 1e-12)), 1, max(1, len(R) // 2)))
    inc_k = Rotation.from_matrix(R[k:] @ np.swapaxes(R[:-k], 1, 2)).as_rotvec()
    _, s, vt = np.linalg.svd(inc_k, full_matrices=False)
    if s[0] < 1e-9:
        raise FitError("the body does not rotate: no axis to find")
    return vt[0]


def rotation_about_axis(R, t=None, axis_hint=None, centre=None) -> RotationAboutAxis:
    """Axis and unwrapped angle of rotations ``R_f`` about one fixed axis.

    The axis is the principal direction of the frame-to-frame rotation vectors
    ``log(R_f R_{f-1}^T)`` (so motions of many turns unwrap correctly as long as
    one frame turns less than pi); the angle is the cumulative sum of their
    projections on the axis.  With translations `t`, the axis point ``q`` is the
    least-squares solution of ``(I - R_f) q = t_f - (n . t_f) n`` closest to
    `centre` (default the origin); pass a point near the moving body (its
    reference centroid) so that the estimate does not suffer from the lever
    arm of a distant origin.
    """
    R = np.asarray(R, dtype=float)
    if len(R) < 3:
        raise InputError(None, "at least 3 frames are needed to find a rotation axis")
    inc = Rotation.from_matrix(R[1:] @ np.swapaxes(R[:-1], 1, 2)).as_rotvec()
    n = _principal_axis(R, inc)
    if axis_hint is not None:
        if np.dot(n, axis_hint) < 0:
            n = -n
    angles = np.concatenate([[0.0], np.cumsum(inc @ n)])
    if axis_hint is None and angles[-1] < 0:
        n, angles = -n, -angles
    off = float(np.sqrt(np.mean(np.sum((inc - np.outer(inc @ n, n)) ** 2, axis=1))))
    point = np.full(3, np.nan)
    if t is not None:
        c = np.zeros(3) if centre is None else np.asarray(centre, dtype=float)
        # Translations of the pose taken about `c`: x' = R (x - c) + c + t'.
        tc = np.asarray(t, dtype=float) + R @ c - c
        A = np.vstack([np.eye(3) - Rf for Rf in R] + [n[None, :]])
        b = np.concatenate([tf - np.dot(n, tf) * n for tf in tc] + [[0.0]])
        q, *_ = np.linalg.lstsq(A, b, rcond=None)
        point = q + c
    return RotationAboutAxis(axis=n, angles=angles, off_axis=off, point=point)


def _in_frame(parent, child, reference, names):
    """Poses of `child` relative to its reference, expressed in `parent`'s reference frame."""
    Rp, tp, _ = body_poses(parent, reference, names[0])
    Rc, tc, _ = body_poses(child, reference, names[1])
    return relative_poses(Rp, tp, Rc, tc)


# --------------------------------------------------------------------------- helical
@dataclass(frozen=True)
class HelicalFit:
    """Screw-and-bolt joint recovered from markers.

    Attributes
    ----------
    pitch : float
        ``alpha`` of ``T = alpha R + c`` in m/rad (positive: right-handed thread).
    lead : float
        Advance per turn, ``2 pi |alpha|`` (m).
    root : float
        ``c``: the bolt centre's position along the axis (m from the screw
        markers' centroid) when its rotation is zero (the reference frame).
    axis, point : (3,) the screw axis in the screw's reference frame (unit vector, m)
    law : CorrelativeLaw
        ``T`` as a function of ``R`` with its covariance and fit statistics.
    angles, translations : (F,) the recovered R (rad) and T (m)
    """

    pitch: float
    lead: float
    root: float
    axis: np.ndarray
    point: np.ndarray
    law: CorrelativeLaw
    angles: np.ndarray
    translations: np.ndarray


def fit_helical(screw_markers, bolt_markers, reference: int = 0) -> HelicalFit:
    """Recover a helical joint ``T = alpha R + c`` from screw and bolt markers (seed 4.3).

    Both marker sets are (F, M, 3) in any common (lab) frame; the screw may move.
    R is the bolt's rotation about the screw axis relative to `reference`;
    T the position of the bolt's marker centroid along the axis, measured from
    the screw's marker centroid (reference configuration).
    """
    S = _markers(screw_markers, "screw")
    B = _markers(bolt_markers, "bolt")
    Rr, tr = _in_frame(S, B, reference, ("screw", "bolt"))
    rot = rotation_about_axis(Rr, tr, centre=np.nanmean(B[reference], axis=0))
    n = rot.axis
    # Bolt centroid in the screw's reference frame, along the axis from the screw centroid.
    Rs, ts, _ = body_poses(S, reference, "screw")
    cb = np.nanmean(B, axis=1)
    cb_local = np.einsum("fji,fj->fi", Rs, cb - ts)
    T = (cb_local - np.nanmean(S[reference], axis=0)) @ n
    law = fit_law(rot.angles[:, None], T[:, None], ("bolt_rotation",), ("bolt_translation",),
                  joint="helical", independent_units="rad", dependent_units="m", source="helical joint")
    a, c = law.coefficients[0]
    return HelicalFit(pitch=float(a), lead=float(2 * math.pi * abs(a)), root=float(c), axis=n, point=rot.point,
                      law=law, angles=rot.angles, translations=T)


# --------------------------------------------------------------------------- gears
@dataclass(frozen=True)
class GearFit:
    """Gear pair ``R_b = beta R_a`` recovered from markers.

    Attributes
    ----------
    ratio : float
        ``beta``; negative when the gears turn in opposite senses about
        (nearly) parallel axes oriented alike.
    axis_a, axis_b : (3,) rotation axes in the housing's reference frame
    law : CorrelativeLaw
    angles_a, angles_b : (F,) recovered rotations (rad)
    """

    ratio: float
    axis_a: np.ndarray
    axis_b: np.ndarray
    law: CorrelativeLaw
    angles_a: np.ndarray
    angles_b: np.ndarray


def fit_gear_pair(housing_markers, gear_a_markers, gear_b_markers, reference: int = 0,
                  intercept: bool = True) -> GearFit:
    """Recover the ratio of a gear pair from housing and gear markers (seed 4.3).

    The axes are found from the motion; when they are nearly parallel
    (|cos| > 0.9) gear b's axis is oriented like gear a's so that the sign of
    the ratio is meaningful.  ``R_b = beta R_a + c`` is fitted with a
    constant by default: the angles are zero at the reference frame, whose
    own pose error would otherwise bias beta (c estimates that error, ~0);
    ``intercept=False`` forces the seed's ``R_b = beta R_a``.
    """
    H = _markers(housing_markers, "housing")
    Ra, ta = _in_frame(H, _markers(gear_a_markers, "gear a"), reference, ("housing", "gear a"))
    Rb, tb = _in_frame(H, _markers(gear_b_markers, "gear b"), reference, ("housing", "gear b"))
    rot_a = rotation_about_axis(Ra, ta, centre=np.nanmean(np.asarray(gear_a_markers, float)[reference], axis=0))
    nb = _principal_axis(Rb, Rotation.from_matrix(Rb[1:] @ np.swapaxes(Rb[:-1], 1, 2)).as_rotvec())
    hint = rot_a.axis if abs(np.dot(nb, rot_a.axis)) > 0.9 else None
    rot_b = rotation_about_axis(Rb, tb, axis_hint=hint,
                                centre=np.nanmean(np.asarray(gear_b_markers, float)[reference], axis=0))
    law = fit_law(rot_a.angles[:, None], rot_b.angles[:, None], ("gear_a_rotation",), ("gear_b_rotation",),
                  joint="gear_pair", independent_units="rad", dependent_units="rad", intercept=intercept,
                  source="gear pair")
    return GearFit(ratio=float(law.coefficients[0, 0]), axis_a=rot_a.axis, axis_b=rot_b.axis, law=law,
                   angles_a=rot_a.angles, angles_b=rot_b.angles)


# --------------------------------------------------------------------------- bow compass
@dataclass(frozen=True)
class BowCompass:
    """Bow drawing compass with a lateral wheel: one input, the wheel rotation R.

    Geometry in the head frame: both legs hinge about the head's z axis at the
    origin; leg i points along ``u(theta) = (sin theta, -cos theta, 0)`` with
    ``theta_1 = -opening/2 + a1 R`` and ``theta_2 = +opening/2 + a2 R``; the
    rod pivots on leg 1 at `rod_pivot` (m from the hinge) with direction
    ``v = (cos psi, sin psi, 0)``, ``psi = rod_angle + a3 R``; the wheel sits on
    the rod at ``T = a4 R + a5`` from the pivot and spins about v by R.

    Attributes
    ----------
    alpha : (5,) ``[a1, a2, a3, a4, a5]`` (rad/rad x3, m/rad, m)
    leg_length : float, m (hinge to tip)
    opening : float, rad (angle between the legs at R = 0)
    rod_pivot : float, m
    rod_angle : float, rad
    wheel_radius : float, m
    """

    alpha: np.ndarray
    leg_length: float
    opening: float
    rod_pivot: float = 0.06
    rod_angle: float = 0.0
    wheel_radius: float = 0.012

    def leg_angles(self, R):
        R = np.asarray(R, dtype=float)
        a = self.alpha
        return -0.5 * self.opening + a[0] * R, 0.5 * self.opening + a[1] * R

    def leg_distance(self, R) -> np.ndarray:
        """Distance between the leg tips: ``2 L sin((theta_2 - theta_1) / 2)``."""
        t1, t2 = self.leg_angles(R)
        return 2 * self.leg_length * np.abs(np.sin(0.5 * (t2 - t1)))

    def solve_leg_distance(self, distance: float) -> float:
        """Inverse kinematics for a leg-tip distance, in closed form (one DOF).

        ``R = (2 asin(d / 2L) - opening) / (a2 - a1)`` (opening between the
        legs kept in (0, pi); signs flip together when the hinge axis is
        oriented the other way).
        """
        d = float(distance)
        if not 0 <= d <= 2 * self.leg_length:
            raise InputError(None, f"leg distance {d} m is outside [0, {2 * self.leg_length}] m")
        da = self.alpha[1] - self.alpha[0]
        if abs(da) < 1e-12:
            raise FitError("the legs do not open with the wheel (a2 == a1): distance not controllable")
        # The opening's sign follows the hinge-axis orientation the angles are measured about.
        half = math.copysign(2 * math.asin(d / (2 * self.leg_length)), self.opening)
        return float((half - self.opening) / da)

    def markers(self, R) -> dict[str, np.ndarray]:
        """Marker positions in the head frame for wheel rotations R (F,): {body: (F, M, 3)}."""
        R = np.atleast_1d(np.asarray(R, dtype=float))
        a = self.alpha
        ez = np.array([0.0, 0.0, 1.0])

        def u(th):
            return np.stack([np.sin(th), -np.cos(th), np.zeros_like(th)], axis=-1)

        def perp(th):
            return np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=-1)

        t1, t2 = self.leg_angles(R)
        L = self.leg_length
        head = np.broadcast_to(np.array([[0.0, 0.03, 0.0], [-0.02, 0.015, 0.025], [0.025, 0.04, -0.02],
                                         [0.0, 0.05, 0.02]]), (len(R), 4, 3)).copy()

        def leg(th):
            return np.stack([L * u(th), 0.5 * L * u(th) + 0.01 * ez, 0.5 * L * u(th) + 0.01 * perp(th),
                             0.3 * L * u(th) - 0.01 * ez], axis=1)

        psi = self.rod_angle + a[2] * R
        v = perp(psi)
        w = np.cross(v, ez)
        P = self.rod_pivot * u(t1)
        rod = np.stack([P + 0.008 * ez, P - 0.008 * ez, P + 0.008 * w, P - 0.008 * w], axis=1)
        T = a[3] * R + a[4]
        C = P + T[:, None] * v
        r = self.wheel_radius
        rim = [C + r * (np.cos(R + k)[:, None] * ez + np.sin(R + k)[:, None] * w)
               for k in (0.0, 2 * math.pi / 3, 4 * math.pi / 3)]
        wheel = np.stack(rim, axis=1)
        return {"head": head, "leg1": leg(t1), "leg2": leg(t2), "rod": rod, "wheel": wheel}


@dataclass(frozen=True)
class CompassFit:
    """Bow compass laws recovered from markers.

    Attributes
    ----------
    alpha : (5,) ``[a1, a2, a3, a4, a5]``
    alpha_sd : (5,) standard deviations from the regressions
    laws : dict ``{"leg1", "leg2", "rod", "wheel"}`` -> CorrelativeLaw
    wheel_rotation : (F,) recovered input R (rad)
    model : BowCompass
        With leg length and opening measured at the reference frame.
    """

    alpha: np.ndarray
    alpha_sd: np.ndarray
    laws: dict
    wheel_rotation: np.ndarray
    model: BowCompass


def fit_bow_compass(head, leg1, leg2, rod, wheel, reference: int = 0, leg_tip: int = 0,
                    hinge_axis=None) -> CompassFit:
    """Recover the five coefficients of the bow compass from markers (seed 4.3).

    Parameters
    ----------
    head, leg1, leg2, rod, wheel : arrays (F, M, 3), metres, any common frame
    reference : frame where the wheel rotation is zero
    leg_tip : index of each leg's tip marker (leg length and opening)
    hinge_axis : (3,), optional
        Orientation wanted for the hinge axis (lab frame at the reference
        frame); the leg and rod angles are measured about it.  Default: the
        orientation in which leg 1 turns positively over the trial.

    The input R is the wheel's rotation relative to the rod; the leg and rod
    rotations are taken about their axes relative to the head; T is the wheel
    centre's position along the wheel axis from the rod markers' centroid.
    """
    parts = {k: _markers(v, k) for k, v in dict(head=head, leg1=leg1, leg2=leg2, rod=rod, wheel=wheel).items()}
    poses = {k: body_poses(v, reference, k) for k, v in parts.items()}

    def rel(parent, child):
        return relative_poses(poses[parent][0], poses[parent][1], poses[child][0], poses[child][1])

    Rw, tw = rel("rod", "wheel")
    wheel_rot = rotation_about_axis(Rw, tw, centre=np.nanmean(parts["wheel"][reference], axis=0))
    Rin = wheel_rot.angles
    n = wheel_rot.axis
    # Helical part: wheel centre along its axis, in the rod's reference frame.
    Rr, tr_, _ = poses["rod"]
    c_w = np.nanmean(parts["wheel"], axis=1)
    c_local = np.einsum("fji,fj->fi", Rr, c_w - tr_)
    T = (c_local - np.nanmean(parts["rod"][reference], axis=0)) @ n

    laws = {}
    angles = {}
    hinge = None
    for k in ("leg1", "leg2", "rod"):
        Rk, tk = rel("head", k)
        rk = rotation_about_axis(Rk, tk, axis_hint=hinge_axis if hinge is None else hinge,
                                 centre=np.nanmean(parts["head"][reference], axis=0))
        if hinge is None:
            hinge = rk.axis
            hinge_point = rk.point
        angles[k] = rk.angles
        # With a constant: the reference pose's error must not bias the slope (the constant is ~0).
        laws[k] = fit_law(Rin[:, None], rk.angles[:, None], ("wheel_rotation",), (f"{k}_rotation",),
                          joint="bow_compass", dependent_units="rad", source=f"bow compass {k}")
    laws["wheel"] = fit_law(Rin[:, None], T[:, None], ("wheel_rotation",), ("wheel_translation",),
                            joint="bow_compass", dependent_units="m", source="bow compass wheel")
    alpha = np.array([laws["leg1"].coefficients[0, 0], laws["leg2"].coefficients[0, 0],
                      laws["rod"].coefficients[0, 0], *laws["wheel"].coefficients[0]])
    sd = np.array([laws["leg1"].coefficient_sd[0, 0], laws["leg2"].coefficient_sd[0, 0],
                   laws["rod"].coefficient_sd[0, 0], *laws["wheel"].coefficient_sd[0]])
    # Geometry at the reference: tips relative to the hinge point, in the head's reference frame.
    Rh, th, _ = poses["head"]
    tips = [Rh[reference].T @ (parts[k][reference, leg_tip] - th[reference]) - hinge_point for k in ("leg1", "leg2")]
    tips = [p - np.dot(p, hinge) * hinge for p in tips]
    L = float(np.mean([np.linalg.norm(p) for p in tips]))
    cosang = np.dot(tips[0], tips[1]) / (np.linalg.norm(tips[0]) * np.linalg.norm(tips[1]))
    opening = float(math.acos(np.clip(cosang, -1.0, 1.0)))
    # Orient the opening with the hinge axis: a2 - a1 > 0 must open the legs.
    if np.dot(np.cross(tips[0], tips[1]), hinge) < 0:
        opening = -opening
    model = BowCompass(alpha=alpha, leg_length=L, opening=opening)
    return CompassFit(alpha=alpha, alpha_sd=sd, laws=laws, wheel_rotation=Rin, model=model)
