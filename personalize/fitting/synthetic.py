"""Point clouds with known truth for tests and benchmarks (seeded, vectorised).

All samplers return ``(points, exact)``: noisy points and the noise-free surface
points they were generated from (for Cramér-Rao bounds).  Noise is Gaussian
along the surface normal with standard deviation ``noise`` (same unit as the
shape).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["sphere_cap", "cylinder_arc", "add_outliers", "superquadric_surface",
           "random_rotation", "sphere_crb", "cylinder_crb"]


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly distributed rotation matrix (3, 3)."""
    return Rotation.random(random_state=rng).as_matrix()


def sphere_cap(rng, n, radius, half_angle, noise, centre=(0, 0, 0), rotation=None):
    """Points on a spherical cap of the given half-angle (radians) around +z (then rotated)."""
    u = rng.uniform(np.cos(half_angle), 1.0, n)          # area-uniform on the cap
    phi = rng.uniform(0.0, 2 * np.pi, n)
    s = np.sqrt(1 - u * u)
    d = np.column_stack([s * np.cos(phi), s * np.sin(phi), u])
    R = np.eye(3) if rotation is None else rotation
    d = d @ R.T
    exact = np.asarray(centre, float) + radius * d
    return exact + rng.normal(0.0, noise, n)[:, None] * d, exact


def cylinder_arc(rng, n, radius, arc, length, noise, point=(0, 0, 0), rotation=None):
    """Points on a cylinder arc (``arc`` radians, centred on +x) of axis z (then rotated)."""
    th = rng.uniform(-arc / 2, arc / 2, n)
    z = rng.uniform(-length / 2, length / 2, n)
    d = np.column_stack([np.cos(th), np.sin(th), np.zeros(n)])
    R = np.eye(3) if rotation is None else rotation
    exact = radius * d + np.column_stack([0 * z, 0 * z, z])
    exact = exact @ R.T + np.asarray(point, float)
    d = d @ R.T
    return exact + rng.normal(0.0, noise, n)[:, None] * d, exact


def add_outliers(rng, points, fraction, margin=0.2):
    """Append uniform outliers in the enlarged bounding box, ``fraction`` of the total.

    Returns ``(all_points, is_outlier)``.
    """
    n_in = points.shape[0]
    n_out = int(round(fraction * n_in / (1.0 - fraction))) if fraction > 0 else 0
    lo, hi = points.min(0), points.max(0)
    pad = margin * (hi - lo).max()
    out = rng.uniform(lo - pad, hi + pad, (n_out, 3))
    mask = np.r_[np.zeros(n_in, bool), np.ones(n_out, bool)]
    return np.vstack([points, out]), mask


def _spow(x, p):
    return np.sign(x) * np.abs(x) ** p


def superquadric_surface(rng, n, scale, shape, noise, centre=(0, 0, 0), rotation=None,
                         n_candidates=40000):
    """Approximately area-uniform points on a superquadric surface.

    Dense parametric samples are drawn and resampled with probability
    proportional to their surface area element (finite differences), so that
    sharp (small epsilon) shapes are not over-sampled at their edges.
    Noise is added along the surface normal (gradient of the inside-outside function).
    """
    a = np.asarray(scale, float)
    e1, e2 = shape
    m = n_candidates
    eta = rng.uniform(-np.pi / 2, np.pi / 2, m)
    om = rng.uniform(-np.pi, np.pi, m)

    def surf(eta, om):
        ce, se = np.cos(eta), np.sin(eta)
        return np.column_stack([a[0] * _spow(ce, e1) * _spow(np.cos(om), e2),
                                a[1] * _spow(ce, e1) * _spow(np.sin(om), e2),
                                a[2] * _spow(se, e1)])
    h = 1e-5
    x = surf(eta, om)
    de = (surf(eta + h, om) - surf(eta - h, om)) / (2 * h)
    do = (surf(eta, om + h) - surf(eta, om - h)) / (2 * h)
    area = np.linalg.norm(np.cross(de, do), axis=1)
    area = np.where(np.isfinite(area), area, 0.0)
    idx = rng.choice(m, size=n, replace=True, p=area / area.sum())
    x = x[idx]
    # Normal from the gradient of F (log-safe enough for the sampled points).
    ax = np.maximum(np.abs(x / a), 1e-12)
    f12 = ax[:, 0] ** (2 / e2) + ax[:, 1] ** (2 / e2)
    g = np.column_stack([
        (2 / e1) * f12 ** (e2 / e1 - 1) * ax[:, 0] ** (2 / e2 - 1) * np.sign(x[:, 0]) / a[0],
        (2 / e1) * f12 ** (e2 / e1 - 1) * ax[:, 1] ** (2 / e2 - 1) * np.sign(x[:, 1]) / a[1],
        (2 / e1) * ax[:, 2] ** (2 / e1 - 1) * np.sign(x[:, 2]) / a[2]])
    nrm = np.linalg.norm(g, axis=1, keepdims=True)
    g = np.where(nrm > 0, g / np.where(nrm > 0, nrm, 1), 0.0)
    R = np.eye(3) if rotation is None else rotation
    exact = x @ R.T + np.asarray(centre, float)
    return exact + rng.normal(0.0, noise, n)[:, None] * (g @ R.T), exact


def sphere_crb(exact, centre, noise):
    """Cramér-Rao bound (4, 4) for ``(centre, radius)`` from noise-free surface points."""
    d = exact - centre
    J = np.column_stack([-d / np.linalg.norm(d, axis=1, keepdims=True), -np.ones(len(d))])
    return noise ** 2 * np.linalg.inv(J.T @ J)


def cylinder_crb(exact, point, axis, noise):
    """Cramér-Rao bound (5, 5) for the local line parameters ``(s, t, alpha, beta, R)``.

    ``(s, t)`` move the axis point across the axis along ``u, v``; ``(alpha, beta)``
    tilt the axis (radians) -- with ``(u, v, axis)`` from
    `personalize.fitting.base.orthonormal_basis` -- and the point is the foot of the
    centroid of ``exact``.
    """
    from .base import orthonormal_basis

    u, v = orthonormal_basis(axis)
    m = exact.mean(0)
    p = point + ((m - point) @ axis) * axis
    Y = exact - p
    h = Y @ axis
    Q = Y - h[:, None] * axis
    N = Q / np.linalg.norm(Q, axis=1, keepdims=True)
    nu, nv = N @ u, N @ v
    J = np.column_stack([-nu, -nv, -h * nu, -h * nv, -np.ones(len(h))])
    return noise ** 2 * np.linalg.inv(J.T @ J)
