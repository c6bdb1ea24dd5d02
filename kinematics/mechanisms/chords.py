"""Distance chords and chains of chords: muscle-path length, lengthening velocity, tension (Taendl 2010, 2.5-2.6).

A chord measures the distance between two points p0, p1 fixed in frames
K0, K1 (MOBILE's linear distance chord between frame origins, with the
points reached through rigid links)::

    d = x1 - x0,  x_i = r_i + R_i p_i,  l = |d|,  e = d / l
    ld  = e . (xd1 - xd0)                       = J [omega0; v0; omega1; v1]
    ldd = e . (xdd1 - xdd0) + (|dd|^2 - ld^2) / l

with J = [-(p0 x R0^T e)^T, -(R0^T e)^T, (p1 x R1^T e)^T, (R1^T e)^T]
(twists in their own frames).  Force: for a generalised force F conjugate to
l (virtual work F delta l) the loads are J^T F: force F e at x1 and -F e at
x0.  A muscle pulling with tension T >= 0 is F = -T.

A chain of chords through via points x_0 ... x_n (a muscle path) has
l = sum_i l_i, ld = [1 ... 1] [ld_1 ... ld_n]^T and the common force
F_i = F on every segment (frictionless guidance, eqs. 20-23).

Two levels are provided: the MOBILE elements `Chord` and `ChordChain`
acting on `FrameState` objects, and `ChordPath`, a muscle path on a `Model`
with its length Jacobian dl/dq (minus the moment arms) from the engine's
analytic point Jacobians, including via points that move with a coordinate
(`MovingPoint`, OpenSim MovingPathPoint) or belong to the path only over a
coordinate range (`ViaCondition`, OpenSim ConditionalPathPoint);
`PathTension` plugs a path tension into the force pass of a
`TransmissionChain` (e.g. for inverse dynamics) and `load_osim_paths` reads
the muscle paths of an OpenSim model (wrapping surfaces are not modelled).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from lowerlimb.errors import InputError
from kinematics.algorithms.fk import as_q, forward_kinematics, points_jacobian
from kinematics.multibody.joints import Transform
from kinematics.multibody.model import GROUND, Model
from kinematics.mechanisms.transmission import FrameState, ScalarState, in_frame

__all__ = ["Chord", "ChordChain", "ChordPath", "MovingPoint", "ViaCondition", "PathTension", "load_osim_paths"]


def _unit(d, where="chord"):
    l = np.linalg.norm(d, axis=-1)
    if np.any(l <= 1e-12):
        raise InputError(where, "chord of zero length: its direction (and lengthening velocity) is undefined")
    return l, d / l[..., None]


@dataclass(frozen=True)
class Chord:
    """Linear distance chord between point ``p0`` fixed in K0 and point ``p1`` fixed in K1 (m, frame coordinates)."""

    p0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    p1: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        object.__setattr__(self, "p0", np.asarray(self.p0, float).reshape(3))
        object.__setattr__(self, "p1", np.asarray(self.p1, float).reshape(3))

    def do_motion(self, K0: FrameState, K1: FrameState) -> ScalarState:
        """Length l (m), lengthening velocity (m/s) and acceleration (m/s^2), each (N,)."""
        d = K1.point(self.p1) - K0.point(self.p0)
        dd = K1.point_velocity(self.p1) - K0.point_velocity(self.p0)
        ddd = K1.point_acceleration(self.p1) - K0.point_acceleration(self.p0)
        l, e = _unit(d)
        ld = np.einsum("ni,ni->n", e, dd)
        ldd = np.einsum("ni,ni->n", e, ddd) + (np.einsum("ni,ni->n", dd, dd) - ld**2) / l
        return ScalarState(l, ld, ldd)

    def jacobian(self, K0: FrameState, K1: FrameState) -> np.ndarray:
        """J (N, 12): ld = J [omega0; v0; omega1; v1] (twists decomposed in their frames)."""
        _, e = _unit(K1.point(self.p1) - K0.point(self.p0))
        e0, e1 = in_frame(K0.R, e), in_frame(K1.R, e)
        return np.concatenate([-np.cross(self.p0, e0), -e0, np.cross(self.p1, e1), e1], axis=1)

    def do_force(self, K0: FrameState, K1: FrameState, F) -> None:
        """Add J^T F to the frames' accumulators (F (N,) or scalar, N, conjugate to the length)."""
        _, e = _unit(K1.point(self.p1) - K0.point(self.p0))
        Fe = np.asarray(F, float).reshape(-1, 1) * e
        K1.add_load(Fe, self.p1)
        K0.add_load(-Fe, self.p0)


