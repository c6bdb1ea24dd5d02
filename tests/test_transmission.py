"""Kinetostatic transmission elements and their composition along a model tree (kinematics.mechanisms.transmission)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kin_helpers import leg_model
from kinematics.algorithms.fk import frame_jacobian, point_jacobian
from kinematics.multibody.joints import Transform
from kinematics.mechanisms.transmission import (AppliedLoad, FrameState, JointElement, MassElement, RigidLink,
                                     TransmissionChain)
from lowerlimb.geometry import skew


@pytest.fixture(scope="module")
def leg():
    return leg_model(exportable=False)          # custom spline knee, swing and exp-map joints included


@pytest.fixture(scope="module")
def motion(leg):
    rng = np.random.default_rng(11)
    N = 4
    q = leg.random_q(N, rng)
    qd = rng.normal(size=q.shape)
    qdd = rng.normal(size=q.shape)
    return q, qd, qdd


def _random_frame(rng, n):
    R = Rotation.random(n, random_state=rng).as_matrix()
    r, w, v, al, a = (rng.normal(size=(n, 3)) for _ in range(5))
    return FrameState(R, r, w, v, al, a)


def _omega_from_R(Rp, Rm, R0, h):
    """Angular velocity in ground from R(t +- h): vee((dR/dt) R^T)."""
    W = ((Rp - Rm) / (2 * h)) @ np.swapaxes(R0, -1, -2)
    return 0.5 * np.stack([W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], -1)


def test_rigid_link_velocity_and_virtual_work():
    """[omega'; v'] = J [omega; v] (eq. 7) and [tau; f] = J^T [tau'; f'] (eq. 9), i.e. t^T w = t'^T w'."""
    rng = np.random.default_rng(0)
    link = RigidLink(Transform(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)))
    K = _random_frame(rng, 5)
    Kp = link.do_motion(K)
    J = link.jacobian()
    np.testing.assert_allclose(Kp.twist, K.twist @ J.T, atol=1e-13)
    Kp.tau, Kp.f = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    link.do_force(Kp, K)
    np.testing.assert_allclose(K.wrench, Kp.wrench @ J, atol=1e-13)
    np.testing.assert_allclose(np.sum(K.twist * K.wrench, 1), np.sum(Kp.twist * Kp.wrench, 1), atol=1e-12)
    # Pose: the output origin is the offset point of K.
    np.testing.assert_allclose(Kp.r, K.point(link.offset.translation), atol=1e-14)


@pytest.mark.parametrize("joint_name", ["knee", "hip", "swing", "shoulder", "sled_joint"])
def test_joint_element_jacobian_and_virtual_work(leg, joint_name):
    """Joint: motion = J [omega; v; qd] with J from the motion subspace; delta q^T Q = delta q'^T Q' (eq. 2)."""
    rng = np.random.default_rng(1)
    j = leg.joint(joint_name)
    el = JointElement(j)
    N, k = 6, j.n_coordinates
    qj = rng.uniform(-0.8, 0.8, (N, k))
    qdj = rng.normal(size=(N, k))
    K = _random_frame(rng, N)
    Kp = el.do_motion(K, qj, qdj)
    J = el.jacobian(qj)
    tin = np.concatenate([K.twist, qdj], axis=1)
    np.testing.assert_allclose(Kp.twist, np.einsum("nij,nj->ni", J, tin), atol=1e-12)
    Kp.tau, Kp.f = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    Q = el.do_force(Kp, K, qj)
    win = np.concatenate([K.wrench, Q], axis=1)
    np.testing.assert_allclose(win, np.einsum("nij,ni->nj", J, Kp.wrench), atol=1e-12)
    np.testing.assert_allclose(np.sum(tin * win, 1), np.sum(Kp.twist * Kp.wrench, 1), atol=1e-11)


def test_joint_element_motion_matches_finite_differences(leg):
    """Pose, velocity and acceleration of the knee output frame (spline translations, dS/dt from the spline's
    second derivative) vs central differences; the input frame is fixed (moving inputs: the chain test)."""
    rng = np.random.default_rng(2)
    el = JointElement(leg.joint("knee"))
    X = Transform(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
    qj, qdj, qddj = np.array([[-0.7], [-1.5], [0.1]]), np.array([[1.3], [-0.4], [2.0]]), np.array([[-2.1], [0.7], [1.1]])
    at = lambda t: el.do_motion(FrameState.fixed(3, X), qj + t * qdj + 0.5 * t * t * qddj, qdj + t * qddj, qddj)
    h = 1e-5
    Kp, Km, K = at(h), at(-h), at(0.0)
    world = lambda S, x: np.einsum("nij,nj->ni", S.R, x)
    np.testing.assert_allclose((Kp.r - Km.r) / (2 * h), world(K, K.v), atol=1e-9)
    np.testing.assert_allclose(_omega_from_R(Kp.R, Km.R, K.R, h), world(K, K.omega), atol=1e-9)
    np.testing.assert_allclose((world(Kp, Kp.v) - world(Km, Km.v)) / (2 * h), world(K, K.a), atol=1e-8)
    np.testing.assert_allclose((world(Kp, Kp.omega) - world(Km, Km.omega)) / (2 * h), world(K, K.alpha), atol=1e-8)


def test_chain_motion_matches_finite_differences(leg, motion):
    """Every body's origin velocity/acceleration and angular velocity/acceleration from the motion pass vs central
    differences along q(t) = q + t qd + t^2/2 qdd."""
    q, qd, qdd = motion
    ch = TransmissionChain(leg)
    h = 1e-5
    sp, sm, s0 = (ch.motion(q + t * qd + 0.5 * t * t * qdd, qd + t * qdd, qdd) for t in (h, -h, 0.0))
    for b in range(1, leg.n_bodies):
        Kp, Km, K = sp.bodies[b], sm.bodies[b], s0.bodies[b]
        world = lambda S, x: np.einsum("nij,nj->ni", S.R, x)
        np.testing.assert_allclose((Kp.r - Km.r) / (2 * h), world(K, K.v), atol=2e-8)
        np.testing.assert_allclose(_omega_from_R(Kp.R, Km.R, K.R, h), world(K, K.omega), atol=2e-8)
        # the exp-map joint's dS/dt is itself a central difference inside the engine: looser there
        np.testing.assert_allclose((world(Kp, Kp.v) - world(Km, Km.v)) / (2 * h), world(K, K.a), atol=2e-6)
        np.testing.assert_allclose((world(Kp, Kp.omega) - world(Km, Km.omega)) / (2 * h), world(K, K.alpha),
                                   atol=2e-6)


def test_chain_velocities_match_engine_jacobians(leg, motion):
    """Composed transmission J qd equals the engine's analytic frame Jacobian at every body origin."""
    q, qd, _ = motion
    st = TransmissionChain(leg).motion(q, qd)
    for name in ("pelvis", "shank", "toes", "pad", "sled", "tail", "arm"):
        K = st.body(leg, name)
        Jf = frame_jacobian(leg, q, name)
        np.testing.assert_allclose(np.einsum("nij,nj->ni", K.R, K.omega), np.einsum("nij,nj->ni", Jf[:, :3], qd),
                                   atol=1e-12)
        np.testing.assert_allclose(np.einsum("nij,nj->ni", K.R, K.v), np.einsum("nij,nj->ni", Jf[:, 3:], qd),
                                   atol=1e-12)


