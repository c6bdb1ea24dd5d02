"""Newton loop closure (kinematics.algorithms.loops) on a planar four-bar linkage with closed-form angles."""
from __future__ import annotations

import numpy as np
import pytest

from kinematics.mechanisms.dynamics import generalized_forces
from lowerlimb.errors import FitError, InputError
from kinematics.algorithms.fk import point_jacobian
from kinematics.multibody.joints import Transform, revolute
from kinematics.algorithms.loops import CoincidentPoints, DistanceConstraint, close_loop, loop_residuals
from kinematics.multibody.model import Body, Coordinate, Model
from kinematics.mechanisms.transmission import AppliedLoad

# Crank-rocker (Grashof: a + b <= c + d): ground pivots A = 0 and D = (d, 0); crank AB, coupler BC, rocker DC.
A_, B_, C_, D_ = 0.1, 0.35, 0.2, 0.3


def four_bar(with_rocker: bool = True) -> Model:
    I = np.eye(3) * 1e-3
    bodies = [Body("crank", 0.5, (A_ / 2, 0, 0), I), Body("coupler", 1.0, (B_ / 2, 0, 0), I)]
    joints = [revolute("A", "ground", "crank", "theta2"),
              revolute("B", "crank", "coupler", "theta3", parent_offset=Transform(np.eye(3), (A_, 0, 0)))]
    coords = [Coordinate("theta2"), Coordinate("theta3")]
    if with_rocker:
        bodies.append(Body("rocker", 0.7, (C_ / 2, 0, 0), I))
        joints.append(revolute("D", "ground", "rocker", "theta4", parent_offset=Transform(np.eye(3), (D_, 0, 0))))
        coords.append(Coordinate("theta4"))
    return Model(tuple(bodies), tuple(joints), tuple(coords), name="four_bar")


def closed_form(theta2):
    """Coupler (relative to the crank) and rocker angles of the open assembly (C above the line BD)."""
    B = np.stack([A_ * np.cos(theta2), A_ * np.sin(theta2)], -1)
    BD = np.array([D_, 0.0]) - B
    e = np.linalg.norm(BD, axis=-1)
    phi = np.arctan2(BD[:, 1], BD[:, 0]) + np.arccos((B_**2 + e**2 - C_**2) / (2 * B_ * e))
    C = B + B_ * np.stack([np.cos(phi), np.sin(phi)], -1)
    theta4 = np.arctan2(C[:, 1], C[:, 0] - D_)
    return np.angle(np.exp(1j * (phi - theta2))), theta4


LOOP = [CoincidentPoints("coupler", (B_, 0, 0), "rocker", (C_, 0, 0))]


@pytest.fixture(scope="module")
def solved():
    m = four_bar()
    theta2 = np.linspace(-np.pi, np.pi, 9)[:-1]
    t3, t4 = closed_form(theta2)
    rng = np.random.default_rng(3)
    q0 = np.stack([theta2, t3 + rng.uniform(-0.25, 0.25, 8), t4 + rng.uniform(-0.25, 0.25, 8)], 1)
    return m, theta2, t3, t4, close_loop(m, q0, LOOP, ["theta3", "theta4"])


def test_coincident_points_close_the_four_bar(solved):
    m, theta2, t3, t4, sol = solved
    np.testing.assert_allclose(sol.q[:, 0], theta2, atol=0)                  # the driving angle is kept
    np.testing.assert_allclose(np.angle(np.exp(1j * (sol.q[:, 1] - t3))), 0.0, atol=1e-10)
    np.testing.assert_allclose(np.angle(np.exp(1j * (sol.q[:, 2] - t4))), 0.0, atol=1e-10)
    assert sol.residual.max() <= 1e-12 and sol.iterations <= 10


def test_distance_chord_closes_the_open_chain():
    """Without the rocker body: the coupler tip kept at the rocker length from the ground pivot D."""
    m = four_bar(with_rocker=False)
    theta2 = np.array([0.3, 1.7, -2.2])
    t3, _ = closed_form(theta2)
    loop = [DistanceConstraint("ground", (D_, 0, 0), "coupler", (B_, 0, 0), C_)]
    sol = close_loop(m, np.stack([theta2, t3 + 0.2], 1), loop, ["theta3"])
    np.testing.assert_allclose(sol.q[:, 1], t3, atol=1e-10)
    single = close_loop(m, np.array([theta2[0], t3[0] - 0.2]), loop, ["theta3"])
    assert single.q.shape == (2,) and single.q[1] == pytest.approx(t3[0], abs=1e-10)


