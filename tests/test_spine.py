"""Coupled spine (Raunhardt & Boulic 2007): model structure, constraints in IK, section-5 experiments (short)."""
from __future__ import annotations

import numpy as np
import pytest

from kinematics.multibody.coupling import initial_projector
from lowerlimb.errors import InputError
from kinematics.multibody.joints import SwingJoint
from kinematics.algorithms.constraints import ConstraintSet, LinearConstraint
from kinematics.algorithms.prioritized import PrioritizedIK
from kinematics.algorithms.recruiting import RecruitingError
from kinematics.algorithms.tasks import KinematicTasks
from kinematics.mechanisms.spine import isolated_spine, mannequin, spine_layout
from kinematics.mechanisms.spine_measures import (posture_distance, spine_coordinates, spine_distance, spine_drift_bound,
                                                  swing_components, torsion_direction_changes, vertebral_twist)
from spine_experiments import balanced_posture_tasks, isolated_spine_tasks, periodic_drift

HANIM = ([f"vl{i}" for i in range(5, 0, -1)] + [f"vt{i}" for i in range(12, 0, -1)]
         + [f"vc{i}" for i in range(7, 0, -1)])


@pytest.fixture(scope="module")
def full_coupled():
    return isolated_spine("full", coupled=True)


@pytest.fixture(scope="module")
def isolated_runs():
    """Experiment 5.1 run once per variant: (model, solver, list of configurations per step)."""
    runs = {}
    for coupled in (True, False):
        model = isolated_spine("full", coupled)
        ik = PrioritizedIK.from_model(model, isolated_spine_tasks(model))
        q = model.default_q
        qs = [q]
        for _ in range(25):
            q = ik.step(q).q
            qs.append(q)
        runs[coupled] = (model, ik, qs)
    return runs


def test_full_spine_structure(full_coupled):
    m = full_coupled
    assert spine_layout("full").joints == tuple(HANIM)
    swing = [j for j in m.joints if isinstance(j, SwingJoint)]
    twist = [j for j in m.joints if j.name in HANIM and not isinstance(j, SwingJoint)]
    assert len(swing) == 17 and len(twist) == 7
    cons = ConstraintSet.from_model(m)
    assert (m.n_q, len(cons.b), len(cons.h)) == (41, 32, 12)
    # each equality removes one dof: 9 left (flexion, bending, torsion per region)
    assert m.n_q - np.linalg.matrix_rank(cons.C) == 9
    # joint limits enforced only on the first joint of each region (swing vl5 vt12 vc7, twist vl2 vt8 vc6)
    clamped = sorted({c.name.split("_")[0] for c in m.coordinates if c.clamped})
    assert clamped == sorted(["vl5", "vt12", "vc7", "vl2", "vt8", "vc6"])


def test_simplified_spine_structure():
    m = isolated_spine("simplified", coupled=True)
    swing = [j for j in m.joints if isinstance(j, SwingJoint)]
    twist = [j for j in m.joints if j.kind == "revolute"]
    cons = ConstraintSet.from_model(m)
    assert (len(swing), len(twist), m.n_q, len(cons.b), len(cons.h)) == (8, 5, 21, 12, 12)
    unc = mannequin("simplified", coupled=False)
    assert sum(j.kind == "expmap" for j in unc.joints) == 8 + 2      # 8 vertebral ball joints + 2 shoulders


def test_projector_matches_shared_coupling_mechanism(full_coupled):
    cons = ConstraintSet.from_model(full_coupled)
    ik = PrioritizedIK.from_model(full_coupled, isolated_spine_tasks(full_coupled))
    np.testing.assert_allclose(ik._Z0 @ ik._Z0.T, initial_projector(cons.C), atol=1e-12)


def test_swing_has_no_twist_and_twist_reads_revolute(full_coupled):
    m = full_coupled
    rng = np.random.default_rng(3)
    q = np.zeros(m.n_q)
    names = m.coordinate_names
    for i, n in enumerate(names):
        q[i] = rng.uniform(-0.2, 0.2)
    tw = vertebral_twist(m, q)
    sw = swing_components(m, q)
    layout = spine_layout("full")
    for reg in layout.regions:
        for k, j in enumerate(reg.joints):
            if j in reg.twist:
                assert tw[reg.name][k] == pytest.approx(q[names.index(f"{j}_rotation")], abs=1e-12)
                np.testing.assert_allclose(sw[reg.name][k], 0.0, atol=1e-12)
            else:
                assert tw[reg.name][k] == pytest.approx(0.0, abs=1e-12)
                # swing rotation vector components are the exponential-map coordinates
                np.testing.assert_allclose(sw[reg.name][k], [q[names.index(f"{j}_extension")],
                                                             q[names.index(f"{j}_bending")]], atol=1e-12)


