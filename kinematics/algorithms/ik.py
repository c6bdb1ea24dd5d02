"""Marker-based inverse kinematics, batched over frames.

Model (per frame f)
-------------------
Coordinates are parametrised so that every equality holds exactly::

    q_R = q_p + N z                (linear couplings C q = d and locked coordinates;
                                    N N^T = P0, Raunhardt & Boulic's initial projector)
    q_D = f(q_I)                   (non-linear couplers: dependent coordinates)

and z minimises the weighted least squares of OpenSim's IK::

    E(z) = sum_m w_m |x_m(q(z)) - y_m,f|^2 + sum_c w_c (q_c(z) - qbar_c)^2

over the markers present in frame f (NaN gaps have weight 0), subject to the
coordinate limits and linear inequalities ``G q <= h`` (rows ``A z <= b``).

Algorithm
---------
Levenberg-Marquardt with analytic Jacobians dE/dz = J_q (dq/dz): each step
solves the equality-constrained damped normal equations

    [J^T J + lambda I   A_W^T] [dz]   [-J^T r]
    [A_W                0    ] [mu] = [ s_W  ]

for the working set W of inequality rows (slack s = b - A z), an active-set
clamping loop: rows with mu < 0 leave W, rows the step would cross enter W,
until the step is feasible.  The first frame starts from the default pose
(or ``q0``); the others are solved in a pipelined window, vectorised: new
frames enter the window warm-started from the newest nearly-solved frame
extrapolated at the velocity of the last solved frames, and leave it once the
estimated distance to their optimum (last step times rho / (1 - rho), rho the
observed linear convergence rate) is below ``tolerance``.  Frames that fail
from their warm start are re-solved alone with stronger damping.  Without
``q0`` the first frame is also solved from the default pose moved rigidly
onto the markers (weighted Kabsch through the root joint), keeping the lower
cost, so that the subject's heading in the lab does not matter.  Finally a
frame whose solution jumps away from a neighbour's (another local minimum,
e.g. an angle 2 pi away) is re-solved from that neighbour, keeping the lower
cost, and the repair walks on frame by frame while it keeps finding a markedly
lower minimum (warm starts chain a wrong minimum over the following frames).
"""
from __future__ import annotations

import os
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from kinematics.multibody.coupling import null_space_parametrization
from lowerlimb.errors import InputError
from kinematics.algorithms.fk import as_q, cross, forward_kinematics, marker_jacobian, marker_positions
from kinematics.multibody.joints import matrix_to_euler_xyz
from kinematics.io.markers import MarkerTrial
from kinematics.multibody.model import Model

__all__ = [
    "CoordinateMap", "coordinate_map", "IKResult", "IKSetup", "CoordinateTask",
    "solve_ik", "solve_pose", "read_ik_setup", "marker_task", "coordinate_task", "check_trial_scale",
    "orientation_task", "com_task",
]


