"""Distance chords and chord chains (muscle paths): kinematics.mechanisms.chords."""
from __future__ import annotations

import numpy as np
import pytest

from kin_helpers import leg_model
from kinematics.mechanisms.chords import Chord, ChordChain, ChordPath, PathTension
from kinematics.mechanisms.dynamics import generalized_forces, inverse_dynamics
from lowerlimb.errors import InputError
from kinematics.algorithms.fk import point_jacobian
from kinematics.multibody.joints import Transform
from kinematics.mechanisms.transmission import AppliedLoad, TransmissionChain


@pytest.fixture(scope="module")
def leg():
    return leg_model(exportable=False)


@pytest.fixture(scope="module")
def gastrocnemius():
    """A biarticular path: thigh origin, a via point on the shank (wrapping around the knee), heel insertion."""
    return ChordPath("gastroc", ("thigh", "shank", "shank", "foot"),
                     [(-0.02, -0.38, 0.03), (-0.03, -0.05, 0.02), (-0.02, -0.25, 0.01), (-0.1, 0.0, 0.0)])


@pytest.fixture(scope="module")
def poses(leg):
    rng = np.random.default_rng(21)
    q = leg.random_q(4, rng)
    return q, rng.normal(size=q.shape), rng.normal(size=q.shape)


def test_path_length_jacobian_matches_central_differences(leg, gastrocnemius, poses):
    q = poses[0]
    l, J = gastrocnemius.length_jacobian(leg, q)
    h = 1e-6
    Jfd = np.stack([(gastrocnemius.length(leg, q + h * e) - gastrocnemius.length(leg, q - h * e)) / (2 * h)
                    for e in np.eye(leg.n_q)], axis=1)
    np.testing.assert_allclose(J, Jfd, atol=1e-9)
    assert np.abs(J[:, leg.coordinate_index("knee_angle")]).min() > 5e-3     # spans the knee...
    assert np.abs(J[:, leg.coordinate_index("ankle_angle")]).min() > 5e-3    # ...and the ankle
    assert np.allclose(J[:, leg.coordinate_index("sled")], 0.0)               # not the sled
    np.testing.assert_allclose(l, gastrocnemius.length(leg, q), atol=1e-15)