@dataclass(frozen=True)
class ChordChain:
    """Chain of chords through via points (frame index k_i, point p_i in that frame), i = 0..n (n >= 1)."""

    frames: tuple[int, ...]
    points: np.ndarray

    def __post_init__(self):
        pts = np.asarray(self.points, float).reshape(-1, 3)
        if len(self.frames) != pts.shape[0] or pts.shape[0] < 2:
            raise ValueError("a chord chain needs at least two via points, one frame index per point")
        object.__setattr__(self, "frames", tuple(int(k) for k in self.frames))
        object.__setattr__(self, "points", pts)

    @property
    def chords(self) -> tuple[Chord, ...]:
        return tuple(Chord(self.points[i], self.points[i + 1]) for i in range(len(self.frames) - 1))

    def do_motion(self, frames: Sequence[FrameState]) -> ScalarState:
        """Path length, lengthening velocity and acceleration: sums over the chords (eqs. 20-22)."""
        out = [c.do_motion(frames[self.frames[i]], frames[self.frames[i + 1]]) for i, c in enumerate(self.chords)]
        return ScalarState(sum(s.value for s in out), sum(s.rate for s in out), sum(s.acceleration for s in out))

    def do_force(self, frames: Sequence[FrameState], F) -> None:
        """Common force F on every chord (eq. 23), each mapped to its two frames."""
        for i, c in enumerate(self.chords):
            c.do_force(frames[self.frames[i]], frames[self.frames[i + 1]], F)


@dataclass(frozen=True)
class MovingPoint:
    """Via point whose location is a function of coordinates (OpenSim ``MovingPathPoint``).

    p(q) = offset.R [f_x(q_cx), f_y(q_cy), f_z(q_cz)] + offset.p   (m, body frame);
    a coordinate name of None means the function is a constant.
    """

    functions: tuple
    coordinates: tuple
    offset: Transform = field(default_factory=Transform)

    def evaluate(self, model: Model, q2: np.ndarray):
        """Location (N,3) in the body frame and its derivative d p / d q (N, 3, n_q)."""
        N = q2.shape[0]
        loc = np.zeros((N, 3))
        d = np.zeros((N, 3, model.n_q))
        for k, (f, c) in enumerate(zip(self.functions, self.coordinates)):
            if c is None:
                loc[:, k] = f.evaluate(np.zeros((N, f.n_inputs)), order=0)[0]
                continue
            ci = model.coordinate_index(c)
            v, g = f.evaluate(q2[:, [ci]], order=1)
            loc[:, k] = v
            d[:, k, ci] = g[:, 0]
        R = self.offset.rotation
        return loc @ R.T + self.offset.translation, np.einsum("ij,njq->niq", R, d)


@dataclass(frozen=True)
class ViaCondition:
    """The via point belongs to the path only while lower - tol <= q[coordinate] <= upper + tol
    (OpenSim ``ConditionalPathPoint``, whose tolerance is 1e-5)."""

    coordinate: str
    lower: float
    upper: float
    tolerance: float = 1e-5


