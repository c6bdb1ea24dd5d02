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

Recruiting levels (Raunhardt & Boulic 2007, eqs. 3-5), for priority levels
``a`` above ``b``::

    (3)  Rec(T_b) & Anc(T_a)  <=  Rec(T_a)
    (4)  (Rec(T_b) | Coup(Rec(T_b))) & (Anc(T_a) | Coup(Rec(T_a)))  <=  Rec(T_a)
    (5)  U_i Coup(Rec(T_i))  <=  U_i Rec(T_i)

``Coup(R)`` is the set of coordinates coupled to ``R`` through the constraint
graph (transitively).  `check_recruiting` reports every violation.

Tasks are plain callables ``task(q) -> (error (m,), jacobian (m, n))`` so the
solver is independent of the kinematic model.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from kinematics.multibody.coupling import LinearCoupling, LinearInequalities, null_space_parametrization
from lowerlimb.errors import InputError

__all__ = [
    "LinearConstraint",
    "ConstraintSet",
    "Task",
    "RecruitingError",
    "RecruitingReport",
    "check_recruiting",
    "StepResult",
    "SolveResult",
    "PrioritizedIK",
]

TaskFunction = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

_REL_RANK_TOL = 1e-10


class RecruitingError(InputError):
    """A task set violates the recruiting-level rules (eqs. 3-5 of the seed)."""


@dataclass(frozen=True)
class LinearConstraint:
    """One linear constraint ``sum_k coefficients[k] * q[k]  (= or <=)  value``.

    Parameters
    ----------
    coefficients : mapping of coordinate name -> float
        Non-zero coefficients (dimensionless for angle-angle couplings).
    value : float
        Right-hand side, in the unit of the combination (rad or m).
    kind : {"eq", "le"}
        Equality ``c^T q = b`` or inequality ``c^T q <= b``.
    name : str
        Label used in reports.
    """

    coefficients: Mapping[str, float]
    value: float = 0.0
    kind: str = "eq"
    name: str = ""

    @staticmethod
    def ratio(a: str, b: str, k: float, name: str = "") -> "LinearConstraint":
        """Equality ``q[a] = k q[b]`` (coupling with coefficient ``k``)."""
        return LinearConstraint({a: 1.0, b: -float(k)}, 0.0, "eq", name or f"{a}={k:g}*{b}")

    @staticmethod
    def band(a: str, b: str, k: float, width: float, name: str = "") -> tuple["LinearConstraint", "LinearConstraint"]:
        """Two inequalities ``|q[a] - k q[b]| <= width`` (relaxed coupling)."""
        nm = name or f"{a}~{k:g}*{b}"
        return (LinearConstraint({a: 1.0, b: -float(k)}, float(width), "le", nm + "<="),
                LinearConstraint({a: -1.0, b: float(k)}, float(width), "le", nm + ">="))


