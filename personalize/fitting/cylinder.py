r"""Circular cylinder fitting (knee axis on the posterior condyles, talar dome, shafts).

Model: an infinite circular cylinder with axis line :math:`\{p + t a\}`
(:math:`\|a\| = 1`) and radius :math:`R`.

Minimised quantity (orthogonal distance, robust-weighted):

.. math::

    \min_{p, a, R} \sum_i c_i w_i \bigl(\|(I - a a^T)(x_i - p)\| - R\bigr)^2 .

The axis is a point on a manifold (4 degrees of freedom for the line, plus
``R``): each step is taken in the local coordinates
``p' = p + s u + t v``, ``a' = normalise(a + alpha u + beta v)`` with ``(u, v, a)``
orthonormal, and ``p`` kept at the foot of the weighted centroid.  With
:math:`y = x - p`, :math:`h = y\cdot a`, :math:`n` the unit radial direction,
the analytic Jacobian is :math:`\partial r/\partial(s, t) = -(n\cdot u, n\cdot v)`,
:math:`\partial r/\partial(\alpha, \beta) = -h\,(n\cdot u, n\cdot v)`,
:math:`\partial r/\partial R = -1`.

Start: the axis is the direction most orthogonal to the surface normals
(smallest eigenvector of :math:`\sum c_i n_i n_i^T`; normals are estimated from
neighbourhoods when not given) -- the principal axis of the points is wrong for
arcs wider than about 120 degrees -- then a Taubin circle fit in the plane
orthogonal to it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .base import (DegenerateError, NotConvergedError, check_inputs, estimate_normals,
                   orthonormal_basis)
from .robust import em_lm

__all__ = ["CylinderFit", "fit_cylinder", "taubin_circle"]


@dataclass(frozen=True)
class CylinderFit:
    """Fitted cylinder.

    Attributes
    ----------
    point : (3,) ndarray
        Point on the axis: the foot of the (weighted) centroid of the points.
    axis : (3,) ndarray
        Unit axis direction; the sign is arbitrary (orient it with a hint).
    radius : float
    covariance : (7, 7) ndarray
        Covariance of ``(point (3), axis (3), radius)``; rank 5 (the point moves
        only across the axis, the axis only orthogonally to itself).
    rms : float
    inlier_weights : (N,) ndarray
    n_iterations : int
    converged : bool
    """

    point: np.ndarray
    axis: np.ndarray
    radius: float
    covariance: np.ndarray
    rms: float
    inlier_weights: np.ndarray = field(repr=False)
    n_iterations: int
    converged: bool

    @property
    def axis_sd(self) -> float:
        """Standard deviation of the axis direction (radians, RMS over the two tilt directions)."""
        return float(np.sqrt(np.trace(self.covariance[3:6, 3:6]) / 2.0))

    @property
    def point_sd(self) -> float:
        """Standard deviation of the axis position across the axis (RMS over two directions)."""
        return float(np.sqrt(np.trace(self.covariance[:3, :3]) / 2.0))

    def residuals(self, points) -> np.ndarray:
        """Signed orthogonal distances to the cylinder surface (positive outside), (N,)."""
        Y = np.asarray(points, float).reshape(-1, 3) - self.point
        Q = Y - np.outer(Y @ self.axis, self.axis)
        return np.linalg.norm(Q, axis=1) - self.radius


def taubin_circle(Y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Taubin algebraic circle fit to 2-D points ``Y`` (N, 2); returns (centre, radius)."""
    m = (w @ Y) / w.sum()
    Z0 = Y - m
    z = np.sum(Z0 * Z0, axis=1)
    zbar = (w @ z) / w.sum()
    sz = 2.0 * np.sqrt(zbar)
    Z = np.column_stack([(z - zbar) / sz, Z0])
    _, _, Vt = np.linalg.svd(np.sqrt(w)[:, None] * Z, full_matrices=False)
    B = Vt[-1]
    A0 = B[0] / sz
    if abs(A0) < 1e-12 * np.linalg.norm(B[1:]):
        raise DegenerateError("cylinder: cross-section is straight (infinite radius)")
    centre = -B[1:] / (2.0 * A0)
    return centre + m, float(np.sqrt(centre @ centre + zbar))


def _initial_axis(X, U, c):
    M = (c[:, None] * U).T @ U
    vals, vecs = np.linalg.eigh(M)
    return vecs[:, 0], vals


def _start(X, U, c, a):
    u, v = orthonormal_basis(a)
    Y2 = np.column_stack([X @ u, X @ v])
    cc, R = taubin_circle(Y2, c)
    p = cc[0] * u + cc[1] * v
    m = (c @ X) / c.sum()
    p = p + ((m - p) @ a) * a
    return p, a, R


