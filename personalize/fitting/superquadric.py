r"""Superquadric fitting (femoral head and condyles, Tändl et al. 2010, section 4).

Model (body frame, :math:`p = R^T (x - c)`): the inside-outside function

.. math::

    F(p) = \Bigl(\bigl|\tfrac{p_1}{a_1}\bigr|^{2/\varepsilon_2}
                + \bigl|\tfrac{p_2}{a_2}\bigr|^{2/\varepsilon_2}\Bigr)^{\varepsilon_2/\varepsilon_1}
           + \bigl|\tfrac{p_3}{a_3}\bigr|^{2/\varepsilon_1},
    \qquad \varepsilon_{1,2} \in [0.1, 1.9],

with the surface at :math:`F = 1`.  Residual: the signed radial Euclidean
distance (Jaklič, Leonardis & Solina 2000)

.. math::

    d(p) = \|p\|\,\bigl(1 - F(p)^{-\varepsilon_1/2}\bigr) = \|p\| - \rho_S(\hat p),

the distance from ``p`` to the surface along the ray from the centre.
Minimised quantity: :math:`\sum_i c_i w_i d_i^2` with EM posterior inlier
weights of a Gaussian-uniform mixture (Liu et al., CVPR 2022, "EMS").

Numerics: ``F`` is evaluated in the log domain (``logaddexp`` of
:math:`\tfrac{2}{\varepsilon}\log|p_k/a_k|`), so small exponents never
overflow; :math:`\rho_S = \exp(\log\|p\| - \tfrac{\varepsilon_1}{2}\log F)` stays
finite at the centre.  Rotation is updated as ``R <- R expm([omega]x)`` (no Euler
angles), scales as ``log a`` and the exponents through a logistic map onto
[0.1, 1.9].  The Jacobian is analytic (softmax weights of the log-sum-exp).

Because the same surface has several parametrisations (axis orderings, and
the ``epsilon2 <-> 2 - epsilon2`` duality under a 45 degree turn about the
z-axis), recovery is restarted over the three axis orderings of the principal
frame, and the best solution is challenged by its similarity/duality switches
(as in EMS); candidates are compared by the mixture likelihood on a subsample,
and the winner is refined on all points.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lowerlimb.geometry import skew

from .base import DegenerateError, NotConvergedError, check_inputs, surface_likeness
from .robust import em_lm

__all__ = ["SuperquadricFit", "fit_superquadric", "sq_radial_distance"]

EPS_MIN, EPS_MAX = 0.1, 1.9
_TINY = 1e-12


def _rodrigues(w):
    th = float(np.sqrt(w @ w))
    K = skew(w)
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + (np.sin(th) / th) * K + ((1 - np.cos(th)) / th ** 2) * (K @ K)


def _eps(phi):
    return EPS_MIN + (EPS_MAX - EPS_MIN) / (1.0 + np.exp(-phi))


def _phi(eps):
    e = np.clip(eps, EPS_MIN + 1e-3, EPS_MAX - 1e-3)
    t = (e - EPS_MIN) / (EPS_MAX - EPS_MIN)
    return float(np.log(t / (1 - t)))


def sq_radial_distance(Pb, log_a, e1, e2, jac=False):
    """Signed radial distance of body-frame points to a superquadric, and its partials.

    Parameters
    ----------
    Pb : (N, 3) ndarray
        Points in the body frame.
    log_a : (3,) ndarray
        Logarithms of the semi-axes.
    e1, e2 : float
        Shape exponents.
    jac : bool
        Also return the partial derivatives.

    Returns
    -------
    d : (N,) ndarray
    parts : tuple or None
        ``(dd/dp (N, 3), dd/dlog_a (N, 3), dd/de1 (N,), dd/de2 (N,))``.
    """
    absP = np.maximum(np.abs(Pb), _TINY)
    lu = np.log(absP)
    lu -= log_a
    t1 = (2.0 / e2) * lu[:, 0]
    t2 = (2.0 / e2) * lu[:, 1]
    A = np.logaddexp(t1, t2)
    B = (e2 / e1) * A
    t3 = (2.0 / e1) * lu[:, 2]
    G = np.logaddexp(B, t3)                       # log F
    rho = np.sqrt(np.einsum("ij,ij->i", Pb, Pb))
    np.maximum(rho, _TINY, out=rho)
    surf = np.exp(np.log(rho) - 0.5 * e1 * G)     # radial distance of the surface
    d = rho - surf
    if not jac:
        return d, None
    s = np.exp(B - G)
    q1 = np.exp(t1 - A)
    q2 = 1.0 - q1
    W = np.empty_like(Pb)
    W[:, 0] = s * q1
    W[:, 1] = s * q2
    W[:, 2] = 1.0 - s
    # d/dp = p/|p| (1 - surf/|p|) + surf * W / p   (W / p ~ |p|^(2/eps - 1): finite)
    g = Pb * ((rho - surf) / (rho * rho))[:, None]
    g += (surf[:, None] * W) / np.copysign(absP, Pb)
    d_loga = -surf[:, None] * W
    d_e1 = 0.5 * surf * (G - (s * B + (1.0 - s) * t3))
    d_e2 = 0.5 * surf * s * (A - (q1 * t1 + q2 * t2))
    return d, (g, d_loga, d_e1, d_e2)


@dataclass(frozen=True)
class SuperquadricFit:
    """Fitted superquadric.

    Attributes
    ----------
    centre : (3,) ndarray
    rotation : (3, 3) ndarray
        Columns are the body axes x, y, z (semi-axes ``a1, a2, a3``); ``a1 >= a2``
        (x and y are interchangeable in the model, so they are ordered).
    scale : (3,) ndarray
        Semi-axes ``(a1, a2, a3)``, unit of the points.
    shape : (2,) ndarray
        ``(epsilon1, epsilon2)`` in [0.1, 1.9].
    covariance : (11, 11) ndarray
        Covariance of ``(centre (3), rotation vector of a small world-frame
        rotation (3, rad), scale (3), epsilon1, epsilon2)``.
    rms : float
        Inlier-weighted RMS radial residual.
    inlier_weights : (N,) ndarray
    n_iterations : int
        Iterations of the final refinement.
    converged : bool
    """

    centre: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    shape: np.ndarray
    covariance: np.ndarray
    rms: float
    inlier_weights: np.ndarray = field(repr=False)
    n_iterations: int
    converged: bool

    def residuals(self, points) -> np.ndarray:
        """Signed radial distances to the surface (positive outside), shape (N,)."""
        Pb = (np.asarray(points, float).reshape(-1, 3) - self.centre) @ self.rotation
        return sq_radial_distance(Pb, np.log(self.scale), *self.shape)[0]


def _problem(X, fixed_shape=None):
    """Residual/Jacobian closures; params ``(c, R, log_a, phi1, phi2)``."""
    n_par = 9 if fixed_shape is not None else 11

    def fun(x, jac):
        c, R, log_a, f1, f2 = x
        e1, e2 = (fixed_shape if fixed_shape is not None else (_eps(f1), _eps(f2)))
        Pb = (X - c) @ R
        d, parts = sq_radial_distance(Pb, log_a, e1, e2, jac)
        if not jac:
            return d, None
        g, d_la, d_e1, d_e2 = parts
        J = np.empty((X.shape[0], n_par))
        J[:, 0:3] = -g                            # body-frame translation
        # body-frame rotation: d(d)/d(omega) = g x p
        J[:, 3] = g[:, 1] * Pb[:, 2] - g[:, 2] * Pb[:, 1]
        J[:, 4] = g[:, 2] * Pb[:, 0] - g[:, 0] * Pb[:, 2]
        J[:, 5] = g[:, 0] * Pb[:, 1] - g[:, 1] * Pb[:, 0]
        J[:, 6:9] = d_la
        if fixed_shape is None:
            for k, (f, dd) in enumerate(((f1, d_e1), (f2, d_e2))):
                sg = 1.0 / (1.0 + np.exp(-f))
                J[:, 9 + k] = dd * (EPS_MAX - EPS_MIN) * sg * (1 - sg)
        return d, J

    def retract(x, dl):
        c, R, log_a, f1, f2 = x
        c2 = c + R @ dl[0:3]
        R2 = R @ _rodrigues(dl[3:6])             # exact rotation: no drift to speak of
        la = log_a + np.clip(dl[6:9], -1.0, 1.0)   # at most a factor e per step
        if fixed_shape is None:
            f1, f2 = np.clip(f1 + dl[9], -12, 12), np.clip(f2 + dl[10], -12, 12)
        return (c2, R2, la, f1, f2)

    return fun, retract


def _principal_start(X, w):
    m = (w @ X) / w.sum()
    Y = X - m
    vals, vecs = np.linalg.eigh((w[:, None] * Y).T @ Y / w.sum())
    if np.linalg.det(vecs) < 0:
        vecs[:, 0] = -vecs[:, 0]
    a = np.sqrt(np.maximum(3.0 * vals, 1e-6))
    return m, vecs, a


def _cyclic(R, a, e1, e2, k):
    """Relabel axes cyclically ``k`` times (x->z...), a right-handed similarity switch."""
    idx = np.roll(np.arange(3), -k)
    R2 = R[:, idx]
    a2 = a[idx]
    if k % 3 == 0:
        return R2, a2, e1, e2
    return R2, a2, e2, e1          # the old x/y (epsilon2) profile now lies in a plane with z


def _dual(R, a, e2):
    """Duality ``epsilon2 -> 2 - epsilon2`` with a 45 degree turn about z."""
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    f = np.sqrt(2.0) if e2 < 1 else 1.0 / np.sqrt(2.0)
    am = np.sqrt(a[0] * a[1]) * f
    return R @ Rz, np.array([am, am, a[2]]), 2.0 - e2


def fit_superquadric(points, normals=None, weights=None, *, robust: bool = True,
                     max_iter: int = 300, n_subsample: int = 400,
                     similarity_rounds: int = 2, rng=0,
                     require_convergence: bool = True) -> SuperquadricFit:
    r"""Fit a superquadric by robust radial-distance least squares with restarts.

    Parameters
    ----------
    points : (N, 3) array_like
        Surface points (any unit; the project passes metres).  N >= 11.
    normals : (N, 3) array_like, optional
        Accepted for a uniform interface (checked, not used).
    weights : (N,) array_like, optional
        Non-negative prior weights.
    robust : bool, default True
        Gaussian-uniform mixture EM (True) or plain least squares (False).
    max_iter : int
        Iteration cap of the final refinement.
    n_subsample : int
        Points used to rank the restarts (all if N is smaller).
    similarity_rounds : int
        Rounds of similarity/duality switching of the best candidate.
    rng : numpy Generator or int
        Seed of the subsample (results are reproducible).
    require_convergence : bool

    Returns
    -------
    SuperquadricFit

    Raises
    ------
    TooFewPointsError, NonFiniteError, DegenerateError, NotConvergedError
    """
    X, _, c, frame = check_inputs(points, normals, weights, n_params=11, model="superquadric")
    sol = _fit_sq(X, c, robust=robust, max_iter=max_iter, n_subsample=n_subsample,
                  similarity_rounds=similarity_rounds, rng=rng, fixed_shape=None,
                  model="superquadric")
    if require_convergence and not sol.converged:
        raise NotConvergedError(f"superquadric: no convergence in {max_iter} iterations")
    ctr, R, la, f1, f2 = sol.params
    e = np.array([_eps(f1), _eps(f2)])
    return _assemble(SuperquadricFit, sol, frame, ctr, R, la, e, n_shape=2)


def _assemble(cls, sol, frame, ctr, R, la, e, n_shape):
    s = frame.scale
    a = np.exp(la)
    if not (np.all(np.isfinite(a)) and a.max() < 1e3 and np.all(np.isfinite(ctr))
            and np.linalg.norm(ctr) < 1e3):
        # normalised units: the points have RMS distance 1 from their centroid
        raise DegenerateError(f"{cls.__name__[:-3].lower()}: the fit diverged (semi-axes or centre "
                              "more than 1000 times the extent of the points)")
    cov = sol.covariance
    n = 9 + n_shape
    G = np.zeros((n, n))
    G[0:3, 0:3] = R * s            # body translation -> world centre
    G[3:6, 3:6] = R                # body rotation vector -> world rotation vector
    G[6:9, 6:9] = np.diag(a * s)   # log a -> a
    for k in range(n_shape):
        t = (e[k] - EPS_MIN) / (EPS_MAX - EPS_MIN)
        G[9 + k, 9 + k] = (EPS_MAX - EPS_MIN) * t * (1 - t)
    cov = G @ cov @ G.T if np.all(np.isfinite(cov)) else np.full((n, n), np.inf)
    if n_shape == 0:
        # Ellipsoid: all labellings are equivalent; order a1 >= a2 >= a3, right-handed.
        order = np.argsort(-a, kind="stable")
        R = R[:, order]
        if np.linalg.det(R) < 0:
            R[:, 2] = -R[:, 2]
        a = a[order]
        perm = np.r_[0, 1, 2, 3, 4, 5, 6 + order]
        cov = cov[np.ix_(perm, perm)]
    elif a[1] > a[0]:
        # x <-> y relabelling (a quarter turn about z) keeps the surface; order a1 >= a2.
        P = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])    # new x = old y, new y = -old x
        R = R @ P
        a = a[[1, 0, 2]]
        perm = np.r_[0, 1, 2, 3, 4, 5, 7, 6, 8, np.arange(9, n)]
        cov = cov[np.ix_(perm, perm)]
    kw = dict(centre=frame.back(ctr), rotation=R, covariance=cov, rms=sol.rms * s,
              inlier_weights=sol.weights, n_iterations=sol.n_iterations,
              converged=sol.converged)
    if n_shape:
        return cls(scale=a * s, shape=e, **kw)
    return cls(radii=a * s, **kw)


def _fit_sq(X, c, *, robust, max_iter, n_subsample, similarity_rounds, rng, fixed_shape, model,
            starts=None, restart_iter=25, screen_iter=5):
    fun_all, retract = _problem(X, fixed_shape)
    n = X.shape[0]
    rng = np.random.default_rng(rng)
    if n > n_subsample:
        sub = np.sort(rng.choice(n, n_subsample, replace=False))
    else:
        sub = np.arange(n)
    Xs, cs = X[sub], c[sub]
    # Restarts are ranked on the subsample with prior weights scaled by how
    # surface-like each point's neighbourhood is: scattered clutter then barely
    # moves the principal-axes start, which otherwise fails beyond ~30 % outliers.
    cs = cs * surface_likeness(X, sub) ** 2
    if not cs.sum() > 0:
        cs = c[sub]
    fun_sub, _ = _problem(Xs, fixed_shape)
    # One outlier density for all candidates so that their likelihoods compare.
    u = 1.0 / (2.0 * np.sqrt(np.max(np.sum(X * X, axis=1))))

    def run(x0, fun, cw, iters):
        try:
            return em_lm(fun, x0, retract, prior_weights=cw, robust=robust, max_iter=iters,
                         outlier_density=u, model=model, xtol=1e-7, sigma_max=0.1)
        except NotConvergedError:
            return None

    m, V, a = _principal_start(Xs, cs)
    extra = starts(Xs, cs) if callable(starts) else starts
    starts = list(extra or [])
    # The principal-moment starts are always candidates (an algebraic start can
    # be wild on clutter).
    for k in range(3):
        R, ak, e1, e2 = _cyclic(V, a, 1.0, 1.0, k)
        starts.append((m, R, np.log(ak), _phi(e1), _phi(e2)))
    margin = 0.05 * cs.sum()        # nats: how far behind a screened candidate may be

    def challenge(cands, best):
        """Screen candidates briefly, then refine the most promising against ``best``."""
        screened = [r for r in (run(x0, fun_sub, cs, screen_iter) for x0 in cands) if r is not None]
        screened.sort(key=lambda r: r.nll)
        improved = False
        for r in screened[:2]:
            if best is not None and r.nll > best.nll + margin:
                break
            r2 = run(r.params, fun_sub, cs, restart_iter) if not r.converged else r
            if r2 is None:
                continue
            if best is None or r2.nll < best.nll - 1e-3 * abs(best.nll) - 1.0:
                best, improved = r2, True
        return best, improved

    best, _ = challenge(starts, None)
    if best is None:
        raise NotConvergedError(f"{model}: every restart failed")
    if fixed_shape is None:
        for _ in range(similarity_rounds):
            ctr, R, la, f1, f2 = best.params
            e1, e2 = _eps(f1), _eps(f2)
            a = np.exp(la)
            # Similar parametrisations of (nearly) the same surface: the other two
            # axis labellings, the epsilon2 dual, and the dual relabelled.
            bases = [(R, a, e1, e2)]
            if abs(e2 - 1.0) > 0.2:
                Rd, ad, e2d = _dual(R, a, e2)
                bases.append((Rd, ad, e1, e2d))
            cands = []
            for jb, (Rb, ab, e1b, e2b) in enumerate(bases):
                for k in (0, 1, 2):
                    if jb == 0 and k == 0:
                        continue
                    Rk, ak, e1k, e2k = _cyclic(Rb, ab, e1b, e2b, k)
                    cands.append((ctr, Rk, np.log(ak), _phi(e1k), _phi(e2k)))
            best, improved = challenge(cands, best)
            if not improved:
                break
    # Start the full-data EM at the subsample's inlier scale: the MAD of all
    # residuals is dominated by clutter when outliers approach half the points.
    sol = em_lm(fun_all, best.params, retract, prior_weights=c, robust=robust,
                max_iter=max_iter, outlier_density=u, model=model, xtol=1e-9,
                sigma0=best.sigma if robust else None, pi0=0.5)
    return sol
