"""Inverse dynamics by composed transmission elements (kinematics.mechanisms.dynamics) against OpenSim and mechanics identities."""
from __future__ import annotations

import numpy as np
import pytest

from kin_helpers import leg_model
from kinematics.multibody.coupling import CoordinateCoupler, LinearCoupling
from kinematics.mechanisms.dynamics import (generalized_forces, generalized_gravity, inverse_dynamics, mass_matrix,
                                 opensim_inverse_dynamics, reduce_generalized_forces)
from kinematics.algorithms.fk import com_jacobian, point_jacobian
from kinematics.multibody.functions import SimmSpline
from kinematics.algorithms.coordinate_map import coordinate_map
from kinematics.io.opensim_io import load_osim, to_opensim
from kinematics.mechanisms.transmission import AppliedLoad, TransmissionChain

GAIT = "opensim_gait2392/subject01_simbody_adjusted.osim"


def _without_forces(om):
    """Switch off every force of the model (gait2392's muscles would otherwise pull with default activations)."""
    fs = om.getForceSet()
    for i in range(fs.getSize()):
        fs.get(i).set_appliesForce(False)
    return om


def _opensim_id(opensim, om, names, q, qd, qdd):
    return opensim_inverse_dynamics(om, names, q, qd, qdd)


def _random_motion(model, n, seed):
    rng = np.random.default_rng(seed)
    q = model.random_q(n, rng)
    return q, rng.normal(size=q.shape) * 2.0, rng.normal(size=q.shape) * 5.0