def test_chain_element_motion_matches_finite_differences(leg, gastrocnemius, poses):
    """ChordChain on the transmission frames: l, ld, ldd (eqs. 20-22) vs the path length along q(t)."""
    q, qd, qdd = poses
    ch = TransmissionChain(leg)
    chain = gastrocnemius.chain(leg)
    h = 1e-5
    path = lambda t: chain.do_motion(ch.motion(q + t * qd + 0.5 * t * t * qdd, qd + t * qdd, qdd).bodies)
    sp, s0, sm = path(h), path(0.0), path(-h)
    np.testing.assert_allclose(s0.value, gastrocnemius.length(leg, q), atol=1e-14)
    np.testing.assert_allclose(s0.rate, (sp.value - sm.value) / (2 * h), atol=1e-8)
    np.testing.assert_allclose(s0.acceleration, (sp.value - 2 * s0.value + sm.value) / h**2, atol=2e-4)
    np.testing.assert_allclose(s0.acceleration, (sp.rate - sm.rate) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(s0.rate, gastrocnemius.lengthening_velocity(leg, q, qd), atol=1e-12)


def test_chord_jacobian_and_force_virtual_work(leg, poses):
    """Single chord: ld = J [omega0; v0; omega1; v1] (eq. 17) and the frame loads are J^T F (eq. 19)."""
    q, qd, _ = poses
    st = TransmissionChain(leg).motion(q, qd)
    K0, K1 = st.body(leg, "pelvis"), st.body(leg, "shank")
    c = Chord([0.03, -0.05, 0.08], [0.02, -0.1, 0.01])
    J = c.jacobian(K0, K1)
    s = c.do_motion(K0, K1)
    np.testing.assert_allclose(s.rate, np.sum(J * np.concatenate([K0.twist, K1.twist], 1), 1), atol=1e-12)
    K0.reset_load(), K1.reset_load()
    F = np.array([10.0, -20.0, 5.0, 1.0])
    c.do_force(K0, K1, F)
    np.testing.assert_allclose(np.concatenate([K0.wrench, K1.wrench], 1), J * F[:, None], atol=1e-12)


def test_path_tension_in_force_pass_equals_moment_arm_mapping(leg, gastrocnemius, poses):
    """Tension T through the element force pass = -(dl/dq)^T T = via-point forces applied as loads; the
    virtual work of the tension is -T delta l."""
    q, qd, qdd = poses
    T = np.array([300.0, 550.0, 80.0, 1000.0])
    Q = gastrocnemius.generalized_forces(leg, q, T)
    np.testing.assert_allclose(generalized_forces(leg, q, elements=[PathTension(gastrocnemius, T)]), Q, atol=1e-9)
    Fp = gastrocnemius.point_forces(leg, q, T)
    np.testing.assert_allclose(Fp.sum(axis=1), 0.0, atol=1e-9)               # internal force: no net force
    loads = [AppliedLoad(b, Fp[:, i], p) for i, (b, p) in enumerate(zip(gastrocnemius.bodies, gastrocnemius.points))]
    np.testing.assert_allclose(generalized_forces(leg, q, loads), Q, atol=1e-9)
    # inverse dynamics: the joints supply less torque where the muscle helps
    d = inverse_dynamics(leg, q, qd, qdd, elements=[PathTension(gastrocnemius, T)]) - inverse_dynamics(leg, q, qd, qdd)
    np.testing.assert_allclose(d, -Q, atol=1e-9)
    rng = np.random.default_rng(22)
    dq = rng.normal(size=q.shape)
    h = 1e-6
    dl = (gastrocnemius.length(leg, q + h * dq) - gastrocnemius.length(leg, q - h * dq)) / (2 * h)
    np.testing.assert_allclose(np.sum(dq * Q, 1), -T * dl, rtol=1e-7)
    # a single segment from one body to another: Q = J_1^T (-T e) + J_0^T (T e)
    seg = ChordPath("strap", ("pelvis", "thigh"), [(0.0, 0.0, 0.1), (0.0, -0.2, 0.05)])
    (x0, J0), (x1, J1) = point_jacobian(leg, q, "pelvis", (0.0, 0.0, 0.1)), point_jacobian(leg, q, "thigh", (0.0, -0.2, 0.05))
    e = (x1 - x0) / np.linalg.norm(x1 - x0, axis=1, keepdims=True)
    ref = np.einsum("nci,nc->ni", J0 - J1, T[:, None] * e)
    np.testing.assert_allclose(seg.generalized_forces(leg, q, T), ref, atol=1e-9)


def test_moving_and_conditional_via_points(leg, poses):
    """A quadriceps-like path with a via point sliding with the knee angle (spline) and a conditional via point:
    dl/dq vs central differences, and the tension through the force pass (body loads plus the moving point's own
    generalised force) equals -(dl/dq)^T T."""
    from kinematics.mechanisms.chords import MovingPoint, ViaCondition
    from kinematics.multibody.functions import Constant, Linear
    from kin_helpers import KNEE_X

    quad = ChordPath("quad", ("pelvis", "thigh", "shank", "shank"),
                     [(-0.03, -0.05, 0.08), (0.04, -0.35, 0.0), (0.0, 0.0, 0.0), (0.05, -0.08, 0.0)],
                     moving=(None, None, MovingPoint((KNEE_X, Linear(0.05, 0.02), Constant(0.01)),
                                                     ("knee_angle", "knee_angle", None),
                                                     Transform.from_euler_xyz((0, 0, 0.2), (0.03, -0.01, 0.0))), None),
                     conditions=(None, ViaCondition("knee_angle", -2.2, -0.8), None, None))
    q = poses[0].copy()
    k = leg.coordinate_index("knee_angle")
    q[:, k] = [-1.5, -1.0, -0.3, 0.05]                                          # via point on, on, off, off
    np.testing.assert_array_equal(quad.active_points(leg, q)[:, 1], [True, True, False, False])
    l, J = quad.length_jacobian(leg, q)
    h = 1e-6
    Jfd = np.stack([(quad.length(leg, q + h * e) - quad.length(leg, q - h * e)) / (2 * h) for e in np.eye(leg.n_q)], 1)
    np.testing.assert_allclose(J, Jfd, atol=1e-9)
    T = np.array([400.0, 50.0, 900.0, 10.0])
    Q = generalized_forces(leg, q, elements=[PathTension(quad, T)])
    np.testing.assert_allclose(Q, quad.generalized_forces(leg, q, T), atol=1e-9)
    assert np.abs(Q[:, k]).min() > 0.1
    with pytest.raises(InputError, match="not a fixed chord chain"):
        quad.chain(leg)


def test_bad_paths_are_rejected(leg):
    with pytest.raises(InputError, match="at least two via points"):
        ChordPath("m", ("thigh",), [(0, 0, 0)])
    with pytest.raises(InputError, match="no body 'femur'"):
        ChordPath("m", ("femur", "shank"), [(0, 0, 0), (0, 0, 0)]).length(leg, leg.default_q)
    with pytest.raises(InputError, match="zero length"):
        ChordPath("m", ("thigh", "thigh"), [(0, 0, 0), (0, 0, 0)]).length(leg, leg.default_q)
    with pytest.raises(ValueError):
        ChordChain((0,), [(0, 0, 0)])


def test_gait2392_muscle_paths_match_opensim(shared_data, opensim):
    """All 92 gait2392 muscle-tendon paths (fixed, conditional and moving via points): length, lengthening speed
    and moment arms (-dl/dq) against OpenSim's GeometryPath, with the knee flexed past the vasti's switches."""
    from kinematics.mechanisms.chords import load_osim_paths
    from kinematics.io.opensim_io import load_osim

    path = shared_data / "opensim_gait2392/subject01_simbody_adjusted.osim"
    model = load_osim(path)
    paths, skipped = load_osim_paths(path, model)
    assert len(paths) == 92 and not skipped
    assert any(m is not None for m in paths["vas_med_r"].moving)
    assert any(c is not None for c in paths["semimem_r"].conditions)
    rng = np.random.default_rng(23)
    q = model.random_q(3, rng)
    q[:, model.coordinate_index("knee_angle_r")] = [-1.9, -1.5, -0.3]     # 2, 1 and 0 active conditional points
    qd = rng.normal(size=q.shape)
    om = opensim.Model(str(path))
    s = om.initSystem()
    cs, muscles = om.getCoordinateSet(), om.getMuscles()
    checked = ("hip_flexion_r", "knee_angle_r", "ankle_angle_r", "lumbar_extension")
    lengths = {n: cp.length_jacobian(model, q) for n, cp in paths.items()}
    for n in range(len(q)):
        for c, v, w in zip(model.coordinate_names, q[n], qd[n]):
            cs.get(c).setValue(s, float(v), False)
            cs.get(c).setSpeedValue(s, float(w))
        om.realizeVelocity(s)
        for name, (l, J) in lengths.items():
            gp = muscles.get(name).getGeometryPath()
            assert l[n] == pytest.approx(gp.getLength(s), abs=1e-12)
            assert J[n] @ qd[n] == pytest.approx(gp.getLengtheningSpeed(s), abs=1e-12)
            ma = [gp.computeMomentArm(s, cs.get(c)) for c in checked]
            np.testing.assert_allclose(-J[n, [model.coordinate_index(c) for c in checked]], ma, atol=1e-12)
    # the vasti really changed path between the poses
    assert len({int(a.sum()) for a in paths["vas_med_r"].active_points(model, q)}) == 3