def test_isolated_spine_constraints_hold_every_step(isolated_runs):
    model, ik, qs = isolated_runs[True]
    cons = ik.constraints
    for q in qs[1:]:
        assert np.max(np.abs(cons.equality_residual(q))) < 1e-10
        assert np.max(cons.inequality_excess(q)) <= 1e-12
        # clamped limits never violated; the coupled (unclamped) ones stay in range through the ratios
        assert np.all(q >= model.lower - 1e-12) and np.all(q <= model.upper + 1e-12)


def test_isolated_spine_coupled_keeps_regional_shape(isolated_runs):
    """Fig. 4/6: coupled swings keep one sign per region; the uncoupled spine bends in an S."""
    def sign_changes(model, q):
        n = 0
        for s in swing_components(model, q).values():
            for col in s.T:
                v = col[np.abs(col) > 1e-6]
                n += int(np.sum(np.sign(v[1:]) != np.sign(v[:-1])))
        return n
    m_c, ik_c, qs_c = isolated_runs[True]
    m_u, ik_u, qs_u = isolated_runs[False]
    assert sign_changes(m_c, qs_c[-1]) == 0
    assert sign_changes(m_u, qs_u[-1]) > 0
    # high-priority orientation reached by both; the coupled position task cannot be met fully (seed 5.1)
    e_c = ik_c.step(qs_c[-1]).errors
    e_u = ik_u.step(qs_u[-1]).errors
    assert e_c[0] < 1e-5 and e_u[0] < 1e-5
    assert e_u[1] < 1e-5 < e_c[1]


@pytest.fixture(scope="module")
def balanced():
    out = {}
    for coupled in (True, False):
        m = mannequin("simplified", coupled)
        ik = PrioritizedIK.from_model(m, balanced_posture_tasks(m, KinematicTasks(m)))
        res = ik.solve(m.default_q, max_iterations=200, tol=1e-6)
        out[coupled] = (m, ik, res)
    return out


def test_balanced_posture_torsion_direction(balanced):
    m, ik, res = balanced[True]
    assert res.converged
    assert np.max(np.abs(ik.constraints.equality_residual(res.q))) < 1e-10
    assert sum(torsion_direction_changes(m, res.q).values()) == 0
    mu, _, ru = balanced[False]
    assert ru.converged
    assert sum(torsion_direction_changes(mu, ru.q).values()) >= 1


def test_recruiting_rule_on_mannequin():
    """A head task below hands that do not recruit the cervical joints violates eq. (4)."""
    m = mannequin("simplified", True)
    kt = KinematicTasks(m)
    tasks = balanced_posture_tasks(m, kt)
    bad = [t if "hand" not in t.name else type(t)(t.name, t.function, t.priority, t.ancestors, t.ancestors)
           for t in tasks]
    with pytest.raises(RecruitingError, match=r"eq\. \(4\).*vc"):
        PrioritizedIK.from_model(m, bad)


@pytest.fixture(scope="module")
def drift_runs():
    """Experiment 5.2.2, 40 cycles, for the coupled spine and two uncoupled baselines."""
    kw = dict(cycles=40, steps_per_cycle=12, checkpoints=(1, 40), settle=30)
    models = {"coupled": mannequin("simplified", True),
              # like-for-like: the same joints and limit set (first joint of each region), no coupling
              "same_limits": mannequin("simplified", False, joint_style="swing_twist", spine_limits="first"),
              "unlimited": mannequin("simplified", False, limit_spine=False)}
    return {k: (m, periodic_drift(m, **kw)) for k, m in models.items()}


def test_like_for_like_baseline_has_the_same_joints_and_limits():
    c = mannequin("simplified", True)
    u = mannequin("simplified", False, joint_style="swing_twist", spine_limits="first")
    assert c.coordinate_names == u.coordinate_names
    assert [k.clamped for k in c.coordinates] == [k.clamped for k in u.coordinates]
    assert len(ConstraintSet.from_model(u).b) == 0 and len(ConstraintSet.from_model(c).b) == 12
    clamped = sorted(k.name for k in u.coordinates if k.clamped and k.name in spine_coordinates(u))
    assert clamped == sorted(["vl5_extension", "vl5_bending", "vl3_rotation", "vt10_extension", "vt10_bending",
                              "vt10_rotation", "vc7_extension", "vc7_bending", "vc7_rotation"])
    ball = mannequin("simplified", False, spine_limits="first")
    assert sorted({k.name.split("_")[0] for k in ball.coordinates
                   if k.clamped and k.name in spine_coordinates(ball)}) == ["vc7", "vl5", "vt10"]
    with pytest.raises(InputError, match="spine limits must be one of"):
        mannequin("simplified", False, spine_limits="some")