@dataclass(frozen=True)
class ChordPath:
    """A muscle (or ligament) path on a `Model`: via points fixed on (or moving with) bodies, origin to insertion.

    Model: the chain of chords through the active via points x_i(q)::

        l(q) = sum_i |x_i+1 - x_i|,   dl/dq = sum_i e_i^T (dx_i+1/dq - dx_i/dq),  e_i = (x_i+1 - x_i) / |.|

    with dx/dq the engine's analytic point Jacobian plus R_body dp/dq for
    moving points.  Conditional points switch the path between chains (l and
    dl/dq may jump where a point switches, as in OpenSim).

    Attributes
    ----------
    name : str
    bodies : tuple of str, one per via point
    points : (P, 3) via-point coordinates in their body frames (m) (ignored for moving points)
    moving : tuple of MovingPoint or None, one per point (or empty: none moves)
    conditions : tuple of ViaCondition or None, one per point (or empty: all always active)
    """

    name: str
    bodies: tuple[str, ...]
    points: np.ndarray
    moving: tuple = ()
    conditions: tuple = ()

    def __post_init__(self):
        pts = np.asarray(self.points, float).reshape(-1, 3)
        object.__setattr__(self, "bodies", tuple(self.bodies))
        object.__setattr__(self, "points", pts)
        P = pts.shape[0]
        if len(self.bodies) != P or P < 2:
            raise InputError(self.name, "a path needs at least two via points and one body per point")
        mv = tuple(self.moving) or (None,) * P
        cd = tuple(self.conditions) or (None,) * P
        if len(mv) != P or len(cd) != P:
            raise InputError(self.name, "moving / conditions must list one entry (or None) per via point")
        object.__setattr__(self, "moving", mv)
        object.__setattr__(self, "conditions", cd)

    @property
    def is_fixed(self) -> bool:
        """Every via point is fixed on its body and always active (a plain MOBILE chord chain)."""
        return all(m is None for m in self.moving) and all(c is None for c in self.conditions)

    def _body_indices(self, model: Model) -> np.ndarray:
        try:
            return np.array([model.body_index(b) for b in self.bodies], int)
        except KeyError as exc:
            raise InputError(self.name, str(exc.args[0])) from None

    def chain(self, model: Model) -> ChordChain:
        """The MOBILE chord chain on the model's body frames (fixed paths only)."""
        if not self.is_fixed:
            raise InputError(self.name, "a path with moving or conditional via points is not a fixed chord chain")
        return ChordChain(tuple(self._body_indices(model)), self.points)

    def _via(self, model: Model, q2: np.ndarray, rotations, positions, st=None):
        """Body-frame locations (N,P,3), their q-derivatives {i: (N,3,n_q)}, ground positions (N,P,3),
        point Jacobians (N,P,3,n_q) (when the FK state `st` with Jacobian screws is given) and the active
        mask (N,P); `rotations` (N,B,3,3) and `positions` (N,B,3) are the body poses."""
        idx = self._body_indices(model)
        N, P = q2.shape[0], len(idx)
        loc = np.broadcast_to(self.points, (N, P, 3)).copy()
        dloc = {}
        for i, mv in enumerate(self.moving):
            if mv is not None:
                loc[:, i], dloc[i] = mv.evaluate(model, q2)
        R = rotations[:, idx]                                              # (N,P,3,3)
        x = np.einsum("npij,npj->npi", R, loc) + positions[:, idx]
        Jx = None
        if st is not None:
            Jx = points_jacobian(model, st, idx, x)
            for i, d in dloc.items():
                Jx[:, i] += np.einsum("nij,njq->niq", R[:, i], d)
        active = np.ones((N, P), bool)
        for i, c in enumerate(self.conditions):
            if c is not None:
                v = q2[:, model.coordinate_index(c.coordinate)]
                active[:, i] = (v >= c.lower - c.tolerance) & (v <= c.upper + c.tolerance)
        if np.any(active.sum(axis=1) < 2):
            raise InputError(self.name, "fewer than two active via points at some pose")
        return loc, dloc, x, Jx, active

    def _groups(self, active):
        """Poses sharing the same active via points: yields (pose indices, point indices)."""
        pats, inv = np.unique(active, axis=0, return_inverse=True)
        for k, pat in enumerate(pats):
            yield np.flatnonzero(inv.ravel() == k), np.flatnonzero(pat)

    def active_points(self, model: Model, q) -> np.ndarray:
        """(N, P) (or (P,)) mask of the via points that belong to the path at each pose."""
        q2, single = as_q(model, q)
        st = forward_kinematics(model, q2)
        active = self._via(model, q2, st.rotations, st.positions)[4]
        return active[0] if single else active

    def length(self, model: Model, q) -> np.ndarray:
        """Path length l = sum_i |x_i+1 - x_i| over the active via points (m): (N,) or scalar."""
        q2, single = as_q(model, q)
        st = forward_kinematics(model, q2)
        _, _, x, _, active = self._via(model, q2, st.rotations, st.positions)
        l = np.empty(len(q2))
        for n, pts in self._groups(active):
            l[n] = _unit(np.diff(x[n][:, pts], axis=1), self.name)[0].sum(axis=1)
        return l[0] if single else l

    def length_jacobian(self, model: Model, q):
        """Length l (N,) and dl/dq (N, n_q) = sum_i e_i^T (J_x,i+1 - J_x,i); moment arms are -dl/dq."""
        q2, single = as_q(model, q)
        st = forward_kinematics(model, q2, jacobian=True)
        _, _, x, Jx, active = self._via(model, q2, st.rotations, st.positions, st)
        l, J = np.empty(len(q2)), np.empty((len(q2), model.n_q))
        for n, pts in self._groups(active):
            ls, e = _unit(np.diff(x[n][:, pts], axis=1), self.name)
            Jp = Jx[n][:, pts]
            l[n] = ls.sum(axis=1)
            J[n] = np.einsum("nsc,nscq->nq", e, Jp[:, 1:] - Jp[:, :-1])
        return (l[0], J[0]) if single else (l, J)

    def lengthening_velocity(self, model: Model, q, qd) -> np.ndarray:
        """ld = (dl/dq) qd (m/s)."""
        _, J = self.length_jacobian(model, q)
        return np.einsum("...q,...q->...", J, np.asarray(qd, float))

    def generalized_forces(self, model: Model, q, tension) -> np.ndarray:
        """Q = -(dl/dq)^T T (N, n_q): generalised forces of a pulling tension T (N) along the path."""
        _, J = self.length_jacobian(model, q)
        T = np.asarray(tension, float)
        return -J * (T[..., None] if T.ndim else T)

    def _point_forces(self, x, active, tension):
        N, P = active.shape
        T = np.broadcast_to(np.asarray(tension, float), (N,))
        F = np.zeros((N, P, 3))
        for n, pts in self._groups(active):
            _, e = _unit(np.diff(x[n][:, pts], axis=1), self.name)
            pad = np.zeros_like(e[:, :1])
            F[n[:, None], pts[None, :]] = T[n, None, None] * (np.concatenate([e, pad], 1) - np.concatenate([pad, e], 1))
        return F

    def point_forces(self, model: Model, q, tension) -> np.ndarray:
        """Forces (N, P, 3) in ground that a tension T applies at each via point: T (e_i - e_i-1).

        The origin is pulled along the first segment, the insertion back along
        the last, an intermediate via point along the bisector of its two
        segments (frictionless guidance); inactive conditional points get 0.
        """
        q2, single = as_q(model, q)
        st = forward_kinematics(model, q2)
        _, _, x, _, active = self._via(model, q2, st.rotations, st.positions)
        F = self._point_forces(x, active, tension)
        return F[0] if single else F


