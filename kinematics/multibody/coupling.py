"""Couplings between generalized coordinates.

One mechanism for linear equalities: rows ``C q = d``.  A correlative degree
of freedom ``X = c0 + sum_i c_i Y_i`` (Pronost et al. 2010, eq. 2) and an
OpenSim CoordinateCouplerConstraint with a linear function are single rows
(``X - sum_i c_i Y_i = c0``).  IK enforces them exactly with the initial
projector of Raunhardt & Boulic (2007): the joint variation is restricted to
the null space of C,

    P0 = I - sum_k c'_k c'_k^T / |c'_k|^2   (c'_k = P0 c_k, Gram-Schmidt over the rows),

and the initial variation dq0 = C^+ (d - C q) restores the constraints (and
removes numerical drift).  Equivalently ``q = q_p + N z`` with N an
orthonormal basis of the null space (P0 = N N^T).

Linear inequalities ``G q <= h`` are kept as rows and enforced by IK's
active-set clamping loop.  Non-linear couplers ``q_dep = f(q_indep)``
(OpenSim CoordinateCouplerConstraint with a spline, the knee of the
correlative models) make the dependent coordinate a function of the others;
its chain rule d q_dep / d q_indep = f'(q_indep) enters IK's Jacobian.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from lowerlimb.errors import InputError
from kinematics.multibody.functions import Function, read_only

__all__ = [
    "LinearCoupling", "LinearInequalities", "CoordinateCoupler",
    "initial_projector", "restoring_variation", "null_space_parametrization",
]


@dataclass(frozen=True, eq=False)
class LinearCoupling:
    """Linear equality rows ``matrix @ q = rhs`` over named coordinates.

    Attributes
    ----------
    coordinates : tuple of str, length n (column names)
    matrix : ndarray (m, n)
    rhs : ndarray (m,)
    labels : tuple of str, length m (row names, e.g. the dependent coordinate)
    """

    coordinates: tuple[str, ...]
    matrix: np.ndarray
    rhs: np.ndarray
    labels: tuple[str, ...] = ()

    def __post_init__(self):
        C = np.atleast_2d(np.asarray(self.matrix, dtype=float))
        d = np.atleast_1d(np.asarray(self.rhs, dtype=float))
        if C.size == 0:
            C = np.zeros((0, len(self.coordinates)))
        if C.shape[1] != len(self.coordinates) or d.shape != (C.shape[0],):
            raise ValueError(f"coupling matrix {C.shape} / rhs {d.shape} do not match {len(self.coordinates)} coordinates")
        labels = tuple(self.labels) or tuple(f"row{i}" for i in range(C.shape[0]))
        object.__setattr__(self, "coordinates", tuple(self.coordinates))
        object.__setattr__(self, "matrix", read_only(C))
        object.__setattr__(self, "rhs", read_only(d))
        object.__setattr__(self, "labels", labels)

    @classmethod
    def correlative(cls, coordinates: Sequence[str], dependent: str, independent: Mapping[str, float],
                    intercept: float = 0.0) -> "LinearCoupling":
        """One row ``dependent = intercept + sum_i independent[i] * q_i`` (Pronost 2010 eq. 2)."""
        coordinates = tuple(coordinates)
        row = np.zeros(len(coordinates))
        row[coordinates.index(dependent)] = 1.0
        for name, c in independent.items():
            if name == dependent:
                raise ValueError(f"coordinate {name!r} cannot depend on itself")
            row[coordinates.index(name)] -= float(c)
        return cls(coordinates, row[None, :], [intercept], (dependent,))

    @property
    def n_rows(self) -> int:
        return self.matrix.shape[0]

    def over(self, coordinates: Sequence[str]) -> "LinearCoupling":
        """The same rows with columns re-ordered/extended to `coordinates` (absent columns are zero)."""
        coordinates = tuple(coordinates)
        C = np.zeros((self.n_rows, len(coordinates)))
        for j, name in enumerate(self.coordinates):
            if name not in coordinates:
                if np.any(self.matrix[:, j]):
                    raise ValueError(f"coupling uses coordinate {name!r} that is not in the target list")
                continue
            C[:, coordinates.index(name)] = self.matrix[:, j]
        return LinearCoupling(coordinates, C, self.rhs, self.labels)

    def without(self, coordinates) -> "LinearCoupling | None":
        """The rows that involve none of `coordinates` (None when no row is left)."""
        names = set(coordinates)
        cols = [i for i, c in enumerate(self.coordinates) if c in names]
        keep = ~np.any(self.matrix[:, cols] != 0, axis=1) if cols else np.ones(self.n_rows, bool)
        if not keep.any():
            return None
        return LinearCoupling(self.coordinates, self.matrix[keep], self.rhs[keep],
                              tuple(l for l, k in zip(self.labels, keep) if k))

    def stack(self, other: "LinearCoupling") -> "LinearCoupling":
        """Rows of both couplings (over the union of their coordinates, self's order first)."""
        names = list(self.coordinates) + [c for c in other.coordinates if c not in self.coordinates]
        a, b = self.over(names), other.over(names)
        return LinearCoupling(tuple(names), np.vstack([a.matrix, b.matrix]), np.concatenate([a.rhs, b.rhs]),
                              a.labels + b.labels)

    def residual(self, q) -> np.ndarray:
        """C q - d, shape (..., m)."""
        return np.asarray(q, float) @ self.matrix.T - self.rhs

    def projector(self) -> np.ndarray:
        """Raunhardt & Boulic's initial projector P0 (n, n) onto the null space of the rows."""
        return initial_projector(self.matrix, self.rhs)

    def restore(self, q) -> np.ndarray:
        """q + dq0 with dq0 = C^+ (d - C q): the smallest change that satisfies the rows."""
        q = np.asarray(q, float)
        return q + restoring_variation(self.matrix, self.rhs, q)


@dataclass(frozen=True, eq=False)
class LinearInequalities:
    """Rows ``matrix @ q <= rhs`` over named coordinates."""

    coordinates: tuple[str, ...]
    matrix: np.ndarray
    rhs: np.ndarray
    labels: tuple[str, ...] = ()

    def __post_init__(self):
        G = np.atleast_2d(np.asarray(self.matrix, dtype=float))
        h = np.atleast_1d(np.asarray(self.rhs, dtype=float))
        if G.shape[1] != len(self.coordinates) or h.shape != (G.shape[0],):
            raise ValueError("inequality matrix/rhs do not match the coordinates")
        object.__setattr__(self, "coordinates", tuple(self.coordinates))
        object.__setattr__(self, "matrix", read_only(G))
        object.__setattr__(self, "rhs", read_only(h))
        object.__setattr__(self, "labels", tuple(self.labels) or tuple(f"ineq{i}" for i in range(G.shape[0])))

    def over(self, coordinates: Sequence[str]) -> "LinearInequalities":
        c = LinearCoupling(self.coordinates, self.matrix, self.rhs, self.labels).over(coordinates)
        return LinearInequalities(c.coordinates, c.matrix, c.rhs, c.labels)


@dataclass(frozen=True, eq=False)
class CoordinateCoupler:
    """Dependent coordinate ``q[dependent] = function(q[independent...])`` (OpenSim CoordinateCouplerConstraint)."""

    dependent: str
    independent: tuple[str, ...]
    function: Function
    name: str = ""

    def __post_init__(self):
        object.__setattr__(self, "independent", tuple(self.independent))
        if self.function.n_inputs != len(self.independent):
            raise ValueError(f"coupler {self.name or self.dependent!r}: function of {self.function.n_inputs} inputs for "
                             f"{len(self.independent)} independent coordinates")


def initial_projector(C: np.ndarray, d: np.ndarray | None = None, tol: float = 1e-10) -> np.ndarray:
    """P0 = I - sum_k c'_k c'_k^T / |c'_k|^2 (Raunhardt & Boulic 2007, procedure init_projector).

    Rows are taken one at a time and projected on the current null space
    (c' = P0 c); a row with |c'| <= tol |c| is linearly dependent on earlier
    rows ("conflicting") and skipped.  Returns an (n, n) symmetric projector.
    """
    C = np.atleast_2d(np.asarray(C, float))
    n = C.shape[1]
    P = np.eye(n)
    for c in C:
        cp = P @ c
        nc = np.linalg.norm(cp)
        if nc <= tol * max(np.linalg.norm(c), 1e-300):
            continue
        u = cp / nc
        P = P - np.outer(u, u)
    return 0.5 * (P + P.T)


def restoring_variation(C: np.ndarray, d: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Initial joint variation dq0 = C^+ (d - C q) (minimum norm), for q of shape (n,) or (N, n)."""
    C = np.atleast_2d(np.asarray(C, float))
    if C.shape[0] == 0:
        return np.zeros_like(np.asarray(q, float))
    r = np.asarray(d, float) - np.asarray(q, float) @ C.T
    return r @ np.linalg.pinv(C, rcond=1e-10).T


def null_space_parametrization(C: np.ndarray, d: np.ndarray, source=None, tol: float = 1e-10):
    """Affine parametrisation q = q_p + N z of {q : C q = d}.

    Returns
    -------
    q_p : (n,) minimum-norm particular solution
    N : (n, n - rank) orthonormal null-space basis (N N^T = P0)

    Raises
    ------
    InputError
        If the rows are inconsistent (no q satisfies them).
    """
    C = np.atleast_2d(np.asarray(C, float))
    n = C.shape[1]
    if C.shape[0] == 0:
        return np.zeros(n), np.eye(n)
    U, s, Vt = np.linalg.svd(C)
    rank = int(np.sum(s > tol * max(s.max(), 1.0)))
    q_p = np.linalg.pinv(C, rcond=tol) @ np.asarray(d, float)
    if np.linalg.norm(C @ q_p - d) > 1e-8 * max(1.0, np.linalg.norm(d)):
        raise InputError(source, "linear coordinate couplings are inconsistent (no pose satisfies them all)")
    return q_p, Vt[rank:].T.copy()