# ----------------------------------------------------------------------------- parametrisation
@dataclass(frozen=True, eq=False)
class CoordinateMap:
    """Affine + non-linear parametrisation q = q(z) that satisfies every equality exactly.

    Attributes
    ----------
    n_q, n_z : int
    reduced : (n_R,) indices of the coordinates that are not coupler-dependent
    dependent : (n_D,) indices of coupler-dependent coordinates
    q_p : (n_R,) particular solution of the linear rows (over q_R)
    basis : (n_R, n_z) orthonormal null-space basis N
    projector : (n_R, n_R) Raunhardt & Boulic's P0 = N N^T
    ineq_matrix, ineq_rhs : rows A z <= b (coordinate limits and G q <= h)
    ineq_labels : tuple of str
    """

    model: Model
    reduced: np.ndarray
    dependent: np.ndarray
    q_p: np.ndarray
    basis: np.ndarray
    ineq_matrix: np.ndarray
    ineq_rhs: np.ndarray
    ineq_labels: tuple

    @property
    def n_q(self) -> int:
        return self.model.n_q

    @property
    def n_z(self) -> int:
        return self.basis.shape[1]

    @property
    def projector(self) -> np.ndarray:
        return self.basis @ self.basis.T

    def expand(self, z) -> np.ndarray:
        """q (N, n_q) from z (N, n_z)."""
        z = np.atleast_2d(z)
        q = np.empty((z.shape[0], self.n_q))
        q[:, self.reduced] = self.q_p + z @ self.basis.T
        for cp, d, ind in self._couplers():
            q[:, d] = cp.function.evaluate(q[:, ind], order=0)[0]
        return q

    def _couplers(self):
        m = self.model
        for cp in m.couplers:
            yield cp, m.coordinate_index(cp.dependent), np.array([m.coordinate_index(c) for c in cp.independent])

    def jacobian(self, q) -> np.ndarray:
        """dq/dz (N, n_q, n_z) at q (N, n_q): N on q_R, chain rule f'(q_I) N_I on q_D."""
        q = np.atleast_2d(q)
        n = q.shape[0]
        E = np.zeros((n, self.n_q, self.n_z))
        E[:, self.reduced, :] = self.basis
        for cp, d, ind in self._couplers():
            g = cp.function.evaluate(q[:, ind], order=1)[1]          # (n, k)
            E[:, d, :] = np.einsum("nk,nkz->nz", g, E[:, ind, :])
        return E

    def project(self, q) -> np.ndarray:
        """z of the closest admissible pose: z = N^T (q_R - q_p) (restores the linear rows)."""
        q = np.atleast_2d(np.asarray(q, float))
        return (q[:, self.reduced] - self.q_p) @ self.basis


def coordinate_map(model: Model, limits: str = "clamped", locked: bool = True,
                   lock_values: Mapping[str, float] | None = None) -> CoordinateMap:
    """Parametrisation of the admissible coordinates of `model`.

    Parameters
    ----------
    limits : {'clamped', 'all', 'none'}
        Which coordinate ranges become inequalities: only coordinates flagged
        ``clamped`` (OpenSim's IK behaviour), every finite range, or none.
    locked : bool
        Hold locked coordinates at their default value (as OpenSim does).
    lock_values : mapping, optional
        Extra coordinates to hold at given values.
    """
    if limits not in ("clamped", "all", "none"):
        raise ValueError("limits must be 'clamped', 'all' or 'none'")
    dep = [model.coordinate_index(cp.dependent) for cp in model.couplers]
    if len(set(dep)) != len(dep):
        raise InputError(model.name, "a coordinate is the dependent of two couplers")
    for cp in model.couplers:
        bad = [c for c in cp.independent if model.coordinate_index(c) in dep]
        if bad:
            raise InputError(model.name, f"coupler of {cp.dependent!r} depends on coupler-dependent coordinates {bad}")
    red = np.array([i for i in range(model.n_q) if i not in dep], dtype=int)
    rows, rhs = [], []
    if model.couplings is not None:
        C = model.couplings.matrix
        if np.any(C[:, dep]) if dep else False:
            raise InputError(model.name, "linear couplings may not involve coupler-dependent coordinates")
        rows.append(C[:, red])
        rhs.append(model.couplings.rhs)
    fixed = dict(lock_values or {})
    if locked:
        for c in model.coordinates:
            if c.locked and c.name not in fixed:
                fixed[c.name] = c.default
    for name, v in fixed.items():
        i = model.coordinate_index(name)
        if i in dep:
            raise InputError(model.name, f"cannot lock coupler-dependent coordinate {name!r}")
        e = np.zeros(red.size)
        e[list(red).index(i)] = 1.0
        rows.append(e[None])
        rhs.append([v])
    C = np.vstack(rows) if rows else np.zeros((0, red.size))
    d = np.concatenate(rhs) if rhs else np.zeros(0)
    q_p, N = null_space_parametrization(C, d, source=model.name)
    # Inequalities over z.
    A, b, lab = [], [], []
    for k, i in enumerate(red):
        c = model.coordinates[i]
        if limits == "none" or (limits == "clamped" and not c.clamped):
            continue
        nrow = N[k]
        if not np.any(np.abs(nrow) > 1e-12):
            continue
        lo, hi = c.range
        if np.isfinite(hi):
            A.append(nrow)
            b.append(hi - q_p[k])
            lab.append(f"{c.name}<=upper")
        if np.isfinite(lo):
            A.append(-nrow)
            b.append(q_p[k] - lo)
            lab.append(f"{c.name}>=lower")
    if model.inequalities is not None:
        G = model.inequalities.matrix
        if dep and np.any(G[:, dep]):
            raise InputError(model.name, "linear inequalities may not involve coupler-dependent coordinates")
        for g, h, l in zip(G[:, red], model.inequalities.rhs, model.inequalities.labels):
            A.append(g @ N)
            b.append(h - g @ q_p)
            lab.append(l)
    A = np.array(A, float).reshape(-1, N.shape[1])
    b = np.array(b, float)
    for a in (red, q_p, N, A, b):
        a.setflags(write=False)
    depa = np.array(dep, dtype=int)
    depa.setflags(write=False)
    return CoordinateMap(model, red, depa, q_p, N, A, b, tuple(lab))


