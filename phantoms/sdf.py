"""Signed distance functions (SDF) of analytic solids and their smooth unions.

Convention: ``f(p) < 0`` inside, ``f(p) = 0`` on the surface, ``f(p) > 0``
outside, in metres.  Spheres, capsules, round cones and capped cylinders are
exact Euclidean distances; ellipsoids, superellipsoids and waisted surfaces of
revolution are implicit functions divided by their gradient norm
(``F / |grad F|``), which is the Euclidean distance to first order near the
surface (a few mm for bone-sized parts).

Every node is immutable and evaluates a whole point array ``(N, 3)`` at once.
Each node knows an axis-aligned box enclosing its solid (`bounds`), which the
union uses to skip far-away parts (their value only matters within the blend
width ``k``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from lowerlimb.geometry import frame_zy, unit

_EPS = 1e-12


def _mm(p: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``p @ M`` for (N,3)x(3,k); einsum is much faster than BLAS matmul for thin arrays."""
    return np.einsum("ij,jk->ik", p, M)


def _mv(p: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``p @ v`` for (N,3)x(3,)."""
    return np.einsum("ij,j->i", p, v)


def _norm(p: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("ij,ij->i", p, p))


class SDF:
    """Base class: a solid with ``__call__(p (N,3)) -> (N,)`` signed distances."""

    def __call__(self, p: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - abstract
        """(lo, hi) corners of a box containing the solid, metres."""
        raise NotImplementedError


@dataclass(frozen=True, eq=False)
class Sphere(SDF):
    """``|p - c| - r`` (exact)."""

    centre: np.ndarray
    radius: float

    def __call__(self, p):
        return _norm(p - self.centre) - self.radius

    def bounds(self):
        c = np.asarray(self.centre, float)
        return c - self.radius, c + self.radius


@dataclass(frozen=True, eq=False)
class RoundCone(SDF):
    """Convex hull of two spheres (a, ra) and (b, rb) (exact; capsule when ra == rb).

    Distance of the 2-D problem in the plane of the axis (Quilez' round cone).
    """

    a: np.ndarray
    b: np.ndarray
    ra: float
    rb: float

    def __call__(self, p):
        a = np.asarray(self.a, float)
        b = np.asarray(self.b, float)
        ba = b - a
        l2 = ba @ ba
        rr = self.ra - self.rb
        a2 = l2 - rr * rr
        il2 = 1.0 / l2
        pa = p - a
        y = _mv(pa, ba)
        z = y - l2
        xv = pa * l2 - y[:, None] * ba
        x2 = np.einsum("ij,ij->i", xv, xv)
        y2 = y * y * l2
        z2 = z * z * l2
        k = np.sign(rr) * rr * rr * x2
        out = np.empty(len(p))
        c1 = np.sign(z) * a2 * z2 > k
        c2 = (~c1) & (np.sign(y) * a2 * y2 < k)
        c3 = ~(c1 | c2)
        out[c1] = np.sqrt(x2[c1] + z2[c1]) * il2 - self.rb
        out[c2] = np.sqrt(x2[c2] + y2[c2]) * il2 - self.ra
        out[c3] = (np.sqrt(x2[c3] * a2 * il2) + y[c3] * rr) * il2 - self.ra
        return out

    def bounds(self):
        a = np.asarray(self.a, float)
        b = np.asarray(self.b, float)
        r = max(self.ra, self.rb)
        return np.minimum(a, b) - r, np.maximum(a, b) + r


@dataclass(frozen=True, eq=False)
class _Oriented(SDF):
    """Solid defined in a local frame: ``q = R^T (p - centre)``."""

    centre: np.ndarray
    rotation: np.ndarray  # (3,3) columns = local axes in the parent frame

    def _local(self, p):
        return _mm(p - self.centre, np.asarray(self.rotation, float))

    def _box(self, half):
        half = np.abs(np.asarray(self.rotation, float)) @ np.asarray(half, float)
        c = np.asarray(self.centre, float)
        return c - half, c + half


@dataclass(frozen=True, eq=False)
class Ellipsoid(_Oriented):
    """``F = |q / r| - 1`` normalised: ``d = F |q/r| / |q/r^2|`` (Quilez)."""

    radii: np.ndarray = field(default_factory=lambda: np.ones(3))

    def __call__(self, p):
        q = self._local(p)
        r = np.asarray(self.radii, float)
        k0 = _norm(q / r)
        k1 = _norm(q / (r * r))
        return k0 * (k0 - 1.0) / np.maximum(k1, _EPS)

    def bounds(self):
        return self._box(self.radii)


@dataclass(frozen=True, eq=False)
class SuperEllipsoid(_Oriented):
    """``F = (sum |q_i/r_i|^n)^(1/n) - 1`` divided by ``|grad F|`` (boxy for n > 2)."""

    radii: np.ndarray = field(default_factory=lambda: np.ones(3))
    exponent: float = 4.0

    def __call__(self, p):
        q = self._local(p)
        r = np.asarray(self.radii, float)
        n = self.exponent
        u = np.abs(q / r) + 1e-15
        s = np.sum(u**n, axis=1)
        g = s ** (1.0 / n)
        # dF/dq_i = u_i^(n-1) / r_i * g^(1-n)
        grad = (u ** (n - 1.0) / r) * (g ** (1.0 - n))[:, None]
        return (g - 1.0) / np.maximum(_norm(grad), _EPS)

    def bounds(self):
        return self._box(self.radii)


@dataclass(frozen=True, eq=False)
class CappedCylinder(_Oriented):
    """Cylinder of radius `radius` along local z, ``|z| <= half_length``, edges rounded by `rounding` (exact)."""

    radius: float = 1.0
    half_length: float = 1.0
    rounding: float = 0.0   # edge fillet radius (exact rounded cylinder)

    def __call__(self, p):
        q = self._local(p)
        rr = self.rounding
        dr = np.hypot(q[:, 0], q[:, 1]) - (self.radius - rr)
        dz = np.abs(q[:, 2]) - (self.half_length - rr)
        outside = np.hypot(np.maximum(dr, 0), np.maximum(dz, 0))
        return np.minimum(np.maximum(dr, dz), 0.0) + outside - rr

    def bounds(self):
        return self._box([self.radius, self.radius, self.half_length])


@dataclass(frozen=True, eq=False)
class WaistedNeck(_Oriented):
    """Surface of revolution about local z with radius ``r(t) = r_min + c (t - t0)^2``.

    Side distance ``(rho - r(t)) / sqrt(1 + r'(t)^2)``, capped by the planes
    ``t = t_start`` and ``t = t_end``.  Its narrowest cross-section (radius
    `r_min`, at ``t = t0``) is exact.
    """

    r_min: float = 0.01
    curvature: float = 0.0
    t0: float = 0.0
    t_start: float = -1.0
    t_end: float = 1.0

    def __call__(self, p):
        q = self._local(p)
        t = q[:, 2]
        rho = np.hypot(q[:, 0], q[:, 1])
        dt = t - self.t0
        r = self.r_min + self.curvature * dt * dt
        dside = (rho - r) / np.sqrt(1.0 + (2.0 * self.curvature * dt) ** 2)
        dcap = np.maximum(self.t_start - t, t - self.t_end)
        return np.maximum(dside, dcap)

    def bounds(self):
        rmax = self.r_min + self.curvature * max((self.t_start - self.t0) ** 2, (self.t_end - self.t0) ** 2)
        return self._local_box_corner(rmax)

    def _local_box_corner(self, rmax):
        c = np.asarray(self.centre, float)
        R = np.asarray(self.rotation, float)
        pts = []
        for t in (self.t_start, self.t_end):
            for sx in (-rmax, rmax):
                for sy in (-rmax, rmax):
                    pts.append(c + R @ np.array([sx, sy, t]))
        pts = np.array(pts)
        return pts.min(0), pts.max(0)


@dataclass(frozen=True, eq=False)
class Offset(SDF):
    """`inner` grown by `distance` (``inner(p) - distance``): a dilated solid."""

    inner: SDF
    distance: float

    def __call__(self, p):
        return self.inner(p) - self.distance

    def bounds(self):
        lo, hi = self.inner.bounds()
        return lo - self.distance, hi + self.distance


@dataclass(frozen=True, eq=False)
class Slab(SDF):
    """Half-space ``n . (p - point) <= 0`` (exact); unbounded."""

    point: np.ndarray
    normal: np.ndarray

    def __call__(self, p):
        return _mv(p - self.point, unit(self.normal))

    def bounds(self):
        return np.full(3, -np.inf), np.full(3, np.inf)


def smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum ``min(a,b) - max(k-|a-b|,0)^2 / (4k)``.

    Equals ``min(a, b)`` wherever ``|a - b| >= k``, so surfaces farther than
    `k` from any other part stay exact.
    """
    if k <= 0:
        return np.minimum(a, b)
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


def smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth maximum (``-smin(-a, -b, k)``)."""
    return -smin(-a, -b, k)


@dataclass(frozen=True, eq=False)
class Union(SDF):
    """Smooth union of `parts` with blend width `k` (folded pairwise).

    Parts whose box is farther than the current minimum plus `k` from a point
    cannot change the result there; they are evaluated only on the points
    whose distance to their box is below that bound.
    """

    parts: tuple
    k: float = 0.0

    def __call__(self, p):
        # Culling: ``|p - c_j| - R_j`` (bounding sphere) is a lower bound of part j's
        # distance.  Each point is first evaluated on the part with the smallest
        # bound, which gives an upper bound ``ub`` of the union; a part can only
        # matter where its lower bound is below ``ub + k``.  Values are then folded
        # in the fixed part order (skipped parts count as +inf).
        n, J = len(p), len(self.parts)
        if n == 0:
            return np.zeros(0)
        if J == 1:
            return self.parts[0](p)
        lb = np.empty((J, n))
        for j, (c, rad) in enumerate(self._part_spheres):
            dc = p - c
            lb[j] = np.sqrt(np.einsum("ij,ij->i", dc, dc)) - rad
        vals = np.full((J, n), np.inf)
        first = np.argmin(lb, axis=0)
        for j in range(J):
            idx = np.nonzero(first == j)[0]
            if len(idx):
                vals[j, idx] = self.parts[j](p[idx])
        ub = vals.min(axis=0)
        for j in range(J):
            idx = np.nonzero((lb[j] < ub + self.k) & (first != j))[0]
            if len(idx):
                vals[j, idx] = self.parts[j](p[idx])
        out = vals[0]
        for j in range(1, J):
            v = vals[j]
            both = np.isfinite(out) & np.isfinite(v)
            res = np.minimum(out, v)
            if both.any():
                res[both] = smin(out[both], v[both], self.k)
            out = res
        return out

    @cached_property
    def _part_spheres(self):
        out = []
        for lo, hi in self._part_bounds:
            out.append(((lo + hi) / 2, 0.5 * np.linalg.norm(hi - lo)))
        return out

    @cached_property
    def _part_bounds(self):
        return [tuple(np.asarray(b, float) for b in q.bounds()) for q in self.parts]

    def bounds(self):
        los, his = zip(*self._part_bounds)
        return np.min(los, axis=0) - self.k, np.max(his, axis=0) + self.k


@dataclass(frozen=True, eq=False)
class Difference(SDF):
    """``max(a, -b)`` (sharp) or smooth with blend `k`: `a` with `b` carved out."""

    a: SDF
    b: SDF
    k: float = 0.0

    def __call__(self, p):
        da = self.a(p)
        lo, hi = self.b.bounds()
        inb = np.all((p >= lo - self.k) & (p <= hi + self.k), axis=1)
        out = da.copy()
        if inb.any():
            db = self.b(p[inb])
            out[inb] = smax(da[inb], -db, self.k)
        return out

    def bounds(self):
        return self.a.bounds()


@dataclass(frozen=True, eq=False)
class Intersection(SDF):
    """``max`` of parts (sharp, or smooth with blend `k`)."""

    parts: tuple
    k: float = 0.0

    def __call__(self, p):
        out = self.parts[0](p)
        for q in self.parts[1:]:
            out = smax(out, q(p), self.k)
        return out

    def bounds(self):
        los, his = zip(*(q.bounds() for q in self.parts))
        return np.max(los, axis=0), np.min(his, axis=0)


@dataclass(frozen=True, eq=False)
class Transformed(SDF):
    """`inner` expressed in another frame: ``inner(A^-1 p)`` for a rigid (possibly reflecting) 4x4 `A`."""

    inner: SDF
    matrix: np.ndarray  # outer_from_inner

    def __call__(self, p):
        A = np.asarray(self.matrix, float)
        R, t = A[:3, :3], A[:3, 3]
        return self.inner(_mm(p - t, R))  # R orthogonal: R^-1 = R^T

    def bounds(self):
        lo, hi = self.inner.bounds()
        if not np.all(np.isfinite(lo)):
            return lo, hi
        A = np.asarray(self.matrix, float)
        c = (lo + hi) / 2
        h = (hi - lo) / 2
        cc = A[:3, :3] @ c + A[:3, 3]
        hh = np.abs(A[:3, :3]) @ h
        return cc - hh, cc + hh


def rotation_from_axes(x=None, y=None, z=None) -> np.ndarray:
    """Right-handed rotation whose columns are unit local axes; give two, the third follows.

    The axis kept exactly is Z if given, else X; the other is orthogonalised
    to it (z with y is `lowerlimb.geometry.frame_zy`).
    """
    if z is not None and y is not None:
        return frame_zy(z, y)
    if z is not None and x is not None:
        Z = unit(z)
        X = unit(np.asarray(x, float) - (np.dot(x, Z)) * Z)
        Y = np.cross(Z, X)
    elif x is not None and y is not None:
        X = unit(x)
        Y = unit(np.asarray(y, float) - (np.dot(y, X)) * X)
        Z = np.cross(X, Y)
    else:
        raise ValueError("give two axes")
    return np.column_stack([X, Y, Z])
