"""Parametrisation of the admissible coordinates: every equality holds exactly.

Model
-----
::

    q_R = q_p + N z                (linear couplings C q = d and locked coordinates;
                                    N N^T = P0, Raunhardt & Boulic's initial projector)
    q_D = f(q_I)                   (non-linear couplers: dependent coordinates)

q_R are the coordinates that no coupler drives, q_D the coupler-dependent
ones; the coordinate limits and linear inequalities ``G q <= h`` become rows
``A z <= b`` over the free parameters z.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from kinematics.multibody.coupling import null_space_parametrization
from kinematics.multibody.model import Model
from lowerlimb.errors import InputError

__all__ = ["CoordinateMap", "coordinate_map"]


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
