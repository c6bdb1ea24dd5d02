"""Kinetostatic transmission elements (MOBILE; Kecskemethy & Hiller 1994, Taendl et al. 2010, section 2).

A mechanical component is a map from input state objects to output state
objects with two services (Taendl 2010, eqs. 1-3):

    motion:  q' = phi(q),   qd' = J qd,   qdd' = J qdd + Jd qd
    force:   Q = J^T Q'     (ideal element: delta q^T Q = delta q'^T Q')

Motion is transmitted from the root outwards, force (the pull-back of
co-vectors) from the leaves inwards.  State objects are

* :class:`FrameState` (MOBILE's ``MoFrame``): rotation ``R`` (ground <- K),
  origin ``r`` (m, in ground), angular velocity ``omega`` (rad/s), origin
  velocity ``v`` (m/s), angular acceleration ``alpha`` (rad/s^2), origin
  acceleration ``a`` (m/s^2) and the load accumulators ``tau`` (N m, about the
  origin) and ``f`` (N).  As in MOBILE, every vector except ``r`` is
  decomposed in the moving frame K (``r`` is kept in ground for convenience:
  MOBILE's K-decomposed radius vector is ``R^T r``).
* :class:`ScalarState` (MOBILE's scalar variable): value, rate, acceleration
  and generalised force ``Q``.

Every array carries a leading sample axis N (N poses evaluated at once).

Elements here: :class:`RigidLink` (eqs. 4-9), :class:`JointElement` (any
engine `Joint`; the revolute joint of eqs. 10-13 is the special case
S = [u; 0]), :class:`MassElement` (d'Alembert forces, eqs. 14-15, plus the
weight) and :class:`TransmissionChain`, the composition of those elements
along a `Model`'s tree (the motion pass root-to-leaves, the force pass
leaves-to-root).  Chords and chains of chords (eqs. 16-23) are in
`kinematics.mechanisms.chords`; inverse dynamics in `kinematics.mechanisms.dynamics`; loop
closure in `kinematics.algorithms.loops`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lowerlimb.errors import InputError
from kinematics.multibody.joints import Joint, Transform
from lowerlimb.geometry import skew
from kinematics.multibody.model import Body, Model

__all__ = [
    "FrameState", "ScalarState", "RigidLink", "JointElement", "MassElement", "AppliedLoad",
    "TransmissionChain", "ChainState", "skew", "in_frame",
]


# `skew` (re-exported from `joints`): the cross-product matrix [x]~ with [x]~ y = x cross y (Taendl 2010, eq. 8).


def _mv(R, x):
    """R x for R (N,3,3) or (3,3) and x (N,3)."""
    return np.einsum("...ij,...j->...i", R, x)


def in_frame(R, x):
    """R^T x: vectors x (..., 3) given in the reference frame, expressed in frames of orientation R (..., 3, 3)."""
    return np.einsum("...ji,...j->...i", R, x)


_cross = np.cross


@dataclass
class FrameState:
    """Per-evaluation state of one frame K (MOBILE ``MoFrame``), N samples.

    Attributes
    ----------
    R : (N,3,3) rotation ground <- K
    r : (N,3) origin of K in ground (m)
    omega, v : (N,3) angular velocity (rad/s) and origin velocity (m/s), decomposed in K
    alpha, a : (N,3) angular acceleration (rad/s^2) and origin acceleration (m/s^2), decomposed in K
    tau, f : (N,3) load accumulators: torque about the origin (N m) and force (N), decomposed in K
    """

    R: np.ndarray
    r: np.ndarray
    omega: np.ndarray
    v: np.ndarray
    alpha: np.ndarray
    a: np.ndarray
    tau: np.ndarray = None  # type: ignore[assignment]
    f: np.ndarray = None    # type: ignore[assignment]

    def __post_init__(self):
        if self.tau is None:
            self.tau = np.zeros_like(self.r)
        if self.f is None:
            self.f = np.zeros_like(self.r)

    @classmethod
    def fixed(cls, n: int, transform: Transform | None = None) -> "FrameState":
        """A frame at rest (the ground, or a frame fixed in ground at `transform`), N samples."""
        X = transform or Transform()
        z = np.zeros((n, 3))
        return cls(np.broadcast_to(X.rotation, (n, 3, 3)).copy(), np.broadcast_to(X.translation, (n, 3)).copy(),
                   z.copy(), z.copy(), z.copy(), z.copy())

    @property
    def n(self) -> int:
        return self.r.shape[0]

    @property
    def twist(self) -> np.ndarray:
        """[omega; v] (N,6) in K."""
        return np.concatenate([self.omega, self.v], axis=1)

    @property
    def wrench(self) -> np.ndarray:
        """[tau; f] (N,6) in K (the accumulated load)."""
        return np.concatenate([self.tau, self.f], axis=1)

    def reset_load(self) -> None:
        self.tau = np.zeros_like(self.r)
        self.f = np.zeros_like(self.r)

    # Ground-decomposed views of the kinematics of a point p fixed in K.
    def point(self, p) -> np.ndarray:
        """Position in ground (N,3) of the point p (3,) or (N,3) given in K."""
        return self.r + _mv(self.R, np.broadcast_to(p, self.r.shape))

    def point_velocity(self, p) -> np.ndarray:
        """Velocity in ground (N,3) of the point p fixed in K: R (v + omega x p)."""
        p = np.broadcast_to(p, self.r.shape)
        return _mv(self.R, self.v + _cross(self.omega, p))

    def point_acceleration(self, p) -> np.ndarray:
        """Acceleration in ground (N,3): R (a + alpha x p + omega x (omega x p))."""
        p = np.broadcast_to(p, self.r.shape)
        return _mv(self.R, self.a + _cross(self.alpha, p) + _cross(self.omega, _cross(self.omega, p)))

    def add_load(self, force=None, point=None, torque=None) -> None:
        """Accumulate a force (N, in ground) acting at `point` (m, in K) and a torque (N m, in ground)."""
        if force is not None:
            fk = in_frame(self.R, np.broadcast_to(force, self.r.shape))
            self.f = self.f + fk
            if point is not None:
                self.tau = self.tau + _cross(np.broadcast_to(point, self.r.shape), fk)
        if torque is not None:
            self.tau = self.tau + in_frame(self.R, np.broadcast_to(torque, self.r.shape))


@dataclass
class ScalarState:
    """Scalar state object (MOBILE scalar variable beta): value, rate, acceleration and generalised force (N,)."""

    value: np.ndarray
    rate: np.ndarray
    acceleration: np.ndarray
    force: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self):
        if self.force is None:
            self.force = np.zeros_like(self.value)


@dataclass(frozen=True)
class RigidLink:
    """Rigid link K -> K' (Taendl 2010, eqs. 4-9): K' sits at ``offset`` (rotation dR, origin dr, in K).

    Motion (vectors in their own frames)::

        R' = R dR,  r' = r + R dr
        omega' = dR^T omega,  v' = dR^T (v + omega x dr)
        alpha' = dR^T alpha,  a' = dR^T (a + alpha x dr + omega x (omega x dr))

    i.e. [omega'; v'] = J [omega; v] with J = [[dR^T, 0], [-dR^T [dr]~, dR^T]];
    force: [tau; f] = J^T [tau'; f'] = [dR tau' + dr x dR f'; dR f'].
    """

    offset: Transform = field(default_factory=Transform)

    def jacobian(self) -> np.ndarray:
        """J (6,6) of eq. (7)."""
        dR, dr = self.offset.rotation, self.offset.translation
        J = np.zeros((6, 6))
        J[:3, :3] = dR.T
        J[3:, :3] = -dR.T @ skew(dr)
        J[3:, 3:] = dR.T
        return J

    def do_motion(self, K: FrameState) -> FrameState:
        if self.offset.is_identity:
            return FrameState(K.R, K.r, K.omega, K.v, K.alpha, K.a)
        dR, dr = self.offset.rotation, self.offset.translation
        w = K.omega
        wxr = _cross(w, dr)
        return FrameState(K.R @ dR, K.r + _mv(K.R, np.broadcast_to(dr, K.r.shape)),
                          K.omega @ dR, (K.v + wxr) @ dR,
                          K.alpha @ dR, (K.a + _cross(K.alpha, dr) + _cross(w, wxr)) @ dR)

    def do_force(self, Kout: FrameState, K: FrameState) -> None:
        """Add J^T [tau'; f'] of the output frame to the accumulators of the input frame."""
        dR, dr = self.offset.rotation, self.offset.translation
        f = Kout.f @ dR.T
        K.f = K.f + f
        K.tau = K.tau + Kout.tau @ dR.T + _cross(np.broadcast_to(dr, f.shape), f)


@dataclass(frozen=True)
class JointElement:
    """Joint K = F (on the parent) -> K' = M (on the child), driven by the joint coordinates q_j.

    With the engine joint's pose X_FM(q) = (R_FM, p) and motion subspace S(q)
    ([omega_rel; v_rel] of M relative to F, in F, = S qd; rows 0-2 ``S_w``,
    rows 3-5 ``S_v``) and dS/dt::

        R' = R R_FM,  r' = r + R p
        omega' = R_FM^T (omega + S_w qd)
        v'     = R_FM^T (v + omega x p + S_v qd)
        alpha' = R_FM^T (alpha + omega x S_w qd + S_w qdd + dS_w/dt qd)
        a'     = R_FM^T (a + alpha x p + omega x (omega x p) + 2 omega x S_v qd + S_v qdd + dS_v/dt qd)

    so [omega'; v'] = J [omega; v; qd] with
    J = [[R_FM^T, 0, R_FM^T S_w], [-R_FM^T [p]~, R_FM^T, R_FM^T S_v]]
    (the revolute joint of Taendl 2010 eq. 13 has S = [u; 0]).  Force: the
    output wrench is moved to F, [tau; f] += [R_FM tau' + p x R_FM f'; R_FM f'],
    and the generalised forces are Q_j = S^T [R_FM tau'; R_FM f'].
    """

    joint: Joint

    def jacobian(self, qj) -> np.ndarray:
        """J (N, 6, 6 + k) mapping [omega; v; qd_j] of F to [omega'; v'] of M."""
        R, p, S = self.joint.motion_subspace(qj)
        N, k = S.shape[0], S.shape[2]
        Rt = np.swapaxes(R, 1, 2)
        J = np.zeros((N, 6, 6 + k))
        J[:, :3, :3] = Rt
        J[:, 3:, :3] = -Rt @ skew(p)
        J[:, 3:, 3:6] = Rt
        J[:, :, 6:] = np.concatenate([Rt @ S[:, :3], Rt @ S[:, 3:]], axis=1)
        return J

    def do_motion(self, K: FrameState, qj, qdj=None, qddj=None) -> FrameState:
        j = self.joint
        N = K.n
        qj = np.asarray(qj, float).reshape(N, j.n_coordinates)
        R, p, S = j.motion_subspace(qj)
        if j.n_coordinates == 0:
            w_rel = v_rel = wd_rel = vd_rel = np.zeros((N, 3))
        else:
            qdj = np.zeros_like(qj) if qdj is None else np.asarray(qdj, float).reshape(qj.shape)
            qddj = np.zeros_like(qj) if qddj is None else np.asarray(qddj, float).reshape(qj.shape)
            Sq = np.einsum("nik,nk->ni", S, qdj)
            Sqq = np.einsum("nik,nk->ni", S, qddj)
            if np.any(qdj):
                Sd = j.motion_subspace_derivative(qj, qdj)
                Sqq = Sqq + np.einsum("nik,nk->ni", Sd, qdj)
            w_rel, v_rel, wd_rel, vd_rel = Sq[:, :3], Sq[:, 3:], Sqq[:, :3], Sqq[:, 3:]
        w, al = K.omega, K.alpha
        wxp = _cross(w, p)
        return FrameState(K.R @ R, K.r + _mv(K.R, p),
                          in_frame(R, w + w_rel),
                          in_frame(R, K.v + wxp + v_rel),
                          in_frame(R, al + _cross(w, w_rel) + wd_rel),
                          in_frame(R, K.a + _cross(al, p) + _cross(w, wxp) + 2.0 * _cross(w, v_rel) + vd_rel))

    def do_force(self, Kout: FrameState, K: FrameState, qj) -> np.ndarray:
        """Add the output load to F's accumulators; return the generalised forces Q_j (N, k)."""
        R, p, S = self.joint.motion_subspace(np.asarray(qj, float).reshape(K.n, self.joint.n_coordinates))
        fF = _mv(R, Kout.f)
        tF = _mv(R, Kout.tau)
        K.f = K.f + fF
        K.tau = K.tau + tF + _cross(p, fF)
        return np.einsum("nik,ni->nk", S[:, :3], tF) + np.einsum("nik,ni->nk", S[:, 3:], fF)


@dataclass(frozen=True)
class MassElement:
    """Mass and inertia of a body acting on its frame K (Taendl 2010, eqs. 14-15, plus the weight).

    With mass m, centre of mass s (in K) and inertia Theta_S (about the
    centre of mass, K axes), the load added to K is the d'Alembert force plus
    the weight m g (g in ground)::

        f   = m [R^T g - (a + alpha x s + omega x (omega x s))]
        tau = -(Theta_S alpha + omega x Theta_S omega) + s x f
    """

    mass: float
    com: np.ndarray
    inertia: np.ndarray

    @classmethod
    def of(cls, body: Body) -> "MassElement":
        return cls(float(body.mass), np.asarray(body.com, float), np.asarray(body.inertia, float))

    def do_force(self, K: FrameState, gravity=None, inertia: bool = True) -> None:
        if self.mass == 0.0 and not np.any(self.inertia):
            return
        s = np.broadcast_to(self.com, K.r.shape)
        f = np.zeros_like(K.r) if gravity is None else self.mass * in_frame(K.R, np.broadcast_to(gravity, K.r.shape))
        tau = np.zeros_like(K.r)
        if inertia:
            w = K.omega
            f = f - self.mass * (K.a + _cross(K.alpha, s) + _cross(w, _cross(w, s)))
            tau = -(K.alpha @ self.inertia.T + _cross(w, w @ self.inertia.T))
        K.f = K.f + f
        K.tau = K.tau + tau + _cross(s, f)


@dataclass(frozen=True)
class AppliedLoad:
    """External load on a body: ``force`` (N, ground) acting at ``point`` (m, body frame) and a free ``torque``
    (N m, ground).  Arrays are (3,) or (N,3)."""

    body: str
    force: np.ndarray = field(default_factory=lambda: np.zeros(3))
    point: np.ndarray = field(default_factory=lambda: np.zeros(3))
    torque: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class ChainState:
    """Result of `TransmissionChain.motion`: frames of every body and of every joint (F, M), N samples."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    bodies: list
    joint_frames: list

    def body(self, model: Model, name: str) -> FrameState:
        """The frame state of body `name`."""
        return self.bodies[model.body_index(name)]


def _as2(x, n_q, name):
    x = np.asarray(x, float)
    x2 = x[None, :] if x.ndim == 1 else x
    if x2.ndim != 2 or x2.shape[1] != n_q:
        raise ValueError(f"{name} must have shape (n_q,) or (N, n_q) with n_q = {n_q}; got {x.shape}")
    return x2


@dataclass(frozen=True)
class TransmissionChain:
    """Composition of the transmission elements of a `Model` along its tree.

    For joint j with parent body P and child body C::

        K_P --RigidLink(parent_offset)--> F --JointElement(q_j)--> M --RigidLink(child_offset^-1)--> K_C

    plus one `MassElement` on every body frame.  `motion` runs the motion
    services from the ground outwards; `force` clears the accumulators,
    lets the mass elements, applied loads and extra elements load the body
    frames, and runs the force services in reverse order, collecting

        Q = sum_j  S_j^T w_M,j   (scattered onto the coordinates each joint reads)

    = J^T (loads): the generalised forces of the loads (virtual work
    delta q^T Q = sum of the loads' virtual work).
    """

    model: Model
    links: tuple = field(init=False, repr=False)
    masses: tuple = field(init=False, repr=False)

    def __post_init__(self):
        links = tuple((RigidLink(j.parent_offset), JointElement(j), RigidLink(j.child_offset.inverse()))
                      for j in self.model.joints)
        object.__setattr__(self, "links", links)
        object.__setattr__(self, "masses", tuple(MassElement.of(b) for b in self.model.bodies))

    def motion(self, q, qd=None, qdd=None) -> ChainState:
        """Position, velocity and acceleration of every body frame for q, qd, qdd (n_q,) or (N, n_q)."""
        m = self.model
        q2 = _as2(q, m.n_q, "q")
        N = q2.shape[0]
        qd2 = np.zeros_like(q2) if qd is None else np.broadcast_to(_as2(qd, m.n_q, "qd"), q2.shape)
        qdd2 = np.zeros_like(q2) if qdd is None else np.broadcast_to(_as2(qdd, m.n_q, "qdd"), q2.shape)
        bodies = [FrameState.fixed(N)] + [None] * (m.n_bodies - 1)
        jframes = []
        for j, (lp, je, lc) in enumerate(self.links):
            ix = m.joint_coordinate_index[j]
            F = lp.do_motion(bodies[m.parent[j + 1]])
            M = je.do_motion(F, q2[:, ix], qd2[:, ix], qdd2[:, ix])
            bodies[j + 1] = lc.do_motion(M)
            jframes.append((F, M))
        return ChainState(q2, qd2, qdd2, bodies, jframes)

    def force(self, state: ChainState, loads=(), gravity=None, inertia: bool = False, elements=()) -> np.ndarray:
        """Generalised forces Q (N, n_q) of the loads on the bodies, by the backward force pass.

        Parameters
        ----------
        state : ChainState from `motion`
        loads : sequence of AppliedLoad
        gravity : (3,) or None
            Weight of every body (m/s^2, ground); None for no weight.
        inertia : bool
            Add the d'Alembert inertia forces of the mass elements.
        elements : sequence of objects with ``do_force(state, model)`` that load body frames
            (e.g. `kinematics.mechanisms.chords.PathTension`) and may return generalised forces (N, n_q)
            acting on the coordinates directly (MOBILE scalar-state forces), or None.
        """
        m = self.model
        for K in state.bodies:
            K.reset_load()
        if gravity is not None or inertia:
            for K, me in zip(state.bodies, self.masses):
                me.do_force(K, gravity, inertia)
        for ld in loads:
            try:
                b = m.body_index(ld.body)
            except KeyError as exc:
                raise InputError(f"load on {ld.body!r}", str(exc.args[0])) from None
            state.bodies[b].add_load(ld.force, ld.point, ld.torque)
        N = state.q.shape[0]
        Q = np.zeros((N, m.n_q))
        for el in elements:
            direct = el.do_force(state, m)
            if direct is not None:            # generalised forces acting on the coordinates directly
                Q += direct
        for j in range(len(self.links) - 1, -1, -1):
            lp, je, lc = self.links[j]
            F, M = state.joint_frames[j]
            F.reset_load()
            M.reset_load()
            ix = m.joint_coordinate_index[j]
            lc.do_force(state.bodies[j + 1], M)
            if ix.size:
                Q[:, ix] += je.do_force(M, F, state.q[:, ix])
            else:
                je.do_force(M, F, state.q[:, ix])
            lp.do_force(F, state.bodies[m.parent[j + 1]])
        return Q
