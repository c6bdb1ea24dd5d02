"""Prioritized IK with coupling constraints: analytic linear cases and a planar arm."""
from __future__ import annotations

import numpy as np
import pytest

from lowerlimb.errors import InputError
from kinematics.algorithms.constraints import ConstraintSet, LinearConstraint
from kinematics.algorithms.prioritized import PrioritizedIK
from kinematics.algorithms.recruiting import RecruitingError, check_recruiting
from kinematics.algorithms.tasks import Task


def linear_task(a, target, name="lin", **kw):
    A = np.atleast_2d(np.asarray(a, float))
    t = np.atleast_1d(np.asarray(target, float))
    return Task(name, lambda q: (t - A @ q, A), **kw)


def planar_arm(lengths, goal):
    """Tip position task of a planar serial arm, angles relative: exact FK/Jacobian."""
    lengths = np.asarray(lengths, float)
    goal = np.asarray(goal, float)

    def f(q):
        phi = np.cumsum(q)
        p = np.array([np.sum(lengths * np.cos(phi)), np.sum(lengths * np.sin(phi))])
        dx = -np.cumsum((lengths * np.sin(phi))[::-1])[::-1]
        dy = np.cumsum((lengths * np.cos(phi))[::-1])[::-1]
        return goal - p, np.vstack([dx, dy])
    return f


NAMES3 = ("q0", "q1", "q2")


def test_two_levels_match_closed_form():
    # level 0: q0 + q1 = 1 exactly; level 1: q close to t in the null space of level 0
    t = np.array([2.0, 0.0, 3.0])
    ik = PrioritizedIK(NAMES3, [linear_task([1, 1, 0], 1.0, priority=0),
                                linear_task(np.eye(3), t, "posture", priority=1)], damping=1e-9)
    q = ik.step(np.zeros(3)).q
    a = np.array([1.0, 1.0, 0.0])
    expected = t - a * (a @ t - 1.0) / (a @ a)   # projection of t on the plane a.q = 1
    np.testing.assert_allclose(q, expected, atol=1e-9)


def test_high_priority_wins_against_conflicting_low_priority():
    ik = PrioritizedIK(NAMES3, [linear_task([[1, 0, 0]], 0.5, "hi", priority=0),
                                linear_task([[1, 0, 0]], -2.0, "lo", priority=1)], damping=1e-9)
    q = ik.step(np.zeros(3)).q
    assert q[0] == pytest.approx(0.5, abs=1e-9)


def test_equalities_hold_every_step_on_nonlinear_arm():
    names = tuple(f"q{i}" for i in range(5))
    cons = ConstraintSet.build(names, [LinearConstraint.ratio("q1", "q0", 0.5),
                                       LinearConstraint.ratio("q2", "q0", 0.25),
                                       LinearConstraint({"q3": 1.0, "q4": 1.0}, 0.2, "eq", "sum34")])
    lengths = [0.3, 0.3, 0.2, 0.2, 0.1]
    q_true = np.array([0.9, 0.45, 0.225, 0.6, -0.4])          # satisfies the three equalities
    goal = -planar_arm(lengths, [0.0, 0.0])(q_true)[0]        # its tip position
    ik = PrioritizedIK(names, [Task("tip", planar_arm(lengths, goal), max_error=0.05)],
                       constraints=cons, damping=1e-2)
    q = np.array([0.3, -0.1, 0.4, 0.0, 0.0])   # violates every equality at start
    for k in range(40):
        q = ik.step(q).q
        assert np.max(np.abs(cons.equality_residual(q))) < 1e-10, k
    # remaining freedom: 5 - 3 = 2 dofs, enough for a 2-D goal
    e, _ = planar_arm(lengths, goal)(q)
    assert np.linalg.norm(e) < 1e-6


def test_inequalities_and_limits_never_violated():
    names = tuple(f"q{i}" for i in range(4))
    ineq = LinearConstraint.band("q1", "q0", 1.0, 0.1)    # |q1 - q0| <= 0.1
    cons = ConstraintSet.build(names, [*ineq])
    lower = np.array([-0.2, -1, -1, -0.3])
    upper = np.array([0.4, 1, 1, 0.3])
    ik = PrioritizedIK(names, [Task("tip", planar_arm([0.3, 0.3, 0.3, 0.3], [-0.1, 0.9]), max_error=0.1)],
                       constraints=cons, lower=lower, upper=upper, damping=1e-2)
    q = np.zeros(4)
    clamped = set()
    for _ in range(60):
        r = ik.step(q)
        q = r.q
        clamped.update(r.clamped)
        assert np.all(cons.inequality_excess(q) <= 1e-12)
        assert np.all(q >= lower - 1e-12) and np.all(q <= upper + 1e-12)
    # the goal is out of the feasible set: clamps must have been active
    assert clamped