# ----------------------------------------------------------------------------- tasks
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


def coordinate_task(model: Model, q, targets: Mapping[str, float], weights: Mapping[str, float]):
    """r_c = sqrt(w_c) (q_c - target_c) and its Jacobian (rows of the identity)."""
    q2, single = as_q(model, q)
    names = list(targets)
    idx = np.array([model.coordinate_index(c) for c in names], dtype=int)
    sw = np.sqrt(np.array([weights[c] for c in names], float))
    r = (q2[:, idx] - np.array([targets[c] for c in names])) * sw
    J = np.zeros((q2.shape[0], len(names), model.n_q))
    J[:, np.arange(len(names)), idx] = sw
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
    from scipy.spatial.transform import Rotation

    from kinematics.algorithms.fk import frame_jacobian
    from kinematics.multibody.joints import left_jacobian_inverse_so3

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
    from kinematics.algorithms.fk import com_jacobian

    q2, single = as_q(model, q)
    c, J = com_jacobian(model, q2)
    sw = np.sqrt(weight)
    e, J = sw * (c - np.asarray(target, float)), sw * J
    return (e[0], J[0]) if single else (e, J)


# ----------------------------------------------------------------------------- setup
@dataclass(frozen=True)
class CoordinateTask:
    """Keep coordinate `name` near `value` (None: the model default) with `weight`."""

    name: str
    weight: float
    value: float | None = None


@dataclass(frozen=True)
class IKSetup:
    """Tasks of an OpenSim IK setup file (``IKMarkerTask`` / ``IKCoordinateTask``)."""

    marker_weights: Mapping[str, float] = field(default_factory=dict)
    coordinate_tasks: tuple[CoordinateTask, ...] = ()
    time_range: tuple[float, float] | None = None
    accuracy: float = 1e-5
    model_file: str | None = None
    marker_file: str | None = None
    disabled_markers: tuple[str, ...] = ()
    source: str | None = None


def _bool(text: str | None) -> bool:
    return (text or "").strip().lower() in ("true", "1", "yes")