def test_loop_jacobian_and_dependency_match_finite_differences(solved):
    m, theta2, _, _, sol = solved
    g, J = loop_residuals(m, sol.q, LOOP)
    h = 1e-6
    Jfd = np.stack([(loop_residuals(m, sol.q + h * e, LOOP)[0] - loop_residuals(m, sol.q - h * e, LOOP)[0]) / (2 * h)
                    for e in np.eye(3)], axis=2)
    np.testing.assert_allclose(J, Jfd, atol=1e-9)
    # velocity transmission of the solver: d(theta3, theta4)/d theta2 vs differentiating the closed form
    d3 = (closed_form(theta2 + h)[0] - closed_form(theta2 - h)[0]) / (2 * h)
    d4 = (closed_form(theta2 + h)[1] - closed_form(theta2 - h)[1]) / (2 * h)
    np.testing.assert_allclose(sol.dependency[:, :, 0], np.stack([np.ones_like(d3), d3, d4], 1), atol=1e-7)
    np.testing.assert_allclose(sol.velocities(np.full((8, 1), 2.0))[:, 2], 2 * d4, atol=1e-6)


def test_closed_loop_force_transmission_satisfies_virtual_work(solved):
    """A force on the rocker tip: Q on all three angles (J^T F), reduced to the crank by the solver's force
    transmission, equals the work of the force per unit crank rotation along the closed loop (FD)."""
    m, theta2, t3, t4, sol = solved
    F = np.array([3.0, -7.0, 0.0])
    tip = (C_, 0.0, 0.0)
    Q = generalized_forces(m, sol.q, [AppliedLoad("rocker", F, tip)])
    Qc = sol.reduce_forces(Q)[:, 0]
    h = 1e-6
    x = lambda th: point_jacobian(m, np.stack([th, *closed_form(th)], 1), "rocker", tip)[0]
    work = (x(theta2 + h) - x(theta2 - h)) @ F / (2 * h)
    np.testing.assert_allclose(Qc, work, atol=1e-7)
    assert np.abs(Qc).max() > 0.1


def test_unclosable_loop_and_bad_input_are_reported():
    m = four_bar(with_rocker=False)
    with pytest.raises(FitError, match="cannot be assembled"):
        close_loop(m, np.array([0.0, 0.0]), [DistanceConstraint("ground", (D_, 0, 0), "coupler", (B_, 0, 0), 2.0)],
                   ["theta3"])
    with pytest.raises(InputError, match="theta9"):
        close_loop(m, np.zeros(2), [DistanceConstraint("ground", (D_, 0, 0), "coupler", (B_, 0, 0), C_)], ["theta9"])
    with pytest.raises(InputError, match="> 0"):
        DistanceConstraint("ground", (0, 0, 0), "coupler", (0, 0, 0), 0.0)


def test_closed_loop_accelerations_and_inverse_dynamics(solved):
    """Solver acceleration transmission vs differentiating the closed form, and the crank torque of the closed
    loop (E^T tau) against the power balance d(kinetic energy)/dt = theta2_dot * torque (no gravity)."""
    from kinematics.mechanisms.dynamics import inverse_dynamics, mass_matrix

    m, theta2, _, _, sol = solved
    w, al = 1.5, -4.0
    qd, qdd = sol.accelerations(np.full((8, 1), w), np.full((8, 1), al))
    h = 1e-5

    def closed(t):
        th = theta2 + w * t + 0.5 * al * t * t
        s = close_loop(m, np.stack([th, *closed_form(th)], 1), LOOP, ["theta3", "theta4"])
        return s.q, s.velocities(np.full((8, 1), w + al * t))

    (qp, vp), (qm, vm) = closed(h), closed(-h)
    np.testing.assert_allclose(qd, (qp - qm) / (2 * h), atol=1e-8)
    np.testing.assert_allclose(qdd, (vp - vm) / (2 * h), atol=1e-6)
    torque = sol.reduce_forces(inverse_dynamics(m, sol.q, qd, qdd, gravity=False))[:, 0]
    kin = lambda q, v: 0.5 * np.einsum("ni,nij,nj->n", v, mass_matrix(m, q), v)
    np.testing.assert_allclose(w * torque, (kin(qp, vp) - kin(qm, vm)) / (2 * h), rtol=1e-6, atol=1e-8)
    assert np.abs(torque).max() > 1e-3