def test_periodic_drift_short_direction(drift_runs):
    """Experiment 5.2.2, 40 cycles: the coupled spine drifts less than the uncoupled spine with the same
    joints and limit set, and much less than an unbounded ball-joint spine."""
    (mc, c), (ms, s), (mu, u) = (drift_runs[k] for k in ("coupled", "same_limits", "unlimited"))
    assert c["max_equality_residual"] < 1e-10
    for r in (c, s, u):
        assert r["max_inequality_or_limit_excess"] <= 1e-12
        assert r["drift_spine_rad"][1] == 0.0 and r["drift_posture_rad"][1] == 0.0
    assert s["drift_spine_rad"][40] > 1.5 * c["drift_spine_rad"][40]
    assert u["drift_spine_rad"][40] > 2.0 * c["drift_spine_rad"][40]
    # the spine is part of the posture: whole-posture geodesic drift >= spine drift
    for r in (c, s, u):
        assert r["drift_posture_rad"][40] >= r["drift_spine_rad"][40] - 1e-12


def test_spine_drift_bound(drift_runs):
    mc, c = drift_runs["coupled"]
    b = spine_drift_bound(mc)
    # the first joints span their ranges; the coupled ones follow by their ratio (1 in the simplified spine)
    lo, hi = mc.coordinates[mc.coordinate_index("vl5_extension")].range
    assert b["span_rad"]["vl5_extension"] == pytest.approx(hi - lo, abs=1e-9)
    assert b["span_rad"]["vl1_extension"] == pytest.approx(hi - lo, abs=1e-9)
    assert np.isfinite(b["geodesic_rad"]) and c["drift_spine_rad"][40] <= b["geodesic_rad"]
    # every ball joint limited: both bounds equal the norm of the range spans
    ball = mannequin("simplified", False)
    spans = [np.diff(ball.coordinates[ball.coordinate_index(n)].range)[0] for n in spine_coordinates(ball)]
    bb = spine_drift_bound(ball)
    assert bb["coordinate_rad"] == pytest.approx(np.linalg.norm(spans), rel=1e-9)
    assert bb["geodesic_rad"] == pytest.approx(np.linalg.norm(spans), rel=1e-9)
    # same limit set without coupling: the unclamped vertebrae are unbounded
    assert spine_drift_bound(drift_runs["same_limits"][0])["geodesic_rad"] == np.inf


def test_posture_distance_is_geodesic():
    m = mannequin("simplified", True)
    q = m.default_q.copy()
    q2 = q.copy()
    names = m.coordinate_names
    q2[names.index("vt10_rotation")] += 0.3
    q2[names.index("elbow_flexion_r")] += 0.4
    q2[names.index("pelvis_tx")] += 1.0            # translations are not part of the distance
    assert posture_distance(m, q2, q) == pytest.approx(0.5, abs=1e-12)
    assert spine_distance(m, q2, q) == pytest.approx(0.3, abs=1e-12)


def test_spine_distance_is_geodesic(full_coupled):
    m = full_coupled
    q = np.zeros(m.n_q)
    q2 = q.copy()
    q2[m.coordinate_names.index("vt8_rotation")] = 0.3
    q2[m.coordinate_names.index("vl5_extension")] = -0.4
    assert spine_distance(m, q2, q) == pytest.approx(0.5, abs=1e-12)


def test_bad_spine_input():
    with pytest.raises(InputError, match="unknown spine kind"):
        spine_layout("cervical-only")
    with pytest.raises(InputError, match="only the swing/twist spine can be coupled"):
        mannequin("simplified", coupled=True, joint_style="ball")
    m = isolated_spine("simplified", True)
    with pytest.raises(InputError, match="'vl9_extension' does not exist"):
        ConstraintSet.from_model(m, [LinearConstraint({"vl9_extension": 1.0}, 0.0)])
    with pytest.raises(InputError, match="inconsistent"):
        ConstraintSet.from_model(m, [LinearConstraint({"vl3_extension": 1.0, "vl5_extension": -1.0}, 0.1)])
