"""Model description, coordinate functions and joints (kinematics.multibody.model / functions / joints / coupling)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from kin_helpers import KNEE_X, leg_model
from kinematics.multibody.coupling import LinearCoupling, initial_projector, null_space_parametrization, restoring_variation
from lowerlimb.errors import InputError
from kinematics.multibody.functions import Constant, Linear, Multiplier, MultivariateLinear, NaturalCubicSpline, SimmSpline
from kinematics.multibody.joints import (ExpMapSpherical, SwingJoint, Transform, euler_to_matrix, exp_so3,
                               left_jacobian_inverse_so3, left_jacobian_so3, revolute, rotation_about)
from kinematics.multibody.model import Body, Coordinate, Marker, Model


@pytest.fixture(scope="module")
def model():
    return leg_model(exportable=False)


def test_model_is_topological_and_immutable(model):
    names = model.body_names
    assert names[0] == "ground"
    for i, j in enumerate(model.joints):
        assert model.bodies[i + 1].name == j.child
        assert names.index(j.parent) < i + 1
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.name = "x"
    with pytest.raises(ValueError):
        model.markers[0].offset[0] = 1.0
    with pytest.raises(ValueError):
        model.bodies[1].inertia[0, 0] = 2.0
    assert model.n_q == len(model.coordinates) == 19
    assert model.total_mass == pytest.approx(sum(b.mass for b in model.bodies))


def test_model_sorts_joints_given_in_any_order(model):
    shuffled = Model(model.bodies[::-1], model.joints[::-1], model.coordinates, model.markers)
    assert shuffled.body_names[0] == "ground"
    q = model.random_q(3, np.random.default_rng(0))
    from kinematics.algorithms.fk import marker_positions

    np.testing.assert_allclose(marker_positions(shuffled, q), marker_positions(model, q), atol=1e-14)


def test_model_rejects_bad_structure():
    c = (Coordinate("a"),)
    j = revolute("j", "ground", "b", "a")
    with pytest.raises(ValueError, match="unknown bod"):
        Model((Body("b"),), (revolute("j", "ground", "zz", "a"),), c)
    with pytest.raises(ValueError, match="no joint"):
        Model((Body("b"), Body("c")), (j,), c)
    with pytest.raises(ValueError, match="undeclared"):
        Model((Body("b"),), (j,), ())
    with pytest.raises(ValueError, match="unknown body"):
        Model((Body("b"),), (j,), c, (Marker("m", "nowhere", (0, 0, 0)),))
    with pytest.raises(ValueError, match="range"):
        Coordinate("x", range=(1.0, -1.0))
    with pytest.raises(ValueError):
        Body("b", inertia=np.eye(2))


def test_simm_spline_interpolates_and_derivatives_match_finite_differences():
    x, y = KNEE_X.x, KNEE_X.y
    np.testing.assert_allclose(KNEE_X(x), y, atol=1e-15)
    t = np.linspace(-2.5, 0.6, 301)
    v, g, h = KNEE_X.evaluate(t, order=2)
    e = 1e-6
    np.testing.assert_allclose(g[:, 0], (KNEE_X(t + e) - KNEE_X(t - e)) / (2 * e), atol=1e-7)
    inside = (t > x[0] + 1e-3) & (t < x[-1] - 1e-3)
    fd2 = (KNEE_X.evaluate(t + e, 1)[1] - KNEE_X.evaluate(t - e, 1)[1])[:, 0] / (2 * e)
    np.testing.assert_allclose(h[inside, 0, 0], fd2[inside], atol=1e-5)
    # Outside the knots the spline continues linearly with its end slopes.
    np.testing.assert_allclose(h[t < x[0], 0, 0], 0.0)
    # Exact on cubics: FMM end conditions reproduce a cubic exactly.
    xs = np.array([0.0, 0.3, 0.7, 1.2, 1.6, 2.0])
    f = lambda s: 0.5 * s**3 - s**2 + 0.25 * s - 1.0
    sp = SimmSpline(xs, f(xs))
    tt = np.linspace(0, 2, 57)
    np.testing.assert_allclose(sp(tt), f(tt), atol=1e-12)


def test_simm_spline_equals_opensim(opensim):
    os_sp = opensim.SimmSpline()
    for a, b in zip(KNEE_X.x, KNEE_X.y):
        os_sp.addPoint(float(a), float(b))
    t = np.linspace(-3.0, 1.0, 97)
    ref = np.array([os_sp.calcValue(opensim.Vector(1, float(s))) for s in t])
    np.testing.assert_allclose(KNEE_X(t), ref, rtol=0, atol=1e-15)


def test_natural_spline_and_simple_functions():
    xs = np.array([0.0, 1.0, 2.5, 3.0])
    ys = np.array([1.0, -1.0, 0.5, 0.0])
    ns = NaturalCubicSpline(xs, ys)
    np.testing.assert_allclose(ns(xs), ys, atol=1e-14)
    _, _, h = ns.evaluate(xs[[0, -1]] + np.array([1e-9, -1e-9]), order=2)
    np.testing.assert_allclose(h[:, 0, 0], 0.0, atol=1e-6)      # natural end conditions
    assert Constant(2.5)(np.zeros((4, 0))).tolist() == [2.5] * 4
    v, g = Linear(2.0, -1.0).evaluate([1.0, 3.0])
    np.testing.assert_allclose(v, [1.0, 5.0])
    np.testing.assert_allclose(g[:, 0], 2.0)
    mv = MultivariateLinear([0.5, -2.0], 0.1)
    v, g = mv.evaluate(np.array([[1.0, 1.0], [2.0, 0.5]]))
    np.testing.assert_allclose(v, [0.5 - 2 + 0.1, 1.0 - 1.0 + 0.1])
    np.testing.assert_allclose(g, [[0.5, -2.0], [0.5, -2.0]])
    m = Multiplier(Linear(2.0, 1.0), 3.0)
    assert m(np.array([1.0]))[0] == pytest.approx(9.0)


def test_euler_and_rotation_helpers():
    a = np.array([0.3, -0.5, 1.1])
    R = euler_to_matrix(a, "XYZ")
    ref = rotation_about([1, 0, 0], a[0]) @ rotation_about([0, 1, 0], a[1]) @ rotation_about([0, 0, 1], a[2])
    np.testing.assert_allclose(R, ref, atol=1e-15)
    from scipy.spatial.transform import Rotation

    np.testing.assert_allclose(R, Rotation.from_euler("XYZ", a).as_matrix(), atol=1e-14)
    from kinematics.multibody.joints import matrix_to_euler_xyz

    np.testing.assert_allclose(matrix_to_euler_xyz(R), a, atol=1e-14)
    lock = euler_to_matrix(np.array([0.4, np.pi / 2, 0.0]), "XYZ")
    np.testing.assert_allclose(euler_to_matrix(matrix_to_euler_xyz(lock), "XYZ"), lock, atol=1e-12)
    r = np.array([[0.2, -0.4, 0.9]])
    np.testing.assert_allclose(exp_so3(r)[0], Rotation.from_rotvec(r[0]).as_matrix(), atol=1e-14)
    T = Transform.from_euler_xyz(a, (1, 2, 3))
    np.testing.assert_allclose((T @ T.inverse()).rotation, np.eye(3), atol=1e-14)
    np.testing.assert_allclose((T @ T.inverse()).translation, 0.0, atol=1e-14)


def _numeric_subspace(joint, qj, h=1e-6):
    """[omega; v] columns by central differences of the joint transform."""
    N, k = qj.shape
    R0, _ = joint.transform(qj)
    S = np.zeros((N, 6, k))
    for i in range(k):
        d = np.zeros(k)
        d[i] = h
        Rp, pp = joint.transform(qj + d)
        Rm, pm = joint.transform(qj - d)
        W = ((Rp - Rm) / (2 * h)) @ np.swapaxes(R0, 1, 2)
        S[:, 0, i], S[:, 1, i], S[:, 2, i] = W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]
        S[:, 3:, i] = (pp - pm) / (2 * h)
    return S


def test_so3_left_jacobian_inverse_inverts_the_left_jacobian():
    rng = np.random.default_rng(3)
    r = rng.normal(size=(6, 3)) * np.array([[1e-9], [1e-7], [1e-3], [0.5], [2.0], [3.0]])
    eye = np.broadcast_to(np.eye(3), (6, 3, 3))
    np.testing.assert_allclose(left_jacobian_inverse_so3(r) @ left_jacobian_so3(r), eye, atol=1e-12)


def test_motion_subspaces_match_finite_differences(model):
    rng = np.random.default_rng(3)
    for joint in model.joints:
        if not joint.coordinates:
            continue
        qj = rng.uniform(-0.8, 0.8, (5, joint.n_coordinates))
        _, _, S = joint.motion_subspace(qj)
        np.testing.assert_allclose(S, _numeric_subspace(joint, qj), atol=1e-8, err_msg=joint.name)
        if joint.kind in ("swing", "expmap"):
            continue                      # their dS/dt is the generic central difference itself
        qd = rng.normal(size=qj.shape)
        Sd = joint.motion_subspace_derivative(qj, qd)
        e = 1e-6
        ref = (joint.motion_subspace(qj + e * qd)[2] - joint.motion_subspace(qj - e * qd)[2]) / (2 * e)
        np.testing.assert_allclose(Sd, ref, atol=1e-7, err_msg=joint.name)


def test_swing_joint_has_no_twist_and_expmap_matches_rotation_vector():
    sw = SwingJoint("s", "a", "b", ("u", "v"), axes=((1, 0, 0), (0, 1, 0)))
    q = np.array([[0.4, -0.7]])
    R, p, _ = sw.motion_subspace(q)
    # The rotation axis lies in the swing plane: R's rotation vector has no z component.
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(R[0]).as_rotvec()
    np.testing.assert_allclose(rv, [0.4, -0.7, 0.0], atol=1e-14)
    np.testing.assert_allclose(p, 0.0)
    ex = ExpMapSpherical("e", "a", "b", ("x", "y", "z"))
    r = np.array([[1.0, -2.0, 0.5]])
    np.testing.assert_allclose(ex.transform(r)[0][0], Rotation.from_rotvec(r[0]).as_matrix(), atol=1e-14)


def test_linear_coupling_projector_and_restoration():
    names = ("a", "b", "c", "d")
    row1 = LinearCoupling.correlative(names, "a", {"b": 0.5, "c": -0.25}, 0.1)
    row2 = LinearCoupling.correlative(names, "d", {"b": 2.0}, 0.0)
    both = row1.stack(row2)
    P = both.projector()
    np.testing.assert_allclose(P @ P, P, atol=1e-14)
    np.testing.assert_allclose(both.matrix @ P, 0.0, atol=1e-14)
    assert np.trace(P) == pytest.approx(2.0)
    q = np.array([1.0, -2.0, 3.0, 4.0])
    qr = both.restore(q)
    np.testing.assert_allclose(both.residual(qr), 0.0, atol=1e-14)
    # dq0 is the minimum-norm correction: orthogonal to the null space.
    np.testing.assert_allclose(P @ (qr - q), 0.0, atol=1e-14)
    # A repeated (dependent) row is skipped by the projector.
    C2 = np.vstack([both.matrix, 2 * both.matrix[0]])
    np.testing.assert_allclose(initial_projector(C2), P, atol=1e-12)
    q_p, N = null_space_parametrization(both.matrix, both.rhs)
    np.testing.assert_allclose(N @ N.T, P, atol=1e-12)
    np.testing.assert_allclose(restoring_variation(both.matrix, both.rhs, q), qr - q, atol=1e-14)


def test_linear_coupling_without_drops_exactly_the_rows_touching_the_names():
    names = ("a", "b", "c", "d")
    both = LinearCoupling.correlative(names, "a", {"b": 0.5, "c": -0.25}, 0.1).stack(
        LinearCoupling.correlative(names, "d", {"b": 2.0}, 0.0))
    kept = both.without({"c"})                     # only row 0 reads c
    assert kept.labels == (both.labels[1],)
    np.testing.assert_array_equal(kept.matrix, both.matrix[1:])
    np.testing.assert_array_equal(kept.rhs, both.rhs[1:])
    assert both.without({"b"}) is None             # both rows read b
    same = both.without({"zz"})                    # unknown names drop nothing
    np.testing.assert_array_equal(same.matrix, both.matrix)
    assert same.labels == both.labels
    with pytest.raises(InputError, match="inconsistent"):
        null_space_parametrization(np.vstack([both.matrix[0], both.matrix[0]]), [0.0, 1.0])


def test_custom_joint_with_constant_and_multivariate_axes():
    """Constant rotations, a two-coordinate (correlative) axis and a spline translation: S and dS/dt by differences."""
    from kinematics.multibody.joints import CustomJoint, TransformAxis

    j = CustomJoint(
        "j", "a", "b", ("u", "v"),
        rotations=(TransformAxis((0, 0, 1), Linear(1.0, 0.0), ("u",)),
                   TransformAxis((1, 0, 0), Constant(0.3), ()),
                   TransformAxis((0.0, 0.6, 0.8), MultivariateLinear([0.4, -0.7], 0.1), ("u", "v"))),
        translations=(TransformAxis((1, 0, 0), Multiplier(KNEE_X, 1.2), ("u",)),
                      TransformAxis((0, 1, 0), Constant(-0.02), ())),
    )
    rng = np.random.default_rng(2)
    qj = rng.uniform(-1.5, 0.3, (6, 2))
    R, p, S = j.motion_subspace(qj)
    np.testing.assert_allclose(S, _numeric_subspace(j, qj), atol=1e-8)
    ref = (rotation_about([0, 0, 1], qj[:, 0]) @ rotation_about([1, 0, 0], np.full(6, 0.3))
           @ rotation_about([0, 0.6, 0.8], 0.4 * qj[:, 0] - 0.7 * qj[:, 1] + 0.1))
    np.testing.assert_allclose(R, ref, atol=1e-14)
    np.testing.assert_allclose(p[:, 1], -0.02)
    qd = rng.normal(size=qj.shape)
    e = 1e-6
    num = (j.motion_subspace(qj + e * qd)[2] - j.motion_subspace(qj - e * qd)[2]) / (2 * e)
    np.testing.assert_allclose(j.motion_subspace_derivative(qj, qd), num, atol=1e-7)