@dataclass(frozen=True)
class PathTension:
    """Load element: a pulling tension (N, scalar or (N,)) along a `ChordPath`, for `TransmissionChain.force`.

    Fixed paths go through the MOBILE chord chain (common force -T on every
    chord).  Otherwise the via-point forces T (e_i - e_i-1) load the body
    frames at the current point locations, and a moving point adds the
    generalised force F_i . R dp_i/dq of its own motion on the body (returned
    to the force pass, which adds it to Q).
    """

    path: ChordPath
    tension: np.ndarray | float

    def do_force(self, state, model: Model):
        N = state.q.shape[0]
        T = np.broadcast_to(np.asarray(self.tension, float), (N,))
        if self.path.is_fixed:
            self.path.chain(model).do_force(state.bodies, -T)
            return None
        idx = self.path._body_indices(model)
        R = np.stack([K.R for K in state.bodies], 1)
        r = np.stack([K.r for K in state.bodies], 1)
        loc, dloc, x, _, active = self.path._via(model, state.q, R, r)
        F = self.path._point_forces(x, active, T)
        Q = np.zeros((N, model.n_q))
        for i, b in enumerate(idx):
            K = state.bodies[b]
            K.add_load(F[:, i], loc[:, i])
            if i in dloc:
                Q += np.einsum("nc,ncq->nq", F[:, i], np.einsum("nij,njq->niq", K.R, dloc[i]))
        return Q