@dataclass(frozen=True)
class ConstraintSet:
    """Linear equalities ``C q = b`` and inequalities ``G q <= h`` over named coordinates.

    Build with `ConstraintSet.build`, which validates names and checks the
    equalities for consistency.

    Attributes
    ----------
    coordinate_names : tuple of str, (n,)
    C : ndarray, (m_eq, n);  b : ndarray, (m_eq,)
    G : ndarray, (m_in, n);  h : ndarray, (m_in,)
    eq_names, in_names : tuple of str
    """

    coordinate_names: tuple[str, ...]
    C: np.ndarray
    b: np.ndarray
    G: np.ndarray
    h: np.ndarray
    eq_names: tuple[str, ...]
    in_names: tuple[str, ...]

    @classmethod
    def build(cls, coordinate_names: Sequence[str], constraints: Sequence[LinearConstraint] = (),
              *, on_conflict: str = "raise", source: str = "constraints") -> "ConstraintSet":
        """Validate and assemble constraints.

        Parameters
        ----------
        coordinate_names : sequence of str
        constraints : sequence of LinearConstraint
        on_conflict : {"raise", "first_wins"}
            An equality inconsistent with earlier ones raises `InputError`
            ("raise") or is kept and later skipped by the solver ("first_wins").

        Raises
        ------
        InputError
            Unknown coordinate, bad kind, non-finite or all-zero coefficients,
            inconsistent equalities (with ``on_conflict="raise"``).
        """
        names = tuple(coordinate_names)
        index = {nm: i for i, nm in enumerate(names)}
        n = len(names)
        if on_conflict not in ("raise", "first_wins"):
            raise InputError(source, f"on_conflict must be 'raise' or 'first_wins', not {on_conflict!r}")
        eq_rows, eq_b, eq_names, in_rows, in_h, in_names = [], [], [], [], [], []
        for k, con in enumerate(constraints):
            label = con.name or f"constraint #{k}"
            if con.kind not in ("eq", "le"):
                raise InputError(source, f"{label}: kind must be 'eq' or 'le', not {con.kind!r}")
            row = np.zeros(n)
            for coord, coef in con.coefficients.items():
                if coord not in index:
                    raise InputError(source, f"{label}: coordinate {coord!r} does not exist in the model")
                if not np.isfinite(coef):
                    raise InputError(source, f"{label}: coefficient of {coord!r} is not finite")
                row[index[coord]] += float(coef)
            if not np.any(row) or not np.isfinite(con.value):
                raise InputError(source, f"{label}: all coefficients are zero or the value is not finite")
            if con.kind == "eq":
                eq_rows.append(row), eq_b.append(float(con.value)), eq_names.append(label)
            else:
                in_rows.append(row), in_h.append(float(con.value)), in_names.append(label)
        C = np.array(eq_rows, float).reshape(-1, n)
        b = np.array(eq_b, float)
        if on_conflict == "raise" and len(C):
            basis = _Basis(n)
            for row, val, label in zip(C, b, eq_names):
                status = basis.add(row, val)
                if status == "conflict":
                    raise InputError(source, f"equality {label!r} is inconsistent with the equalities before it "
                                     "(linearly dependent with a different right-hand side)")
        return cls(names, C, b, np.array(in_rows, float).reshape(-1, n), np.array(in_h, float),
                   tuple(eq_names), tuple(in_names))

    @classmethod
    def from_model(cls, model, extra: Sequence[LinearConstraint] = (), *, on_conflict: str = "raise") -> "ConstraintSet":
        """Constraints stored on a `kinematics.multibody.model.Model` (``couplings``, ``inequalities``) plus `extra`."""
        names = model.coordinate_names
        rows = []
        for lin, kind in ((model.couplings, "eq"), (model.inequalities, "le")):
            if lin is None:
                continue
            for row, val, label in zip(lin.matrix, lin.rhs, lin.labels):
                rows.append(LinearConstraint({names[i]: row[i] for i in np.flatnonzero(row)}, float(val), kind, label))
        return cls.build(names, [*rows, *extra], on_conflict=on_conflict, source=f"model {model.name!r}")

    def as_linear(self) -> tuple[LinearCoupling | None, LinearInequalities | None]:
        """The same rows as the shared containers of `kinematics.multibody.coupling` (for `Model.replace`)."""
        eq = LinearCoupling(self.coordinate_names, self.C, self.b, self.eq_names) if len(self.b) else None
        ineq = (LinearInequalities(self.coordinate_names, self.G, self.h, self.in_names) if len(self.h) else None)
        return eq, ineq

    def coupled_groups(self) -> list[set[int]]:
        """Connected components (coordinate indices) of the constraint graph."""
        parent = list(range(len(self.coordinate_names)))

        def find(i):
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for row in np.vstack([self.C, self.G]):
            idx = np.flatnonzero(row)
            for j in idx[1:]:
                parent[find(j)] = find(idx[0])
        groups: dict[int, set[int]] = {}
        for i in range(len(parent)):
            groups.setdefault(find(i), set()).add(i)
        return [g for g in groups.values() if len(g) > 1]

    def equality_residual(self, q: np.ndarray) -> np.ndarray:
        """``C q - b`` (m_eq,) in the unit of each row."""
        return self.C @ q - self.b

    def inequality_excess(self, q: np.ndarray) -> np.ndarray:
        """``G q - h`` (m_in,); positive entries are violations."""
        return self.G @ q - self.h


class _Basis:
    """Orthonormal basis of accepted constraint rows, built by Gram-Schmidt.

    Implements the seed's ``init_projector``: a row whose component outside the
    span of the accepted rows vanishes is conflicting (different right-hand
    side) or redundant, and is skipped: the first added wins.
    """

    def __init__(self, n: int):
        self.n = n
        self.Q = np.zeros((0, n))
        self.rows = np.zeros((0, n))
        self.values = np.zeros(0)
        self._pinv = None

    def copy(self) -> "_Basis":
        other = _Basis(self.n)
        other.Q, other.rows, other.values = self.Q.copy(), self.rows.copy(), self.values.copy()
        return other

    def add(self, row: np.ndarray, value: float) -> str:
        scale = np.linalg.norm(row)
        r = row - self.Q.T @ (self.Q @ row)
        r = r - self.Q.T @ (self.Q @ r)          # re-orthogonalise (stability)
        if np.linalg.norm(r) <= 1e-9 * scale:
            if len(self.rows):
                coef, *_ = np.linalg.lstsq(self.rows.T, row, rcond=None)
                implied = coef @ self.values
            else:
                implied = 0.0
            return "redundant" if abs(implied - value) <= 1e-9 * max(1.0, abs(value)) else "conflict"
        self.Q = np.vstack([self.Q, r / np.linalg.norm(r)])
        self.rows = np.vstack([self.rows, row])
        self.values = np.append(self.values, value)
        return "accepted"

    def nullspace(self) -> np.ndarray:
        """Orthonormal basis Z (n, n - k) of the range of ``P_0`` (``P_0 = Z Z^T``).

        Uses the shared coupling mechanism (`kinematics.multibody.coupling`) on the accepted rows.
        """
        if not len(self.rows):
            return np.eye(self.n)
        return null_space_parametrization(self.rows, self.values)[1]

    def restoring_variation(self, q: np.ndarray) -> np.ndarray:
        """Minimum-norm ``dq_0 = A^+ (b - A q)`` over the accepted rows (n,).

        Same as `kinematics.multibody.coupling.restoring_variation`, with ``A^+`` cached:
        the basis of the user equalities is reused by every step.
        """
        if not len(self.rows):
            return np.zeros(self.n)
        if self._pinv is None or self._pinv.shape[1] != len(self.rows):
            self._pinv = np.linalg.pinv(self.rows, rcond=1e-10)
        return self._pinv @ (self.values - self.rows @ q)


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


