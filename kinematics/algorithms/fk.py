"""Forward kinematics and analytic Jacobians, vectorised over N poses.

For a pose q (N, n_q) the bodies are placed from the ground outwards:

    X_WF = X_W,parent X_parent,F       (joint frame on the parent)
    X_WM = X_WF X_FM(q_j)              (joint transform)
    X_W,child = X_WM X_child,M^-1      (child body frame)

Jacobians use each joint coordinate's world screw: a unit rate of the
coordinate behind column k of the model (``model.column_coordinate``) gives
every point x of every body downstream of that joint the velocity

    v_k(x) = v0_k + omega_k x,   omega_k = R_WF S_omega,  v0_k = R_WF S_v - omega_k x p_WM

and the point Jacobian is the sum of those columns over the ancestors of the
body, scattered onto the coordinates.  Coupled coordinates read by several
joints therefore appear automatically with their summed contributions.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from kinematics.multibody.model import Model

__all__ = [
    "KinematicState", "forward_kinematics", "marker_positions", "marker_jacobian",
    "point_positions", "point_jacobian", "frame_pose", "frame_jacobian", "com_position", "com_jacobian",
    "body_pose", "as_q", "points_jacobian", "column_scatter", "cross",
]


def as_q(model: Model, q) -> tuple[np.ndarray, bool]:
    """Coordinates as an (N, n_q) float array and whether `q` was a single pose (n_q,).

    Raises
    ------
    ValueError
        `q` is not of shape (n_q,) or (N, n_q).
    """
    q = np.asarray(q, dtype=float)
    single = q.ndim == 1
    q2 = q[None, :] if single else q
    if q2.ndim != 2 or q2.shape[1] != model.n_q:
        raise ValueError(f"q must have shape (n_q,) or (N, n_q) with n_q = {model.n_q}; got {q.shape}")
    return q2, single


@dataclass(frozen=True, eq=False)
class KinematicState:
    """Result of forward kinematics for N poses (arrays indexed by ``model.bodies``).

    Attributes
    ----------
    q : (N, n_q)
    rotations : (N, B, 3, 3)  R_W,body
    positions : (N, B, 3)     origin of each body frame in ground (m)
    omega, v0 : (N, K, 3) or None
        World screws of the K joint-coordinate columns (see module docstring);
        present when ``forward_kinematics(..., jacobian=True)``.
    joint_frames : tuple of (R_WF (N,3,3), p_WM (N,3)) per joint, or None
    """

    q: np.ndarray
    rotations: np.ndarray
    positions: np.ndarray
    omega: np.ndarray | None = None
    v0: np.ndarray | None = None
    joint_frames: tuple | None = None


def forward_kinematics(model: Model, q, jacobian: bool = False) -> KinematicState:
    """Body poses for every pose in q (n_q,) or (N, n_q); with ``jacobian`` also the column screws."""
    q2, _ = as_q(model, q)
    N, B = q2.shape[0], model.n_bodies
    Rw = np.empty((N, B, 3, 3))
    pw = np.empty((N, B, 3))
    Rw[:, 0] = np.eye(3)
    pw[:, 0] = 0.0
    K = model.column_coordinate.size
    omega = np.empty((N, K, 3)) if jacobian else None
    v0 = np.empty((N, K, 3)) if jacobian else None
    porig = np.empty((N, K, 3)) if jacobian else None
    frames = []
    col = 0
    for j, joint in enumerate(model.joints):
        c = j + 1
        par = model.parent[c]
        qj = q2[:, model.joint_coordinate_index[j]]
        po, co = joint.parent_offset, joint.child_offset
        R_par, p_par = Rw[:, par], pw[:, par]
        if po.is_identity:
            R_WF, p_WF = R_par, p_par
        else:
            R_WF = R_par @ po.rotation
            p_WF = p_par + R_par @ po.translation
        if jacobian:
            R_FM, p_FM, S = joint.motion_subspace(qj)
        else:
            R_FM, p_FM = joint.transform(qj)
        R_WM = R_WF @ R_FM
        p_WM = p_WF + (R_WF @ p_FM[:, :, None])[:, :, 0]
        R_Wc = R_WM @ co.rotation.T if not co.is_identity else R_WM
        Rw[:, c] = R_Wc
        pw[:, c] = (p_WM - R_Wc @ co.translation) if not co.is_identity else p_WM
        if jacobian:
            k = joint.n_coordinates
            if k:
                WV = np.swapaxes(R_WF @ S.reshape(N, 2, 3, k).transpose(0, 2, 1, 3).reshape(N, 3, 2 * k), 1, 2)
                omega[:, col:col + k] = WV[:, :k]                             # (N,k,3)
                v0[:, col:col + k] = WV[:, k:]                                # M-origin velocity; shifted below
                porig[:, col:col + k] = p_WM[:, None, :]
            frames.append((R_WF, p_WM))
            col += k
    if jacobian and K:
        v0 -= cross(omega, porig)                # screw at the ground origin: v0 = v_M - omega x p_WM
    return KinematicState(q2, Rw, pw, omega, v0, tuple(frames) if jacobian else None)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis with broadcasting (faster than np.cross for small batches)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def column_scatter(model: Model) -> np.ndarray:
    """Matrix A (K, n_q) with A[k, column_coordinate[k]] = 1: sums joint-coordinate columns onto coordinates."""
    K = model.column_coordinate.size
    A = np.zeros((K, model.n_q))
    A[np.arange(K), model.column_coordinate] = 1.0
    return A


def _squeeze(a, single):
    return a[0] if single else a


def point_positions(model: Model, state: KinematicState, bodies: np.ndarray, points: np.ndarray) -> np.ndarray:
    """World positions (N, P, 3) of `points` (P,3) fixed on body indices `bodies` (P,)."""
    R = state.rotations[:, bodies]                 # (N,P,3,3)
    return np.einsum("npij,pj->npi", R, points) + state.positions[:, bodies]


def points_jacobian(model: Model, state: KinematicState, bodies: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Jacobian (N, P, 3, n_q) of world points x (N,P,3) fixed on `bodies` (P,).

    `state` must come from ``forward_kinematics(..., jacobian=True)``; x is
    usually ``point_positions(model, state, bodies, points)``.
    """
    mask = model.body_columns[bodies].astype(float)            # (P,K)
    cols = cross(state.omega[:, None, :, :], x[:, :, None, :]) + state.v0[:, None, :, :]   # (N,P,K,3)
    cols *= mask[None, :, :, None]
    return np.einsum("npkc,kq->npcq", cols, column_scatter(model))