def read_ik_setup(path: str | os.PathLike) -> IKSetup:
    """Parse an OpenSim ``InverseKinematicsTool`` setup file (defusedxml).

    IKMarkerTask weights (tasks with ``apply`` false are dropped), IKCoordinateTask
    targets (``default_value``: the model default; ``manual_value``: ``value``,
    rotational values in radians as in OpenSim; ``from_file`` is rejected),
    ``time_range``, ``accuracy``, ``model_file``, ``marker_file``.
    """
    from kinematics.io.opensim_io import read_xml

    path = Path(path)
    root = read_xml(path, "IK setup file not found", "not an OpenSim IK setup: the file is not XML")
    tool = root if root.tag == "InverseKinematicsTool" else root.find("InverseKinematicsTool")
    if tool is None:
        raise InputError(path, "not an OpenSim IK setup: no <InverseKinematicsTool> element")
    weights, disabled, ctasks = {}, [], []
    for t in tool.iter("IKMarkerTask"):
        name = t.get("name")
        w = float((t.findtext("weight") or "1").strip())
        if _bool(t.findtext("apply") or "true") and w > 0:
            weights[name] = w
        else:
            disabled.append(name)
    for t in tool.iter("IKCoordinateTask"):
        if not _bool(t.findtext("apply") or "true"):
            continue
        w = float((t.findtext("weight") or "1").strip())
        vt = (t.findtext("value_type") or "default_value").strip()
        if vt == "default_value":
            ctasks.append(CoordinateTask(t.get("name"), w, None))
        elif vt == "manual_value":
            ctasks.append(CoordinateTask(t.get("name"), w, float((t.findtext("value") or "0").strip())))
        else:
            raise InputError(path, f"IKCoordinateTask {t.get('name')!r}: value_type {vt!r} is not supported "
                                   "(use default_value or manual_value)")
    tr = (tool.findtext("time_range") or "").split()
    time_range = (float(tr[0]), float(tr[1])) if len(tr) == 2 else None
    acc = float((tool.findtext("accuracy") or "1e-5").strip())
    return IKSetup(weights, tuple(ctasks), time_range, acc, (tool.findtext("model_file") or "").strip() or None,
                   (tool.findtext("marker_file") or "").strip() or None, tuple(disabled), os.fspath(path))


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
_EXTRAP = 4
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


def _constrained_step(H, g, A, s, tol=1e-12, max_loops=None):
    """Active-set solution of min 1/2 d^T H d + g^T d  s.t.  A d <= s, for a batch.

    H (n,p,p), g (n,p), A (m,p), s (n,m) slack (>= -tol).  Returns d (n,p).
    """
    n, p = g.shape
    m = A.shape[0]
    d_free = np.linalg.solve(H, -g[..., None])[..., 0]
    if m == 0:
        return d_free
    W = s <= 1e-10                                # rows already on their bound
    need = W.any(1) | (d_free @ A.T > s + tol).any(1)
    if not need.any():
        return d_free                             # no bound touched: the plain damped step
    if not need.all():
        d_free[need] = _constrained_step(H[need], g[need], A, s[need], tol, max_loops)
        return d_free
    max_loops = max_loops or 2 * m + 2
    d = None
    for _ in range(max_loops):
        K = np.zeros((n, p + m, p + m))
        K[:, :p, :p] = H
        Aw = A[None, :, :] * W[..., None]
        K[:, :p, p:] = np.swapaxes(Aw, 1, 2)
        K[:, p:, :p] = Aw
        K[:, p:, p:] = np.eye(m)[None] * (~W)[:, :, None] * -1.0
        rhs = np.concatenate([-g, np.where(W, s, 0.0)], axis=1)
        sol = np.linalg.solve(K, rhs[..., None])[..., 0]
        d, mu = sol[:, :p], sol[:, p:]
        changed = np.zeros(n, bool)
        # Drop rows whose multiplier pulls inward (the bound is not binding).
        drop = W & (mu < -1e-12)
        if drop.any():
            # one at a time per frame: the most negative multiplier
            k = np.argmin(np.where(drop, mu, np.inf), axis=1)
            rowsel = drop.any(1)
            W[np.flatnonzero(rowsel), k[rowsel]] = False
            changed |= rowsel
        viol = (~W) & (d @ A.T > s + tol)
        if viol.any():
            # Clamp the row crossed first along the step.
            Ad = d @ A.T
            t = np.where(viol, s / np.where(Ad > 0, Ad, 1.0), np.inf)
            k = np.argmin(t, axis=1)
            rowsel = viol.any(1) & ~changed
            W[np.flatnonzero(rowsel), k[rowsel]] = True
            changed |= rowsel
        if not changed.any():
            break
    return d


