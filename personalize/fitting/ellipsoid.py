r"""Ellipsoid fitting (condyle and head shapes, a superquadric with epsilon1 = epsilon2 = 1).

Model (body frame, :math:`p = R^T (x - c)`):
:math:`F(p) = \sum_k (p_k / a_k)^2 = 1`.

Minimised quantity: the robust-weighted squared orthogonal distance

.. math::

    \min_{c, R, a} \sum_i c_i w_i\, d_\perp(x_i; c, R, a)^2 ,

with :math:`d_\perp` the signed distance to the closest surface point
(`ellipsoid_distance`, safeguarded Newton on the Lagrange multiplier) and the
analytic Jacobian of the implicit-function theorem.  Start: the algebraic
ellipsoid (least-squares quadric, accepted when its quadratic form is
definite) and the principal-moment ellipsoid, each in its three axis
labellings, ranked on a subsample with the cheaper radial distance
:math:`\|p\|(1 - F(p)^{-1/2})` (as in `superquadric`); the winner is refined
with the radial distance, then with the orthogonal distance, which -- unlike
the radial one -- is not biased by noise on partial surfaces.

`fit_ellipsoid_about_axis` is the same estimator with one semi-axis held
along a known direction (7 parameters), for partial arcs whose free fit is
ill-posed (femoral condyles about the flexion axis).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .base import DegenerateError, NotConvergedError, check_inputs
from .robust import em_lm
from .superquadric import _assemble, _fit_sq, _problem, _rodrigues

__all__ = ["EllipsoidFit", "fit_ellipsoid", "fit_ellipsoid_about_axis", "algebraic_ellipsoid", "ellipsoid_distance"]


@dataclass(frozen=True)
class EllipsoidFit:
    """Fitted ellipsoid.

    Attributes
    ----------
    centre : (3,) ndarray
    radii : (3,) ndarray
        Semi-axes, in decreasing order.
    rotation : (3, 3) ndarray
        Columns are the semi-axis directions.
    covariance : (9, 9) ndarray
        Covariance of ``(centre (3), world rotation vector (3, rad), radii (3))``.
    rms, inlier_weights, n_iterations, converged
        As for the other fits.
    """

    centre: np.ndarray
    radii: np.ndarray
    rotation: np.ndarray
    covariance: np.ndarray
    rms: float
    inlier_weights: np.ndarray = field(repr=False)
    n_iterations: int
    converged: bool

    def residuals(self, points) -> np.ndarray:
        """Signed orthogonal distances to the surface (positive outside), (N,)."""
        Pb = (np.asarray(points, float).reshape(-1, 3) - self.centre) @ self.rotation
        return ellipsoid_distance(Pb, self.radii)[0]


def ellipsoid_distance(Pb: np.ndarray, a: np.ndarray, jac: bool = False):
    r"""Signed orthogonal distance of body-frame points to the ellipsoid with semi-axes ``a``.

    The foot point is :math:`y_k = a_k^2 p_k / (a_k^2 + t)` where ``t`` is the
    root of :math:`g(t) = \sum_k (a_k p_k / (a_k^2 + t))^2 - 1` on
    :math:`t > -\min a_k^2` (``t > 0`` outside).  ``g`` is convex and
    decreasing, so the root is bracketed and found by safeguarded Newton
    (bisection whenever Newton leaves the bracket), vectorised over points.

    Returns ``d`` (N,) and, if ``jac``, ``(n, d_loga)``: the outward unit normal
    at the foot, :math:`\partial d/\partial p = n`, and
    :math:`\partial d/\partial\log a_k = -(y_k/a_k)^2 / \|y/a^2\|`
    (the implicit-function derivative :math:`G_\theta / \|\nabla G\|`).
    """
    a2 = a * a
    q = (a * Pb) ** 2
    amin2, amax2 = a2.min(), a2.max()
    root_q = np.sqrt(q.sum(axis=1))
    lo = np.maximum(root_q - amax2, -amin2)
    hi = np.maximum(root_q - amin2, lo)
    # Start at t = 0 (the root for points on the surface; fitted points are
    # near it).  g is convex and decreasing: from the left of the root Newton
    # increases monotonically to it; from the right one step lands left of it.
    t = np.clip(0.0, lo, hi)
    tiny = 1e-300
    act = np.arange(len(t))          # points still iterating (the loop shrinks to them)
    for _ in range(100):
        ta, qa, la, ha = t[act], q[act], lo[act], hi[act]
        den = a2 + ta[:, None]
        h = qa / np.maximum(den * den, tiny)
        g = h.sum(axis=1) - 1.0
        la = np.where(g > 0, ta, la)
        ha = np.where(g > 0, ha, ta)
        dg = -2.0 * (h / np.maximum(den, tiny)).sum(axis=1)
        step = g / np.where(dg < 0, dg, -1.0)
        t_new = ta - step
        bad = ~((t_new >= la) & (t_new <= ha))
        t_new = np.where(bad, 0.5 * (la + ha), t_new)
        tol = 1e-12 * (1.0 + np.abs(ta))
        done = (np.abs(step) <= tol) | (ha - la <= tol)
        t[act], lo[act], hi[act] = t_new, la, ha
        act = act[~done]
        if act.size == 0:
            break
    y = a2 * Pb / np.maximum(a2 + t[:, None], tiny)
    # Inside points on the plane of the shortest axis (t at the pole -min a^2):
    # the foot leaves that plane (Eberly's degenerate case).
    kmin = int(np.argmin(a2))
    deg = t <= -amin2 * (1.0 - 1e-9)
    if np.any(deg):
        others = [k for k in range(3) if k != kmin]
        yd = np.zeros((int(deg.sum()), 3))
        for k in others:
            yd[:, k] = a2[k] * Pb[deg, k] / max(a2[k] - amin2, tiny)
        rest = 1.0 - sum((yd[:, k] / a[k]) ** 2 for k in others)
        yd[:, kmin] = a[kmin] * np.sqrt(np.clip(rest, 0.0, None)) * np.where(
            Pb[deg, kmin] < 0, -1.0, 1.0)
        y[deg] = yd
        t[deg] = -amin2
    inside = np.sum((Pb / a) ** 2, axis=1) < 1.0
    d = np.where(inside, -1.0, 1.0) * np.sqrt(np.sum((Pb - y) ** 2, axis=1))
    if not jac:
        return d, None
    grad = y / a2                                  # half the gradient of G at the foot
    gn = np.sqrt(np.sum(grad * grad, axis=1))
    gn = np.maximum(gn, tiny)
    n = grad / gn[:, None]
    d_loga = -(y * y / a2) / gn[:, None]
    return d, (n, d_loga)


def _orthogonal_problem(X):
    """Closures like `superquadric._problem` (epsilon fixed at 1) with orthogonal distances."""
    _, retract = _problem(X, fixed_shape=(1.0, 1.0))

    def fun(x, jac):
        c, R, log_a, _, _ = x
        Pb = (X - c) @ R
        d, parts = ellipsoid_distance(Pb, np.exp(log_a), jac)
        if not jac:
            return d, None
        n, d_la = parts
        J = np.empty((X.shape[0], 9))
        J[:, 0:3] = -n                               # body-frame translation
        J[:, 3] = n[:, 1] * Pb[:, 2] - n[:, 2] * Pb[:, 1]   # body rotation: n x p
        J[:, 4] = n[:, 2] * Pb[:, 0] - n[:, 0] * Pb[:, 2]
        J[:, 5] = n[:, 0] * Pb[:, 1] - n[:, 1] * Pb[:, 0]
        J[:, 6:9] = d_la
        return d, J

    return fun, retract


def algebraic_ellipsoid(X: np.ndarray, w: np.ndarray):
    r"""Algebraic quadric :math:`x^T A x + b^T x + d = 0`.

    Minimises :math:`\sum_i w_i (x_i^T A x_i + b^T x_i + d)^2` subject to
    :math:`\|(A, b, d)\| = 1` (one SVD).

    Returns ``(centre, rotation, radii)`` or None when the quadric is not an ellipsoid.
    """
    x, y, z = X.T
    D = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, x, y, z,
                         np.ones_like(x)])
    _, _, Vt = np.linalg.svd(np.sqrt(w)[:, None] * D, full_matrices=False)
    v = Vt[-1]
    A = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    b, d = v[6:9], v[9]
    vals = np.linalg.eigvalsh(A)
    if vals[0] * vals[2] <= 0:
        return None
    if vals[0] < 0:
        A, b, d = -A, -b, -d
    try:
        centre = -0.5 * np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return None
    k = centre @ A @ centre - d
    if not k > 0:
        return None
    vals, vecs = np.linalg.eigh(A / k)
    if np.linalg.det(vecs) < 0:
        vecs[:, 0] = -vecs[:, 0]
    return centre, vecs, 1.0 / np.sqrt(vals)


def fit_ellipsoid(points, normals=None, weights=None, *, robust: bool = True,
                  max_iter: int = 300, n_subsample: int = 400, rng=0,
                  require_convergence: bool = True) -> EllipsoidFit:
    """Fit an ellipsoid by robust radial-distance least squares.

    Parameters
    ----------
    points : (N, 3) array_like
        Surface points (any unit; the project passes metres).  N >= 9.
    normals : (N, 3) array_like, optional
        Accepted for a uniform interface (checked, not used).
    weights : (N,) array_like, optional
    robust : bool, default True
    max_iter, n_subsample, rng, require_convergence
        As in `fit_superquadric`.

    Returns
    -------
    EllipsoidFit

    Raises
    ------
    TooFewPointsError, NonFiniteError, DegenerateError, NotConvergedError
    """
    X, _, c, frame = check_inputs(points, normals, weights, n_params=9, model="ellipsoid")
    sv = np.linalg.svd(np.sqrt(c)[:, None] * (X - (c @ X) / c.sum()), compute_uv=False)
    if sv[2] < 1e-6 * sv[0]:
        raise DegenerateError("ellipsoid: points are coplanar or collinear")

    def starts(Xs, cs):
        # algebraic ellipsoid on the (clutter-down-weighted) subsample, all 3 labellings
        alg = algebraic_ellipsoid(Xs, cs)
        if alg is None:
            return None                      # -> principal-moment ellipsoid
        ctr, V, a = alg
        return [(ctr, V[:, np.roll(np.arange(3), -k)], np.log(a[np.roll(np.arange(3), -k)]),
                 0.0, 0.0) for k in range(3)]
    sol = _fit_sq(X, c, robust=robust, max_iter=max_iter, n_subsample=n_subsample,
                  similarity_rounds=0, rng=rng, fixed_shape=(1.0, 1.0), model="ellipsoid",
                  starts=starts)
    # Final refinement in orthogonal distance: the radial distance is cheap and
    # fine for ranking restarts, but biased under noise on partial surfaces.
    u = 1.0 / (2.0 * np.sqrt(np.max(np.sum(X * X, axis=1))))
    fun, retract = _orthogonal_problem(X)
    sol = em_lm(fun, sol.params, retract, prior_weights=c, robust=robust, max_iter=max_iter,
                outlier_density=u, sigma0=sol.sigma if robust else None,
                pi0=max(sol.inlier_fraction, 0.1), model="ellipsoid")
    if require_convergence and not sol.converged:
        raise NotConvergedError(f"ellipsoid: no convergence in {max_iter} iterations")
    ctr, R, la, _, _ = sol.params
    return _assemble(EllipsoidFit, sol, frame, ctr, R, la, None, n_shape=0)


def fit_ellipsoid_about_axis(points, axis, *, centre0, radii0, rotation0=None, weights=None,
                             robust: bool = True, max_iter: int = 300,
                             require_convergence: bool = True) -> EllipsoidFit:
    r"""Fit an ellipsoid one of whose semi-axes lies along a known direction.

    Model: as `fit_ellipsoid` with :math:`R = R_0\,\mathrm{Rot}_z(\phi)`, the
    third column of :math:`R_0` being the unit ``axis``: the ellipsoid may
    turn only about ``axis``.  Parameters: centre (3), :math:`\phi` (1) and
    log semi-axes (3) -- seven instead of nine.  Minimised quantity: the
    robust-weighted squared orthogonal distance
    :math:`\sum_i c_i w_i\, d_\perp(x_i; c, R, a)^2`, analytic Jacobian as
    in `fit_ellipsoid` restricted to the rotation about the body z axis.

    Fixing the axis removes the near-flat directions of a free ellipsoid on
    a partial, noisy surface patch (e.g. a femoral condyle's posterior-distal
    arc, whose medio-lateral axis is known from the bone).

    Parameters
    ----------
    points : (N, 3) array_like
    axis : (3,) array_like
        Direction of one semi-axis (normalised here).
    centre0 : (3,) array_like
        Starting centre (same unit as ``points``).
    radii0 : (3,) array_like
        Starting semi-axes along ``rotation0``'s columns (the third along ``axis``).
    rotation0 : (3, 3) array_like, optional
        Starting orientation; its third column is replaced by ``axis`` and the
        first two are re-orthonormalised.  Default: any frame with z = ``axis``.
    weights : (N,) array_like, optional
    robust, max_iter, require_convergence
        As in `fit_ellipsoid`.

    Returns
    -------
    EllipsoidFit
        Radii in decreasing order (the covariance's rotation block has rank 1,
        about ``axis``).
    """
    from .base import orthonormal_basis

    X, _, c, frame = check_inputs(points, None, weights, n_params=7, model="ellipsoid")
    z = np.asarray(axis, float).reshape(3)
    nz = np.linalg.norm(z)
    if not (np.isfinite(nz) and nz > 0):
        raise DegenerateError("ellipsoid: the axis must be a finite non-zero vector")
    z = z / nz
    if rotation0 is None:
        u, v = orthonormal_basis(z)
    else:
        R0 = np.asarray(rotation0, float).reshape(3, 3)
        u = R0[:, 0] - (R0[:, 0] @ z) * z
        if np.linalg.norm(u) < 1e-9:
            u, v = orthonormal_basis(z)
        else:
            u = u / np.linalg.norm(u)
            v = np.cross(z, u)
    R = np.column_stack([u, v, z])
    a0 = np.asarray(radii0, float).reshape(3)
    if not np.all(np.isfinite(a0) & (a0 > 0)):
        raise DegenerateError("ellipsoid: starting semi-axes must be positive")
    x0 = (frame.forward(np.asarray(centre0, float).reshape(3)), R, np.log(a0 / frame.scale), 0.0, 0.0)

    def fun(x, jac):
        ctr, Rx, log_a, _, _ = x
        Pb = (X - ctr) @ Rx
        d, parts = ellipsoid_distance(Pb, np.exp(log_a), jac)
        if not jac:
            return d, None
        n, d_la = parts
        J = np.empty((X.shape[0], 7))
        J[:, 0:3] = -n                                # body-frame translation
        J[:, 3] = n[:, 0] * Pb[:, 1] - n[:, 1] * Pb[:, 0]   # rotation about body z: (n x p)_z
        J[:, 4:7] = d_la
        return d, J

    def retract(x, dl):
        ctr, Rx, log_a, _, _ = x
        return (ctr + Rx @ dl[0:3], Rx @ _rodrigues(np.array([0.0, 0.0, dl[3]])),
                log_a + np.clip(dl[4:7], -1.0, 1.0), 0.0, 0.0)

    uo = 1.0 / (2.0 * np.sqrt(np.max(np.sum(X * X, axis=1))))
    sol = em_lm(fun, x0, retract, prior_weights=c, robust=robust, max_iter=max_iter,
                outlier_density=uo, model="ellipsoid")
    if require_convergence and not sol.converged:
        raise NotConvergedError(f"ellipsoid: no convergence in {max_iter} iterations")
    # pad the 7-parameter covariance to (translation, rotation vector, log a)
    C7 = sol.covariance
    C9 = np.zeros((9, 9))
    keep = np.r_[0, 1, 2, 5, 6, 7, 8]
    C9[np.ix_(keep, keep)] = C7
    ctr, Rf, la, _, _ = sol.params
    return _assemble(EllipsoidFit, replace(sol, covariance=C9), frame, ctr, Rf, la, None, n_shape=0)
