"""Named linear constraints over coordinates: equalities ``C q = b`` and inequalities ``G q <= h``.

`ConstraintSet.build` validates the rows (names, finite non-zero coefficients)
and checks the equalities for consistency with `ConstraintBasis`, the
Gram-Schmidt basis of accepted rows behind Raunhardt & Boulic's initial
projector ``P_0 = I - sum_k u_k u_k^T``: a row dependent on earlier accepted
rows is conflicting (other right-hand side) or redundant, and the first added wins.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from kinematics.multibody.coupling import LinearCoupling, LinearInequalities, null_space_parametrization
from lowerlimb.errors import InputError

__all__ = ["LinearConstraint", "ConstraintSet", "ConstraintBasis"]


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
            basis = ConstraintBasis(n)
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


class ConstraintBasis:
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

    def copy(self) -> "ConstraintBasis":
        other = ConstraintBasis(self.n)
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