def _converged(dq, prev, acc, tol, lam):
    """Accepted, (nearly) undamped steps whose estimated remaining error is below `tol`.

    Gauss-Newton on a problem with non-zero residuals converges linearly;
    with the observed rate rho = |dq_k| / |dq_k-1| the distance of the new
    iterate to the optimum is about |dq_k| rho / (1 - rho).  A step shortened
    by strong damping says nothing about convergence, hence ``lam`` (the
    relative damping the step used) must be small.
    """
    rho = np.clip(np.where(np.isfinite(prev) & (prev > 0), dq / np.where(prev > 0, prev, 1.0), 1.0), 0.0, 0.9)
    est = np.where(np.isfinite(prev), dq * rho / (1.0 - rho), dq)
    return acc & (lam <= 1e-4) & (np.minimum(est, dq) < tol)


def _lm_direction(J, r, lam, z, A, bnd):
    """Damped Gauss-Newton step for a batch, restricted by the active inequalities."""
    Jt = np.swapaxes(J, 1, 2)
    H = Jt @ J
    g = (Jt @ r[..., None])[..., 0]
    p = H.shape[1]
    scale = np.maximum(np.trace(H, axis1=1, axis2=2) / p, 1e-12)
    H[:, np.arange(p), np.arange(p)] += (lam * scale)[:, None]
    s = (bnd - z @ A.T) if A.shape[0] else np.zeros((z.shape[0], 0))
    return _constrained_step(H, g, A, np.maximum(s, 0.0))


def _feasible(z, A, bnd):
    """Move z onto the inequality rows it violates (coordinate limits are axis rows in practice)."""
    if not A.shape[0]:
        return z
    z = z.copy()
    for _ in range(3):
        viol = z @ A.T - bnd
        if not (viol > 0).any():
            break
        for k in range(A.shape[0]):
            v = viol[:, k] > 0
            if v.any():
                z[v] -= np.outer(viol[v, k], A[k]) / (A[k] @ A[k])
    return z


