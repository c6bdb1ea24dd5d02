"""Geometry helpers shared by `kinematics`, `phantoms` and `personalize`.

Unit vectors, cross-product matrices, the two ISB-style frame constructions
(one axis exact, a second hint orthogonalised), the weighted Kabsch / Horn
rigid fit, area-weighted vertex normals of a triangle mesh, and the marker
size convention.  Everything is SI (metres) and works on plain numpy arrays.

Conventions
-----------
* Vectors run along the last axis; rotations are ``(..., 3, 3)`` with the
  local axes as columns (``R @ p_local = p_parent``).
* A zero vector has no direction: `unit` returns NaN for it unless the caller
  names a ``where`` context, in which case it raises `InputError` (use that on
  user-supplied directions).
"""
from __future__ import annotations

import numpy as np

from .errors import InputError

__all__ = ["unit", "skew", "frame_zy", "frame_yz", "kabsch", "kabsch_rotation", "vertex_normals", "signed_volume",
           "orient", "DEFAULT_MARKER_DIAMETER", "DEFAULT_MARKER_RADIUS", "marker_radius"]


def unit(v, *, where: str | None = None) -> np.ndarray:
    """``v / |v|`` along the last axis.

    Parameters
    ----------
    v : (..., 3) array_like
    where : str, optional
        Name of the input the vectors come from.  When given, a zero (< 1e-12)
        or non-finite length raises `InputError` naming it; otherwise such a
        vector divides to NaN/inf (numpy's warning).

    Returns
    -------
    (..., 3) ndarray of unit vectors.
    """
    v = np.asarray(v, float)
    # a single vector takes norm's dot-product path (its exact float result is what the callers had)
    n = np.linalg.norm(v) if v.ndim == 1 else np.linalg.norm(v, axis=-1, keepdims=True)
    if where is not None and (not np.all(np.isfinite(n)) or np.any(n < 1e-12)):
        raise InputError(where, "a zero or non-finite direction")
    return v / n


def orient(v, ref) -> np.ndarray:
    """``v`` flipped if needed so that it points along ``ref`` (``v . ref >= 0``); one vector."""
    return v if float(np.dot(v, ref)) >= 0 else -np.asarray(v)


