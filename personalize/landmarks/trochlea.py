r"""Talar trochlea cylinder in STAPLE's talus-intrinsic convention (an option).

STAPLE (Modenese & Renault 2021, ``CS_talus_trochleaCylinder`` with
GIBOC-core's ``fitQuadriTalus`` and ``fitCSATalus``) finds the trochlea from
the talus alone, independent of the ankle angle in the scan:

1. long axis ``X0``: the talus' principal axis of least inertia (volume);
2. superior ``Z0``: a quadrilateral fitted to the bone's outline projected on
   the plane normal to ``X0``; the edge opposite the longest one is superior;
3. cross-section areas along ``X0`` fitted by two Gaussians
   :math:`a_1 e^{-((x-b_1)/c_1)^2} + a_2 e^{-((x-b_2)/c_2)^2}`: the smaller
   one is the head (``X0`` is oriented towards it), the neck starts midway
   between the peaks, the tibial surface behind ``b_body - c_body``;
4. seed: vertices with low curvature (max |principal curvature| under its
   median), normal within 60 deg of ``Z0``, not within 60 deg of
   ``Y0 = Z0 x X0``, behind the neck; morphological clean-up on faces
   (close, keep largest, erode, keep largest, close, dilate; steps scaled to
   0.5 mm edges);
5. cylinder fitted to the face incentres; faces kept within
   :math:`-0.05 R < d < 0.10 R` of it and in front of the tibial start; refit.
   Minimised: :math:`\sum_i (\lVert (I - a a^T)(x_i - p) \rVert - R)^2`
   over the kept incentres :math:`x_i` (unweighted, as STAPLE's ``lscylinder``).
6. centre: the axis point level with the incentres' centroid.

``refit_iterations > 1`` repeats step 5 until the selection stops changing;
``centre="mid"`` puts the centre in the middle of the selection's extent
along the axis; ``posterior_cut=False`` drops step 5's back-of-bone limit.
Measured on ICL-MRI and TLEM2-MRI (``benchmarks/landmarks.py``), none of
these is the project default: see `personalize.landmarks.talus`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import curve_fit
from scipy.spatial import ConvexHull
from scipy.sparse.csgraph import connected_components

from lowerlimb.errors import FitError
from lowerlimb.geometry import orient, unit

from .surface import Surface

__all__ = ["TrochleaCylinder", "staple_trochlea_cylinder"]


@dataclass(frozen=True)
class TrochleaCylinder:
    """Talar trochlea cylinder (metres).

    point : (3,) centre on the axis; axis : (3,) unit (sign arbitrary);
    radius : float; covariance : (7, 7) of (point, axis, radius) from the fit;
    faces : (F,) bool, the trochlea faces used; long_axis, superior : (3,)
    the talus-intrinsic X0 (anterior) and Z0; n_iterations : refits done.
    """

    point: np.ndarray
    axis: np.ndarray
    radius: float
    covariance: np.ndarray
    rms: float
    faces: np.ndarray
    long_axis: np.ndarray
    superior: np.ndarray
    n_iterations: int
    converged: bool


def staple_trochlea_cylinder(surface: Surface, *, centre: str = "centroid", refit_iterations: int = 1,
                             posterior_cut: bool = True, curvature_quantile: float = 0.5,
                             superior_deg: float = 60.0, side_deg: float = 60.0, band_inside: float = 0.05,
                             band_outside: float = 0.10, posterior_widths: float = 1.0,
                             morphology: float = 1.0, up_hint: np.ndarray | None = None) -> TrochleaCylinder:
    """Trochlea cylinder of a talus surface in STAPLE's convention (module docstring).

    Parameters
    ----------
    surface : Surface
        Closed talus surface (m, outward normals).
    centre : {"centroid", "mid"}
        Axis point level with the trochlea incentres' centroid (STAPLE) or
        the middle of their extent along the axis.
    refit_iterations : int
        Band re-selections (1 = STAPLE; more: until the selection is stable).
    posterior_cut : bool
        Drop faces behind ``b_body - posterior_widths * c_body`` (STAPLE).
    curvature_quantile, superior_deg, side_deg, band_inside, band_outside, posterior_widths, morphology
        STAPLE's selection settings (defaults are STAPLE's; exposed for
        sensitivity studies).
    up_hint : (3,) array, optional
        Coarse superior direction (the tibia's) choosing the superior edge of
        the outline quadrilateral; STAPLE's rule (opposite the longest edge)
        without it.  It fails on the phantom tali, whose outline is not the
        real talus' trapezoid.

    Raises
    ------
    FitError
        If the cross-section profile or the trochlea patch cannot be found.
    """
    import igl

    from personalize.fitting import fit_cylinder

    V, F, N = surface.vertices, surface.faces, surface.normals
    topo = _FaceTopo(V, F)
    X0 = _inertia_long_axis(topo.mesh)
    Z0 = _quadri_superior(V, X0, up_hint)
    Z0 = unit(Z0 - (Z0 @ X0) * X0)
    csa = _csa_talus(V, F, X0)
    X0 = csa["or"] * X0
    Y0 = np.cross(Z0, X0)
    tib = csa["body"] - posterior_widths * csa["cbody"] if posterior_cut else -np.inf
    _, _, k1, k2, _ = igl.principal_curvature(V, F.astype(np.int64))
    kmax = np.maximum(np.abs(k1), np.abs(k2))
    vsel = ((kmax < np.quantile(kmax, curvature_quantile)) & (N @ Z0 > np.cos(np.radians(superior_deg)))
            & (N @ Y0 < np.cos(np.radians(side_deg))) & (V @ X0 < csa["neck"]))
    C = topo.coeff * morphology
    f = topo.faces_of_vertices(vsel)
    f = topo.close(f, 1 * C)
    f = topo.largest(f)
    f = topo.erode(f, 2 * C)
    f = topo.largest(f)
    f = topo.close(f, 3 * C)
    f = topo.dilate(f, 2 * C)
    if f.sum() < 30:
        raise FitError(f"talar trochlea: only {int(f.sum())} faces selected")
    fit = fit_cylinder(topo.incentre[f], normals=topo.fnormal[f], axis_hint=Y0, robust=False,
                       require_convergence=False)
    u, p, r = unit(np.asarray(fit.axis, float)), np.asarray(fit.point, float), float(fit.radius)
    sel, it, converged = f, 0, refit_iterations <= 1
    for it in range(1, max(1, refit_iterations) + 1):
        d = topo.incentre - p
        dist = np.linalg.norm(d - np.outer(d @ u, u), axis=1) - r
        new = f & (dist > -band_inside * r) & (np.abs(dist) < band_outside * r) & (topo.incentre @ X0 > tib)
        new = topo.largest(new)
        if new.sum() < 30:
            raise FitError(f"talar trochlea: only {int(new.sum())} faces near the first cylinder")
        if it > 1 and np.array_equal(new, sel):
            converged = True
            break
        sel = new
        fit = fit_cylinder(topo.incentre[sel], normals=topo.fnormal[sel], axis_hint=u, robust=False,
                           require_convergence=False)
        u, p, r = orient(unit(np.asarray(fit.axis, float)), u), np.asarray(fit.point, float), float(fit.radius)
    P = topo.incentre[sel]
    t = (P - p) @ u
    pc = p + (t.mean() if centre == "centroid" else 0.5 * (t.min() + t.max())) * u
    return TrochleaCylinder(point=pc, axis=u, radius=r, covariance=np.asarray(fit.covariance), rms=float(fit.rms),
                            faces=sel, long_axis=X0, superior=Z0, n_iterations=it, converged=bool(converged))


class _FaceTopo:
    """Face adjacency and face-set morphology on a triangle mesh (STAPLE's Tri*Mesh operations)."""

    def __init__(self, V, F):
        import trimesh
        self.V, self.F = V, F
        m = trimesh.Trimesh(V, F, process=False)
        if m.volume < 0:                       # inward winding: inertia and face normals need outward
            m.invert()
        self.mesh = m
        adj = m.face_adjacency
        nf = len(F)
        self.A = sparse.coo_matrix((np.ones(2 * len(adj)), (np.r_[adj[:, 0], adj[:, 1]], np.r_[adj[:, 1], adj[:, 0]])),
                                   shape=(nf, nf)).tocsr()
        self.VF = sparse.coo_matrix((np.ones(3 * nf), (F.ravel(), np.repeat(np.arange(nf), 3))),
                                    shape=(len(V), nf)).tocsr()
        tri = V[F]
        a = np.linalg.norm(tri[:, 1] - tri[:, 2], axis=1)
        b = np.linalg.norm(tri[:, 2] - tri[:, 0], axis=1)
        c = np.linalg.norm(tri[:, 0] - tri[:, 1], axis=1)
        self.incentre = (a[:, None] * tri[:, 0] + b[:, None] * tri[:, 1] + c[:, None] * tri[:, 2]) / (a + b + c)[:, None]
        self.fnormal = np.asarray(m.face_normals, float)
        self.farea = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        # STAPLE's morphology scale: operations were tuned for 0.5 mm edges
        mean_edge = np.sqrt(4 / np.sqrt(3) * self.farea.sum() / nf)
        self.coeff = 0.0005 / mean_edge

    def faces_of_vertices(self, vmask):
        return (self.VF.T @ vmask.astype(float)) > 0

    def vertices_of_faces(self, fmask):
        return (self.VF @ fmask.astype(float)) > 0

    def dilate(self, fmask, n, support=None):
        out = self.faces_of_vertices(self.vertices_of_faces(fmask))
        if support is not None:
            out &= support
        front = out.copy()
        for _ in range(int(np.ceil(n))):
            nb = (self.A @ front.astype(float)) > 0
            if support is not None:
                nb &= support
            front = nb
            out |= nb
        return out

    def erode(self, fmask, n):
        F = self.F[fmask]
        e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        eu, cnt = np.unique(e, axis=0, return_counts=True)
        bv = np.zeros(len(self.V), bool)
        bv[eu[cnt == 1].ravel()] = True
        border = fmask & self.faces_of_vertices(bv)
        front = border.copy()
        for _ in range(int(np.ceil(n)) - 1):
            front = ((self.A @ front.astype(float)) > 0) & fmask
            border |= front
        return fmask & ~border

    def close(self, fmask, n):
        return self.erode(self.dilate(fmask, n), n)

    def largest(self, fmask, erode_first=True):
        core = self.erode(fmask, 1) if erode_first else fmask
        if not core.any():
            core = fmask
        idx = np.flatnonzero(core)
        sub = self.A[idx][:, idx]
        ncomp, lab = connected_components(sub, directed=False)
        areas = np.bincount(lab, self.farea[idx], ncomp)
        keep = np.zeros(len(self.F), bool)
        keep[idx[lab == np.argmax(areas)]] = True
        return self.dilate(keep, 1, support=fmask) if erode_first else keep


def _inertia_long_axis(mesh):
    # volume inertia: smallest principal moment = longest direction
    comps = mesh.principal_inertia_components
    vecs = mesh.principal_inertia_vectors
    return unit(vecs[int(np.argmin(comps))])


def _quadri_superior(V, X0, up_hint=None):
    """fitQuadriTalus: superior direction from a quadrilateral fitted to the projection on the plane normal to X0.

    STAPLE takes the edge opposite the longest one as superior; with
    ``up_hint`` (e.g. the tibia's superior axis) the edge whose outward normal
    is closest to it is taken instead (a coarse cue: any ankle angle within
    +-45 deg picks the same edge).
    """
    # orthonormal basis of the plane
    e1 = unit(np.cross(X0, [1.0, 0, 0] if abs(X0[0]) < 0.9 else [0, 1.0, 0]))
    e2 = np.cross(X0, e1)
    P = np.c_[V @ e1, V @ e2]
    K = ConvexHull(P).vertices
    H = P[K]
    D = np.linalg.norm(H[:, None] - H[None], axis=2)
    i, j = np.unravel_index(np.argmax(D), D.shape)
    U1 = unit(H[j] - H[i])
    Ru = np.array([[U1[0], -U1[1]], [U1[1], U1[0]]])
    Hs = (Ru @ np.diag([0.5, 1.0]) @ Ru.T @ H.T).T
    Ds = np.linalg.norm(Hs[:, None] - Hs[None], axis=2)
    k, l = np.unravel_index(np.argmax(Ds), Ds.shape)
    quad = [H[i], H[k], H[j], H[l], H[i]]
    L = [np.linalg.norm(quad[m + 1] - quad[m]) for m in range(4)]
    normals = []
    for m in range(4):
        a, b = quad[m], quad[m + 1]
        ue = b - a
        z = np.array([-ue[1], ue[0]])
        if (0.5 * (a + b) - P.mean(0)) @ z < 0:        # outward: from the centroid to the edge
            z = -z
        z = unit(z)
        normals.append(unit(z[0] * e1 + z[1] * e2))
    if up_hint is None:
        isup = (int(np.argmax(L)) + 2) % 4                # the edge opposite the longest
    else:
        isup = int(np.argmax([nz @ up_hint for nz in normals]))
    return normals[isup]


def _gauss2(x, a1, b1, c1, a2, b2, c2):
    return a1 * np.exp(-((x - b1) / c1) ** 2) + a2 * np.exp(-((x - b2) / c2) ** 2)


def _section_areas(V, F, n, heights):
    """Areas of the plane sections {x . n = h} of a closed, outward-oriented mesh.

    Each triangle crossing the plane contributes a segment oriented along
    n x face-normal (the boundary of the section, counter-clockwise about n);
    the area is (1/2) sum (a x b) . n over the segments (Green's theorem).
    """
    tri = V[F]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    hv = tri @ n
    out = np.zeros(len(heights))
    for k, h in enumerate(heights):
        s = hv - h
        above = s > 0
        cnt = above.sum(1)
        m = (cnt == 1) | (cnt == 2)
        if not m.any():
            continue
        T, S = tri[m], s[m]
        pts = []
        for i, j in ((0, 1), (1, 2), (2, 0)):
            cross = (S[:, i] > 0) != (S[:, j] > 0)
            w = S[:, i] / np.where(cross, S[:, i] - S[:, j], 1.0)
            p = T[:, i] + w[:, None] * (T[:, j] - T[:, i])
            pts.append(np.where(cross[:, None], p, np.nan))
        P = np.stack(pts, 1)                       # (m, 3 edges, 3)
        ok = ~np.isnan(P[..., 0])
        a = np.array([P[r][ok[r]][0] for r in range(len(P))])
        b = np.array([P[r][ok[r]][1] for r in range(len(P))])
        t = np.cross(n, fn[m])
        flip = np.einsum("ij,ij->i", b - a, t) < 0
        a2 = np.where(flip[:, None], b, a)
        b2 = np.where(flip[:, None], a, b)
        out[k] = abs(0.5 * np.sum(np.cross(a2, b2) @ n))
    return out


def _csa_talus(V, F, X0, step=0.0003, offset=0.0003):
    """fitCSATalus: orientation `or` and the altitudes (along X0 after orientation) of
    the talonavicular start, the neck start and the tibial-surface start."""
    h = V @ X0
    alt = np.arange(h.min() + offset, h.max() - offset, step)
    area = _section_areas(V, F, X0, alt)
    length = np.ptp(alt)
    ok = area >= 0.2 * area.max()
    x, y = alt[ok], area[ok]
    amax = y.max()
    lo = [0.1 * amax, -np.inf, 1e-9, 0.1 * amax, -np.inf, 1e-9]
    hi = [10 * amax, np.inf, 0.2 * length, 10 * amax, np.inf, 0.2 * length]
    best = None
    for f1, f2 in ((0.25, 0.75), (0.35, 0.65), (0.2, 0.6), (0.4, 0.8)):
        b1, b2 = x.min() + f1 * np.ptp(x), x.min() + f2 * np.ptp(x)
        p0 = [amax, b1, 0.1 * length, amax, b2, 0.1 * length]
        try:
            p, _ = curve_fit(_gauss2, x, y, p0=p0, bounds=(lo, hi), maxfev=20000)
        except RuntimeError:
            continue
        sse = float(np.sum((_gauss2(x, *p) - y) ** 2))
        if best is None or sse < best[0]:
            best = (sse, p)
    if best is None:
        raise FitError("talus cross-section areas: two-Gaussian fit failed")
    a1, b1, c1, a2, b2, c2 = best[1]
    if a1 < a2:      # gaussian 1 (smaller) = head / talonavicular part
        nav, body, cb = b1, b2, c2
    else:
        nav, body, cb = b2, b1, c1
    orient_sign = 1.0 if nav > body else -1.0          # X0 to point at the head (anterior)
    return {"or": orient_sign, "nav": orient_sign * nav, "neck": orient_sign * 0.5 * (b1 + b2),
            "tib": orient_sign * body - cb, "body": orient_sign * body, "cbody": cb, "params": best[1], "alt": alt, "area": area}
