"""Shared pieces of the shape fitters: errors, input checks, normalisation.

Every fitter works in a normalised frame: points are translated to their
centroid ``m`` and divided by their RMS distance ``s`` from it, fitted there,
and the parameters mapped back.  This makes tolerances dimensionless and the
fits equivariant under rigid motion and scaling (the project passes metres,
but nothing here depends on the unit).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lowerlimb.errors import FitError

__all__ = [
    "FittingError",
    "TooFewPointsError",
    "NonFiniteError",
    "DegenerateError",
    "NotConvergedError",
    "Frame",
    "check_inputs",
]


class FittingError(FitError):
    """A shape could not be fitted to the given points (base of the errors below)."""


class TooFewPointsError(FittingError):
    """Fewer (usable) points than the model has parameters."""


class NonFiniteError(FittingError):
    """Points, normals or weights contain NaN or infinite values (or weights are invalid)."""


class DegenerateError(FittingError):
    """The points do not determine the model (collinear, coplanar for a sphere, ...)."""


class NotConvergedError(FittingError):
    """The iterative refinement did not converge or produced non-finite values."""


@dataclass(frozen=True)
class Frame:
    """Similarity used to normalise points: ``x_normalised = (x - origin) / scale``."""

    origin: np.ndarray
    scale: float

    def forward(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, float) - self.origin) / self.scale

    def back(self, y: np.ndarray) -> np.ndarray:
        return np.asarray(y, float) * self.scale + self.origin


def check_inputs(points, normals=None, weights=None, *, n_params: int, model: str):
    """Validate and normalise fitter inputs.

    Parameters
    ----------
    points : (N, 3) array_like
        Point coordinates (any length unit; the project uses metres).
    normals : (N, 3) array_like or None
        Surface normals at the points (need not be unit length, sign ignored).
    weights : (N,) array_like or None
        Non-negative prior weights (e.g. inverse variances), at least one positive.
    n_params : int
        Number of model parameters; at least this many weighted points are needed.
    model : str
        Name used in error messages.

    Returns
    -------
    X : (N, 3) ndarray
        Points in the normalised frame.
    U : (N, 3) ndarray or None
        Unit normals (rotation only, so valid in the normalised frame).
    w : (N,) ndarray
        Prior weights scaled to mean 1 over the positive ones.
    frame : Frame
        The normalising similarity.
    """
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise FittingError(f"{model}: points must be an (N, 3) array, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(P), axis=1)))
        raise NonFiniteError(f"{model}: {bad} point(s) contain NaN or infinite coordinates")
    n = P.shape[0]
    if weights is None:
        w = np.ones(n)
    else:
        w = np.asarray(weights, dtype=float).reshape(-1)
        if w.shape[0] != n:
            raise FittingError(f"{model}: {w.shape[0]} weights for {n} points")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise NonFiniteError(f"{model}: weights must be finite and non-negative")
    n_used = int(np.count_nonzero(w > 0))
    if n_used < n_params:
        raise TooFewPointsError(
            f"{model}: {n_used} usable point(s), at least {n_params} needed")
    w = w * (n_used / w.sum())
    U = None
    if normals is not None:
        U = np.asarray(normals, dtype=float)
        if U.shape != P.shape:
            raise FittingError(f"{model}: normals shape {U.shape} does not match points {P.shape}")
        if not np.all(np.isfinite(U)):
            raise NonFiniteError(f"{model}: normals contain NaN or infinite values")
        norm = np.linalg.norm(U, axis=1)
        if np.any(norm[w > 0] == 0):
            raise NonFiniteError(f"{model}: some normals have zero length")
        U = U / np.where(norm > 0, norm, 1.0)[:, None]
    origin = (w @ P) / w.sum()
    scale = float(np.sqrt((w @ np.sum((P - origin) ** 2, axis=1)) / w.sum()))
    if not scale > 0 or not np.isfinite(scale):
        raise DegenerateError(f"{model}: all points coincide")
    frame = Frame(origin=origin, scale=scale)
    return frame.forward(P), U, w, frame


def orthonormal_basis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors ``u, v`` completing unit ``a`` to a right-handed frame."""
    i = int(np.argmin(np.abs(a)))
    e = np.zeros(3)
    e[i] = 1.0
    # explicit cross products: np.cross costs more than the arithmetic here
    u = np.array([a[1] * e[2] - a[2] * e[1], a[2] * e[0] - a[0] * e[2], a[0] * e[1] - a[1] * e[0]])
    u /= np.sqrt(u @ u)
    v = np.array([a[1] * u[2] - a[2] * u[1], a[2] * u[0] - a[0] * u[2], a[0] * u[1] - a[1] * u[0]])
    return u, v


def estimate_normals(X: np.ndarray, k: int = 12, query: np.ndarray | None = None,
                     return_likeness: bool = False):
    """Unit normals by PCA of the ``k`` nearest neighbours (sign arbitrary).

    Uses `scipy.spatial.cKDTree`; the normal is the eigenvector of the smallest
    eigenvalue of each neighbourhood covariance.  ``query`` (indices) restricts
    the points whose normals are returned; with ``return_likeness`` the
    `surface_likeness` of the same neighbourhoods is returned too.
    """
    from scipy.spatial import cKDTree

    k = int(min(k, X.shape[0]))
    Q = X if query is None else X[query]
    _, idx = cKDTree(X).query(Q, k=k)
    nb = X[idx]                                   # (M, k, 3)
    nb = nb - nb.mean(axis=1, keepdims=True)
    C = np.einsum("nki,nkj->nij", nb, nb)
    lam, vecs = np.linalg.eigh(C)
    if not return_likeness:
        return vecs[:, :, 0]
    tot = lam.sum(axis=1)
    like = np.clip(1.0 - 3.0 * lam[:, 0] / np.where(tot > 0, tot, 1.0), 0.0, 1.0)
    return vecs[:, :, 0], like


def surface_likeness(X: np.ndarray, query: np.ndarray | None = None, k: int = 12,
                     tree=None) -> np.ndarray:
    r"""How much each point's neighbourhood looks like a surface patch, in [0, 1].

    :math:`s = 1 - 3\lambda_0 / (\lambda_0 + \lambda_1 + \lambda_2)` from the
    eigenvalues of the covariance of the ``k`` nearest neighbours: 1 on a
    noise-free surface, 0 for isotropic (volume-filling) clutter.  Used to
    down-weight scattered outliers when forming closed-form starting estimates,
    which otherwise break down beyond ~30 % outliers.

    Parameters
    ----------
    X : (N, 3) ndarray
        All points (neighbours are searched among them).
    query : (M,) int ndarray, optional
        Indices of the points to score (default all).
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(X) if tree is None else tree
    Q = X if query is None else X[query]
    k = int(min(k, X.shape[0]))
    _, idx = tree.query(Q, k=k)
    nb = X[idx]
    nb = nb - nb.mean(axis=1, keepdims=True)
    C = np.einsum("nki,nkj->nij", nb, nb)
    lam = np.linalg.eigvalsh(C)
    tot = lam.sum(axis=1)
    s = 1.0 - 3.0 * lam[:, 0] / np.where(tot > 0, tot, 1.0)
    return np.clip(s, 0.0, 1.0)
