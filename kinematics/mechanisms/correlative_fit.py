"""Fitting correlative laws by multiple linear regression (Pronost et al. 2010, eq. 1).

`fit_law` solves the least-squares problem on the design matrix
``M = [a1 ... ak 1]`` (F, k+1) by a QR factorisation after checking its rank
and condition number itself (a non-varying or collinear independent coordinate
is a `FitError`, never a silent minimum-norm solution).  Statistics: R squared,
residual RMS, maximum absolute deviation, the seed's validation criterion
(section 3.2 step 5), the Table 2 mean deviation (mean Euclidean distance
between data and law) and, with trial groups, leave-one-trial-out errors.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy.linalg import solve_triangular

from kinematics.mechanisms.correlative import CorrelativeLaw, LawFit
from lowerlimb.errors import FitError, InputError

__all__ = ["fit_law", "fit_laws_by_group", "CONDITION_LIMIT", "CONDITION_WARN"]

#: Condition number (of the standardised design) above which the fit is refused.
CONDITION_LIMIT = 1e8
#: Condition number above which the fit is flagged as poorly determined.
CONDITION_WARN = 1e3



def _prepare(independent, dependent, independent_names, dependent_names, source):
    X = np.asarray(independent, dtype=float)
    Y = np.asarray(dependent, dtype=float)
    if X.ndim == 1:
        X = X[:, None]
    if Y.ndim == 1:
        Y = Y[:, None]
    ind = tuple(independent_names) if independent_names is not None else tuple(f"a{i + 1}" for i in range(X.shape[1]))
    dep = tuple(dependent_names) if dependent_names is not None else tuple(f"y{i + 1}" for i in range(Y.shape[1]))
    if X.ndim != 2 or Y.ndim != 2 or X.shape[0] != Y.shape[0]:
        raise InputError(source, f"independent {X.shape} and dependent {Y.shape} arrays must share the frame count")
    if X.shape[1] != len(ind) or Y.shape[1] != len(dep):
        raise InputError(source, "one name per independent and dependent column needed")
    if not ind or not dep:
        raise InputError(source, "at least one independent and one dependent coordinate needed")
    both = [n for n in dep if n in ind]
    if both:
        raise InputError(source, f"{', '.join(both)} listed both as dependent and independent")
    for names, what in ((ind, "independent"), (dep, "dependent")):
        if len(set(names)) != len(names):
            raise InputError(source, f"duplicate {what} names")
    if np.isinf(X).any() or np.isinf(Y).any():
        raise InputError(source, "infinite values in the kinematics")
    return X, Y, ind, dep


def _check_design(X, names, intercept, source):
    """Rank and condition of the design, on standardised columns (units cancel).

    Returns the condition number; raises FitError for a non-varying
    independent or a rank-deficient design.
    """
    F, k = X.shape
    p = k + int(intercept)
    if F < p:
        raise InputError(source, f"{F} frames for {p} coefficients per dependent: at least {p + 1} frames needed")
    if F == p:
        raise InputError(source, f"{F} frames for {p} coefficients: no residual degree of freedom to judge the fit; "
                                 f"at least {p + 1} frames needed")
    mean = X.mean(axis=0)
    sd = X.std(axis=0)
    scale = np.maximum(np.abs(mean), 1.0)
    flat = [names[i] for i in range(k) if sd[i] <= 1e-9 * scale[i]]
    if flat and intercept:
        raise FitError(f"{source + ': ' if source else ''}independent coordinate(s) {', '.join(flat)} do not vary "
                       f"(sd {', '.join(f'{sd[names.index(n)]:.3g}' for n in flat)}): the design matrix is rank deficient")
    if intercept:
        Z = np.column_stack([(X - mean) / np.where(sd > 0, sd, 1.0), np.ones(F)])
    else:
        rms = np.sqrt(np.mean(X ** 2, axis=0))
        if np.any(rms == 0):
            raise FitError(f"{source + ': ' if source else ''}independent coordinate(s) "
                           f"{', '.join(n for n, r in zip(names, rms) if r == 0)} are identically zero")
        Z = X / rms
    s = np.linalg.svd(Z, compute_uv=False)
    cond = float(s[0] / s[-1]) if s[-1] > 0 else math.inf
    rank = int(np.sum(s > s[0] * max(F, p) * np.finfo(float).eps))
    if rank < p or cond > CONDITION_LIMIT:
        _, _, vt = np.linalg.svd(Z)
        null = vt[-1][:k]
        involved = [names[i] for i in np.argsort(-np.abs(null)) if abs(null[i]) > 0.1]
        raise FitError(f"{source + ': ' if source else ''}design matrix rank {rank} < {p} (condition number "
                       f"{cond:.3g}): independents {', '.join(involved) or names} are (nearly) collinear")
    return cond


def _solve(X, Y, intercept):
    """QR least squares. Returns coefficients (D, k+1), residuals (F, D), (M^T M)^-1."""
    F = X.shape[0]
    M = np.column_stack([X, np.ones(F)]) if intercept else X
    Q, R = np.linalg.qr(M, mode="reduced")
    B = solve_triangular(R, Q.T @ Y)  # (p, D)
    Rinv = solve_triangular(R, np.eye(R.shape[0]))
    N_inv = Rinv @ Rinv.T
    E = Y - M @ B
    if not intercept:
        B = np.vstack([B, np.zeros((1, Y.shape[1]))])
        pad = np.zeros((N_inv.shape[0] + 1,) * 2)
        pad[:-1, :-1] = N_inv
        N_inv = pad
    return B.T, E, N_inv


def fit_law(independent, dependent, independent_names: Sequence[str] | None = None,
            dependent_names: Sequence[str] | None = None, groups=None, joint: str = "",
            independent_units: Sequence[str] | str = "rad", dependent_units: Sequence[str] | str = "m",
            intercept: bool = True, source: str | None = None) -> CorrelativeLaw:
    """Fit a correlative law by multiple linear least squares (seed section 3.2).

    Model and minimised quantity, for each dependent d separately::

        E_d = M c_d + e,   M = [a1 ... ak 1] (F, k+1),   min_c || M c - E_d ||^2

    Parameters
    ----------
    independent : array (F, k)
        Controlling coordinates per frame (e.g. the three knee rotations, rad).
    dependent : array (F, D)
        Correlative coordinates per frame (e.g. the three translations, m).
    independent_names, dependent_names : sequences of str
    groups : array (F,), optional
        Trial label per frame; enables leave-one-trial-out statistics.
    joint : str
    independent_units, dependent_units : str or sequence of str
        ``"rad"`` or ``"m"``.
    intercept : bool
        Fit the constant term ``c0`` (seed eq. 1); False for laws through
        the origin (a gear pair, ``R_b = beta R_a``).
    source : str, optional
        Named in error messages.

    Returns
    -------
    CorrelativeLaw
        With coefficient covariance ``S_ij (M^T M)^-1`` (ordinary least squares;
        frames of a motion are serially correlated, so treat it as a lower
        bound and prefer the leave-one-trial-out error as a prediction error).

    Raises
    ------
    InputError
        Shapes/names inconsistent, a coordinate both dependent and independent,
        fewer frames than coefficients + 1.
    FitError
        An independent coordinate that does not vary, collinear independents
        (rank-deficient or condition number > `CONDITION_LIMIT`).
    """
    X, Y, ind, dep = _prepare(independent, dependent, independent_names, dependent_names, source)
    iu = (independent_units,) * len(ind) if isinstance(independent_units, str) else tuple(independent_units)
    du = (dependent_units,) * len(dep) if isinstance(dependent_units, str) else tuple(dependent_units)
    if groups is not None and len(np.asarray(groups)) != len(X):
        raise InputError(source, "one group label per frame needed")
    ok = np.isfinite(X).all(axis=1) & np.isfinite(Y).all(axis=1)
    n_dropped = int((~ok).sum())
    X, Y = X[ok], Y[ok]
    g = None if groups is None else np.asarray(groups)[ok]
    if n_dropped and len(X) <= X.shape[1] + int(intercept):
        raise InputError(source, f"only {len(X)} complete frames ({n_dropped} with missing values dropped) "
                                 f"for {X.shape[1] + int(intercept)} coefficients")
    cond = _check_design(X, list(ind), intercept, source)
    coef, E, N_inv = _solve(X, Y, intercept)
    F, p = X.shape[0], X.shape[1] + int(intercept)
    S = E.T @ E / (F - p)

    # Statistics.
    ss_res = np.sum(E ** 2, axis=0)
    ss_tot = np.sum((Y - Y.mean(axis=0)) ** 2, axis=0) if intercept else np.sum(Y ** 2, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r2 = np.where(ss_tot > 0, 1.0 - ss_res / ss_tot, np.nan)
    rms = np.sqrt(ss_res / F)
    max_abs = np.max(np.abs(E), axis=0)
    # Seed 3.2 step 5: max|MC - E| < min(E).  Taken on magnitudes: the seed's
    # own T_y (about -0.5 m) could never pass the signed form, yet it is reported valid.
    seed = max_abs < np.min(np.abs(Y), axis=0)
    same_unit = len(set(du)) == 1
    mean_dev = float(np.mean(np.linalg.norm(E, axis=1))) if same_unit else math.nan
    well = cond < CONDITION_WARN

    loto_rms = loto_dev = None
    n_groups = 1
    if g is not None:
        labels = list(dict.fromkeys(g.tolist()))
        n_groups = len(labels)
        if n_groups >= 2:
            held = np.full_like(Y, np.nan)
            for lab in labels:
                test = g == lab
                try:
                    _check_design(X[~test], list(ind), intercept, source)
                except (FitError, InputError):
                    continue  # the remaining trials cannot determine the law: leave NaN
                c_k, _, _ = _solve(X[~test], Y[~test], intercept)
                held[test] = Y[test] - (X[test] @ c_k[:, :-1].T + c_k[:, -1])
            good = np.isfinite(held).all(axis=1)
            loto_rms = np.sqrt(np.mean(held[good] ** 2, axis=0)) if good.any() else np.full(len(dep), np.nan)
            loto_dev = float(np.mean(np.linalg.norm(held[good], axis=1))) if good.any() and same_unit else math.nan

    fit = LawFit(r2=r2, rms=rms, max_abs=max_abs, seed_criterion=seed, valid=bool(seed.all() and well),
                 n_frames=F, n_dropped=n_dropped, condition=cond, well_conditioned=well,
                 mean_deviation=mean_dev, n_groups=n_groups, loto_rms=loto_rms, loto_mean_deviation=loto_dev)
    return CorrelativeLaw(joint=joint, independent=ind, dependent=dep, coefficients=coef,
                          independent_units=iu, dependent_units=du, residual_covariance=S,
                          normal_inverse=N_inv, fit=fit)


def fit_laws_by_group(independent, dependent, groups, independent_names=None, dependent_names=None,
                      **kwargs) -> dict:
    """One law per group label (per trial or per sub-motion, e.g. crouch per foot angle).

    Returns ``{label: CorrelativeLaw}`` in order of first appearance.
    """
    X = np.asarray(independent, dtype=float)
    Y = np.asarray(dependent, dtype=float)
    g = np.asarray(groups)
    if len(g) != len(X):
        raise InputError(kwargs.get("source"), "one group label per frame needed")
    src = kwargs.pop("source", None)
    out = {}
    for lab in dict.fromkeys(g.tolist()):
        sel = g == lab
        out[lab] = fit_law(X[sel], Y[sel], independent_names, dependent_names,
                           source=f"{src} [{lab}]" if src else f"group {lab}", **kwargs)
    return out

