"""Prioritized inverse kinematics with linearly coupled joints.

The solver follows Baerlocher & Boulic (2004) and Raunhardt & Boulic (2007):
tasks are grouped into strict priority levels, each level acting only in the
null space of all higher levels, and "hard" linear constraints over the
coordinates act as a level of infinite priority in front of every task.

Model of one step from configuration ``q`` (n coordinates)
---------------------------------------------------------
Working set.  The rows ``A q = b`` of the working set are, in this order, the
user equalities ``c_i^T q = b_i`` and the inequalities ``g_j^T q <= h_j``
(user-defined first, then joint limits) clamped to their boundary during this
step.  A row dependent on earlier accepted rows is *conflicting* (or redundant)
and skipped: the first added wins.

Initial projector and initial variation::

    P_0  = I - sum_k  u_k u_k^T          (u_k: Gram-Schmidt of accepted rows,
                                           i.e. P_0 <- P_0 - P_0 c c^T P_0 / |P_0 c|^2)
    dq_0 = A^+ (b - A q)                  (minimum-norm variation restoring A q = b;
                                           removes numerical drift)

Priority levels ``i = 1..L`` with error ``e_i`` (m_i,) and Jacobian ``J_i``
(m_i, n), columns of non-recruited coordinates set to zero::

    Jh_i  = J_i P_{i-1}
    dq_i  = dq_{i-1} + Jh_i^{+lambda} (e_i - J_i dq_{i-1})
    P_i   = P_{i-1} - Jh_i^+ Jh_i

with the damped pseudo-inverse ``Jh^{+lambda} = V diag(s / (s^2 + lambda^2)) U^T``
(``Jh = U diag(s) V^T``) and the undamped, rank-revealing ``Jh^+ Jh = V_r V_r^T``
for the projector.  The step minimises, level after level,
``|e_i - J_i dq|^2 + lambda^2 |dq - dq_{i-1}|^2`` over the null space of the
levels above.

Clamping loop (Raunhardt & Boulic 2007, Fig. 2).  After computing ``dq`` the
trial configuration ``q + dq`` is checked against the user inequalities, then
the joint limits.  Among the violated ones, the one crossed first along the
step (smallest ``t = (h - g^T q) / g^T dq``, i.e. closest to the initial
configuration) is clamped (added to the working set as ``g^T q = h``) and the
step is recomputed, until nothing is violated.  A clamp dependent on the
working set is conflicting: it is skipped (the first added wins, reported in
`StepResult.conflicts`) and the step is then shortened to the largest
fraction that keeps every inequality satisfied (`StepResult.scaled`).

Recruiting levels: `kinematics.algorithms.recruiting`.

Tasks are plain callables ``task(q) -> (error (m,), jacobian (m, n))`` so the
solver is independent of the kinematic model.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from kinematics.algorithms.constraints import ConstraintBasis, ConstraintSet
from kinematics.algorithms.recruiting import check_recruiting, task_sets
from kinematics.algorithms.tasks import Task
from lowerlimb.errors import InputError

__all__ = ["StepResult", "SolveResult", "PrioritizedIK"]

_REL_RANK_TOL = 1e-10


@dataclass(frozen=True)
class StepResult:
    """One prioritized IK step.

    Attributes
    ----------
    q : ndarray (n,)            configuration after the step
    dq : ndarray (n,)           joint variation
    errors : ndarray (L,)       error norm of each level before the step
    clamped : tuple of str      inequalities clamped (working set additions)
    conflicts : tuple of str    constraints skipped because they conflicted (first added wins)
    clamp_iterations : int      number of solves in the clamping loop
    scaled : float              step scale (1 unless a conflict forced a feasibility cut)
    """

    q: np.ndarray
    dq: np.ndarray
    errors: np.ndarray
    clamped: tuple[str, ...]
    conflicts: tuple[str, ...]
    clamp_iterations: int
    scaled: float = 1.0


@dataclass(frozen=True)
class SolveResult:
    """Iterated IK: final ``q`` and per-iteration histories.

    errors : (K, L) error norm of each level at the start of each iteration
    step_norms : (K,) |dq| (rad / m mixed, as the coordinates)
    times : (K,) wall time of each iteration (s)
    """

    q: np.ndarray
    errors: np.ndarray
    step_norms: np.ndarray
    times: np.ndarray
    iterations: int
    converged: bool
    conflicts: tuple[str, ...] = field(default_factory=tuple)


class PrioritizedIK:
    """Prioritized IK with coupling constraints and clamped joint limits.

    Parameters
    ----------
    coordinate_names : sequence of str (n,)
    tasks : sequence of Task
    constraints : ConstraintSet or None
        Equalities (coupling) and user inequalities over the same coordinates.
    lower, upper : array_like (n,) or None
        Joint limits (rad or m); +-inf where unbounded.
    damping : float
        lambda of the damped pseudo-inverse (unit of the task error).
    check : bool
        Run `check_recruiting` and raise `RecruitingError` on violations.
    """

    def __init__(self, coordinate_names: Sequence[str], tasks: Sequence[Task],
                 constraints: ConstraintSet | None = None, lower=None, upper=None,
                 damping: float = 1e-3, check: bool = True):
        self.names = tuple(coordinate_names)
        n = self.n = len(self.names)
        if constraints is None:
            constraints = ConstraintSet.build(self.names, ())
        if constraints.coordinate_names != self.names:
            raise InputError("constraints", "constraint set built over different coordinates than the solver")
        self.constraints = constraints
        if not tasks:
            raise InputError("tasks", "no task given")
        self.report = check_recruiting(tasks, constraints)
        if check:
            self.report.raise_if_violated()
        index = {nm: i for i, nm in enumerate(self.names)}
        self.levels: list[list[tuple[Task, np.ndarray]]] = []
        for p in sorted({t.priority for t in tasks}):
            level = []
            for t in (t for t in tasks if t.priority == p):
                rec, _ = task_sets(t, self.names)
                mask = np.zeros(n, bool)
                mask[[index[c] for c in rec if c in index]] = True
                level.append((t, mask))
            self.levels.append(level)
        self.lower = np.full(n, -np.inf) if lower is None else np.asarray(lower, float).copy()
        self.upper = np.full(n, np.inf) if upper is None else np.asarray(upper, float).copy()
        if self.lower.shape != (n,) or self.upper.shape != (n,) or np.any(self.lower > self.upper):
            raise InputError("limits", f"lower/upper must have shape ({n},) with lower <= upper")
        self.damping = float(damping)
        # P0 of the user equalities is constant: build it once (first added wins).
        self._base = ConstraintBasis(n)
        self._base_conflicts = []
        for row, val, nm in zip(constraints.C, constraints.b, constraints.eq_names):
            if self._base.add(row, val) == "conflict":
                self._base_conflicts.append(nm)
        self._Z0 = self._base.nullspace()
        lim = np.flatnonzero(np.isfinite(self.lower))
        lim_u = np.flatnonzero(np.isfinite(self.upper))
        # joint limits as rows g^T q <= h: -q_i <= -lo_i and q_i <= up_i
        self._lim_idx = np.concatenate([lim, lim_u])
        self._lim_sign = np.concatenate([-np.ones(len(lim)), np.ones(len(lim_u))])
        self._lim_h = np.concatenate([-self.lower[lim], self.upper[lim_u]])
        self._lim_names = tuple([f"{self.names[i]} >= lower limit" for i in lim]
                                + [f"{self.names[i]} <= upper limit" for i in lim_u])

    @classmethod
    def from_model(cls, model, tasks: Sequence[Task], damping: float = 0.05, check: bool = True) -> "PrioritizedIK":
        """Solver over a `Model`: its couplings and inequalities, and the ranges of its clamped coordinates."""
        cons = ConstraintSet.from_model(model)
        clamped = np.array([c.clamped for c in model.coordinates])
        lower = np.where(clamped, model.lower, -np.inf)
        upper = np.where(clamped, model.upper, np.inf)
        return cls(model.coordinate_names, tasks, cons, lower, upper, damping=damping, check=check)

    # -- core -----------------------------------------------------------------
    def _evaluate(self, q):
        out, norms = [], []
        for level in self.levels:
            es, Js, sq = [], [], 0.0
            for task, mask in level:
                e, J = task.function(q)
                e = np.atleast_1d(np.asarray(e, float))
                J = np.atleast_2d(np.asarray(J, float)) * mask
                ne = np.linalg.norm(e)
                sq += ne * ne
                if task.max_error is not None and ne > task.max_error:
                    e = e * (task.max_error / ne)
                es.append(e)
                Js.append(J)
            out.append((np.concatenate(es), np.vstack(Js)))
            norms.append(np.sqrt(sq))
        return out, np.array(norms)

    def _prioritized(self, evaluated, Z0, dq0):
        """Recursive null-space projection over the priority levels (see module docstring).

        Projectors are carried as orthonormal bases of their range, ``P_i = Z_i Z_i^T``
        (Z_i: n x r_i), so each level decomposes the reduced Jacobian ``J_i Z_{i-1}``
        (m_i x r_{i-1}): every equality removes one column, which is why the coupled
        solver is cheaper per iteration than the uncoupled one.
        """
        dq = dq0.copy()
        Z = Z0
        lam2 = self.damping ** 2
        for e, J in evaluated:
            if Z.shape[1] == 0:
                break
            A = J @ Z
            U, s, Wt = np.linalg.svd(A, full_matrices=True)
            # singular values at round-off level are directions already removed: drop them
            # (damping alone would amplify their noise by s / lambda^2)
            rank = int(np.sum(s > _REL_RANK_TOL * max(1.0, s[0] if s.size else 0.0)))
            if rank == 0:
                continue
            r = e - J @ dq
            dq = dq + Z @ (Wt[:rank].T @ ((s[:rank] / (s[:rank] ** 2 + lam2)) * (U[:, :rank].T @ r)))
            Z = Z @ Wt[rank:].T
        return dq

    def step(self, q: np.ndarray) -> StepResult:
        """One IK step with the clamping loop.  ``q`` (n,) -> `StepResult`."""
        q = np.asarray(q, float)
        evaluated, errors = self._evaluate(q)
        cons = self.constraints
        basis = self._base
        Z0 = self._Z0
        dq0 = basis.restoring_variation(q)
        clamped_user = np.zeros(len(cons.h), bool)
        clamped_lim = np.zeros(len(self._lim_h), bool)
        clamped, conflicts = [], list(self._base_conflicts)
        iterations = 0
        while True:
            iterations += 1
            dq = self._prioritized(evaluated, Z0, dq0)
            added = False
            for kind in ("user", "limit"):  # user inequalities are checked before joint limits
                if kind == "user":
                    gq, gd = cons.G @ q, cons.G @ dq
                    h, done, names = cons.h, clamped_user, cons.in_names
                else:
                    gq = self._lim_sign * q[self._lim_idx]
                    gd = self._lim_sign * dq[self._lim_idx]
                    h, done, names = self._lim_h, clamped_lim, self._lim_names
                excess = gq + gd - h
                viol = np.flatnonzero((excess > 1e-12 * np.maximum(1.0, np.abs(h))) & ~done)
                if not len(viol):
                    continue
                # the violated constraint closest to the initial configuration
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = np.where(gd[viol] > 0, (h[viol] - gq[viol]) / gd[viol], 0.0)
                j = viol[int(np.argmin(np.clip(t, 0.0, None)))]
                done[j] = True
                if kind == "user":
                    row = cons.G[j]
                else:
                    row = np.zeros(self.n)
                    row[self._lim_idx[j]] = self._lim_sign[j]
                if basis is self._base:
                    basis = basis.copy()
                status = basis.add(row, h[j])
                if status == "accepted":
                    clamped.append(names[j])
                    Z0 = basis.nullspace()
                    dq0 = basis.restoring_variation(q)
                    added = True
                    break
                conflicts.append(names[j])  # first added wins: later, conflicting clamp skipped
                added = True  # re-check the others with the same dq
                break
            if not added:
                break
        scale = 1.0
        if conflicts[len(self._base_conflicts):]:
            scale = self._feasible_fraction(q, dq)
            dq = dq * scale
        return StepResult(q + dq, dq, errors, tuple(clamped), tuple(conflicts), iterations, scale)

    def _feasible_fraction(self, q, dq):
        """Largest alpha in [0, 1] keeping q + alpha dq inside every inequality (when q is inside)."""
        G = np.vstack([self.constraints.G, np.zeros((len(self._lim_h), self.n))])
        G[len(self.constraints.h) + np.arange(len(self._lim_h)), self._lim_idx] = self._lim_sign
        h = np.concatenate([self.constraints.h, self._lim_h])
        slack, rate = h - G @ q, G @ dq
        moving = (rate > 0) & (slack >= 0)
        if not np.any(moving):
            return 1.0
        return float(np.clip(np.min(slack[moving] / rate[moving]), 0.0, 1.0))

    def solve(self, q0: np.ndarray, max_iterations: int = 50, tol: float = 1e-6) -> SolveResult:
        """Iterate `step` until every level's error is below ``tol`` or the step vanishes."""
        q = np.asarray(q0, float).copy()
        errs, norms, times, conflicts = [], [], [], set()
        converged = False
        for _ in range(max_iterations):
            t0 = time.perf_counter()
            res = self.step(q)
            times.append(time.perf_counter() - t0)
            errs.append(res.errors)
            norms.append(np.linalg.norm(res.dq))
            conflicts.update(res.conflicts)
            q = res.q
            if np.all(res.errors < tol) or norms[-1] < 1e-12:
                converged = bool(np.all(res.errors < tol))
                break
        return SolveResult(q, np.array(errs), np.array(norms), np.array(times), len(errs), converged,
                           tuple(sorted(conflicts)))