def test_conflicting_equalities_first_added_wins():
    a = LinearConstraint({"q0": 1.0}, 0.2, "eq", "first")
    b = LinearConstraint({"q0": 2.0}, 1.0, "eq", "second")     # q0 = 0.5: conflicts with q0 = 0.2
    with pytest.raises(InputError, match="second.*inconsistent"):
        ConstraintSet.build(NAMES3, [a, b])
    cons = ConstraintSet.build(NAMES3, [a, b], on_conflict="first_wins")
    ik = PrioritizedIK(NAMES3, [linear_task(np.eye(3), [1.0, 1.0, 1.0])], constraints=cons, damping=1e-9)
    r = ik.step(np.zeros(3))
    assert r.q[0] == pytest.approx(0.2, abs=1e-12)
    assert "second" in r.conflicts
    np.testing.assert_allclose(r.q[1:], 1.0, atol=1e-6)
    # reversed order: the other one wins
    cons2 = ConstraintSet.build(NAMES3, [b, a], on_conflict="first_wins")
    r2 = PrioritizedIK(NAMES3, [linear_task(np.eye(3), [1.0, 1.0, 1.0])], constraints=cons2).step(np.zeros(3))
    assert r2.q[0] == pytest.approx(0.5, abs=1e-12)


def test_user_inequality_wins_over_conflicting_joint_limit():
    cons = ConstraintSet.build(NAMES3, [LinearConstraint({"q0": 1.0}, 0.3, "le", "user q0<=0.3")])
    ik = PrioritizedIK(NAMES3, [linear_task([[1, 0, 0]], 1.0)], constraints=cons,
                       lower=[0.5, -1, -1], upper=[2, 1, 1], damping=1e-9)
    r = ik.step(np.zeros(3))
    assert r.q[0] == pytest.approx(0.3, abs=1e-12)
    assert r.clamped == ("user q0<=0.3",)
    assert r.conflicts == ("q0 >= lower limit",)


def test_redundant_equality_is_accepted():
    cons = ConstraintSet.build(NAMES3, [LinearConstraint({"q0": 1.0, "q1": -1.0}, 0.0),
                                        LinearConstraint({"q0": 2.0, "q1": -2.0}, 0.0)])
    r = PrioritizedIK(NAMES3, [linear_task(np.eye(3), [1.0, 0.0, 0.0])], constraints=cons).step(np.zeros(3))
    assert r.q[0] == pytest.approx(r.q[1], abs=1e-12)
    assert r.conflicts == ()


def test_bad_constraint_input_messages():
    with pytest.raises(InputError, match="'knee_angle' does not exist"):
        ConstraintSet.build(NAMES3, [LinearConstraint({"knee_angle": 1.0}, 0.0)])
    with pytest.raises(InputError, match="kind"):
        ConstraintSet.build(NAMES3, [LinearConstraint({"q0": 1.0}, 0.0, "ge")])
    with pytest.raises(InputError, match="zero"):
        ConstraintSet.build(NAMES3, [LinearConstraint({"q0": 0.0}, 0.0)])


def test_recruiting_rules_reported():
    names = ("a", "b", "c", "d")
    cons = ConstraintSet.build(names, [LinearConstraint.ratio("c", "d", 1.0)])
    ok = [Task("hi", None, 0, recruited=("a", "b", "c", "d"), ancestors=("a", "b", "c", "d")),
          Task("lo", None, 1, recruited=("a", "b"), ancestors=("a", "b"))]
    assert check_recruiting(ok, cons).ok
    # (3): the low-priority task recruits 'b', an ancestor of the high task that the high task does not recruit
    bad3 = [Task("hi", None, 0, recruited=("a",), ancestors=("a", "b")),
            Task("lo", None, 1, recruited=("b",), ancestors=("a", "b"))]
    rep = check_recruiting(bad3, cons)
    assert any(v.startswith("eq. (3)") for v in rep.violations)
    # (4): the low task recruits c, coupled to d which the high task reaches but does not recruit
    bad4 = [Task("hi", None, 0, recruited=("a",), ancestors=("a", "d")),
            Task("lo", None, 1, recruited=("c",), ancestors=("c",))]
    rep = check_recruiting(bad4, cons)
    assert any(v.startswith("eq. (4)") for v in rep.violations)
    assert not any(v.startswith("eq. (3)") for v in rep.violations)
    # (5): d coupled to c, recruited by nobody
    bad5 = [Task("only", None, 0, recruited=("a", "c"), ancestors=("a", "c"))]
    rep = check_recruiting(bad5, cons)
    assert any(v.startswith("eq. (5)") and "'d'" in v for v in rep.violations)
    with pytest.raises(RecruitingError, match="eq. \\(5\\)"):
        PrioritizedIK(names, bad5, constraints=cons)
    with pytest.raises(InputError, match="'zz'.*do not exist"):
        check_recruiting([Task("t", None, 0, recruited=("zz",))], cons).raise_if_violated()
