"""Task functions (error and Jacobian of a pose) for stacking in IK or prioritized IK."""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.algorithms.fk import as_q, com_jacobian, forward_kinematics, frame_jacobian, marker_jacobian
from kinematics.multibody.joints import left_jacobian_inverse_so3
from kinematics.multibody.model import Model

__all__ = ["marker_task", "orientation_task", "com_task"]


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