@dataclass(frozen=True)
class RecruitingReport:
    """Result of `check_recruiting`: ``violations`` is a tuple of one-line messages."""

    violations: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.violations

    def raise_if_violated(self, source: str = "tasks") -> None:
        if self.violations:
            raise RecruitingError(source, "recruiting-level rules violated: " + "; ".join(self.violations))


def _task_sets(task: Task, names: Sequence[str]) -> tuple[set[str], set[str]]:
    anc = set(task.ancestors) if task.ancestors is not None else set(names)
    rec = set(task.recruited) if task.recruited is not None else set(anc)
    return rec, anc


def check_recruiting(tasks: Sequence[Task], constraints: ConstraintSet) -> RecruitingReport:
    """Check the recruiting-level conditions (eqs. 3-5 of Raunhardt & Boulic 2007).

    For every pair of levels ``a`` (higher priority) and ``b`` (lower)::

        (3) Rec_b & Anc_a <= Rec_a
        (4) (Rec_b | Coup(Rec_b)) & (Anc_a | Coup(Rec_a)) <= Rec_a
        (5) U Coup(Rec_i) <= U Rec_i

    Rec, Anc of a level are the unions over its tasks.  Coup(R) contains the
    coordinates linked to R through the constraint graph (equalities and user
    inequalities, transitively), R excluded.
    """
    names = constraints.coordinate_names
    known = set(names)
    violations = []
    for t in tasks:
        for label, group in (("recruited", t.recruited), ("ancestors", t.ancestors)):
            missing = sorted(set(group or ()) - known)
            if missing:
                violations.append(f"task {t.name!r}: {label} coordinate(s) {missing[:5]} do not exist")
    if violations:
        return RecruitingReport(tuple(violations))
    groups = [{names[i] for i in g} for g in constraints.coupled_groups()]

    def coup(rec: set[str]) -> set[str]:
        out = set()
        for g in groups:
            if g & rec:
                out |= g
        return out - rec

    levels: dict[int, tuple[set[str], set[str], list[str]]] = {}
    for t in tasks:
        rec, anc = _task_sets(t, names)
        r, a, nm = levels.setdefault(t.priority, (set(), set(), []))
        r |= rec
        a |= anc
        nm.append(t.name)
    order = sorted(levels)

    def show(s):
        s = sorted(s)
        return str(s[:4])[:-1] + (", ...]" if len(s) > 4 else "]")

    for ia, pa in enumerate(order):
        rec_a, anc_a, names_a = levels[pa]
        for pb in order[ia + 1:]:
            rec_b, anc_b, names_b = levels[pb]
            bad3 = (rec_b & anc_a) - rec_a
            if bad3:
                violations.append(f"eq. (3): level {pb} {names_b} recruits {show(bad3)} which are ancestors "
                                  f"of level {pa} {names_a} but not recruited by it")
            bad4 = ((rec_b | coup(rec_b)) & (anc_a | coup(rec_a))) - rec_a - bad3
            if bad4:
                violations.append(f"eq. (4): through coupling, level {pb} {names_b} moves {show(bad4)} which "
                                  f"level {pa} {names_a} reaches but does not recruit")
    all_rec = set().union(*(levels[p][0] for p in order)) if order else set()
    bad5 = coup(all_rec) - all_rec
    if bad5:
        violations.append(f"eq. (5): coordinates {show(bad5)} are coupled to recruited ones but recruited by no task")
    return RecruitingReport(tuple(violations))


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
                rec, _ = _task_sets(t, self.names)
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
        self._base = _Basis(n)
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