def _solve_stream(problem: _Problem, z_start, Y, ok, tolerance, max_iterations, admit, lam0=1e-6, progress=None,
                  admit_step=None):
    """Pipelined Levenberg-Marquardt over consecutive frames.

    A window of frames is iterated together (one vectorised evaluation per
    iteration).  New frames (up to `admit` per iteration) enter once the last
    frame of the window is nearly solved (its last step below `admit_step`,
    default 10 x `tolerance`), started from that frame's iterate plus the
    velocity of the last solved frames; converged frames leave.  Every frame
    thus starts next to an almost-solved neighbour (warm start) while the
    per-evaluation overhead is shared by the whole window.  The admission step
    must be small: a start extrapolated from an iterate still moving (e.g.
    0.05 rad from its optimum) lands, on nearly singular problems (hip and knee
    rotation with Plug-in-Gait markers only), in another local minimum that
    the warm starts then carry over the following frames.
    """
    if admit_step is None:
        admit_step = 10.0 * tolerance
    cmap = problem.cmap
    A, bnd = cmap.ineq_matrix, cmap.ineq_rhs
    F, nz = Y.shape[0], cmap.n_z
    Z = np.full((F, nz), np.nan)
    its = np.zeros(F, int)
    conv = np.zeros(F, bool)
    win = np.zeros(0, int)
    z = np.zeros((0, nz))
    r = J = None
    cost = lam = last = np.zeros(0)
    it = np.zeros(0, int)
    nxt = 0
    solved = {-1: np.asarray(z_start, float)}      # frame -> solution (converged frames; -1: the start)
    done = 0

    def velocity():
        # The newest pair of consecutive solved frames (a bounded look-back keeps long trials linear).
        top = max(solved)
        for b in range(top, max(top - 64, 0), -1):
            if b in solved and b - 1 in solved:
                return solved[b] - solved[b - 1]
        return np.zeros(nz)

    while nxt < F or win.size:
        if win.size:
            d = _lm_direction(J, r, lam, z, A, bnd)
            zt = z + d
        else:
            d = zt = np.zeros((0, nz))
        n_new = min(admit, F - nxt)
        if n_new and win.size and last[-1] > admit_step:
            n_new = 0                                # wait: the newest frame is not solved well enough yet
        if n_new:
            if win.size:
                base_f, base = win[-1], z[-1]
            else:
                base_f = max(solved)
                base = solved[base_f]
            new = np.arange(nxt, nxt + n_new)
            steps = np.minimum(new - base_f, _EXTRAP)[:, None]
            zi = _feasible(problem.wrap(base[None] + steps * velocity()[None]), A, bnd)
            nxt += n_new
        else:
            zi = np.zeros((0, nz))
            new = np.zeros(0, int)
        idx = np.concatenate([win, new])
        rr, JJ, _, _ = problem.evaluate(np.concatenate([zt, zi]), Y[idx], ok[idx])
        cc = np.einsum("ni,ni->n", rr, rr)
        m = win.size
        if m:
            acc = cc[:m] <= cost * (1 + 1e-12) + 1e-30
            z[acc], r[acc], J[acc], cost[acc] = zt[acc], rr[:m][acc], JJ[:m][acc], cc[:m][acc]
            dq = np.abs(d @ cmap.basis.T).max(axis=1)
            small = _converged(dq, last, acc, tolerance, lam) | ((~acc) & (dq < tolerance) & (lam <= 1e-4))
            lam = np.where(acc, np.maximum(lam / 10.0, 1e-14), lam * 10.0)
            it += 1
            last = np.where(acc, dq, last)
            leave = small | (~acc & (lam > 1e12)) | (it >= max_iterations)
            if leave.any():
                Z[win[leave]] = z[leave]
                its[win[leave]] = it[leave]
                conv[win[leave]] = small[leave]
                for f, zf, c in zip(win[leave], z[leave], small[leave]):
                    if c:
                        solved[int(f)] = zf
                newest = max(solved)                 # never empty: the warm start needs a solved frame
                for f in [k for k in solved if k < nxt - 256 and k != newest]:
                    del solved[f]
                keep = ~leave
                win, z, r, J = win[keep], z[keep], r[keep], J[keep]
                cost, lam, it, last = cost[keep], lam[keep], it[keep], last[keep]
                done += int(leave.sum())
                if progress is not None:
                    progress(done, F)
        if new.size:
            win = np.concatenate([win, new])
            z = np.concatenate([z, zi])
            r = rr[m:] if r is None or r.shape[0] == 0 else np.concatenate([r, rr[m:]])
            J = JJ[m:] if J is None or J.shape[0] == 0 else np.concatenate([J, JJ[m:]])
            cost = np.concatenate([cost, cc[m:]])
            lam = np.concatenate([lam, np.full(new.size, lam0)])
            it = np.concatenate([it, np.zeros(new.size, int)])
            last = np.concatenate([last, np.full(new.size, np.inf)])
    return Z, its, conv


