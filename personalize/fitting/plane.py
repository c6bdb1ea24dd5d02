r"""Plane fitting (tibial plateau, condylar tangent planes, cut planes).

Model: the plane :math:`\{x : n\cdot(x - p) = 0\}`, :math:`\|n\| = 1`.

Minimised quantity (orthogonal distance, robust-weighted):

.. math::

    \min_{p, n} \sum_i c_i w_i \bigl(n\cdot(x_i - p)\bigr)^2 .

For fixed weights this has the closed-form solution ``p`` = weighted centroid,
``n`` = eigenvector of the smallest eigenvalue of the weighted scatter matrix,
so the M-step is exact (no iteration inside).  The covariance uses the local
parametrisation ``p' = p + s n``, ``n' = normalise(n + alpha u + beta v)`` with
Jacobian :math:`\partial r/\partial(s, \alpha, \beta) = (-1, (x-p)\cdot u, (x-p)\cdot v)`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .base import DegenerateError, NotConvergedError, check_inputs, orthonormal_basis
from .robust import posterior, sigma_now

__all__ = ["PlaneFit", "fit_plane"]


@dataclass(frozen=True)
class PlaneFit:
    """Fitted plane.

    Attributes
    ----------
    point : (3,) ndarray
        Weighted centroid of the inliers (lies on the plane).
    normal : (3,) ndarray
        Unit normal; oriented along the mean of the given normals, or the hint,
        otherwise arbitrary.
    covariance : (6, 6) ndarray
        Covariance of ``(point (3), normal (3))``, rank 3 (the point moves
        along the normal only, the normal only orthogonally to itself).
    rms : float
    inlier_weights : (N,) ndarray
    n_iterations : int
    converged : bool
    """

    point: np.ndarray
    normal: np.ndarray
    covariance: np.ndarray
    rms: float
    inlier_weights: np.ndarray = field(repr=False)
    n_iterations: int
    converged: bool

    @property
    def normal_sd(self) -> float:
        """Standard deviation of the normal direction (radians, RMS over two tilts)."""
        return float(np.sqrt(np.trace(self.covariance[3:, 3:]) / 2.0))

    def residuals(self, points) -> np.ndarray:
        """Signed distances ``n . (x - p)`` (N,)."""
        return (np.asarray(points, float).reshape(-1, 3) - self.point) @ self.normal


def _weighted_plane(X, W):
    m = (W @ X) / W.sum()
    Y = X - m
    vals, vecs = np.linalg.eigh((W[:, None] * Y).T @ Y)
    return m, vecs[:, 0], vals


def fit_plane(points, normals=None, weights=None, *, robust: bool = True,
              normal_hint=None, max_iter: int = 200,
              require_convergence: bool = True) -> PlaneFit:
    r"""Fit a plane by robust orthogonal-distance least squares.

    Parameters
    ----------
    points : (N, 3) array_like
        Points (any unit; the project passes metres).  N >= 3.
    normals : (N, 3) array_like, optional
        If given, only used to orient the result.
    weights : (N,) array_like, optional
        Non-negative prior weights.
    robust : bool, default True
        Gaussian-uniform mixture EM (True) or plain least squares (False).
    normal_hint : (3,) array_like, optional
        Orient the normal to have a positive dot product with it.

    Returns
    -------
    PlaneFit

    Raises
    ------
    TooFewPointsError, NonFiniteError, DegenerateError, NotConvergedError
    """
    X, U, c, frame = check_inputs(points, normals, weights, n_params=3, model="plane")
    m, n, vals = _weighted_plane(X, c)
    if vals[1] < 1e-12 * vals[2]:
        raise DegenerateError("plane: points are collinear; the plane is undetermined")
    w = np.ones_like(c)
    it, converged = 0, not robust
    if robust:
        r = (X - m) @ n
        sigma = max(1.4826 * float(np.median(np.abs(r[c > 0]))), 1e-9)
        u = 1.0 / max(float(np.ptp(r[c > 0])), 10.0 * sigma)
        pi = 0.8
        w = posterior(r, sigma, pi, u)
        for it in range(1, max_iter + 1):
            m2, n2, vals = _weighted_plane(X, c * w)
            if vals[1] < 1e-12 * vals[2]:
                raise DegenerateError("plane: inliers are collinear")
            step = np.linalg.norm(m2 - m) + min(np.linalg.norm(n2 - n), np.linalg.norm(n2 + n))
            m, n = m2, n2
            r = (X - m) @ n
            w_old = w
            for _ in range(4):
                W = c * w
                sigma = max(sigma_now(r, W), 1e-9)
                pi = float(np.clip(W.sum() / c.sum(), 0.05, 1 - 1e-6))
                w = posterior(r, sigma, pi, u)
            dw = float(np.max(np.abs(w - w_old)))
            tol = max(1e-9, 1e-2 * sigma / np.sqrt(max((c * w).sum(), 1.0)))
            if step < tol and dw < 1e-2:
                converged = True
                break
        if require_convergence and not converged:
            raise NotConvergedError(f"plane: no convergence in {max_iter} iterations")
        m, n, _ = _weighted_plane(X, c * w)
    W = c * w
    r = (X - m) @ n
    uu, vv = orthonormal_basis(n)
    J = np.column_stack([-np.ones_like(r), (X - m) @ uu, (X - m) @ vv])
    dof = W.sum() - 3
    s2 = (W @ (r * r)) / dof if dof > 0.5 else np.inf   # exactly determined: unknown
    try:
        cov_local = np.linalg.inv(J.T @ (W[:, None] * J))
        cov_local = np.full((3, 3), np.inf) if np.isinf(s2) else s2 * cov_local
    except np.linalg.LinAlgError as exc:
        raise DegenerateError("plane: singular normal equations") from exc
    hint = normal_hint
    if hint is None and U is not None:
        hint = c @ U
    sign = 1.0
    if hint is not None and np.dot(n, np.asarray(hint, float)) < 0:
        n, sign = -n, -1.0
    s = frame.scale
    G = np.zeros((6, 3))
    G[:3, 0] = sign * n * s       # p moves along the (unflipped) normal
    G[3:, 1], G[3:, 2] = sign * uu, sign * vv
    cov = G @ cov_local @ G.T if np.all(np.isfinite(cov_local)) else np.full((6, 6), np.inf)
    if np.any(np.isnan(cov)):
        raise NotConvergedError("plane: non-finite covariance")
    return PlaneFit(
        point=frame.back(m), normal=n, covariance=cov,
        rms=float(np.sqrt((W @ (r * r)) / W.sum())) * s, inlier_weights=w,
        n_iterations=it, converged=converged,
    )