def load_osim_paths(path, model: Model | None = None) -> tuple[dict, dict]:
    """Muscle paths of an OpenSim model as `ChordPath` objects.

    Supported: ``PathPoint``, ``ConditionalPathPoint`` (-> `ViaCondition`)
    and ``MovingPathPoint`` (-> `MovingPoint`).  Paths with wrapping surfaces
    are not chains of straight chords; they are returned in ``skipped`` with
    the reason instead of being approximated silently.

    Returns
    -------
    paths : dict name -> ChordPath (via points in their body frames, m)
    skipped : dict name -> reason
    """
    from kinematics.io.opensim_io import (function_from_opensim, import_opensim, open_osim_model, transform_from_opensim,
                             vec_from_opensim)

    om = open_osim_model(path)
    osim = import_opensim()
    ground = om.getGround().getName()
    paths, skipped = {}, {}
    ms = om.getMuscles()
    for i in range(ms.getSize()):
        mu = ms.get(i)
        gp = mu.getGeometryPath()
        if gp.getWrapSet().getSize():
            skipped[mu.getName()] = "wrapping surfaces"
            continue
        pps = gp.getPathPointSet()
        bodies, pts, moving, conds, bad = [], [], [], [], None
        for k in range(pps.getSize()):
            app = pps.get(k)
            kind = app.getConcreteClassName()
            frame = app.getParentFrame()
            base = frame.findBaseFrame().getName()
            X = transform_from_opensim(frame.findTransformInBaseFrame())
            bodies.append(GROUND if base == ground else base)
            mv, cd = None, None
            if kind in ("PathPoint", "ConditionalPathPoint"):
                pp = osim.PathPoint.safeDownCast(app)
                pts.append(X.apply(vec_from_opensim(pp.get_location())))
                if kind == "ConditionalPathPoint":
                    c = osim.ConditionalPathPoint.safeDownCast(app)
                    cd = ViaCondition(c.getCoordinate().getName(), c.get_range(0), c.get_range(1))
            elif kind == "MovingPathPoint":
                mp = osim.MovingPathPoint.safeDownCast(app)
                fns, names = [], []
                for ax in "xyz":
                    f = function_from_opensim(osim, getattr(mp, f"get_{ax}_location")(),
                                              f"{mu.getName()} {app.getName()}", path)
                    has = getattr(mp, f"has{ax.upper()}Coordinate")()
                    fns.append(f)
                    names.append(getattr(mp, f"get{ax.upper()}Coordinate")().getName() if has and f.n_inputs else None)
                mv = MovingPoint(tuple(fns), tuple(names), X)
                pts.append(np.zeros(3))
            else:
                bad = kind
                break
            moving.append(mv)
            conds.append(cd)
        if bad is not None:
            skipped[mu.getName()] = f"path points of type {bad}"
            continue
        cp = ChordPath(mu.getName(), tuple(bodies), np.array(pts), tuple(moving), tuple(conds))
        if model is not None:
            cp._body_indices(model)             # every body must exist in the engine model
            for m_ in moving:
                for c in (m_.coordinates if m_ is not None else ()):
                    if c is not None and c not in model.coordinate_names:
                        raise InputError(path, f"path {mu.getName()!r} reads unknown coordinate {c!r}")
        paths[mu.getName()] = cp
    return paths, skipped
