"""Closure of kinematic loops by a Newton solver (MOBILE ``MoSolver``; Taendl et al. 2010, section 2.7).

A loop is cut into a tree (the `Model`) plus measurements whose vanishing
means the loop is closed: the distance between points on two bodies minus
its target, or the separation of two points that must coincide.  With the
stacked measurements g(q) (m,) and a set of free (dependent) coordinates
q_f, the solver runs Gauss-Newton steps

    q_f <- q_f - J_f^+ g(q),   J_f = dg/dq_f   (analytic, from the point Jacobians of `kinematics.algorithms.fk`)

until max |g| <= tol (the pseudo-inverse handles redundant rows such as the
out-of-plane component of a planar loop).  Like every MOBILE solver, the
result is itself a transmission element from the other (independent)
coordinates q_i to all coordinates:

    velocity:     qd_f = D qd_i,   D = -J_f^+ J_i
    acceleration: qdd_f = D qdd_i - J_f^+ b(q, qd),  b = d^2 g/dt^2 at qdd = 0 (from the transmission chain)
    force:        Q_i' = Q_i + D^T Q_f   (virtual work, `LoopSolution.dependency`)

so the inverse dynamics of the closed loop (driving forces on q_i) is
``reduce_forces(inverse_dynamics(model, q, qd, qdd))`` with qd, qdd from
`LoopSolution.velocities` / `LoopSolution.accelerations`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from kinematics.mechanisms.chords import Chord
from lowerlimb.errors import FitError, InputError
from kinematics.algorithms.fk import as_q, forward_kinematics, point_positions, points_jacobian
from kinematics.multibody.model import Model
from kinematics.mechanisms.transmission import TransmissionChain

__all__ = ["DistanceConstraint", "CoincidentPoints", "loop_residuals", "LoopSolution", "close_loop"]


def _vec3(x, what):
    a = np.asarray(x, float)
    if a.shape != (3,):
        raise InputError(what, f"point must be a 3-vector (m, body frame), got shape {a.shape}")
    return a


@dataclass(frozen=True)
class DistanceConstraint:
    """g = |x_b - x_a| - distance  (1 row): points fixed on two bodies (m, body frames) kept `distance` apart."""

    body_a: str
    point_a: np.ndarray
    body_b: str
    point_b: np.ndarray
    distance: float

    n_rows = 1

    def __post_init__(self):
        object.__setattr__(self, "point_a", _vec3(self.point_a, f"distance {self.body_a}-{self.body_b}"))
        object.__setattr__(self, "point_b", _vec3(self.point_b, f"distance {self.body_a}-{self.body_b}"))
        if not self.distance > 0:
            raise InputError(f"distance {self.body_a}-{self.body_b}",
                             "target distance must be > 0 (use CoincidentPoints for coincident points)")

    def evaluate(self, xa, xb, Ja, Jb):
        d = xb - xa
        l = np.linalg.norm(d, axis=-1)
        e = d / np.maximum(l, 1e-300)[:, None]
        return (l - self.distance)[:, None], np.einsum("nc,ncq->nq", e, Jb - Ja)[:, None, :]

    def bias(self, state, model: Model) -> np.ndarray:
        """d^2 g/dt^2 at qdd = 0 (N, 1): the chord's length acceleration from the frames' motion."""
        K0, K1 = state.body(model, self.body_a), state.body(model, self.body_b)
        return Chord(self.point_a, self.point_b).do_motion(K0, K1).acceleration[:, None]


@dataclass(frozen=True)
class CoincidentPoints:
    """g = x_b - x_a  (3 rows, ground): two points fixed on two bodies must coincide."""

    body_a: str
    point_a: np.ndarray
    body_b: str
    point_b: np.ndarray

    n_rows = 3

    def __post_init__(self):
        object.__setattr__(self, "point_a", _vec3(self.point_a, f"coincidence {self.body_a}-{self.body_b}"))
        object.__setattr__(self, "point_b", _vec3(self.point_b, f"coincidence {self.body_a}-{self.body_b}"))

    def evaluate(self, xa, xb, Ja, Jb):
        return xb - xa, Jb - Ja

    def bias(self, state, model: Model) -> np.ndarray:
        """d^2 g/dt^2 at qdd = 0 (N, 3)."""
        K0, K1 = state.body(model, self.body_a), state.body(model, self.body_b)
        return K1.point_acceleration(self.point_b) - K0.point_acceleration(self.point_a)


def loop_residuals(model: Model, q, constraints: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """Stacked measurements g (N, m) and their Jacobian dg/dq (N, m, n_q) (or unbatched for q (n_q,))."""
    q2, single = as_q(model, q)
    st = forward_kinematics(model, q2, jacobian=True)
    try:
        bodies = np.array([[model.body_index(c.body_a), model.body_index(c.body_b)] for c in constraints], int)
    except KeyError as exc:
        raise InputError(model.name, f"loop constraint: {exc.args[0]}") from None
    pts = np.array([[c.point_a, c.point_b] for c in constraints], float).reshape(-1, 3)
    x = point_positions(model, st, bodies.ravel(), pts)
    J = points_jacobian(model, st, bodies.ravel(), x)
    gs, Js = [], []
    for k, c in enumerate(constraints):
        g, Jg = c.evaluate(x[:, 2 * k], x[:, 2 * k + 1], J[:, 2 * k], J[:, 2 * k + 1])
        gs.append(g)
        Js.append(Jg)
    g, Jg = np.concatenate(gs, axis=1), np.concatenate(Js, axis=1)
    return (g[0], Jg[0]) if single else (g, Jg)


@dataclass(frozen=True)
class LoopSolution:
    """Closed-loop poses.

    Attributes
    ----------
    q : (N, n_q) (or (n_q,)) coordinates with the loop closed
    residual : (N,) max |g| at the solution (m)
    iterations : int, Newton iterations used
    free : (n_f,) indices of the solved (dependent) coordinates
    independent : (n_i,) indices of the other coordinates
    dependency : (N, n_q, n_i) dq/dq_i along the closed loop (identity rows on q_i, D = -J_f^+ J_i on q_f):
        velocity transmission qd = dependency qd_i, force transmission Q_i' = dependency^T Q
    """

    q: np.ndarray
    residual: np.ndarray
    iterations: int
    free: np.ndarray
    independent: np.ndarray
    dependency: np.ndarray
    model: Model = None  # type: ignore[assignment]
    constraints: tuple = ()

    def velocities(self, qd_independent) -> np.ndarray:
        """qd (N, n_q) from the independent velocities (N, n_i)."""
        return np.einsum("...qi,...i->...q", self.dependency, np.asarray(qd_independent, float))

    def accelerations(self, qd_independent, qdd_independent) -> tuple[np.ndarray, np.ndarray]:
        """qd, qdd (N, n_q) of the closed loop from the independent velocities and accelerations (N, n_i)."""
        qd = self.velocities(qd_independent)
        q2, qd2 = np.atleast_2d(self.q), np.atleast_2d(qd)
        st = TransmissionChain(self.model).motion(q2, qd2)
        b = np.concatenate([c.bias(st, self.model) for c in self.constraints], axis=1)
        _, J = loop_residuals(self.model, q2, self.constraints)
        E = self.dependency if self.dependency.ndim == 3 else self.dependency[None]
        qdd = np.einsum("nqi,ni->nq", E, np.atleast_2d(qdd_independent))
        qdd[:, self.free] -= np.einsum("nfm,nm->nf", np.linalg.pinv(J[:, :, self.free], rcond=1e-10), b)
        return (qd, qdd[0]) if self.q.ndim == 1 else (qd, qdd)

    def reduce_forces(self, Q) -> np.ndarray:
        """Generalised forces on the independent coordinates: dependency^T Q (N, n_i)."""
        return np.einsum("...qi,...q->...i", self.dependency, np.asarray(Q, float))


def close_loop(model: Model, q, constraints: Sequence, free_coordinates: Sequence[str], tol: float = 1e-12,
               max_iterations: int = 50) -> LoopSolution:
    """Solve the free coordinates so that every loop measurement vanishes (Gauss-Newton, analytic Jacobians).

    Minimises |g(q)|^2 over q_f (the other coordinates held), stopping when
    max |g| <= tol (m); steps are limited to 0.5 rad (or m) per coordinate.
    Newton converges to the assembly mode (branch) whose basin holds the
    starting values, so start near the wanted branch (e.g. the previous
    frame).  Redundant rows are handled by the pseudo-inverse; with more
    free coordinates than independent rows the minimum-norm step is taken.

    Parameters
    ----------
    q : (n_q,) or (N, n_q) starting coordinates (the independent ones are kept)
    constraints : sequence of `DistanceConstraint` / `CoincidentPoints`
    free_coordinates : names of the coordinates to solve for

    Raises
    ------
    InputError  unknown coordinate/body names, or no free coordinates
    FitError    some pose did not close (loop cannot be assembled from these values)
    """
    q2, single = as_q(model, q)
    q2 = q2.copy()
    if not free_coordinates or not constraints:
        raise InputError(model.name, "loop closure needs at least one constraint and one free coordinate")
    try:
        free = np.array([model.coordinate_index(c) for c in free_coordinates], int)
    except KeyError as exc:
        raise InputError(model.name, str(exc.args[0])) from None
    ind = np.array([i for i in range(model.n_q) if i not in set(free.tolist())], int)
    it = 0
    for it in range(1, max_iterations + 1):
        g, J = loop_residuals(model, q2, constraints)
        err = np.abs(g).max(axis=1)
        todo = err > tol
        if not todo.any():
            it -= 1
            break
        Jf = J[todo][:, :, free]
        step = np.einsum("nfm,nm->nf", np.linalg.pinv(Jf, rcond=1e-10), g[todo])
        # Keep rotations from wrapping around wildly on a poor start: limit the step to 0.5 rad / 0.5 m.
        s = np.abs(step).max(axis=1, keepdims=True)
        step *= np.minimum(1.0, 0.5 / np.maximum(s, 1e-300))
        q2[np.ix_(np.flatnonzero(todo), free)] -= step
    g, J = loop_residuals(model, q2, constraints)
    err = np.abs(g).max(axis=1)
    bad = np.flatnonzero(err > max(tol, 1e-9))
    if bad.size:
        raise FitError(f"loop closure failed for {bad.size} of {len(q2)} poses (max residual {err.max():.3g} m "
                       f"after {max_iterations} iterations): the loop cannot be assembled from these coordinates")
    Jf, Ji = J[:, :, free], J[:, :, ind]
    D = -np.linalg.pinv(Jf, rcond=1e-10) @ Ji                                 # (N, n_f, n_i)
    E = np.zeros((len(q2), model.n_q, ind.size))
    E[:, ind, np.arange(ind.size)] = 1.0
    E[:, free, :] = D
    if single:
        return LoopSolution(q2[0], err[0], it, free, ind, E[0], model, tuple(constraints))
    return LoopSolution(q2, err, it, free, ind, E, model, tuple(constraints))