def test_chain_force_pass_is_transposed_jacobian_and_does_virtual_work(leg, motion):
    """Q from the backward force pass = J_point^T F + J_rot^T T, and delta q^T Q = work of the loads (FD)."""
    q, _, _ = motion
    rng = np.random.default_rng(3)
    N = q.shape[0]
    F, T, p = rng.normal(size=(N, 3)) * 50, rng.normal(size=(N, 3)) * 5, np.array([0.05, -0.3, 0.02])
    ch = TransmissionChain(leg)
    Q = ch.force(ch.motion(q), [AppliedLoad("shank", F, p, T)])
    _, Jp = point_jacobian(leg, q, "shank", p)
    Jw = frame_jacobian(leg, q, "shank")[:, :3]
    np.testing.assert_allclose(Q, np.einsum("nci,nc->ni", Jp, F) + np.einsum("nci,nc->ni", Jw, T), atol=1e-10)
    # Virtual work with a finite displacement: the work of F over the point's displacement, of T over the rotation.
    dq = rng.normal(size=q.shape)
    h = 1e-6
    (xp, _), (xm, _) = point_jacobian(leg, q + h * dq, "shank", p), point_jacobian(leg, q - h * dq, "shank", p)
    Rp, Rm, R0 = (ch.motion(qq).body(leg, "shank").R for qq in (q + h * dq, q - h * dq, q))
    work = np.sum(F * (xp - xm) / (2 * h), 1) + np.sum(T * _omega_from_R(Rp, Rm, R0, h), 1)
    np.testing.assert_allclose(np.sum(dq * Q, 1), work, rtol=1e-7, atol=1e-7)


def test_mass_element_dalembert_forces():
    """Eqs. 14-15 against the rate of change of momentum of a body spinning about an off-centre point."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(3, 3))
    I = A @ A.T + np.eye(3)
    me = MassElement(2.5, np.array([0.1, -0.2, 0.05]), I)
    K = _random_frame(rng, 3)
    me.do_force(K, gravity=np.array([0.0, -9.81, 0.0]))
    s = me.com
    w, al = K.omega, K.alpha
    ac = K.a + np.cross(al, s) + np.cross(w, np.cross(w, s))
    g = np.einsum("nji,j->ni", K.R, np.array([0.0, -9.81, 0.0]))
    np.testing.assert_allclose(K.f, 2.5 * (g - ac), atol=1e-12)
    dH = al @ I.T + np.cross(w, w @ I.T)               # rate of angular momentum about the com (body axes)
    np.testing.assert_allclose(K.tau, -dH + np.cross(s, K.f), atol=1e-12)


def test_skew_matches_cross():
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", skew(a), b), np.cross(a, b), atol=1e-15)
