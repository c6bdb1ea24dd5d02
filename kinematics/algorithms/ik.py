"""Marker-based inverse kinematics, batched over frames.

Model (per frame f)
-------------------
Coordinates are parametrised so that every equality holds exactly
(`kinematics.algorithms.coordinate_map`)::

    q_R = q_p + N z                (linear couplings C q = d and locked coordinates;
                                    N N^T = P0, Raunhardt & Boulic's initial projector)
    q_D = f(q_I)                   (non-linear couplers: dependent coordinates)

and z minimises the weighted least squares of OpenSim's IK::

    E(z) = sum_m w_m |x_m(q(z)) - y_m,f|^2 + sum_c w_c (q_c(z) - qbar_c)^2

over the markers present in frame f (NaN gaps have weight 0), subject to the
coordinate limits and linear inequalities ``G q <= h`` (rows ``A z <= b``).

Algorithm
---------
Levenberg-Marquardt with analytic Jacobians dE/dz = J_q (dq/dz), batched and
inequality-constrained (`kinematics.algorithms.least_squares`).  The first
frame starts from the default pose (or ``q0``); the others are solved in a
pipelined window, each warm-started next to an almost-solved neighbour.
Frames that fail from their warm start are re-solved alone with stronger
damping.  Without ``q0`` the first frame is also solved from the default pose
moved rigidly onto the markers (weighted Kabsch through the root joint),
keeping the lower cost, so that the subject's heading in the lab does not
matter.  Finally a frame whose solution jumps away from a neighbour's
(another local minimum, e.g. an angle 2 pi away) is re-solved from that
neighbour, keeping the lower cost, and the repair walks on frame by frame
while it keeps finding a markedly lower minimum (warm starts chain a wrong
minimum over the following frames).  The first frame's root rotations (the
pelvis) are taken on their canonical Cardan branch (middle angle within +-90
deg: a subject facing back has a heading of 180 deg, not a pelvis tilted and
listed by 180 deg).  Unbounded rotations that only turn a body (no coupling, identity
axis functions: e.g. the pelvis' tilt, list and rotation) are then unwrapped
over the frames, the first solved frame's value brought into (-pi, pi], so that
a trial's angles are continuous and free of 2 pi branch offsets; bounded
coordinates stay inside their ranges (clamped ones in the solve itself).

Coordinates the markers cannot determine in some frame (a zero singular value
of the Jacobian at the solution) are named in ``undetermined_coordinates``:
the coordinates that the null-space directions move.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

from kinematics.algorithms.coordinate_map import coordinate_map
from kinematics.algorithms.fk import cross, forward_kinematics, marker_positions
from kinematics.algorithms.least_squares import feasible, repair_jumps, solve_block, solve_stream
from kinematics.io.ik_setup import CoordinateTask
from kinematics.io.markers import MarkerTrial
from kinematics.multibody.joints import matrix_to_euler_xyz
from kinematics.multibody.model import Model
from lowerlimb.errors import InputError
from lowerlimb.geometry import kabsch_rotation

__all__ = ["IKResult", "solve_ik", "solve_pose", "check_trial_scale", "unwrap_rotations"]


# ----------------------------------------------------------------------------- result
@dataclass(frozen=True, eq=False)
class IKResult:
    """IK solution of a trial.

    Attributes
    ----------
    coordinates : tuple of str (n_q)
    time : (F,) s
    q : (F, n_q) radians / metres (NaN rows for unsolved frames)
    markers : tuple of str (M), the markers used
    marker_errors : (F, M) m, |x_m - y_m| (NaN where the marker is missing)
    rms, max_error : (F,) m, over the markers present
    iterations : (F,) int
    converged : (F,) bool, step below tolerance
    solved : (F,) bool, False for frames without any marker
    cost : (F,) weighted objective E at the solution
    residuals : (F, M, 3) m, x_m(q) - y_m in ground (NaN where the marker is missing)
    determined : (F,) bool, the markers present (and coordinate tasks) determine
        every free coordinate (Jacobian of full rank at the solution); where
        False some coordinates just kept their warm-start value
    undetermined_coordinates : tuple of str, the coordinates moved by the Jacobian's null space in
        some frame (those that kept their warm-start value where `determined` is False)
    """

    coordinates: tuple[str, ...]
    time: np.ndarray
    q: np.ndarray
    markers: tuple[str, ...]
    marker_errors: np.ndarray
    rms: np.ndarray
    max_error: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    solved: np.ndarray
    cost: np.ndarray
    seconds: float = 0.0
    determined: np.ndarray | None = None
    residuals: np.ndarray | None = None
    undetermined_coordinates: tuple[str, ...] = ()


# ----------------------------------------------------------------------------- input checks
def check_trial_scale(model: Model, trial: MarkerTrial, markers: Sequence[str] | None = None) -> float:
    """Ratio of inter-marker distances in the trial to the model's, for markers on the same body.

    Pairs of markers fixed to one body keep their distance in any pose, so the
    median ratio is ~1 when the trial is in the model's unit (metres).  A ratio
    near 1000 (or 0.001) means the TRC ``Units`` header is wrong (millimetres
    read as metres or the reverse).

    Raises
    ------
    InputError
        If the median ratio is outside [0.5, 2] (naming the probable unit).
    """
    names = [m for m in (markers or model.marker_names) if m in trial.names]
    by_body: dict[str, list[str]] = {}
    for n in names:
        by_body.setdefault(model.marker(n).body, []).append(n)
    ratios = []
    for ms in by_body.values():
        for a in range(len(ms)):
            for b in range(a + 1, len(ms)):
                dm = np.linalg.norm(model.marker(ms[a]).offset - model.marker(ms[b]).offset)
                if dm < 1e-3:
                    continue
                dt = np.linalg.norm(trial.marker(ms[a]) - trial.marker(ms[b]), axis=1)
                dt = dt[np.isfinite(dt)]
                if dt.size:
                    ratios.append(np.median(dt) / dm)
    if not ratios:
        return float("nan")
    r = float(np.median(ratios))
    if not 0.5 <= r <= 2.0:
        unit = trial.extra.get("units", "?") if isinstance(trial.extra, dict) else "?"
        hint = ("the coordinates look like millimetres" if 300 < r < 3000 else
                "the coordinates look like centimetres" if 30 < r < 300 else
                "the coordinates look like metres read as millimetres" if 3e-4 < r < 3e-3 else
                "the marker set does not fit this model")
        raise InputError(trial.source, f"marker distances are {r:.3g} times the model's (header Units={unit}): {hint}; "
                                       "fix the Units line of the TRC header")
    return r


# ----------------------------------------------------------------------------- solver
class _Problem:
    """Residuals and Jacobians in z for a block of frames."""

    def __init__(self, model, cmap, marker_idx, sw_m, coord_idx, coord_target, sw_c):
        self.model, self.cmap = model, cmap
        self.names = tuple(model.markers[i].name for i in marker_idx)
        self.sw_m, self.coord_idx, self.coord_target, self.sw_c = sw_m, coord_idx, coord_target, sw_c
        st_bodies = np.array([model.body_index(model.markers[i].body) for i in marker_idx], dtype=int)
        self.bodies = st_bodies
        self.offsets = np.array([model.markers[i].offset for i in marker_idx], float).reshape(-1, 3)
        # mask[m, k]: joint-coordinate column k moves marker m.
        self.mask = model.body_columns[st_bodies].astype(float)
        # Exp-map spherical joints on free coordinates: z indices of their rotation vectors (re-wrapped to |r| <= pi).
        from kinematics.multibody.joints import ExpMapSpherical

        self.expmap = []
        for j, ix in zip(model.joints, model.joint_coordinate_index):
            if not isinstance(j, ExpMapSpherical):
                continue
            red = list(cmap.reduced)
            if not all(i in red for i in ix):
                continue
            rows = cmap.basis[[red.index(i) for i in ix]]
            cols = [np.flatnonzero(np.abs(rw) > 1e-12) for rw in rows]
            if all(c.size == 1 and abs(rows[k][c[0]] - 1.0) < 1e-12 for k, c in enumerate(cols)) and \
                    not np.any(cmap.q_p[[red.index(i) for i in ix]]):
                self.expmap.append(np.array([c[0] for c in cols]))
        self.E_const = self.Ek_const = None
        if not model.couplers:
            self.E_const = cmap.jacobian(cmap.expand(np.zeros((1, cmap.n_z))))[0]
            self.Ek_const = self.E_const[model.column_coordinate]
            ub, self.slot = np.unique(st_bodies, return_inverse=True)
            bmask = model.body_columns[ub].astype(float)                                   # (B,K)
            self.MEkT = np.swapaxes(bmask[:, :, None] * self.Ek_const[None], 1, 2).copy()  # (B,n_z,K)

    def wrap(self, z):
        """Same poses with every exp-map rotation vector r replaced by r (1 - 2 pi / |r|) when |r| > pi."""
        if not self.expmap:
            return z
        z = z.copy()
        for ix in self.expmap:
            r = z[:, ix]
            th = np.linalg.norm(r, axis=1)
            big = th > np.pi
            if big.any():
                z[np.ix_(big, ix)] = r[big] * (1.0 - 2.0 * np.pi / th[big])[:, None]
        return z

    def evaluate(self, z, y, ok, jac=True):
        """r (n, 3M + C), J (n, 3M + C, n_z), q (n, n_q)."""
        cmap, model = self.cmap, self.model
        q = cmap.expand(z)
        st = forward_kinematics(model, q, jacobian=jac)
        R = st.rotations[:, self.bodies]
        x = np.einsum("nmij,mj->nmi", R, self.offsets) + st.positions[:, self.bodies]
        w = self.sw_m[None, :] * ok
        rm = (x - y) * w[..., None]
        rc = (q[:, self.coord_idx] - self.coord_target) * self.sw_c
        r = np.concatenate([rm.reshape(len(z), -1), rc], axis=1)
        if not jac:
            return r, None, q, x
        n, M = x.shape[:2]
        if self.E_const is not None:
            # No non-linear couplers: dq/dz is constant, so the screws of each marker-carrying body can be
            # projected onto z once (W_b, V_b: (n, B, n_z, 3)); then J_m = W_b(m) x x_m + V_b(m).
            E = self.E_const[None]
            W = self.MEkT[None] @ st.omega[:, None]
            V = self.MEkT[None] @ st.v0[:, None]
            Jm = cross(W[:, self.slot], x[:, :, None, :]) + V[:, self.slot]            # (n,M,n_z,3)
            Jm = np.swapaxes(Jm * w[:, :, None, None], 2, 3).reshape(n, 3 * M, -1)
        else:
            cols = cross(st.omega[:, None, :, :], x[:, :, None, :]) + st.v0[:, None, :, :]   # (n,M,K,3)
            cols *= (self.mask[None, :, :] * w[:, :, None])[..., None]
            E = cmap.jacobian(q)                                                           # (n,n_q,n_z)
            Ek = E[:, model.column_coordinate, :]                                          # (n,K,n_z)
            Jm = np.swapaxes(cols, 2, 3).reshape(n, 3 * M, -1) @ Ek
        Jc = np.broadcast_to(E[:, self.coord_idx, :] * self.sw_c[None, :, None], (n, self.coord_idx.size, cmap.n_z))
        J = np.concatenate([Jm, Jc], axis=1)
        return r, J, q, x


def _rigid_start(model: Model, q_default: np.ndarray, names, y, ok, w) -> np.ndarray | None:
    """Default pose moved rigidly onto the markers (weighted Kabsch), through the root joint's coordinates.

    Gives IK's first frame a start that is right whatever the subject's heading
    in the lab (a Gauss-Newton start 180 degrees off converges to a wrong
    minimum).  Only for a root joint with three identity rotations about
    orthonormal axes and three identity translations (free / ground-pelvis
    joints); otherwise None.
    """
    from kinematics.multibody.joints import CustomJoint, is_identity_function

    if not model.joints:
        return None
    root = model.joints[0]
    if not isinstance(root, CustomJoint) or len(root.rotations) != 3 or len(root.translations) != 3:
        return None
    axes = root.rotations + root.translations
    if not all(is_identity_function(a.function) and len(a.coordinates) == 1 for a in axes):
        return None
    Ar = np.array([a.axis for a in root.rotations]).T
    Bt = np.array([a.axis for a in root.translations]).T
    if not (np.allclose(Ar.T @ Ar, np.eye(3), atol=1e-9) and np.allclose(Bt.T @ Bt, np.eye(3), atol=1e-9)):
        return None
    if ok.sum() < 3:
        return None
    x0 = marker_positions(model, q_default, names)[ok]
    yy, ww = y[ok], w[ok]
    cx, cy = (ww @ x0) / ww.sum(), (ww @ yy) / ww.sum()
    H = ((x0 - cx) * ww[:, None]).T @ (yy - cy)
    Rk, S = kabsch_rotation(H)
    if S[1] < 1e-9 * max(S[0], 1e-300):
        return None                                # collinear markers: rotation undetermined
    tk = cy - Rk @ cx
    # Desired pose of the root's joint frame M in ground, then of M in F (the ground-side joint frame).
    st = forward_kinematics(model, q_default)
    b = 1
    R_Wb, p_Wb = st.rotations[0, b], st.positions[0, b]
    co, po = root.child_offset, root.parent_offset
    R_WM = Rk @ R_Wb @ co.rotation
    p_WM = Rk @ (R_Wb @ co.translation + p_Wb) + tk
    R_FM = po.rotation.T @ R_WM
    p_FM = po.rotation.T @ (p_WM - po.translation)
    # R_FM = A Rx(t1) Ry(t2) Rz(t3) A^T with A = [a1 a2 a3] (right-handed; else flip the third axis).
    sgn = 1.0
    A = Ar.copy()
    if np.linalg.det(A) < 0:
        A[:, 2] *= -1.0
        sgn = -1.0
    th = matrix_to_euler_xyz(A.T @ R_FM @ A)
    th[2] *= sgn
    q = np.array(q_default, float).copy()
    idx = [model.coordinate_index(a.coordinates[0]) for a in axes]
    q[idx[:3]] = th
    q[idx[3:]] = Bt.T @ p_FM
    return q


def _unwrappable_rotations(model: Model) -> list[int]:
    """Indices of unbounded rotational coordinates (range over two turns) whose 2 pi shifts leave every pose unchanged.

    Such a coordinate drives only rotation axes through the identity function
    and is neither coupled (linear rows, non-linear couplers) nor locked.
    """
    from kinematics.multibody.joints import CustomJoint, is_identity_function

    coupled = set()
    if model.couplings is not None:
        M = np.asarray(model.couplings.matrix, float)
        coupled |= {n for j, n in enumerate(model.couplings.coordinates) if np.any(M[:, j] != 0)}
    for cp in model.couplers:
        coupled |= {cp.dependent, *cp.independent}
    ok: dict[str, bool] = {}
    for j in model.joints:
        if not isinstance(j, CustomJoint):
            for n in j.coordinates:
                ok[n] = False
            continue
        for a in j.rotations:
            for n in a.coordinates:
                ok[n] = ok.get(n, True) and is_identity_function(a.function) and len(a.coordinates) == 1
        for a in j.translations:
            for n in a.coordinates:
                ok[n] = False
    out = []
    for i, c in enumerate(model.coordinates):
        lo, hi = c.range
        # ranges wider than two turns bound nothing a 2 pi shift could break (OpenSim writes unbounded as +-1000)
        if (c.kind == "rotational" and ok.get(c.name, False) and c.name not in coupled and not c.locked
                and hi - lo > 4.0 * np.pi):
            out.append(i)
    return out


def unwrap_rotations(model: Model, q: np.ndarray) -> np.ndarray:
    """`q` (F, n_q) with each unbounded free rotation (`_unwrappable_rotations`) continuous over the frames.

    The first finite value is brought into (-pi, pi] and the rest unwrapped (numpy.unwrap over the finite
    frames): the poses are the same, the angles free of 2 pi jumps and offsets.
    """
    q = np.array(q, float, copy=True)
    for i in _unwrappable_rotations(model):
        col = q[:, i]
        fin = np.isfinite(col)
        if not fin.any():
            continue
        v = np.unwrap(col[fin])
        v -= 2.0 * np.pi * np.round(v[0] / (2.0 * np.pi))
        if v[0] <= -np.pi:
            v += 2.0 * np.pi
        lo, hi = model.coordinates[i].range
        if np.all((v >= lo) & (v <= hi)):
            col[fin] = v
    return q


def _canonical_root(model: Model, q: np.ndarray) -> np.ndarray:
    """`q` (n_q,) with the root joint's three Cardan angles on their canonical branch (middle angle in
    [-pi/2, pi/2], the others in (-pi, pi]): the same pose.

    A Cardan sequence has two angle triples per orientation, (a, b, c) and (a + pi, pi - b, c + pi); a subject
    facing back (heading near 180 deg) is as well described by a pelvis tilted and listed by 180 deg.  Only for
    a root with three identity rotations about orthonormal axes whose coordinates `_unwrappable_rotations`
    allows to change; otherwise `q` unchanged.
    """
    from kinematics.multibody.joints import CustomJoint, is_identity_function, rotation_about

    q = np.array(q, float, copy=True)
    if not model.joints:
        return q
    root = model.joints[0]
    if not isinstance(root, CustomJoint) or len(root.rotations) != 3:
        return q
    if not all(is_identity_function(a.function) and len(a.coordinates) == 1 for a in root.rotations):
        return q
    idx = [model.coordinate_index(a.coordinates[0]) for a in root.rotations]
    if not set(idx) <= set(_unwrappable_rotations(model)):
        return q
    A = np.array([a.axis for a in root.rotations], float).T
    if not np.allclose(A.T @ A, np.eye(3), atol=1e-9):
        return q
    R = np.eye(3)
    for a, i in zip(root.rotations, idx):
        R = R @ rotation_about(a.axis, q[i])
    sgn = 1.0
    if np.linalg.det(A) < 0:
        A = A.copy()
        A[:, 2] *= -1.0
        sgn = -1.0
    th = matrix_to_euler_xyz(A.T @ R @ A)
    th[2] *= sgn
    q[idx] = th
    return q


def _null_coordinates(model: Model, cmap, J: np.ndarray, z: np.ndarray, rtol: float = 1e-8,
                      share: float = 0.1) -> set[str]:
    """Coordinates moved (|dq_i| > `share` max |dq|) by the null-space directions of the Jacobians `J` (n, r, n_z)."""
    names: set[str] = set()
    if not cmap.n_z or not len(J):
        return names
    _, sv, vt = np.linalg.svd(J, full_matrices=True)
    E = cmap.jacobian(cmap.expand(z))                                         # (n, n_q, n_z)
    for k in range(len(J)):
        s_k = np.zeros(cmap.n_z)
        s_k[:sv.shape[1]] = sv[k]
        null = vt[k][s_k <= rtol * max(s_k[0], 1e-300)]
        for v in null:
            dq = np.abs(E[k] @ v)
            if dq.max() > 0:
                names |= {model.coordinates[i].name for i in np.flatnonzero(dq > share * dq.max())}
    return names


def solve_pose(model: Model, targets, weights=None, q0=None, markers=None, **kw) -> tuple[np.ndarray, float]:
    """IK of one frame: q (n_q,) and the RMS marker error (m) for targets (M,3)."""
    names = model.marker_names if markers is None else tuple(markers)
    tr = MarkerTrial(names, np.asarray(targets, float)[None], 1.0, np.zeros(1), "targets")
    res = solve_ik(model, tr, marker_weights=None if weights is None else dict(zip(names, np.broadcast_to(weights, len(names)))),
                   q0=q0, **kw)
    return res.q[0], float(res.rms[0])


def solve_ik(model: Model, trial: MarkerTrial, marker_weights: Mapping[str, float] | None = None,
             coordinate_tasks: Sequence[CoordinateTask] = (), q0=None, limits: str = "clamped",
             tolerance: float = 1e-5, max_iterations: int = 30, first_frame_iterations: int = 300,
             block: int = 16, progress: Callable[[int, int], None] | None = None,
             check_units: bool = True) -> IKResult:
    """Inverse kinematics of a marker trial (see the module docstring for model and algorithm).

    Parameters
    ----------
    model : Model
    trial : MarkerTrial
        Positions (F, M, 3) in metres, in the model's ground frame, NaN gaps.
    marker_weights : mapping name -> weight, optional
        Markers to track; default: every model marker present in the trial, weight 1.
    coordinate_tasks : sequence of CoordinateTask
        Weighted squared deviations of coordinates from targets (OpenSim IKCoordinateTask).
    q0 : (n_q,), optional
        Start of the first frame (default: the model's default pose).
    limits : {'clamped', 'all', 'none'}
        Which coordinate ranges are enforced (OpenSim enforces clamped ones).
    tolerance : float
        A frame is converged when the estimated distance of its coordinates to
        the least-squares optimum (from the last step and the observed linear
        convergence rate) is below `tolerance` (rad or m).
    block : int
        Frames admitted per iteration into the pipelined window (see `kinematics.algorithms.least_squares.solve_stream`);
        1 is nearly sequential warm starting, larger values share more work per evaluation.
    check_units : bool
        Refuse a trial whose inter-marker distances disagree with the model's
        (`check_trial_scale`: millimetres read as metres and the like).

    Raises
    ------
    InputError
        No model marker in the trial, marker weights naming markers the model lacks,
        marker distances in another unit than the model's, or every frame empty.
    """
    t_start = _time.perf_counter()
    src = trial.source
    if marker_weights is None:
        use = [m for m in model.marker_names if m in trial.names]
        wts = {m: 1.0 for m in use}
    else:
        unknown = [m for m in marker_weights if m not in model.marker_names]
        if unknown:
            raise InputError(src, f"marker weights name markers that are not in the model: {', '.join(unknown)}")
        wts = {m: float(w) for m, w in marker_weights.items() if float(w) > 0}
        use = [m for m in wts if m in trial.names]
    if not use:
        raise InputError(src, f"none of the model's markers ({', '.join(model.marker_names[:6])}...) is in the trial")
    if check_units:
        check_trial_scale(model, trial, use)
    midx = np.array([model.marker_index(m) for m in use], dtype=int)
    tidx = [trial.names.index(m) for m in use]
    Y = trial.positions[:, tidx, :]
    ok_all = np.isfinite(Y).all(-1)
    Y = np.nan_to_num(Y)
    solvable = ok_all.any(1)
    if not solvable.any():
        raise InputError(src, "every frame has all tracked markers missing")
    ctasks = list(coordinate_tasks)
    cidx = np.array([model.coordinate_index(t.name) for t in ctasks], dtype=int)
    ctarget = np.array([model.coordinates[i].default if t.value is None else t.value for t, i in zip(ctasks, cidx)], float)
    csw = np.sqrt(np.array([t.weight for t in ctasks], float))
    cmap = coordinate_map(model, limits=limits)
    prob = _Problem(model, cmap, midx, np.sqrt(np.array([wts[m] for m in use])), cidx, ctarget, csw)
    F = trial.n_frames
    Zs = np.full((F, cmap.n_z), np.nan)
    its = np.zeros(F, int)
    conv = np.zeros(F, bool)
    qstart = model.default_q if q0 is None else np.asarray(q0, float)
    z_prev = cmap.project(qstart)[0]
    frames = np.flatnonzero(solvable)
    # First frame: cold start with more iterations and stronger initial damping; without a given q0 also
    # from the default pose moved rigidly onto the markers, keeping the better of the two.
    f0 = frames[0]
    z, it, cv, _, _ = solve_block(prob, z_prev[None], Y[f0:f0 + 1], ok_all[f0:f0 + 1], tolerance,
                                   first_frame_iterations, 1e-3)
    if q0 is None:
        wm = np.array([wts[m] for m in use])
        qr = _rigid_start(model, qstart, use, Y[f0], ok_all[f0], wm)
        if qr is not None:
            zr0 = feasible(cmap.project(qr), cmap.ineq_matrix, cmap.ineq_rhs)
            z2, it2, cv2, _, _ = solve_block(prob, zr0, Y[f0:f0 + 1], ok_all[f0:f0 + 1], tolerance,
                                              first_frame_iterations, 1e-3)
            c1, c2 = (np.sum(prob.evaluate(zz, Y[f0:f0 + 1], ok_all[f0:f0 + 1], jac=False)[0] ** 2) for zz in (z, z2))
            if c2 < c1:
                z, cv = z2, cv2
            it = it + it2
    # the root's heading on its canonical Cardan branch (the warm starts then keep it)
    z = cmap.project(_canonical_root(model, cmap.expand(z)[0]))
    Zs[f0], its[f0], conv[f0] = z[0], it[0], cv[0]
    rest = frames[1:]
    if progress is not None:
        progress(1, frames.size)
    if rest.size:
        zr, ir, cr = solve_stream(prob, z[0], Y[rest], ok_all[rest], tolerance, max_iterations, max(1, block),
                                   progress=None if progress is None else (lambda d, n: progress(d + 1, n + 1)))
        # Frames that did not converge from their warm start are retried one by one with strong damping.
        for b in np.flatnonzero(~cr):
            start = zr[b - 1] if b > 0 and np.isfinite(zr[b - 1]).all() else z[0]
            zb, ib, cb, _, _ = solve_block(prob, start[None], Y[rest[b]:rest[b] + 1], ok_all[rest[b]:rest[b] + 1],
                                            tolerance, first_frame_iterations, 1e-3)
            zr[b], ir[b], cr[b] = zb[0], ir[b] + ib[0], cb[0]
        Zs[rest], its[rest], conv[rest] = zr, ir, cr
    repair_jumps(prob, Zs, its, conv, frames, Y, ok_all, tolerance, first_frame_iterations)
    Zs[frames] = prob.wrap(Zs[frames])
    Q = np.full((F, model.n_q), np.nan)
    Q[frames] = unwrap_rotations(model, cmap.expand(Zs[frames]))
    # Final errors (unweighted distances) for reporting.
    Xall = marker_positions(model, Q[frames], use)
    err = np.full((F, len(use)), np.nan)
    resid = np.full((F, len(use), 3), np.nan)
    resid[frames] = np.where(ok_all[frames][..., None], Xall - Y[frames], np.nan)
    err[frames] = np.linalg.norm(resid[frames], axis=-1)
    present = np.isfinite(err)
    cnt = present.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.where(present, err**2, 0.0).sum(1) / cnt)
        mx = np.where(present, err, -np.inf).max(1)
    rms[cnt == 0] = np.nan
    mx[cnt == 0] = np.nan
    cost = np.full(F, np.nan)
    determined = np.zeros(F, bool)
    undetermined: set[str] = set()
    for s0 in range(0, frames.size, 256):           # chunks bound the Jacobian's memory on long trials
        fr = frames[s0:s0 + 256]
        r, J, _, _ = prob.evaluate(Zs[fr], Y[fr], ok_all[fr], jac=True)
        cost[fr] = np.einsum("ni,ni->n", r, r)
        if cmap.n_z:
            sv = np.linalg.svd(J, compute_uv=False)
            if J.shape[1] < cmap.n_z:
                sv = np.concatenate([sv, np.zeros((len(fr), cmap.n_z - J.shape[1]))], axis=1)
            determined[fr] = sv[:, -1] > 1e-8 * np.maximum(sv[:, 0], 1e-300)
            bad = np.flatnonzero(~determined[fr])
            # a null space usually repeats over a trial: name its coordinates from a few frames of each chunk
            pick = bad[np.unique(np.linspace(0, bad.size - 1, min(bad.size, 8)).astype(int))] if bad.size else bad
            undetermined |= _null_coordinates(model, cmap, J[pick], Zs[fr][pick])
        else:
            determined[fr] = True
    return IKResult(model.coordinate_names, np.asarray(trial.time, float), Q, tuple(use), err, rms, mx, its, conv,
                    solvable, cost, _time.perf_counter() - t_start, determined, resid,
                    tuple(c for c in model.coordinate_names if c in undetermined))