def _marker_arrays(model: Model, markers: Sequence[str] | None):
    names = model.marker_names if markers is None else tuple(markers)
    idx = [model.marker_index(m) for m in names]
    bodies = np.array([model.body_index(model.markers[i].body) for i in idx], dtype=int)
    offs = np.array([model.markers[i].offset for i in idx], dtype=float).reshape(-1, 3)
    return bodies, offs


def marker_positions(model: Model, q, markers: Sequence[str] | None = None) -> np.ndarray:
    """Marker positions in ground (m): (M,3) for q of shape (n_q,), (N,M,3) for (N,n_q)."""
    q2, single = as_q(model, q)
    st = forward_kinematics(model, q2)
    bodies, offs = _marker_arrays(model, markers)
    return _squeeze(point_positions(model, st, bodies, offs), single)


def marker_jacobian(model: Model, q, markers: Sequence[str] | None = None):
    """Marker positions and their Jacobians d x / d q.

    Returns
    -------
    x : (N, M, 3) (or (M, 3) for a single pose), metres
    J : (N, M, 3, n_q) (or (M, 3, n_q)), metres per coordinate unit
    """
    q2, single = as_q(model, q)
    st = forward_kinematics(model, q2, jacobian=True)
    bodies, offs = _marker_arrays(model, markers)
    x = point_positions(model, st, bodies, offs)
    J = points_jacobian(model, st, bodies, x)
    return _squeeze(x, single), _squeeze(J, single)


def point_jacobian(model: Model, q, body: str, point=(0.0, 0.0, 0.0)):
    """Position (N,3) and Jacobian (N,3,n_q) of a point fixed on `body` (coordinates in the body frame)."""
    q2, single = as_q(model, q)
    st = forward_kinematics(model, q2, jacobian=True)
    b = np.array([model.body_index(body)])
    x = point_positions(model, st, b, np.asarray(point, float).reshape(1, 3))
    J = points_jacobian(model, st, b, x)
    return _squeeze(x[:, 0], single), _squeeze(J[:, 0], single)


def body_pose(model: Model, q, body: str):
    """Rotation (N,3,3) and origin (N,3) of `body` in ground."""
    q2, single = as_q(model, q)
    st = forward_kinematics(model, q2)
    b = model.body_index(body)
    return _squeeze(st.rotations[:, b], single), _squeeze(st.positions[:, b], single)


def frame_pose(model: Model, q, frame: str):
    """Pose of a named model frame in ground: R (N,3,3), p (N,3)."""
    f = model.frame(frame)
    R, p = body_pose(model, q, f.body)
    return R @ f.offset.rotation, p + R @ f.offset.translation


def frame_jacobian(model: Model, q, body: str, point=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Spatial Jacobian (N, 6, n_q) of a frame on `body` located at `point` (body coordinates).

    Rows 0-2: angular velocity of the body in ground per unit qdot; rows 3-5:
    velocity of the point in ground.  Orientation tasks use rows 0-2.
    """
    q2, single = as_q(model, q)
    st = forward_kinematics(model, q2, jacobian=True)
    b = model.body_index(body)
    x = point_positions(model, st, np.array([b]), np.asarray(point, float).reshape(1, 3))
    Jv = points_jacobian(model, st, np.array([b]), x)[:, 0]
    mask = model.body_columns[b].astype(float)
    Jw = np.einsum("nkc,k,kq->ncq", st.omega, mask, column_scatter(model))
    return _squeeze(np.concatenate([Jw, Jv], axis=1), single)


def com_position(model: Model, q) -> np.ndarray:
    """Whole-body centre of mass in ground (N,3) (m)."""
    q2, single = as_q(model, q)
    st = forward_kinematics(model, q2)
    m = np.array([b.mass for b in model.bodies])
    com = np.array([b.com for b in model.bodies])
    x = point_positions(model, st, np.arange(model.n_bodies), com)
    return _squeeze(np.einsum("b,nbi->ni", m, x) / m.sum(), single)


def com_jacobian(model: Model, q):
    """Centre of mass (N,3) and its Jacobian (N,3,n_q): the mass-weighted mean of body com Jacobians."""
    q2, single = as_q(model, q)
    st = forward_kinematics(model, q2, jacobian=True)
    m = np.array([b.mass for b in model.bodies])
    com = np.array([b.com for b in model.bodies])
    bodies = np.arange(model.n_bodies)
    x = point_positions(model, st, bodies, com)
    J = points_jacobian(model, st, bodies, x)
    w = m / m.sum()
    return _squeeze(np.einsum("b,nbi->ni", w, x), single), _squeeze(np.einsum("b,nbiq->niq", w, J), single)