def _cylinder_problem(X, c):
    m = (c @ X) / c.sum()

    def fun(x, jac):
        p, a, R = x
        Y = X - p
        h = Y @ a
        Q = Y - h[:, None] * a
        rho = np.sqrt(np.einsum("ij,ij->i", Q, Q))
        r = rho - R
        if not jac:
            return r, None
        u, v = orthonormal_basis(a)
        Nr = Q / np.maximum(rho, 1e-300)[:, None]
        nu, nv = Nr @ u, Nr @ v
        J = np.column_stack([-nu, -nv, -h * nu, -h * nv, -np.ones_like(r)])
        return r, J

    def retract(x, d):
        p, a, R = x
        u, v = orthonormal_basis(a)
        a2 = a + d[2] * u + d[3] * v
        a2 = a2 / np.linalg.norm(a2)
        p2 = p + d[0] * u + d[1] * v
        p2 = p2 + ((m - p2) @ a2) * a2      # keep the point at the centroid's foot
        return (p2, a2, R + d[4])

    return fun, retract


def fit_cylinder(points, normals=None, weights=None, *, robust: bool = True,
                 axis_hint=None, max_iter: int = 200,
                 require_convergence: bool = True) -> CylinderFit:
    r"""Fit a circular cylinder by robust orthogonal-distance least squares.

    Parameters
    ----------
    points : (N, 3) array_like
        Surface points (any unit; the project passes metres).  N >= 5.
    normals : (N, 3) array_like, optional
        Surface normals (sign ignored).  Estimated from 12 nearest neighbours
        when absent; they give the starting axis.
    weights : (N,) array_like, optional
        Non-negative prior weights.
    robust : bool, default True
        Gaussian-uniform mixture EM (True) or plain least squares (False).
    axis_hint : (3,) array_like, optional
        The returned axis is oriented to have a positive dot product with it.
    max_iter : int
    require_convergence : bool, default True

    Returns
    -------
    CylinderFit

    Raises
    ------
    TooFewPointsError, NonFiniteError, DegenerateError, NotConvergedError
    """
    X, U, c, frame = check_inputs(points, normals, weights, n_params=5, model="cylinder")
    sv = np.linalg.svd(np.sqrt(c)[:, None] * X, compute_uv=False)
    if sv[1] < 1e-6 * sv[0]:
        raise DegenerateError("cylinder: points are collinear")
    if U is None:
        # Normals of a subsample suffice for the starting axis (and keep large N
        # fast); neighbourhoods that do not look like a surface (scattered
        # clutter) are down-weighted in the starting axis and circle.
        rng = np.random.default_rng(0)
        n = X.shape[0]
        sub = np.sort(rng.choice(n, 600, replace=False)) if n > 600 else np.arange(n)
        Us, like = estimate_normals(X, query=sub, return_likeness=True)
        ws = c[sub] * like ** 2 if robust else c[sub]
        if not ws.sum() > 0:
            ws = c[sub]
        a0, _ = _initial_axis(X[sub], Us, ws)
        p0, a0, R0 = _start(X[sub], None, ws, a0)
        p0 = p0 + (((c @ X) / c.sum() - p0) @ a0) * a0
    else:
        a0, _ = _initial_axis(X, U, c)
        p0, a0, R0 = _start(X, U, c, a0)
    fun, retract = _cylinder_problem(X, c)
    sol = em_lm(fun, (p0, a0, R0), retract, prior_weights=c, robust=robust,
                max_iter=max_iter, model="cylinder")
    if require_convergence and not sol.converged:
        raise NotConvergedError(f"cylinder: no convergence in {max_iter} iterations")
    p, a, R = sol.params
    if not R > 0:
        raise DegenerateError("cylinder: non-positive radius")
    # Map the local covariance (s, t, alpha, beta, R) to (point, axis, radius),
    # in the basis the Jacobian was computed in.
    u, v = orthonormal_basis(a)
    sign = 1.0
    if axis_hint is not None and np.dot(a, np.asarray(axis_hint, float)) < 0:
        a, sign = -a, -1.0
    s = frame.scale
    G = np.zeros((7, 5))
    G[:3, 0], G[:3, 1] = u * s, v * s
    G[3:6, 2], G[3:6, 3] = sign * u, sign * v
    G[6, 4] = s
    # exactly determined fits carry an unknown (infinite) covariance; avoid inf * 0
    cov = (G @ sol.covariance @ G.T if np.all(np.isfinite(sol.covariance))
           else np.full((7, 7), np.inf))
    return CylinderFit(
        point=frame.back(p), axis=a, radius=float(R * s), covariance=cov,
        rms=sol.rms * s, inlier_weights=sol.weights,
        n_iterations=sol.n_iterations, converged=sol.converged,
    )