def _solve_block(problem: _Problem, z0, y, ok, tolerance, max_iterations, lam0):
    """LM on a block of frames; returns z, iterations, converged, r."""
    cmap = problem.cmap
    A, bnd = cmap.ineq_matrix, cmap.ineq_rhs
    n = z0.shape[0]
    z = _feasible(z0, A, bnd) if A.shape[0] else z0.copy()      # start feasible (a copy either way)
    r, J, q, _ = problem.evaluate(z, y, ok)
    cost = np.einsum("ni,ni->n", r, r)
    lam = np.full(n, lam0)
    it = np.zeros(n, int)
    conv = np.zeros(n, bool)
    act = np.ones(n, bool)
    prev = np.full(n, np.inf)
    qtol = tolerance
    for _ in range(max_iterations):
        ia = np.flatnonzero(act)
        if ia.size == 0:
            break
        Ja, ra = J[ia], r[ia]
        d = _lm_direction(Ja, ra, lam[ia], z[ia], A, bnd)
        zt = z[ia] + d
        rt, Jt, qt, _ = problem.evaluate(zt, y[ia], ok[ia])
        ct = np.einsum("ni,ni->n", rt, rt)
        acc = ct <= cost[ia] * (1 + 1e-12) + 1e-30
        it[ia] += 1
        ai = ia[acc]
        z[ai], r[ai], J[ai], cost[ai], q[ai] = zt[acc], rt[acc], Jt[acc], ct[acc], qt[acc]
        dq = np.abs(d @ cmap.basis.T).max(axis=1) if d.size else np.zeros(ia.size)
        lam_used = lam[ia].copy()
        done_acc = _converged(dq, prev[ia], acc, qtol, lam_used)
        lam[ai] = np.maximum(lam[ai] / 10.0, 1e-14)
        ri = ia[~acc]
        lam[ri] = lam[ri] * 10.0
        prev[ia] = np.where(acc, dq, prev[ia])
        conv[ia[done_acc]] = True
        # A rejected tiny step means we are at the minimum to working precision.
        # A rejected, undamped, tiny step: the cost cannot decrease any more (optimum to round-off).
        at_min = (~acc) & (dq < qtol) & (lam_used <= 1e-4)
        done_rej = at_min | ((~acc) & (lam[ia] > 1e12))
        conv[ia[done_rej]] = at_min[done_rej]
        act[ia[done_acc | done_rej]] = False
    return z, it, conv, r, q


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
    U, S, Vt = np.linalg.svd(H)
    if S[1] < 1e-9 * max(S[0], 1e-300):
        return None                                # collinear markers: rotation undetermined
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    Rk = Vt.T @ D @ U.T
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


