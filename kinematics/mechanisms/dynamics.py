"""Inverse dynamics by composing kinetostatic transmission elements (Taendl et al. 2010, section 2).

For a pose q, velocities qd and accelerations qdd, the motion pass of the
model's `TransmissionChain` gives every body's acceleration; the mass
elements turn them into d'Alembert loads, to which the weights m g, the
external loads and the muscle-path tensions are added; the force pass pulls
all of them back onto the coordinates.  By d'Alembert's principle in
Lagrange's form the joint forces that produce the motion balance that
pull-back::

    tau = -J^T (w_inertia + w_gravity + w_external)
        = M(q) qdd + C(q, qd) qd - G(q) - J^T w_external

which is what OpenSim's ``InverseDynamicsSolver`` returns (one value per
coordinate, constraints ignored).  Units: N m for rotational coordinates,
N for translational ones.

With coordinate couplings q = q(z) (couplers, linear rows, loop closures)
the generalised forces on the independent parameters follow from virtual
work, delta q^T tau = delta z^T tau_z, i.e. ``tau_z = (dq/dz)^T tau``
(`reduce_generalized_forces`).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from kinematics.multibody.model import Model
from kinematics.mechanisms.transmission import AppliedLoad, TransmissionChain

__all__ = ["inverse_dynamics", "mass_matrix", "generalized_gravity", "generalized_forces",
           "reduce_generalized_forces", "opensim_inverse_dynamics"]


def _chain(model: Model, chain: TransmissionChain | None) -> TransmissionChain:
    if chain is None:
        return TransmissionChain(model)
    if chain.model is not model:
        raise ValueError("the transmission chain was built for another model")
    return chain


def inverse_dynamics(model: Model, q, qd=None, qdd=None, loads: Sequence[AppliedLoad] = (), elements=(),
                     gravity: bool = True, chain: TransmissionChain | None = None) -> np.ndarray:
    """Generalised forces tau (N, n_q) (or (n_q,)) producing qdd at (q, qd) under gravity and the loads.

    Model: tau = M(q) qdd + C(q, qd) qd - G(q) - J(q)^T w_ext, computed as
    tau = -J^T (d'Alembert + weight + external loads) by the transmission
    chain (no mass matrix is formed).

    Parameters
    ----------
    q, qd, qdd : (n_q,) or (N, n_q)
        Coordinates (rad, m), velocities and accelerations; qd, qdd default to 0.
    loads : sequence of `AppliedLoad`
        External forces/torques on bodies (e.g. ground reactions).
    elements : sequence of load elements with ``do_force(state, model)``
        (e.g. `kinematics.mechanisms.chords.PathTension` for muscle tensions).
    gravity : bool
        Include the weights (``model.gravity``).
    """
    q = np.asarray(q, float)
    single = q.ndim == 1
    ch = _chain(model, chain)
    st = ch.motion(q, qd, qdd)
    tau = -ch.force(st, loads, model.gravity if gravity else None, inertia=True, elements=elements)
    return tau[0] if single else tau


def generalized_forces(model: Model, q, loads: Sequence[AppliedLoad] = (), elements=(),
                       chain: TransmissionChain | None = None) -> np.ndarray:
    """Q = J^T w (N, n_q): generalised forces of static loads alone (no inertia, no gravity)."""
    q = np.asarray(q, float)
    ch = _chain(model, chain)
    Q = ch.force(ch.motion(q), loads, None, inertia=False, elements=elements)
    return Q[0] if q.ndim == 1 else Q


def generalized_gravity(model: Model, q, chain: TransmissionChain | None = None) -> np.ndarray:
    """G(q) (N, n_q): generalised forces of the weights (= -inverse_dynamics at rest)."""
    q = np.asarray(q, float)
    ch = _chain(model, chain)
    G = ch.force(ch.motion(q), (), model.gravity, inertia=False)
    return G[0] if q.ndim == 1 else G


def mass_matrix(model: Model, q, chain: TransmissionChain | None = None) -> np.ndarray:
    """Joint-space inertia M(q) (N, n_q, n_q) (or (n_q, n_q)): column i = inverse dynamics for qdd = e_i, qd = 0, g = 0."""
    q = np.asarray(q, float)
    single = q.ndim == 1
    q2 = np.atleast_2d(q)
    N, n = q2.shape
    ch = _chain(model, chain)
    # All n unit accelerations of all N poses in one vectorised pass.
    qq = np.repeat(q2, n, axis=0)
    qdd = np.tile(np.eye(n), (N, 1))
    st = ch.motion(qq, None, qdd)
    M = -ch.force(st, (), None, inertia=True).reshape(N, n, n)
    M = np.swapaxes(M, 1, 2)
    return M[0] if single else M


def reduce_generalized_forces(dq_dz, Q) -> np.ndarray:
    """Generalised forces on independent parameters z: Q_z = (dq/dz)^T Q (virtual work).

    Parameters
    ----------
    dq_dz : (N, n_q, n_z) or (n_q, n_z)
        Jacobian of the parametrisation q = q(z), e.g.
        ``kinematics.algorithms.coordinate_map.coordinate_map(model, limits='none', locked=False).jacobian(q)`` for couplers and
        linear couplings, or `kinematics.algorithms.loops.LoopSolution.dependency` for a closed loop.
    Q : (N, n_q) or (n_q,)
    """
    E = np.asarray(dq_dz, float)
    Q = np.asarray(Q, float)
    return np.einsum("...qz,...q->...z", E, Q)


def opensim_inverse_dynamics(osim_model, coordinates: Sequence[str], q, qd, qdd) -> np.ndarray:
    """OpenSim's own ``InverseDynamicsSolver`` (reference for tests and benchmarks).

    Parameters
    ----------
    osim_model : opensim.Model, not yet initialised; every force in its ForceSet
        that applies force is included (switch muscles off first for pure
        multibody inverse dynamics).
    coordinates : names of the columns of q, qd, qdd
    q, qd, qdd : (N, n)

    Returns
    -------
    tau : (N, n) in the column order of `coordinates` (Simbody's mobility
    order is mapped by probing each coordinate's speed slot).
    """
    from kinematics.io.opensim_io import import_opensim

    opensim = import_opensim()
    q, qd, qdd = (np.atleast_2d(np.asarray(a, float)) for a in (q, qd, qdd))
    s = osim_model.initSystem()
    cs = osim_model.getCoordinateSet()
    coords = [cs.get(n) for n in coordinates]
    uix = []
    for c in coords:
        for o in coords:
            o.setSpeedValue(s, 0.0)
        c.setSpeedValue(s, 1.0)
        u = s.getU()
        hit = [i for i in range(u.size()) if u.get(i) != 0.0]
        if len(hit) != 1:
            raise ValueError(f"coordinate {c.getName()!r} does not own exactly one mobility")
        uix.append(hit[0])
    nu = s.getNU()
    solver = opensim.InverseDynamicsSolver(osim_model)
    out = np.empty_like(q)
    for n in range(len(q)):
        for c, v, w in zip(coords, q[n], qd[n]):
            c.setValue(s, float(v), False)
            c.setSpeedValue(s, float(w))
        osim_model.realizeVelocity(s)
        udot = opensim.Vector(nu, 0.0)
        for k, i in enumerate(uix):
            udot.set(i, float(qdd[n, k]))
        tau = solver.solve(s, udot)
        out[n] = [tau.get(i) for i in uix]
    return out