def test_inverse_dynamics_matches_opensim_gait2392(shared_data, opensim):
    """gait2392 (spline knee translations, 23 coordinates): random q, qd, qdd within 1e-6 relative of OpenSim."""
    path = shared_data / GAIT
    model = load_osim(path)
    q, qd, qdd = _random_motion(model, 6, 0)
    tau = inverse_dynamics(model, q, qd, qdd)
    ref = _opensim_id(opensim, _without_forces(opensim.Model(str(path))), model.coordinate_names, q, qd, qdd)
    assert np.abs(ref).max() > 10.0
    np.testing.assert_allclose(tau, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_inverse_dynamics_with_external_load_matches_opensim(shared_data, opensim):
    """A ground reaction (force in ground at a point of calcn_r, plus a free torque) as an OpenSim PrescribedForce."""
    path = shared_data / GAIT
    model = load_osim(path)
    q, qd, qdd = _random_motion(model, 3, 4)
    F, T, p = np.array([40.0, 700.0, -25.0]), np.array([1.0, -3.0, 12.0]), np.array([0.12, -0.02, 0.01])
    om = _without_forces(opensim.Model(str(path)))
    pf = opensim.PrescribedForce("grf", om.getBodySet().get("calcn_r"))
    pf.setForceFunctions(*[opensim.Constant(float(v)) for v in F])
    pf.setPointFunctions(*[opensim.Constant(float(v)) for v in p])
    pf.setTorqueFunctions(*[opensim.Constant(float(v)) for v in T])
    pf.set_forceIsGlobal(True)
    pf.set_pointIsGlobal(False)
    om.addForce(pf)
    ref = _opensim_id(opensim, om, model.coordinate_names, q, qd, qdd)
    tau = inverse_dynamics(model, q, qd, qdd, [AppliedLoad("calcn_r", F, p, T)])
    assert np.abs(tau - inverse_dynamics(model, q, qd, qdd)).max() > 100.0     # the load matters
    np.testing.assert_allclose(tau, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_inverse_dynamics_matches_opensim_engine_model(opensim):
    """Engine-built leg (free, spherical, spline knee, universal, pin, weld, slider) exported to OpenSim."""
    model = leg_model()
    q, qd, qdd = _random_motion(model, 5, 1)
    tau = inverse_dynamics(model, q, qd, qdd)
    ref = _opensim_id(opensim, _without_forces(to_opensim(model)), model.coordinate_names, q, qd, qdd)
    np.testing.assert_allclose(tau, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


@pytest.fixture(scope="module")
def leg():
    return leg_model(exportable=False)


def test_mass_matrix_is_symmetric_positive_definite_and_linear_in_qdd(leg):
    q, qd, qdd = _random_motion(leg, 3, 2)
    M = mass_matrix(leg, q)
    np.testing.assert_allclose(M, np.swapaxes(M, 1, 2), atol=1e-12)
    assert np.linalg.eigvalsh(M).min() > 0
    h = inverse_dynamics(leg, q, qd, None)
    np.testing.assert_allclose(inverse_dynamics(leg, q, qd, qdd) - h, np.einsum("nij,nj->ni", M, qdd), atol=1e-10)


def test_power_balance_without_gravity(leg):
    """d/dt (qd^T M qd / 2) = qd^T tau along q(t) = q + t qd + t^2/2 qdd (no gravity): checks the velocity terms."""
    q, qd, qdd = _random_motion(leg, 3, 3)
    kin = lambda t: 0.5 * np.einsum("ni,nij,nj->n", qd + t * qdd, mass_matrix(leg, q + t * qd + 0.5 * t * t * qdd),
                                    qd + t * qdd)
    h = 1e-5
    dT = (kin(h) - kin(-h)) / (2 * h)
    tau = inverse_dynamics(leg, q, qd, qdd, gravity=False)
    np.testing.assert_allclose(np.sum(qd * tau, 1), dT, rtol=1e-7, atol=1e-7)


def test_gravity_is_whole_body_com_jacobian(leg):
    """G(q) = m_total J_com^T g, and the static inverse dynamics is -G."""
    q, _, _ = _random_motion(leg, 4, 4)
    _, Jc = com_jacobian(leg, q)
    G = generalized_gravity(leg, q)
    np.testing.assert_allclose(G, leg.total_mass * np.einsum("nci,c->ni", Jc, leg.gravity), atol=1e-10)
    np.testing.assert_allclose(inverse_dynamics(leg, q), -G, atol=1e-10)


def test_external_load_enters_as_transposed_jacobian(leg):
    """A ground reaction on the foot changes tau by -J_p^T F (d'Alembert: the joints need less torque)."""
    q, qd, qdd = _random_motion(leg, 3, 5)
    rng = np.random.default_rng(6)
    F, p = rng.normal(size=(3, 3)) * 300.0, np.array([0.12, -0.04, 0.01])
    ch = TransmissionChain(leg)
    load = AppliedLoad("foot", F, p)
    d = inverse_dynamics(leg, q, qd, qdd, [load], chain=ch) - inverse_dynamics(leg, q, qd, qdd, chain=ch)
    _, Jp = point_jacobian(leg, q, "foot", p)
    np.testing.assert_allclose(d, -np.einsum("nci,nc->ni", Jp, F), atol=1e-9)
    np.testing.assert_allclose(generalized_forces(leg, q, [load]), np.einsum("nci,nc->ni", Jp, F), atol=1e-9)


def test_reparametrised_forces_satisfy_virtual_work():
    """With a linear coupling and a spline coupler q = q(z): delta q^T Q = delta z^T Q_z, Q_z = (dq/dz)^T Q."""
    m = leg_model()
    names = m.coordinate_names
    m = m.replace(couplings=LinearCoupling.correlative(names, "subtalar_angle", {"ankle_angle": 0.3}, 0.01),
                  couplers=(CoordinateCoupler("mtp_angle", ("knee_angle",),
                                              SimmSpline([-2.0, -1.0, 0.0, 0.3], [0.2, 0.1, -0.05, 0.0])),))
    cmap = coordinate_map(m, limits="none", locked=False)
    rng = np.random.default_rng(7)
    z = cmap.project(m.random_q(3, rng))
    q = cmap.expand(z)
    tau = inverse_dynamics(m, q, rng.normal(size=q.shape), rng.normal(size=q.shape))
    E = cmap.jacobian(q)
    tz = reduce_generalized_forces(E, tau)
    dz = rng.normal(size=z.shape)
    h = 1e-6
    dq = (cmap.expand(z + h * dz) - cmap.expand(z - h * dz)) / (2 * h)
    np.testing.assert_allclose(np.sum(dz * tz, 1), np.sum(dq * tau, 1), rtol=1e-8)


def test_load_on_unknown_body_is_an_input_error(leg):
    from lowerlimb.errors import InputError

    with pytest.raises(InputError, match="no body 'femur_r'"):
        inverse_dynamics(leg, leg.default_q, loads=[AppliedLoad("femur_r", (0.0, 10.0, 0.0))])