def _repair_jumps(prob, Zs, its, conv, frames, Y, ok, tolerance, max_iterations, max_passes=3, sweep_gain=1e-3):
    """Re-solve frames whose solution jumps away from a neighbour's, keeping the lower cost.

    A warm start far from the solution (fast motion, extrapolation, a nearly
    singular problem such as hip and knee rotation with Plug-in-Gait markers
    only) can land in another local minimum, e.g. an angle 2 pi away that a
    coupling makes distinct.  Each frame whose coordinates differ from a
    neighbour's by more than max(0.1, 5 x the median inter-frame change) is
    solved again from that neighbour; the result replaces it when its cost is
    lower.  While a replacement lowers the cost by more than `sweep_gain`
    (relative: another minimum, not round-off), the repair walks on, re-solving
    the next frame from the repaired one, because the warm starts chain the
    wrong minimum over the whole run of frames that follows (or precedes) the
    jump.  Repeated forwards and backwards.
    """
    if frames.size < 2:
        return

    def cost(idx, z):
        r = prob.evaluate(z, Y[idx], ok[idx], jac=False)[0]
        return np.einsum("ni,ni->n", r, r)

    for _ in range(max_passes):
        Z = Zs[frames]
        jump = np.abs(np.diff(Z, axis=0)).max(axis=1)
        thr = max(0.1, 5.0 * float(np.median(jump)))
        bad = np.flatnonzero(jump > thr)
        if bad.size == 0:
            return
        c = cost(frames, Z)
        changed = False
        for k in bad:
            for src, dst in ((k, k + 1), (k + 1, k)):
                step = dst - src
                while 0 <= dst < frames.size:
                    f = frames[dst]
                    zb, ib, cb, _, _ = _solve_block(prob, Zs[frames[src]][None], Y[f:f + 1], ok[f:f + 1], tolerance,
                                                    max_iterations, 1e-3)
                    cn = cost(np.array([f]), zb)[0]
                    if not cn < c[dst] * (1 - 1e-9):
                        break
                    Zs[f], its[f], conv[f] = zb[0], its[f] + ib[0], cb[0]
                    gain, c[dst] = cn < c[dst] * (1 - sweep_gain), cn
                    changed = True
                    if not gain:
                        break
                    src, dst = dst, dst + step
        if not changed:
            return


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
        Frames admitted per iteration into the pipelined window (see `_solve_stream`);
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
    z, it, cv, _, _ = _solve_block(prob, z_prev[None], Y[f0:f0 + 1], ok_all[f0:f0 + 1], tolerance,
                                   first_frame_iterations, 1e-3)
    if q0 is None:
        wm = np.array([wts[m] for m in use])
        qr = _rigid_start(model, qstart, use, Y[f0], ok_all[f0], wm)
        if qr is not None:
            zr0 = _feasible(cmap.project(qr), cmap.ineq_matrix, cmap.ineq_rhs)
            z2, it2, cv2, _, _ = _solve_block(prob, zr0, Y[f0:f0 + 1], ok_all[f0:f0 + 1], tolerance,
                                              first_frame_iterations, 1e-3)
            c1, c2 = (np.sum(prob.evaluate(zz, Y[f0:f0 + 1], ok_all[f0:f0 + 1], jac=False)[0] ** 2) for zz in (z, z2))
            if c2 < c1:
                z, cv = z2, cv2
            it = it + it2
    Zs[f0], its[f0], conv[f0] = z[0], it[0], cv[0]
    rest = frames[1:]
    if progress is not None:
        progress(1, frames.size)
    if rest.size:
        zr, ir, cr = _solve_stream(prob, z[0], Y[rest], ok_all[rest], tolerance, max_iterations, max(1, block),
                                   progress=None if progress is None else (lambda d, n: progress(d + 1, n + 1)))
        # Frames that did not converge from their warm start are retried one by one with strong damping.
        for b in np.flatnonzero(~cr):
            start = zr[b - 1] if b > 0 and np.isfinite(zr[b - 1]).all() else z[0]
            zb, ib, cb, _, _ = _solve_block(prob, start[None], Y[rest[b]:rest[b] + 1], ok_all[rest[b]:rest[b] + 1],
                                            tolerance, first_frame_iterations, 1e-3)
            zr[b], ir[b], cr[b] = zb[0], ir[b] + ib[0], cb[0]
        Zs[rest], its[rest], conv[rest] = zr, ir, cr
    _repair_jumps(prob, Zs, its, conv, frames, Y, ok_all, tolerance, first_frame_iterations)
    Zs[frames] = prob.wrap(Zs[frames])
    Q = np.full((F, model.n_q), np.nan)
    Q[frames] = cmap.expand(Zs[frames])
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
    for s0 in range(0, frames.size, 256):           # chunks bound the Jacobian's memory on long trials
        fr = frames[s0:s0 + 256]
        r, J, _, _ = prob.evaluate(Zs[fr], Y[fr], ok_all[fr], jac=True)
        cost[fr] = np.einsum("ni,ni->n", r, r)
        if cmap.n_z:
            sv = np.linalg.svd(J, compute_uv=False)
            determined[fr] = sv[:, -1] > 1e-8 * np.maximum(sv[:, 0], 1e-300)
        else:
            determined[fr] = True
    return IKResult(model.coordinate_names, np.asarray(trial.time, float), Q, tuple(use), err, rms, mx, its, conv,
                    solvable, cost, _time.perf_counter() - t_start, determined, resid)
