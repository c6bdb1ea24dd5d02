r"""Generic RANSAC over the fitters of this package.

Any function ``fit_fn(points, **kw) -> result`` whose result has a
``residuals(points)`` method can be served (all ``fit_*`` functions qualify).
RANSAC maximises the consensus

.. math::

    \max_{\text{minimal sample}} \#\{i : |r_i| < \tau\},

then refits on the consensus set (re-taking the consensus of the refit).
Use it when clutter outnumbers the surface (beyond about 50 %, where the
Gaussian-uniform mixture of the fitters can lock onto the clutter), or when a
second surface competes with the first.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .base import FittingError, TooFewPointsError

__all__ = ["RansacResult", "ransac"]


@dataclass(frozen=True)
class RansacResult:
    """Best model refitted on its consensus set.

    Attributes
    ----------
    model : object
        Result of ``fit_fn`` on the inliers.
    inliers : (N,) ndarray of bool
        Consensus set of the refitted model.
    n_trials : int
    """

    model: object
    inliers: np.ndarray = field(repr=False)
    n_trials: int


def ransac(points, fit_fn, min_samples: int, residual_threshold: float, *,
           normals=None, max_trials: int = 200, stop_probability: float = 0.99,
           rng: np.random.Generator | int | None = 0, **fit_kw) -> RansacResult:
    """Random sample consensus around any ``fit_*`` function.

    Parameters
    ----------
    points : (N, 3) array_like
    fit_fn : callable
        ``fit_fn(points, normals, robust=False, **fit_kw)`` returning an object with
        ``residuals(points)``.
    min_samples : int
        Size of the random subsets (at least the number of parameters; a few more
        gives better hypotheses from noisy data).
    residual_threshold : float
        Inlier threshold on ``|residual|`` (same unit as the points).
    normals : (N, 3) array_like, optional
        Passed to ``fit_fn`` with the matching subset.
    max_trials : int
    stop_probability : float
        Stop early once a hypothesis free of outliers has been drawn with this probability.
    rng : numpy Generator or seed
        For reproducibility (default seed 0).

    Returns
    -------
    RansacResult

    Raises
    ------
    FittingError
        If no hypothesis could be fitted.
    """
    P = np.asarray(points, float)
    Nn = None if normals is None else np.asarray(normals, float)
    n = P.shape[0]
    if n < min_samples:
        raise TooFewPointsError(f"ransac: {n} points, at least {min_samples} needed")
    rng = np.random.default_rng(rng)
    best, best_count, trials = None, -1, 0
    needed = max_trials
    while trials < min(max_trials, needed):
        trials += 1
        idx = rng.choice(n, size=min_samples, replace=False)
        try:
            model = fit_fn(P[idx], None if Nn is None else Nn[idx], robust=False, **fit_kw)
        except FittingError:
            continue
        inl = np.abs(model.residuals(P)) < residual_threshold
        count = int(inl.sum())
        if count > best_count:
            best, best_count = inl, count
            frac = count / n
            if frac >= 1.0:
                break
            denom = np.log(max(1e-12, 1.0 - frac ** min_samples))
            needed = (int(np.ceil(np.log(1.0 - stop_probability) / denom)) if denom < 0
                      else max_trials)
    if best is None or best_count < min_samples:
        raise FittingError("ransac: no hypothesis could be fitted")
    # Local optimisation (as in LO-RANSAC): refit on the consensus set, take the
    # consensus of the refit (minimal-sample hypotheses are noisy) and refit again.
    for _ in range(3):
        model = fit_fn(P[best], None if Nn is None else Nn[best], **fit_kw)
        inl = np.abs(model.residuals(P)) < residual_threshold
        if np.array_equal(inl, best) or inl.sum() < min_samples:
            break
        best = inl
    return RansacResult(model=model, inliers=best, n_trials=trials)
