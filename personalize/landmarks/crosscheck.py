r"""Independent estimates of one joint centre or axis, tested against each other and combined.

Each joint is estimated from several surfaces (knee: posterior-condyle
cylinder, posterior-arc cylinder, condyle spheres, epicondyles; ankle: talar
dome, tibial plafond, malleoli; hip: femoral head, acetabulum).  Every
estimate :math:`i` gives a point :math:`x_i` with its fit covariance
:math:`C_i` and a *model* standard deviation :math:`\sigma_i`: how far that
surface's construction can lie from the joint on a real bone (an epicondylar
midpoint is a coarser knee centre than a condyle cylinder).  Its total
covariance is :math:`S_i = C_i + \sigma_i^2 P` with :math:`P` the projector on
the compared subspace (the whole space for centres, the plane across the axis
for points on a line, the tangent plane for directions).

Agreement of a pair :math:`(i, j)`:

.. math::

    \chi^2_{ij} = (x_i - x_j)^T (S_i + S_j)^{+} (x_i - x_j) < \chi^2_{df}(1 - \alpha),

``df`` the dimension of the compared subspace, :math:`\alpha` = `ALPHA`.

Rule on disagreement (robust, documented): the estimates kept are the
largest set that agree pairwise and hold at least one estimate that is not
a mere check (`Estimate.check`); among sets of equal size the one holding
the primary estimate (the first), then the one of smallest total
:math:`\chi^2`.  When no such pair agrees the primary is kept alone.  The
result is the precision-weighted mean of the kept estimates that are not
checks,

.. math::

    \hat x = \Bigl(\sum_k S_k^{+}\Bigr)^{+} \sum_k S_k^{+} x_k ,

with the fit covariance :math:`A (\sum_k W_k C_k W_k) A`
(:math:`W_k = S_k^+`, :math:`A = (\sum W_k)^+`).  Whenever an estimate is left
out the result is flagged low-confidence and the spread of the left-out
estimates about :math:`\hat x`, :math:`\frac1m \sum_{r} (x_r - \hat x)(x_r - \hat x)^T`,
is added to the stated covariance: the surfaces disagree, so the joint is
known no better than that.  A left-out check is not counted when two
non-check estimates agree (it is outweighed), only when it stood against a
lone estimate.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import numpy as np
from scipy.stats import chi2

__all__ = ["Estimate", "CrossCheck", "cross_check", "cross_check_directions", "ALPHA"]

#: significance of the pairwise agreement test
ALPHA = 0.01


@dataclass(frozen=True)
class Estimate:
    """One surface's estimate of a joint centre (m) or axis (unit vector).

    ``cov``: fit covariance (3, 3), m² (rad² for directions);
    ``model_sd``: isotropic model standard deviation, m (rad for directions);
    ``check``: a coarse construction (epicondyles, malleoli, tibial torsion)
    that takes part in the agreement test but not in the combined value.
    """

    source: str
    value: np.ndarray
    cov: np.ndarray
    model_sd: float
    check: bool = False


@dataclass(frozen=True)
class CrossCheck:
    """Combined estimate and how the estimates agreed.

    ``value`` (3,); ``cov_fit`` the fit covariance of the combination;
    ``cov_spread`` the spread of the left-out estimates (zero when all agree);
    ``used`` / ``left_out`` source names; ``disagreeing`` the left-out ones
    that count (all but checks outweighed by two agreeing estimates);
    ``chi2`` per pair; ``spread`` the largest distance of a counted estimate
    from ``value`` (m, or rad for directions; 0 when all agree); ``offsets``
    every estimate's distance from it.
    """

    value: np.ndarray
    cov_fit: np.ndarray
    cov_spread: np.ndarray
    used: tuple
    left_out: tuple
    chi2: dict = field(default_factory=dict)
    spread: float = 0.0
    offsets: dict = field(default_factory=dict)
    disagreeing: tuple = ()

    @property
    def agree(self) -> bool:
        """No counted disagreement (a check left out against two agreeing estimates is not counted)."""
        return not self.disagreeing

    def to_json(self, unit: str = "m") -> dict:
        k = 1e3 if unit == "m" else float(np.degrees(1.0))
        u = "mm" if unit == "m" else "deg"
        return {"used": list(self.used), "left_out": list(self.left_out), "disagreeing": list(self.disagreeing),
                "agree": self.agree,
                f"spread_{u}": round(self.spread * k, 4),
                f"offsets_{u}": {s: round(v * k, 4) for s, v in self.offsets.items()},
                "chi2": {f"{a}|{b}": round(float(c), 3) for (a, b), c in self.chi2.items()},
                "test": f"pairwise chi2 < chi2_df(1 - {ALPHA})"}


def _pinv(S: np.ndarray, P: np.ndarray) -> np.ndarray:
    return np.linalg.pinv(P @ S @ P, rcond=1e-10, hermitian=True)


def cross_check(estimates: list[Estimate], plane_normal=None, alpha: float = ALPHA) -> CrossCheck:
    """Test estimates of one point against each other and combine them (see the module docstring).

    Parameters
    ----------
    estimates : list of Estimate
        The first is the primary estimate.
    plane_normal : (3,), optional
        Compare and combine only across this direction (points on lines along
        it, e.g. a knee axis): values are projected on the plane through the
        primary value normal to it, the component along it is the primary's.

    Returns
    -------
    CrossCheck
    """
    if not estimates:
        raise ValueError("no estimates")
    x0 = np.asarray(estimates[0].value, float)
    if plane_normal is not None:
        n = np.asarray(plane_normal, float) / np.linalg.norm(plane_normal)
        P = np.eye(3) - np.outer(n, n)
        df = 2
    else:
        P = np.eye(3)
        df = 3
    X = [x0 + P @ (np.asarray(e.value, float) - x0) for e in estimates]
    C = [P @ np.asarray(e.cov, float) @ P for e in estimates]
    S = [c + (e.model_sd ** 2) * P for c, e in zip(C, estimates)]
    names = [e.source for e in estimates]
    lim = float(chi2.ppf(1.0 - alpha, df))
    m = len(estimates)
    c2 = np.zeros((m, m))
    for i, j in combinations(range(m), 2):
        d = X[i] - X[j]
        c2[i, j] = c2[j, i] = float(d @ _pinv(S[i] + S[j], P) @ d)
    ok = c2 < lim
    check = [e.check for e in estimates]
    best = None
    for size in range(m, 1, -1):
        for sub in combinations(range(m), size):
            if all(check[k] for k in sub):
                continue
            if all(ok[i, j] for i, j in combinations(sub, 2)):
                key = (0 not in sub, sum(c2[i, j] for i, j in combinations(sub, 2)))
                if best is None or key < best[0]:
                    best = (key, sub)
        if best is not None:
            break
    keep = (0,) if best is None else best[1]
    comb = [k for k in keep if not check[k]] or [0]
    W = [_pinv(S[k], P) for k in comb]
    A = np.linalg.pinv(sum(W), rcond=1e-10, hermitian=True)
    xh = x0 + A @ sum(w @ (X[k] - x0) for w, k in zip(W, comb))
    cov_fit = A @ sum(w @ C[k] @ w for w, k in zip(W, comb)) @ A
    if plane_normal is not None:                       # along the line: the primary's
        cov_fit = cov_fit + float(n @ estimates[0].cov @ n) * np.outer(n, n)
    out = [k for k in range(m) if k not in keep]
    # a left-out check counts only when it stood against a lone estimate: two agreeing surfaces outweigh it
    real_kept = sum(not check[k] for k in keep)
    counted = [r for r in out if not check[r] or real_kept < 2]
    spread = np.zeros((3, 3))
    for r in counted:
        spread += np.outer(X[r] - xh, X[r] - xh) / len(counted)
    offs = {names[k]: float(np.linalg.norm(X[k] - xh)) for k in range(m)}
    return CrossCheck(value=xh, cov_fit=0.5 * (cov_fit + cov_fit.T), cov_spread=spread,
                      used=tuple(names[k] for k in keep), left_out=tuple(names[k] for k in out),
                      chi2={(names[i], names[j]): c2[i, j] for i, j in combinations(range(m), 2)},
                      spread=max((offs[names[r]] for r in counted), default=0.0), offsets=offs,
                      disagreeing=tuple(names[r] for r in counted))


def cross_check_directions(estimates: list[Estimate], alpha: float = ALPHA) -> CrossCheck:
    """`cross_check` for unit directions: compared in the tangent plane of the primary direction.

    ``value`` of each estimate is a unit vector (sign free: each is turned to
    the primary's side); ``cov`` its fit covariance (rad², e.g.
    ``sd_rad**2 * I``) and ``model_sd`` in radians.  The combined value is a
    unit vector; ``cov_fit`` / ``cov_spread`` are rad² in the tangent plane.
    """
    u0 = np.asarray(estimates[0].value, float)
    u0 = u0 / np.linalg.norm(u0)
    P = np.eye(3) - np.outer(u0, u0)
    es = []
    for e in estimates:
        v = np.asarray(e.value, float) / np.linalg.norm(e.value)
        v = v if v @ u0 >= 0 else -v
        es.append(Estimate(e.source, u0 + (P @ v) / max(float(v @ u0), 1e-6), P @ e.cov @ P, e.model_sd, e.check))
    r = cross_check(es, plane_normal=u0, alpha=alpha)
    v = r.value / np.linalg.norm(r.value)
    # offsets and spread as angles (the tangent-plane distance is tan(angle), unbounded near 90 deg)
    ang = {}
    for e in es:
        w = e.value / np.linalg.norm(e.value)
        ang[e.source] = float(np.arccos(np.clip(w @ v, -1.0, 1.0)))
    Pv = np.eye(3) - np.outer(v, v)
    spread = np.zeros((3, 3))
    for e in es:
        if e.source in r.disagreeing:
            t = Pv @ (e.value / np.linalg.norm(e.value))
            t = t / max(np.linalg.norm(t), 1e-12)
            spread += ang[e.source] ** 2 * np.outer(t, t) / len(r.disagreeing)
    return CrossCheck(value=v, cov_fit=P @ r.cov_fit @ P, cov_spread=spread, used=r.used, left_out=r.left_out,
                      chi2=r.chi2, spread=max((ang[k] for k in r.disagreeing), default=0.0), offsets=ang,
                      disagreeing=r.disagreeing)
