"""IK tasks: error and Jacobian of a pose, for stacking in IK or prioritized IK.

`marker_task`, `orientation_task` and `com_task` evaluate batches of poses;
`Task` is one task of `kinematics.algorithms.prioritized.PrioritizedIK` (a
callable ``q -> (error, jacobian)`` with its priority and recruited
coordinates) and `KinematicTasks` builds such tasks on a `Model`, sharing one
forward-kinematics evaluation per configuration.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.algorithms.fk import (KinematicState, as_q, com_jacobian, forward_kinematics, frame_jacobian,
                                     marker_jacobian, point_positions)
from kinematics.multibody.joints import left_jacobian_inverse_so3
from kinematics.multibody.model import Model

__all__ = ["marker_task", "orientation_task", "com_task", "Task", "KinematicTasks"]

TaskFunction = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def marker_task(model: Model, q, targets, weights=None, markers: Sequence[str] | None = None):
    """Weighted marker residuals and Jacobian, for stacking in IK or prioritized IK.

    r = sqrt(w_m) (x_m(q) - y_m), zero for NaN targets.

    Returns
    -------
    r : (N, 3M) (or (3M,) for one pose), metres
    J : (N, 3M, n_q) (or (3M, n_q))
    """
    q2, single = as_q(model, q)
    names = model.marker_names if markers is None else tuple(markers)
    y = np.asarray(targets, float).reshape(q2.shape[0] if np.ndim(targets) == 3 else 1, len(names), 3)
    w = np.ones(len(names)) if weights is None else np.asarray(weights, float)
    x, J = marker_jacobian(model, q2, names)
    ok = np.isfinite(y).all(-1)
    sw = np.sqrt(w)[None, :] * ok
    r = np.where(ok[..., None], x - np.nan_to_num(y), 0.0) * sw[..., None]
    J = J * sw[..., None, None]
    r = r.reshape(q2.shape[0], -1)
    J = J.reshape(q2.shape[0], -1, model.n_q)
    return (r[0], J[0]) if single else (r, J)



def orientation_task(model: Model, q, body: str, target_rotation, weight: float = 1.0):
    """Orientation error of `body` and its Jacobian (for prioritized IK).

    e = sqrt(w) log(R_W,body R_target^T)^vee, the rotation vector (rad, ground
    frame) that takes the target orientation to the current one;
    de/dq = sqrt(w) J_l^-1(e) J_omega with J_omega the body's angular-velocity
    Jacobian and J_l the SO(3) left Jacobian (exact, not only near e = 0).

    Returns
    -------
    e : (N, 3) (or (3,))
    J : (N, 3, n_q) (or (3, n_q))
    """
    q2, single = as_q(model, q)
    st = forward_kinematics(model, q2)
    R = st.rotations[:, model.body_index(body)]
    Rt = np.broadcast_to(np.asarray(target_rotation, float), R.shape)
    e = Rotation.from_matrix(R @ np.swapaxes(Rt, 1, 2)).as_rotvec()
    Jw = frame_jacobian(model, q2, body)[:, :3]
    sw = np.sqrt(weight)
    e, J = sw * e, sw * (left_jacobian_inverse_so3(e) @ Jw)
    return (e[0], J[0]) if single else (e, J)


def com_task(model: Model, q, target, weight: float = 1.0):
    """Whole-body centre-of-mass error sqrt(w) (c(q) - target) (m) and its Jacobian (N,3,n_q)."""
    q2, single = as_q(model, q)
    c, J = com_jacobian(model, q2)
    sw = np.sqrt(weight)
    e, J = sw * (c - np.asarray(target, float)), sw * J
    return (e[0], J[0]) if single else (e, J)


@dataclass(frozen=True)
class Task:
    """One IK task.

    Parameters
    ----------
    name : str
    function : callable ``q -> (error (m,), jacobian (m, n))``
        ``error`` is the desired minus the current value of the task
        (m or rad); ``jacobian`` its derivative with respect to the
        coordinates of the current value.
    priority : int
        0 is the highest priority; tasks with equal priority share a level.
    recruited : tuple of str or None
        Rec(T): coordinates allowed to move for this task (None: all of
        ``ancestors``, or every coordinate when ``ancestors`` is None too).
    ancestors : tuple of str or None
        Anc(T): coordinates between the task's body and the root.
    max_error : float or None
        Error norm clamped to this value per step (step-size control).
    """

    name: str
    function: TaskFunction
    priority: int = 0
    recruited: tuple[str, ...] | None = None
    ancestors: tuple[str, ...] | None = None
    max_error: float | None = None



class KinematicTasks:
    """Factory of IK tasks on a `Model` sharing one forward-kinematics evaluation per configuration.

    Every task returned is a `Task` whose function maps q (n_q,) to
    (error, Jacobian); all of them read the same cached `KinematicState`
    (FK with column screws) for the last q, so a step costs one FK.
    """

    def __init__(self, model: Model):
        self.model = model
        self._key = None
        self._state: KinematicState | None = None
        K = model.column_coordinate.size
        self._scatter = np.zeros((K, model.n_q))
        self._scatter[np.arange(K), model.column_coordinate] = 1.0
        self._mass = np.array([bd.mass for bd in model.bodies])
        self._com = np.array([bd.com for bd in model.bodies])

    def state(self, q) -> KinematicState:
        q = np.asarray(q, float)
        key = q.tobytes()
        if key != self._key:
            self._state = forward_kinematics(self.model, q, jacobian=True)
            self._key = key
        return self._state

    def ancestors(self, body: str | None) -> tuple[str, ...]:
        """Coordinates moving `body` (all coordinates for None)."""
        names = self.model.coordinate_names
        if body is None:
            return names
        cols = self.model.body_columns[self.model.body_index(body)]
        return tuple(names[i] for i in sorted(set(self.model.column_coordinate[cols].tolist())))

    def _point_jac(self, st, b: int, x: np.ndarray) -> np.ndarray:
        mask = self.model.body_columns[b]
        cols = np.cross(st.omega[0], x) + st.v0[0]         # (K, 3)
        return (cols * mask[:, None]).T @ self._scatter      # (3, n_q)

    def position(self, name: str, body: str, point, target, priority: int, recruited=None,
                 max_error: float | None = 0.05, axes=(0, 1, 2)) -> Task:
        """Point `point` (body frame, m) of `body` to `target` (callable t() or array, ground, m)."""
        b = self.model.body_index(body)
        p = np.asarray(point, float).reshape(1, 3)
        ax = list(axes)
        target_fn = target if callable(target) else (lambda t=np.asarray(target, float): t)

        def f(q):
            st = self.state(q)
            x = point_positions(self.model, st, np.array([b]), p)[0, 0]
            return (target_fn() - x)[ax], self._point_jac(st, b, x)[ax]
        return Task(name, f, priority, recruited, self.ancestors(body), max_error)

    def orientation(self, name: str, body: str, target_rotation, priority: int, recruited=None,
                    max_error: float | None = 0.1) -> Task:
        """Orientation of `body` to `target_rotation` (3x3, ground): error log(R_t R^T) (rad, ground)."""
        b = self.model.body_index(body)
        Rt = np.asarray(target_rotation, float)

        def f(q):
            st = self.state(q)
            R = st.rotations[0, b]
            e = Rotation.from_matrix(Rt @ R.T).as_rotvec()
            Jw = (st.omega[0] * self.model.body_columns[b][:, None]).T @ self._scatter
            return e, Jw
        return Task(name, f, priority, recruited, self.ancestors(body), max_error)

    def com(self, name: str, target, priority: int, recruited=None, axes=(0, 2),
            max_error: float | None = 0.02) -> Task:
        """Whole-body centre of mass (components `axes`, default horizontal x, z) to `target` (m)."""
        ax = list(axes)
        target = np.asarray(target, float)
        w = self._mass / self._mass.sum()
        nb = self.model.n_bodies

        def f(q):
            st = self.state(q)
            x = point_positions(self.model, st, np.arange(nb), self._com)[0]        # (B, 3)
            c = w @ x
            mask = self.model.body_columns.astype(float)                          # (B, K)
            # sum_b w_b (omega_k x x_b + v0_k) mask_bk
            wx = np.einsum("b,bk,bi->ki", w, mask, x)
            v = np.einsum("b,bk->k", w, mask)[:, None] * st.v0[0]
            cols = np.cross(st.omega[0], wx) + v
            J = cols.T @ self._scatter
            return (target - c[ax]), J[ax]
        return Task(name, f, priority, recruited, self.model.coordinate_names, max_error)

