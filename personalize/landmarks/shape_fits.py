"""Articular primitives on a bone surface: principal axes, Hough votes, refined sphere and cylinder fits.

Hough voting along the surface normals finds sphere (or cylinder-axis)
centres without a starting guess; `refine_sphere` / `refine_cylinder` then
iterate "fit, keep the points within a band of the primitive, refit" around
the project's shape fitters (`personalize.fitting`).  The covariances of
their results are what the landmarks report (`sphere_centre_cov`,
`axis_sd_deg`).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from lowerlimb.errors import FitError
from lowerlimb.geometry import orient, unit

from .common import Axis, Landmark

__all__ = ["principal_axes", "hough_centres", "sphere_centre_cov", "refine_sphere", "refine_cylinder",
           "line_through", "axis_sd_deg", "perpendicular", "isotropic_cov", "sphere_fit_json"]


# Smallest positional variance reported (1 micrometre^2): fits of exact
# synthetic surfaces have ~zero residuals, a covariance must stay positive.
_VAR_FLOOR = 1e-12


def principal_axes(points: np.ndarray, weights: np.ndarray | None = None):
    """Weighted centroid and principal axes, largest spread first.

    Returns
    -------
    centre : (3,) ndarray
    axes : (3, 3) ndarray, columns are unit axes (signs arbitrary)
    sd : (3,) ndarray, standard deviation along each axis (m)
    """
    P = np.asarray(points, float)
    w = np.ones(len(P)) if weights is None else np.asarray(weights, float)
    c = (w @ P) / w.sum()
    D = P - c
    C = (D * w[:, None]).T @ D / w.sum()
    ev, vec = np.linalg.eigh(C)
    order = np.argsort(ev)[::-1]
    return c, vec[:, order], np.sqrt(np.maximum(ev[order], 0))


def size_unit(points, axis, adult: float, res, what: str) -> float:
    """The search's unit of length for a bone: its extent along `axis` over `adult` (m), at most 1.

    Detectors written for adult bones keep their constants (1) on every adult of the real sets; a smaller
    (child's) bone is searched at its own size, its constants times this unit, and `res` gets a note.
    """
    extent = float(np.ptp(np.asarray(points, float) @ np.asarray(axis, float)))
    u = min(1.0, extent / adult)
    if u < 1.0:
        res.notes.append(f"{res.bone}: {extent * 1e3:.0f} mm {what}, searched at {u:.2f} x adult size")
    return u


def hough_centres(points, normals, radii, *, inward: bool, tol: float, n_peaks: int = 1,
                  min_separation: float = 0.0, max_points: int = 2500):
    """Vote for centres of spheres (or cylinder axes) tangent to the surface.

    Each surface point ``p`` with outward unit normal ``n`` votes, for each
    radius ``r``, for the centre ``p - r n`` (convex shapes such as a femoral
    head; ``p + r n`` for sockets, ``inward=True``).  A patch of a sphere of
    radius ``r`` concentrates its votes at the sphere's centre, so the support
    of a vote (number of votes within ``tol`` of it) peaks there.  Points are
    thinned by a fixed stride over their indices (never by coordinates), so
    the result moves rigidly with the input.

    Returns
    -------
    peaks : list of (support, centre (3,), radius)
        Up to ``n_peaks`` maxima, best first, pairwise at least
        ``min_separation`` apart.
    """
    P = np.asarray(points, float)
    N = np.asarray(normals, float)
    step = max(1, int(np.ceil(len(P) / max_points)))
    P, N = P[::step], N[::step]
    s = 1.0 if inward else -1.0
    C = np.concatenate([P + s * r * N for r in radii])
    R = np.repeat(np.asarray(radii, float), len(P))
    if len(C) == 0:
        return []
    # the number of votes within `tol` of each vote, itself included: query_ball_point's count, from the
    # pair list (2x less CPU on 10-40 k votes of 2-330 neighbours each)
    pairs = cKDTree(C).query_pairs(tol, output_type="ndarray")
    support = 1.0 + np.bincount(pairs.ravel(), minlength=len(C))
    peaks = []
    alive = np.ones(len(C), bool)
    for _ in range(n_peaks):
        if not alive.any():
            break
        k = int(np.argmax(np.where(alive, support, -1.0)))
        peaks.append((float(support[k]), C[k].copy(), float(R[k])))
        alive &= np.linalg.norm(C - C[k], axis=1) >= max(min_separation, tol)
    return peaks


def sphere_centre_cov(fit) -> np.ndarray:
    cov = np.asarray(fit.covariance, float)[:3, :3]
    return cov + _VAR_FLOOR * np.eye(3)


def _in_band(d, dist, N, r, band, convex, min_cos, mask) -> np.ndarray:
    """Points within `band` of a primitive of radius `r` (``d`` their offsets from its centre or axis, ``dist``
    the offsets' lengths) whose normals point away from it (``convex``) or towards it, cosine above `min_cos`."""
    cosn = np.einsum("ij,ij->i", d, N) / np.maximum(dist, 1e-12)
    if not convex:
        cosn = -cosn
    sel = (np.abs(dist - r) < band) & (cosn > min_cos)
    if mask is not None:
        sel &= mask
    return sel


def _reselect_and_fit(select, refit, iterations: int, min_points: int, kind: str):
    """Alternate ``sel = select()`` and ``fit = refit(sel)`` until the selection stops changing.

    Raises FitError when the first selection has fewer than `min_points`
    points; a later one that small stops the iteration at the last fit.
    """
    fit, sel = None, None
    for _ in range(iterations):
        sel_new = select()
        if sel_new.sum() < min_points:
            if fit is None:
                raise FitError(f"{kind}: only {int(sel_new.sum())} surface points near the initial guess")
            break
        if sel is not None and np.array_equal(sel, sel_new):
            break
        sel = sel_new
        fit = refit(sel)
    return fit, sel


def refine_sphere(points, normals, centre, radius, *, band: float, convex: bool = True,
                  min_cos: float = 0.7, mask=None, iterations: int = 3):
    """Fit a sphere to the points near a first guess, then re-select and refit.

    Points are kept when their distance to the sphere is within ``band`` and
    their normal points away from the centre (towards it for a concave
    socket, ``convex=False``) with cosine at least ``min_cos``.

    Returns
    -------
    fit : sphere result of `personalize.fitting.fit_sphere`
    sel : (N,) bool mask of the points used in the last fit
    """
    from personalize.fitting import fit_sphere

    P = np.asarray(points, float)
    N = np.asarray(normals, float)
    c, r = np.asarray(centre, float), float(radius)

    def select():
        d = P - c
        return _in_band(d, np.linalg.norm(d, axis=1), N, r, band, convex, min_cos, mask)

    def refit(sel):
        nonlocal c, r
        fit = fit_sphere(P[sel], normals=N[sel])
        c, r = np.asarray(fit.centre, float), float(fit.radius)
        return fit

    return _reselect_and_fit(select, refit, iterations, 20, "sphere")


def refine_cylinder(points, normals, point, axis, radius, *, band: float, convex: bool = True,
                    min_cos: float = 0.6, mask=None, iterations: int = 3, half_length: float | None = None):
    """Cylinder analogue of `refine_sphere` (distance measured to the axis line)."""
    from personalize.fitting import fit_cylinder

    P = np.asarray(points, float)
    N = np.asarray(normals, float)
    p0, u, r = np.asarray(point, float), unit(axis), float(radius)

    def select():
        d = P - p0
        t = d @ u
        radial = d - t[:, None] * u
        sel = _in_band(radial, np.linalg.norm(radial, axis=1), N, r, band, convex, min_cos, mask)
        if half_length is not None:
            sel &= np.abs(t) < half_length
        return sel

    def refit(sel):
        nonlocal p0, u, r
        fit = fit_cylinder(P[sel], normals=N[sel], axis_hint=u)
        u = orient(unit(np.asarray(fit.axis, float)), u)
        p0, r = np.asarray(fit.point, float), float(fit.radius)
        # keep the reference point mid-selection so `half_length` stays centred
        tt = (P[sel] - p0) @ u
        p0 = p0 + 0.5 * (tt.min() + tt.max()) * u
        return fit

    fit, sel = _reselect_and_fit(select, refit, iterations, 30, "cylinder")
    return fit, sel, p0, u


def line_through(a: Landmark, b: Landmark) -> Axis:
    """Axis from ``a`` to ``b`` with the angular sd implied by the two point covariances."""
    d = b.position - a.position
    L = float(np.linalg.norm(d))
    u = d / L
    C = a.cov + b.cov
    Pp = np.eye(3) - np.outer(u, u)
    var_perp = float(np.trace(Pp @ C @ Pp)) / 2.0  # per perpendicular direction
    sd = np.degrees(np.sqrt(max(var_perp, 0.0)) / L)
    return Axis(point=0.5 * (a.position + b.position), direction=u, sd_deg=float(sd))


def axis_sd_deg(fit) -> float:
    if hasattr(fit, "axis_sd"):
        return float(np.degrees(fit.axis_sd))
    """1-sd angle (deg) of a fitted cylinder's axis from its covariance.

    The fitters parametrise the axis direction by two tangent-plane angles;
    their variances are read from the covariance block named by the result
    (``axis_covariance``) when present, otherwise from the documented
    parameter order (point, axis angles, radius).
    """
    ac = getattr(fit, "axis_covariance", None)
    if ac is not None:
        ac = np.asarray(ac, float)
        return float(np.degrees(np.sqrt(max(np.trace(ac) / 2.0 if ac.shape[0] >= 2 else float(ac), 0.0))))
    cov = np.asarray(fit.covariance, float)
    if cov.shape == (5, 5):  # (2 point offsets, 2 axis angles, radius)
        return float(np.degrees(np.sqrt(max((cov[2, 2] + cov[3, 3]) / 2.0, 0.0))))
    if cov.shape == (7, 7):  # (point 3, direction 3, radius)
        return float(np.degrees(np.sqrt(max(np.trace(cov[3:6, 3:6]) / 2.0, 0.0))))
    return float("nan")


def perpendicular(v: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Component of ``v`` perpendicular to unit ``axis``."""
    return v - (v @ axis) * axis



def isotropic_cov(*sd: float) -> np.ndarray:
    """``(sum of sd_i^2) I``: the 3x3 covariance of independent isotropic errors of the given sds (m)."""
    return sum(s * s for s in sd) * np.eye(3)


def sphere_fit_json(fit, n: int) -> dict:
    """A sphere fit as written to landmarks.json's ``fits`` (m)."""
    return {"type": "sphere", "centre": np.asarray(fit.centre).tolist(), "radius": float(fit.radius),
            "rms": float(fit.rms), "n_points": int(n), "converged": bool(fit.converged)}
