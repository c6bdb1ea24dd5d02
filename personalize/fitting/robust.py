r"""Robust geometric least squares: EM over a Gaussian-uniform mixture + Levenberg-Marquardt.

Model for the signed geometric residuals :math:`r_i(\theta)` of a fitted surface:

.. math::

    p(r_i) = \pi\,\mathcal N(r_i; 0, \sigma^2) + (1 - \pi)\,u ,

a Gaussian for points on the surface (segmentation noise) and a uniform density
``u`` over the residual range for points that do not belong (neck, fovea,
neighbouring bone), as in the probabilistic superquadric recovery of Liu et al.
(CVPR 2022).  Generalised EM alternates

* E-step: posterior inlier probability
  :math:`w_i = \pi\mathcal N(r_i;0,\sigma^2) / p(r_i)`;
* M-step: one Levenberg-Marquardt step on :math:`\sum_i c_i w_i r_i(\theta)^2`
  (``c_i`` are prior weights) with the analytic Jacobian, then
  :math:`\sigma^2 = \sum c_i w_i r_i^2 / \sum c_i w_i`, :math:`\pi = \sum c_i w_i / \sum c_i`.

With ``robust=False`` the same loop is plain (prior-weighted) least squares.
The covariance at the solution is the Gauss-Newton one,
:math:`\hat\sigma^2 (J^T W J)^{-1}` with
:math:`\hat\sigma^2 = \sum W_i r_i^2 / (\sum W_i - P)`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .base import NotConvergedError

__all__ = ["SolverResult", "em_lm"]

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


@dataclass(frozen=True)
class SolverResult:
    """Outcome of `em_lm` in the local parametrisation of the model."""

    params: object
    residuals: np.ndarray       # (N,) at the solution
    jacobian: np.ndarray        # (N, P) local Jacobian at the solution
    weights: np.ndarray         # (N,) posterior inlier probabilities (ones if not robust)
    sigma: float                # inlier residual standard deviation
    inlier_fraction: float
    covariance: np.ndarray      # (P, P) in local coordinates
    n_iterations: int
    converged: bool
    nll: float                  # mixture negative log-likelihood (comparable for equal u)

    @property
    def rms(self) -> float:
        w = self.weights
        return float(np.sqrt((w @ self.residuals ** 2) / max(w.sum(), 1e-300)))


def posterior(r: np.ndarray, sigma: float, pi: float, u: float) -> np.ndarray:
    """Posterior inlier probability under the Gaussian-uniform mixture (log-domain)."""
    log_in = np.log(pi) - 0.5 * (r / sigma) ** 2 - np.log(sigma) - _LOG_SQRT_2PI
    log_out = np.log1p(-pi) + np.log(u)
    # logistic of the log-odds via tanh: stable for any magnitude, numpy only
    return 0.5 * (1.0 + np.tanh(0.5 * (log_in - log_out)))


def weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """Median of ``x`` under non-negative weights ``w``."""
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cw, 0.5 * cw[-1])])


def sigma_now(r, W):
    return float(np.sqrt((W @ (r * r)) / max(W.sum(), 1e-300)))


def em_lm(
    fun: Callable,
    x0,
    retract: Callable,
    *,
    prior_weights: np.ndarray,
    robust: bool = True,
    max_iter: int = 200,
    xtol: float = 1e-9,
    wtol: float = 1e-2,
    sigma_floor: float = 1e-9,
    min_inlier_fraction: float = 0.05,
    outlier_density: float | None = None,
    sigma0: float | None = None,
    pi0: float = 0.8,
    sigma_max: float = np.inf,
    model: str = "fit",
) -> SolverResult:
    """Minimise robustly with EM + Levenberg-Marquardt.

    Parameters
    ----------
    fun : callable
        ``fun(x, jac) -> (r, J)``: signed residuals (N,) and, if ``jac``, the
        Jacobian (N, P) with respect to a local step at ``x``.
    x0 : object
        Starting parameters (any structure ``retract`` understands).
    retract : callable
        ``retract(x, delta) -> x_new`` applies a local step (P,) (manifold update).
    prior_weights : (N,) ndarray
        Non-negative prior weights ``c_i``.
    robust : bool
        Use the Gaussian-uniform mixture (True) or plain least squares (False).
    max_iter : int
        Maximum number of EM/LM iterations.
    xtol : float
        Convergence when the step norm falls below ``max(xtol, 0.01 sigma /
        sqrt(sum W))`` -- one hundredth of the statistical precision of a
        parameter in normalised units --
    wtol : float
        ... and the largest change in posterior weight is below ``wtol``.
    sigma_floor : float
        Lower bound of the inlier scale (noise-free data).
    min_inlier_fraction : float
        Lower bound of ``pi``.
    outlier_density : float, optional
        Uniform outlier density ``u`` (1 / length); default 1 / span of the
        starting residuals.  Fix it to compare likelihoods between restarts.
    sigma0, pi0 : float, optional
        Starting inlier scale (default: weighted MAD of the starting residuals)
        and inlier fraction.
    sigma_max : float
        Cap on the inlier scale (normalised units).  A cap stops the mixture from
        explaining heavy clutter as one wide Gaussian during restarts.
    model : str
        Name used in error messages.

    Returns
    -------
    SolverResult
        Parameters, residuals, Jacobian, posterior weights, inlier scale and
        fraction, covariance (local coordinates), iterations, convergence flag
        and the mixture negative log-likelihood.

    Raises
    ------
    NotConvergedError
        If residuals become non-finite or the normal equations are singular.
    """
    c = prior_weights
    x = x0
    r, J = fun(x, True)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        raise NotConvergedError(f"{model}: non-finite residuals at the starting estimate")
    n_par = J.shape[1]
    active = c > 0
    if robust:
        if sigma0 is None:
            sigma = max(1.4826 * weighted_median(np.abs(r[active]), c[active]), sigma_floor)
        else:
            sigma = max(float(sigma0), sigma_floor)
        sigma = min(sigma, sigma_max)
        span = float(np.ptp(r[active]))
        u = 1.0 / max(span, 10.0 * sigma) if outlier_density is None else outlier_density
        pi = float(pi0)
        w = posterior(r, sigma, pi, u)
    else:
        w = np.ones_like(r)
    lam = 1e-4
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        W = c * w
        cost = W @ (r * r)
        A = J.T @ (W[:, None] * J)
        g = J.T @ (W * r)
        dA = np.diag(A).copy()
        dA[dA <= 0] = 1e-12
        step_ok = False
        for _ in range(12):
            try:
                delta = np.linalg.solve(A + lam * np.diag(dA), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            x_new = retract(x, delta)
            r_new, J_new = fun(x_new, True)
            if np.all(np.isfinite(r_new)):
                cost_new = W @ (r_new * r_new)
                if cost_new <= cost * (1 + 1e-12):
                    step_ok = True
                    break
            lam *= 10.0
        if step_ok:
            x, r, J = x_new, r_new, J_new
            lam = max(lam * 0.2, 1e-10)
            step = float(np.linalg.norm(delta))
        else:
            step = 0.0
        if not np.all(np.isfinite(J)):
            raise NotConvergedError(f"{model}: non-finite Jacobian during refinement")
        dw = 0.0
        if robust:
            # A few 1-D mixture EM sweeps at fixed geometry: sigma and pi converge
            # linearly, and these sweeps are much cheaper than geometric steps.
            w_old = w
            r2 = r * r
            for _ in range(4):
                Wa = c * w
                sigma_old, pi_old = sigma, pi
                sigma = min(max(float(np.sqrt((Wa @ r2) / max(Wa.sum(), 1e-300))), sigma_floor),
                            sigma_max)
                pi = float(np.clip(Wa.sum() / c.sum(), min_inlier_fraction, 1.0 - 1e-6))
                w = posterior(r, sigma, pi, u)
                if abs(sigma - sigma_old) < 1e-4 * sigma and abs(pi - pi_old) < 1e-5:
                    break
            dw = float(np.max(np.abs(w - w_old)))
        # Stop when the step is negligible against the statistical precision
        # (EM converges linearly in pi and sigma; chasing them further is wasted work).
        tol = max(xtol, 1e-2 * sigma_now(r, c * w) / np.sqrt(max((c * w).sum(), 1.0)))
        if step < tol and dw < wtol:
            converged = True
            break
    W = c * w
    A = J.T @ (W[:, None] * J)
    dof = W.sum() - n_par
    # Exactly determined (e.g. a RANSAC minimal sample): the residual variance,
    # hence the covariance, is unknown -> reported as infinite, never NaN.
    s2 = (W @ (r * r)) / dof if dof > 0.5 else np.inf
    try:
        cov = np.full((n_par, n_par), np.inf) if np.isinf(s2) else s2 * np.linalg.inv(A)
    except np.linalg.LinAlgError as exc:
        raise NotConvergedError(f"{model}: singular normal equations at the solution") from exc
    if robust:
        lik = pi * np.exp(-0.5 * (r / sigma) ** 2) / (sigma * np.sqrt(2 * np.pi)) + (1 - pi) * u
        nll = float(-(c @ np.log(np.maximum(lik, 1e-300))))
    else:
        nll = float(0.5 * (c @ (r * r)))
    if np.any(np.isnan(cov)):
        raise NotConvergedError(f"{model}: non-finite covariance at the solution")
    return SolverResult(
        params=x, residuals=r, jacobian=J, weights=w,
        sigma=float(np.sqrt((W @ (r * r)) / W.sum())),
        inlier_fraction=float(W.sum() / c.sum()),
        covariance=cov, n_iterations=it, converged=converged, nll=nll,
    )
