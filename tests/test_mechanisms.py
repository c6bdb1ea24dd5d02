"""Helical joint, gear pair and bow compass recovered from simulated markers (seed section 4.3)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from lowerlimb.errors import FitError, InputError
from kinematics.mechanisms.recovery import (BowCompass, body_poses, fit_bow_compass, fit_gear_pair, fit_helical,
                                   rotation_about_axis)


def lab_motion(F, rng):
    """A slowly moving rigid lab transform per frame (the whole mechanism is carried around)."""
    rv = np.cumsum(rng.normal(0, 0.01, (F, 3)), axis=0) + [0.2, -0.4, 0.1]
    t = np.cumsum(rng.normal(0, 0.002, (F, 3)), axis=0) + [0.5, 1.0, -0.2]
    return Rotation.from_rotvec(rv).as_matrix(), t


def to_lab(G, t, X):
    return np.einsum("fij,fmj->fmi", G, X) + t[:, None, :]


def axis_rotation(n, theta):
    return Rotation.from_rotvec(np.outer(theta, n)).as_matrix()


def test_body_poses_exact():
    rng = np.random.default_rng(0)
    ref = rng.normal(0, 0.05, (4, 3))
    G, t = lab_motion(6, rng)
    X = to_lab(G, t, np.broadcast_to(ref, (6, 4, 3)))
    R, tt, rms = body_poses(X, reference=ref)
    np.testing.assert_allclose(R, G, atol=1e-12)
    np.testing.assert_allclose(tt, t, atol=1e-12)
    assert rms.max() < 1e-12
    X[2, 1] = np.nan  # a gap: the 3 remaining markers still give the pose
    R2, _, _ = body_poses(X, reference=ref)
    np.testing.assert_allclose(R2[2], G[2], atol=1e-12)
    X[3, :2] = np.nan
    with pytest.raises(FitError, match="frame 3 has 2 markers"):
        body_poses(X, reference=ref)
    with pytest.raises(InputError, match="at least 3"):
        body_poses(X[:, :2])


def test_helical_joint_pitch_and_root_within_1_percent():
    rng = np.random.default_rng(1)
    F = 300
    screw = np.array([[0.02, 0.0, 0.0], [-0.01, 0.017, 0.0], [0.0, -0.015, 0.12], [0.005, 0.005, 0.06]])
    q0 = screw.mean(axis=0)
    n = np.array([0.1, 0.2, 1.0]) / np.linalg.norm([0.1, 0.2, 1.0])
    p0 = np.array([0.001, -0.002, 0.0])
    pitch = 0.0015 / (2 * math.pi)  # 1.5 mm per turn, m/rad
    c_abs = 0.03
    theta = np.linspace(0, 6 * 2 * math.pi, F)  # six turns
    e1 = np.cross(n, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    ring = np.array([0.015 * (math.cos(k) * e1 + math.sin(k) * e2) for k in (0.0, 1.7, 3.3, 4.9)])
    Rb = axis_rotation(n, theta)
    bolt = np.einsum("fij,mj->fmi", Rb, ring) + (p0 + np.outer(pitch * theta + c_abs, n))[:, None, :]
    G, t = lab_motion(F, rng)
    S = to_lab(G, t, np.broadcast_to(screw, (F, 4, 3))) + rng.normal(0, 1e-4, (F, 4, 3))
    B = to_lab(G, t, bolt) + rng.normal(0, 1e-4, (F, 4, 3))
    fit = fit_helical(S, B)
    # Axis direction in the screw's reference frame (= lab at frame 0).
    n_lab0 = G[0] @ n
    assert math.degrees(math.acos(min(1.0, abs(np.dot(fit.axis, n_lab0))))) < 0.5
    assert fit.pitch == pytest.approx(pitch, rel=0.01)
    assert fit.lead == pytest.approx(0.0015, rel=0.01)
    root_true = np.dot(n, p0 - q0) + c_abs
    assert fit.root == pytest.approx(root_true, rel=0.01)
    # Point on the axis: its distance to the true axis is sub-millimetre.
    p_lab0 = G[0] @ p0 + t[0]
    off = (fit.point - p_lab0) - np.dot(fit.point - p_lab0, n_lab0) * n_lab0
    assert np.linalg.norm(off) < 1e-3
    assert fit.law.fit.r2[0] > 0.999
    assert fit.law.coefficient_sd[0, 0] < 0.01 * pitch


def test_gear_pair_ratio_within_1_percent():
    rng = np.random.default_rng(2)
    F = 240
    housing = np.array([[0.0, 0.0, 0.0], [0.08, 0.0, 0.0], [0.0, 0.05, 0.0], [0.03, 0.02, 0.03]])
    n = np.array([0.0, 0.0, 1.0])
    ratio = -24 / 40
    th_a = np.linspace(0, 3 * 2 * math.pi, F) + 0.05 * np.sin(np.linspace(0, 9, F))
    th_b = ratio * th_a

    def gear(center, theta, r):
        pts = np.array([[r * math.cos(k), r * math.sin(k), 0.004 * (k > 3)] for k in (0.0, 2.1, 4.2)])
        return np.einsum("fij,mj->fmi", axis_rotation(n, theta), pts) + center

    A = gear(np.array([0.02, 0.02, 0.01]), th_a, 0.012)
    Bg = gear(np.array([0.052, 0.02, 0.01]), th_b, 0.02)
    G, t = lab_motion(F, rng)
    noise = lambda X: X + rng.normal(0, 5e-5, X.shape)  # noqa: E731
    fit = fit_gear_pair(noise(to_lab(G, t, np.broadcast_to(housing, (F, 4, 3)))), noise(to_lab(G, t, A)),
                        noise(to_lab(G, t, Bg)))
    assert fit.ratio == pytest.approx(ratio, rel=0.01)
    assert np.dot(fit.axis_a, fit.axis_b) > 0.999
    assert abs(fit.law.coefficients[0, 1]) < 1e-2  # the constant only absorbs the reference pose error (rad)
    forced = fit_gear_pair(noise(to_lab(G, t, np.broadcast_to(housing, (F, 4, 3)))), noise(to_lab(G, t, A)),
                           noise(to_lab(G, t, Bg)), intercept=False)  # the seed's R_b = beta R_a
    assert forced.law.coefficients[0, 1] == 0.0 and forced.ratio == pytest.approx(ratio, rel=0.01)
    assert fit.law.fit.r2[0] > 0.999


def test_bow_compass_five_coefficients_and_closed_form_ik():
    rng = np.random.default_rng(3)
    F = 400
    truth = BowCompass(alpha=np.array([-0.004, 0.005, 0.004, 0.001 / (2 * math.pi), 0.03]),
                       leg_length=0.12, opening=math.radians(40), rod_pivot=0.06, rod_angle=0.05)
    R = np.linspace(0, 8 * 2 * math.pi, F)
    parts = truth.markers(R)
    G, t = lab_motion(F, rng)
    lab = {k: to_lab(G, t, v) + rng.normal(0, 5e-5, v.shape) for k, v in parts.items()}
    fit = fit_bow_compass(lab["head"], lab["leg1"], lab["leg2"], lab["rod"], lab["wheel"],
                          hinge_axis=G[0] @ [0.0, 0.0, 1.0])
    np.testing.assert_allclose(fit.alpha, truth.alpha, rtol=0.01)
    assert np.all(fit.alpha_sd < 0.01 * np.abs(truth.alpha))
    np.testing.assert_allclose(fit.wheel_rotation, R, atol=0.02)
    assert fit.model.leg_length == pytest.approx(0.12, rel=0.01)
    assert fit.model.opening == pytest.approx(truth.opening, rel=0.01)

    # IK on the leg distance: one unknown, closed form; agrees with a numerical root of the true mechanism.
    d_target = 0.095
    r_closed = fit.model.solve_leg_distance(d_target)
    assert fit.model.leg_distance(r_closed) == pytest.approx(d_target, abs=1e-12)
    r_numeric = brentq(lambda r: truth.leg_distance(r) - d_target, 0.0, R[-1])  # opening monotonic on the trial
    # The true mechanism driven to the solved wheel angle reaches the target within 1 %.
    assert truth.leg_distance(r_closed) == pytest.approx(d_target, rel=0.01)
    # R itself is a small difference of angles (opening change 0.12 rad over 0.7 rad): 2 %.
    assert r_closed == pytest.approx(r_numeric, rel=0.02)
    with pytest.raises(InputError, match="outside"):
        fit.model.solve_leg_distance(0.5)


def test_compass_hinge_orientation_does_not_change_ik():
    truth = BowCompass(alpha=np.array([-0.004, 0.005, 0.004, 1.6e-4, 0.03]), leg_length=0.12,
                       opening=math.radians(40))
    # The same compass with angles measured about the opposite hinge direction.
    flipped = BowCompass(alpha=np.array([0.004, -0.005, -0.004, 1.6e-4, 0.03]), leg_length=0.12,
                         opening=-math.radians(40))
    for d in (0.05, 0.08, 0.11):
        assert flipped.solve_leg_distance(d) == pytest.approx(truth.solve_leg_distance(d), rel=1e-12)


def test_rotation_about_axis_unwraps_many_turns():
    n = np.array([0.6, 0.0, 0.8])
    theta = np.linspace(0, 5 * 2 * math.pi, 200)
    rot = rotation_about_axis(axis_rotation(n, theta))
    np.testing.assert_allclose(rot.angles, theta, atol=1e-9)
    np.testing.assert_allclose(rot.axis, n, atol=1e-12)
    with pytest.raises(FitError, match="does not rotate"):
        rotation_about_axis(np.broadcast_to(np.eye(3), (5, 3, 3)))