def skew(v) -> np.ndarray:
    """Cross-product matrices ``[v]x`` (``[v]x @ u == np.cross(v, u)``), shape ``(..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack([
        np.stack([z, -v[..., 2], v[..., 1]], -1),
        np.stack([v[..., 2], z, -v[..., 0]], -1),
        np.stack([-v[..., 1], v[..., 0], z], -1),
    ], -2)


def frame_zy(z, y_hint, *, where: str | None = None) -> np.ndarray:
    """Rotation with columns X, Y, Z: ``Z = unit(z)``, Y = `y_hint` made orthogonal to Z, ``X = Y x Z``.

    The femoral and tibial ISB frames: Z along the joint axis, Y the long axis
    as near as orthogonality allows.  ``where`` as in `unit`.
    """
    Z = unit(z, where=where)
    yh = np.asarray(y_hint, float)
    Y = unit(yh - (yh @ Z) * Z, where=where)
    return np.column_stack([np.cross(Y, Z), Y, Z])


def frame_yz(y, z_hint, *, where: str | None = None) -> np.ndarray:
    """Rotation with columns X, Y, Z: ``Y = unit(y)``, Z = `z_hint` made orthogonal to Y, ``X = Y x Z``.

    A segment frame whose long axis is exact (OpenSim body frames).  ``where``
    as in `unit`.
    """
    Y = unit(y, where=where)
    zh = np.asarray(z_hint, float)
    Z = unit(zh - (zh @ Y) * Y, where=where)
    return np.column_stack([np.cross(Y, Z), Y, Z])


def kabsch_rotation(H) -> tuple[np.ndarray, np.ndarray]:
    """Proper rotation maximising ``tr(R H)``, from a cross-covariance ``H = sum w (p - p̄)(q - q̄)ᵀ``.

    ``H = U S Vᵀ`` gives ``R = V diag(1, 1, det(V Uᵀ)) Uᵀ`` (Kabsch 1976; the
    sign fix keeps ``det R = +1`` for noisy or planar sets).

    Parameters
    ----------
    H : (..., 3, 3) array_like

    Returns
    -------
    R : (..., 3, 3) ndarray
    s : (..., 3) ndarray
        Singular values of H, largest first: ``s[..., 1] ~ 0`` means collinear
        points (rotation about their line undetermined).
    """
    U, s, Vt = np.linalg.svd(np.asarray(H, float))
    V, Ut = np.swapaxes(Vt, -1, -2), np.swapaxes(U, -1, -2)
    D = np.zeros(U.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = np.sign(np.linalg.det(V @ Ut))
    return V @ D @ Ut, s


def kabsch(P, Q, weights=None) -> tuple[np.ndarray, np.ndarray]:
    r"""Weighted least-squares rigid motion taking points `P` onto `Q` (Kabsch / Horn, closed form).

    Model and minimised quantity::

        q_k ~ R p_k + t,        min_{R in SO(3), t}  sum_k w_k |R p_k + t - q_k|^2

    solved by the weighted centroids ``p̄, q̄`` and `kabsch_rotation` of
    ``H = sum_k w_k (p_k - p̄)(q_k - q̄)ᵀ``; ``t = q̄ - R p̄``.

    Parameters
    ----------
    P, Q : (K, 3) array_like, K >= 3 corresponding points (m)
    weights : (K,) array_like, optional, non-negative (uniform if omitted)

    Returns
    -------
    R : (3, 3) ndarray, rotation
    t : (3,) ndarray, translation (m)
    """
    P, Q = np.asarray(P, float), np.asarray(Q, float)
    if weights is None:
        pb, qb = P.mean(axis=0), Q.mean(axis=0)
        H = (P - pb).T @ (Q - qb)
    else:
        w = np.asarray(weights, float)
        w = w / w.sum()
        pb, qb = w @ P, w @ Q
        H = (P - pb).T @ (w[:, None] * (Q - qb))
    R, _ = kabsch_rotation(H)
    return R, qb - R @ pb


def signed_volume(vertices, faces) -> float:
    """Signed enclosed volume ``sum_f v0 . (v1 x v2) / 6`` of a triangle mesh (positive for outward faces).

    Taken about the vertex centroid: exact for closed meshes (any origin), and a
    stable orientation measure for open ones.
    """
    vv = np.asarray(vertices, float)
    v = (vv - vv.mean(axis=0))[np.asarray(faces)]
    return float(np.einsum("ij,ij->", v[:, 0], np.cross(v[:, 1], v[:, 2])) / 6.0)


def vertex_normals(vertices, faces) -> np.ndarray:
    """Area-weighted unit vertex normals of a triangle mesh; a vertex on no face of area gets (0, 0, 0).

    Each vertex sums the unnormalised normals ``(v1 - v0) x (v2 - v0)`` (length
    twice the area) of its faces, then is normalised.  Works on raw arrays
    (trimesh's cached ``vertex_normals`` needs a Trimesh and weights by angle).

    Parameters
    ----------
    vertices : (V, 3) array_like (m)
    faces : (F, 3) array_like of int, counter-clockwise seen from outside

    Returns
    -------
    (V, 3) ndarray
    """
    V = np.asarray(vertices, float)
    F = np.asarray(faces, np.int64)
    tri = V[F]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    # per-vertex sums over the incident faces (bincount: an order of magnitude faster than np.add.at)
    idx = F.ravel()
    fn3 = np.repeat(fn, 3, axis=0)
    vn = np.column_stack([np.bincount(idx, weights=fn3[:, c], minlength=len(V)) for c in range(3)])
    nn = np.linalg.norm(vn, axis=1)
    ok = nn > 0
    vn[ok] /= nn[ok][:, None]
    return vn


#: marker size is stated as a diameter, as Vicon's ``MarkerDiameter`` subject parameter (m; 14 mm markers)
DEFAULT_MARKER_DIAMETER = 0.014


def marker_radius(diameter: float = DEFAULT_MARKER_DIAMETER) -> float:
    """Radius (m) of a spherical marker of the given diameter: the marker centre sits this far off the skin."""
    return 0.5 * float(diameter)


#: radius of the default marker (m): the only radius constant; a subject's own size comes as a diameter
DEFAULT_MARKER_RADIUS = marker_radius(DEFAULT_MARKER_DIAMETER)
