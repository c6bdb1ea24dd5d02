"""Shared pieces of the bone landmark detectors.

Result containers (`Landmark`, `Axis`, `BoneLandmarks`, `LandmarkSet`), the
surface adapter (`Surface`) and the geometric helpers every detector uses:
area-weighted principal axes, Hough voting for sphere / cylinder centres from
surface normals, and iterative "fit, keep the points within a band, refit"
refinement around the project's shape fitters (`personalize.fitting`).

Nothing here depends on the scanner axes: every choice is made from the
bone's own geometry (principal axes, extremities, normals), and every random
choice is made over vertex *indices* with a seeded generator, so a rigid
motion of the input moves every output by the same motion.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from lowerlimb.errors import FitError, InputError
from lowerlimb.estimates import Gaussian

__all__ = [
    "Landmark", "Axis", "BoneLandmarks", "LandmarkSet", "Surface", "as_surface",
    "principal_axes", "unit", "hough_centres", "refine_sphere", "refine_cylinder",
    "sphere_centre_cov", "axis_sd_deg", "line_through", "orient",
    "FLAG_TRUNCATED", "FLAG_LOW_CONFIDENCE", "FLAG_SIDE_MISMATCH", "FLAG_NAME_MISMATCH",
    "FLAG_NOT_CLOSED", "edge_curvature",
]

FLAG_TRUNCATED = "truncated"
FLAG_LOW_CONFIDENCE = "low_confidence"
FLAG_SIDE_MISMATCH = "side_mismatch"
FLAG_NAME_MISMATCH = "name_mismatch"
FLAG_NOT_CLOSED = "not_closed"

# Smallest positional variance reported (1 micrometre^2): fits of exact
# synthetic surfaces have ~zero residuals, a covariance must stay positive.
_VAR_FLOOR = 1e-12


def unit(v: np.ndarray) -> np.ndarray:
    """``v / |v|`` (last axis)."""
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class Landmark:
    """A point on or in a bone: position (3,) in metres and its 3x3 covariance (m^2)."""

    position: np.ndarray
    cov: np.ndarray

    def to_json(self) -> dict:
        return {"position": _r(self.position), "cov": _r(self.cov, 12)}

    @classmethod
    def from_json(cls, d: dict) -> "Landmark":
        return cls(np.asarray(d["position"], float).reshape(3), np.asarray(d.get("cov", np.zeros((3, 3))), float).reshape(3, 3))

    @property
    def gaussian(self) -> Gaussian:
        return Gaussian(self.position, self.cov)


@dataclass(frozen=True)
class Axis:
    """A directed line: a point (m), a unit direction and the direction's 1-sd angle (deg)."""

    point: np.ndarray
    direction: np.ndarray
    sd_deg: float

    def to_json(self) -> dict:
        return {"point": _r(self.point), "direction": _r(self.direction, 9), "sd_deg": round(float(self.sd_deg), 6)}

    @classmethod
    def from_json(cls, d: dict) -> "Axis":
        return cls(np.asarray(d["point"], float), np.asarray(d["direction"], float), float(d.get("sd_deg", 0.0)))


@dataclass
class BoneLandmarks:
    """Everything detected on one bone (built by a detector, then read-only).

    ``scalars`` (m) are written as ``{"value": v, "sd": s}`` (``sd`` null when
    no fit provides it), like the phantom's truth.
    ``frames`` maps a frame name to ``{"origin": (3,), "rotation": (3, 3)}``
    (axes as columns: X anterior, Y proximal/superior, Z to the subject's
    right, ISB conventions); ``fits`` maps a primitive name to a JSON-ready
    description of the fitted primitive.
    """

    bone: str
    side: str | None
    landmarks: dict[str, Landmark] = field(default_factory=dict)
    axes: dict[str, Axis] = field(default_factory=dict)
    scalars: dict[str, float] = field(default_factory=dict)
    frames: dict[str, dict] = field(default_factory=dict)
    flags: list[str] = field(default_factory=list)
    fits: dict[str, dict] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    scalar_sd: dict[str, float] = field(default_factory=dict)

    def flag(self, flag: str, note: str | None = None) -> None:
        if flag not in self.flags:
            self.flags.append(flag)
        if note:
            self.notes.append(note)

    def to_json(self) -> dict:
        return {
            "landmarks": {k: v.to_json() for k, v in self.landmarks.items()},
            "axes": {k: v.to_json() for k, v in self.axes.items()},
            "scalars": {k: {"value": round(float(v), 9),
                            "sd": (round(float(self.scalar_sd[k]), 9) if k in self.scalar_sd else None)}
                        for k, v in self.scalars.items()},
            "frames": {k: {"origin": _r(f["origin"]), "rotation": _r(f["rotation"], 9)} for k, f in self.frames.items()},
            "flags": list(self.flags),
            "notes": list(self.notes),
        }

    @classmethod
    def from_json(cls, bone: str, d: dict) -> "BoneLandmarks":
        """One bone of a landmarks.json (fits are in fits.json and are not read)."""
        sc = d.get("scalars", {})
        return cls(bone=bone, side=bone[-1] if bone[-2:] in ("_r", "_l") else None,
                   landmarks={k: Landmark.from_json(v) for k, v in d.get("landmarks", {}).items()},
                   axes={k: Axis.from_json(v) for k, v in d.get("axes", {}).items()},
                   scalars={k: float(v["value"] if isinstance(v, dict) else v) for k, v in sc.items()},
                   frames={k: {"origin": np.asarray(f["origin"], float), "rotation": np.asarray(f["rotation"], float)}
                           for k, f in d.get("frames", {}).items()},
                   flags=list(d.get("flags", [])), notes=list(d.get("notes", [])),
                   scalar_sd={k: float(v["sd"]) for k, v in sc.items() if isinstance(v, dict) and v.get("sd") is not None})


@dataclass
class LandmarkSet:
    """Landmarks of every detected bone plus the bones that could not be used."""

    bones: dict[str, BoneLandmarks] = field(default_factory=dict)
    missing: list[str] = field(default_factory=list)
    rejected: dict[str, str] = field(default_factory=dict)

    def __getitem__(self, bone: str) -> BoneLandmarks:
        return self.bones[bone]

    def __contains__(self, bone: str) -> bool:
        return bone in self.bones

    def to_json(self) -> dict:
        return {
            "units": "m",
            "frame": "input",
            "bones": {k: v.to_json() for k, v in self.bones.items()},
            "rejected": dict(self.rejected),
        }

    def fits_json(self) -> dict:
        return {"units": "m", "frame": "input", "bones": {k: v.fits for k, v in self.bones.items()}}

    @classmethod
    def from_json(cls, d: dict, source: str = "landmarks.json") -> "LandmarkSet":
        """A landmarks.json document (`to_json`); `InputError` naming `source` when it is not one."""
        if not isinstance(d, dict) or not isinstance(d.get("bones"), dict):
            raise InputError(source, "not a landmarks file (no 'bones')")
        if d.get("units", "m") != "m":
            raise InputError(source, f"landmark units must be 'm', got {d.get('units')!r}")
        try:
            bones = {k: BoneLandmarks.from_json(k, v) for k, v in d["bones"].items()}
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(source, f"malformed landmark entry ({' '.join(str(exc).split())})") from None
        return cls(bones=bones, missing=list(d.get("missing_bones", [])), rejected=dict(d.get("rejected", {})))


def _r(a, nd: int = 9):
    return np.round(np.asarray(a, float), nd).tolist()


# --------------------------------------------------------------------------- surfaces
@dataclass(frozen=True)
class Surface:
    """Triangle surface of one bone in metres (input frame).

    Attributes
    ----------
    vertices : (N, 3) ndarray
    faces : (F, 3) int ndarray
    normals : (N, 3) ndarray, unit, pointing out of the bone
    areas : (N,) ndarray, one third of the adjacent triangle areas (m^2)
    closed : bool, whether the mesh is watertight
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    closed: bool

    @property
    def centroid(self) -> np.ndarray:
        return (self.areas @ self.vertices) / self.areas.sum()

    def tree(self) -> cKDTree:
        t = self.__dict__.get("_tree")
        if t is None:
            t = cKDTree(self.vertices)
            object.__setattr__(self, "_tree", t)
        return t


#: bone mesh edges longer than this (m) are split at their midpoints before detection:
#: the detectors' fits and votes count vertices, so a decimated ("low-quality") mesh's
#: uneven sampling (dense where curved, sparse where flat) would weight its surface
#: unevenly; splitting leaves the surface itself unchanged
SUBDIVIDED_EDGE = 0.003
#: the bone gets a "coarse mesh" note when more than this fraction of its edges had to be
#: split (ICL-MRI's 2-3 mm meshes: 6-21 % for the leg bones, 57 % for the pelvis)
COARSE_EDGE_FRACTION = 0.5


def even_sampling(obj, name: str = "bone"):
    """The bone mesh with its edges longer than `SUBDIVIDED_EDGE` split, and a note when it was coarse.

    Returns ``(obj, None)`` unchanged when no edge is that long (or for a
    `Surface`).  Midpoint subdivision keeps every point of the surface where
    it was (the faceted surface is the same point set), so results stay
    rigid-motion and mirror equivariant; only the sampling of the detectors'
    vertex sets is evened out.
    """
    if isinstance(obj, Surface):
        return obj, None
    mesh = getattr(obj, "mesh", obj)
    try:
        edges = np.asarray(mesh.edges_unique_length, float)
    except (AttributeError, ValueError, IndexError):
        return obj, None
    if len(edges) == 0 or not np.all(np.isfinite(edges)) or np.median(edges) > 0.05:
        return obj, None                     # empty, broken or in millimetres: as_surface says so
    long = float(np.mean(edges > SUBDIVIDED_EDGE))
    if long == 0.0:
        return obj, None
    import trimesh
    from trimesh.remesh import subdivide_to_size

    v, f = subdivide_to_size(np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64),
                             max_edge=SUBDIVIDED_EDGE, max_iter=12)
    out = trimesh.Trimesh(v, f, process=False)
    trimesh.grouping.merge_vertices(out)   # an edge shared by two faces gets one midpoint
    note = None
    if long > COARSE_EDGE_FRACTION:
        note = (f"{name}: coarse mesh ({100 * long:.0f} % of edges longer than {SUBDIVIDED_EDGE * 1e3:.0f} mm, "
                f"median {np.median(edges) * 1e3:.1f} mm): edges split before detection (surface unchanged)")
    return out, note


def as_surface(obj, name: str = "bone") -> Surface:
    """Wrap a trimesh, a `BoneSurface` (``.mesh``) or a Surface.

    Raises
    ------
    InputError
        If the mesh is empty or has too few vertices to hold a bone.
    """
    if isinstance(obj, Surface):
        return obj
    mesh = getattr(obj, "mesh", obj)
    V = np.asarray(mesh.vertices, float)
    F = np.asarray(mesh.faces, np.int64)
    if V.ndim != 2 or V.shape[0] < 50 or F.shape[0] < 50:
        raise InputError(name, f"mesh has only {len(V)} vertices / {len(F)} faces, too few for a bone surface")
    if not np.all(np.isfinite(V)):
        raise InputError(name, "mesh has non-finite vertex coordinates")
    ext = float(np.ptp(V, axis=0).max())
    if ext > 2.0:
        raise InputError(name, f"mesh extent is {ext:.1f} m: coordinates look like millimetres, expected metres")
    tri = V[F]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fa = 0.5 * np.linalg.norm(fn, axis=1)
    # per-vertex sums over the incident faces (bincount: an order of magnitude faster than np.add.at)
    idx = F.ravel()
    areas = np.bincount(idx, weights=np.repeat(fa / 3.0, 3), minlength=len(V))
    fn3 = np.repeat(fn, 3, axis=0)              # area-weighted (|fn| = 2 area)
    vn = np.column_stack([np.bincount(idx, weights=fn3[:, c], minlength=len(V)) for c in range(3)])
    nn = np.linalg.norm(vn, axis=1)
    ok = nn > 0
    vn[ok] /= nn[ok][:, None]
    closed = bool(getattr(mesh, "is_watertight", False))
    # Orient normals outwards: signed volume of a closed surface must be positive.
    vol = float(np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))) / 6.0
    if vol < 0:
        vn = -vn
    keep = areas > 0
    if keep.sum() < 50:
        raise InputError(name, "mesh has (almost) no surface area")
    return Surface(vertices=V, faces=F, normals=vn, areas=areas, closed=closed)


# --------------------------------------------------------------------------- geometry
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


def orient(v: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``v`` flipped if needed so that it points along ``ref``."""
    return v if float(v @ ref) >= 0 else -v


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
    support = cKDTree(C).query_ball_point(C, tol, return_length=True, workers=-1).astype(float)
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
    fit, sel = None, None
    for _ in range(iterations):
        d = P - c
        dist = np.linalg.norm(d, axis=1)
        cosn = np.einsum("ij,ij->i", d, N) / np.maximum(dist, 1e-12)
        if not convex:
            cosn = -cosn
        sel_new = (np.abs(dist - r) < band) & (cosn > min_cos)
        if mask is not None:
            sel_new &= mask
        if sel_new.sum() < 20:
            if fit is None:
                raise FitError(f"sphere: only {int(sel_new.sum())} surface points near the initial guess")
            break
        if sel is not None and np.array_equal(sel, sel_new):
            break
        sel = sel_new
        fit = fit_sphere(P[sel], normals=N[sel])
        c, r = np.asarray(fit.centre, float), float(fit.radius)
    return fit, sel


def refine_cylinder(points, normals, point, axis, radius, *, band: float, convex: bool = True,
                    min_cos: float = 0.6, mask=None, iterations: int = 3, half_length: float | None = None):
    """Cylinder analogue of `refine_sphere` (distance measured to the axis line)."""
    from personalize.fitting import fit_cylinder

    P = np.asarray(points, float)
    N = np.asarray(normals, float)
    p0, u, r = np.asarray(point, float), unit(axis), float(radius)
    fit, sel = None, None
    for _ in range(iterations):
        d = P - p0
        t = d @ u
        radial = d - t[:, None] * u
        dist = np.linalg.norm(radial, axis=1)
        cosn = np.einsum("ij,ij->i", radial, N) / np.maximum(dist, 1e-12)
        if not convex:
            cosn = -cosn
        sel_new = (np.abs(dist - r) < band) & (cosn > min_cos)
        if half_length is not None:
            sel_new &= np.abs(t) < half_length
        if mask is not None:
            sel_new &= mask
        if sel_new.sum() < 30:
            if fit is None:
                raise FitError(f"cylinder: only {int(sel_new.sum())} surface points near the initial guess")
            break
        if sel is not None and np.array_equal(sel, sel_new):
            break
        sel = sel_new
        fit = fit_cylinder(P[sel], normals=N[sel], axis_hint=u)
        u_new = unit(np.asarray(fit.axis, float))
        u = orient(u_new, u)
        p0, r = np.asarray(fit.point, float), float(fit.radius)
        # keep the reference point mid-selection so `half_length` stays centred
        tt = (P[sel] - p0) @ u
        p0 = p0 + 0.5 * (tt.min() + tt.max()) * u
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


def landmark_from_vertex(surface: Surface, idx: int, sd: float) -> Landmark:
    """A landmark at a surface vertex with isotropic sd ``sd`` (m)."""
    return Landmark(surface.vertices[idx].copy(), (sd * sd) * np.eye(3))


def extreme_vertex(surface: Surface, direction: np.ndarray, mask=None, smooth: float = 0.0) -> int:
    """Index of the vertex farthest along ``direction`` (optionally among ``mask``).

    With ``smooth > 0`` the vertices within ``smooth`` (m, along the
    direction) of the extreme are averaged and the nearest vertex to their
    centroid is returned: the landmark then no longer jumps between two
    near-equal bumps (segmentation noise).
    """
    V = surface.vertices
    h = V @ direction
    if mask is not None:
        h = np.where(mask, h, -np.inf)
    k = int(np.argmax(h))
    if smooth <= 0:
        return k
    near = h > h[k] - smooth
    c = (surface.areas[near] @ V[near]) / surface.areas[near].sum()
    d = np.linalg.norm(V - c, axis=1)
    d = np.where(near, d, np.inf)
    return int(np.argmin(d))


# --------------------------------------------------------------------------- long bones
@dataclass(frozen=True)
class LongBoneAxes:
    """Long axis of a bone and what its two ends look like.

    ``axis`` points towards end ``+1``; ``h`` is each vertex's height along it
    from ``centre``; ``flatness[e]`` is the ratio of the smaller to the larger
    cross-sectional spread of the end region ``e`` (``+1`` / ``-1``),
    ``area[e]`` its surface area and ``cut[e]`` whether the end is a planar
    cut (truncated by the field of view).
    """

    centre: np.ndarray
    axis: np.ndarray
    h: np.ndarray
    length: float
    flatness: dict
    area: dict
    cut: dict
    shaft_radius: float


def long_bone_axes(surface: Surface, end_fraction: float = 0.2, end_max: float = 0.08) -> LongBoneAxes:
    """Principal long axis and end descriptors of a long bone (femur, tibia)."""
    V, A, Nrm = surface.vertices, surface.areas, surface.normals
    c, ax, _ = principal_axes(V, A)
    e = ax[:, 0]
    h = (V - c) @ e
    L = float(h.max() - h.min())
    mid = np.abs(h - 0.5 * (h.max() + h.min())) < 0.1 * L
    if mid.sum() > 10:
        cm = (A[mid] @ V[mid]) / A[mid].sum()
        d = V[mid] - cm
        d -= np.outer(d @ e, e)
        r_shaft = float(np.median(np.linalg.norm(d, axis=1)))
    else:
        r_shaft = 0.1 * L
    flat, area, cut = {}, {}, {}
    depth = min(end_fraction * L, end_max)
    for sgn in (1, -1):
        hh = sgn * h
        top = hh > hh.max() - depth
        _, _, sd2 = principal_axes(V[top] - np.outer((V[top] - c) @ e, e), A[top])
        flat[sgn] = float(sd2[1] / max(sd2[0], 1e-12))
        area[sgn] = float(A[top].sum())
        cut[sgn] = _is_cut(V, Nrm, A, hh, sgn * e, r_shaft)
    return LongBoneAxes(centre=c, axis=e, h=h, length=L, flatness=flat, area=area, cut=cut, shaft_radius=r_shaft)


def shaft_line(surface: Surface, axis: np.ndarray, h: np.ndarray, lo: float, hi: float, n_slices: int = 9):
    """Line through the area centroids of slices ``lo < h < hi`` (m along ``axis``).

    Returns ``(point, direction)`` with the direction oriented along ``axis``.
    """
    V, A = surface.vertices, surface.areas
    edges = np.linspace(lo, hi, n_slices + 1)
    cents = []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (h >= a) & (h < b)
        if m.sum() >= 6:
            cents.append((A[m] @ V[m]) / A[m].sum())
    cents = np.array(cents)
    if len(cents) < 3:
        m = (h >= lo) & (h <= hi)
        c, ax, _ = principal_axes(V[m], A[m])
        return c, orient(ax[:, 0], axis)
    c, ax, _ = principal_axes(cents)
    return c, orient(ax[:, 0], axis)


def perpendicular(v: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Component of ``v`` perpendicular to unit ``axis``."""
    return v - (v @ axis) * axis


def _is_cut(V, Nrm, A, hh, direction, r_shaft) -> bool:
    """Whether the end of a long bone at the top of ``hh`` is a planar cut.

    A field-of-view cut leaves a flat cap (normals along the axis, coplanar
    within 0.5 mm) nearly as wide as the bone just below it (at least a third
    of the convex cross-section 8 mm below the tip, the rest being the rim
    rounded by surface smoothing), and below it the sides run along the axis
    (mean |n.axis| < 0.68 between 3 and 8 mm below the tip, rounded rim
    included).  A rounded epiphysis, even with a flat staircase patch at its
    top (slice-thick MRI), keeps a small top patch (< 30 % of that section)
    and turns gradually (mean |n.axis| >= 0.7 there).
    """
    from scipy.spatial import ConvexHull, QhullError

    tip = hh > hh.max() - 0.004
    cosn = Nrm @ direction
    flat = tip & (cosn > 0.95)
    if flat.sum() < 10 or A[flat].sum() < 0.25 * np.pi * r_shaft ** 2:
        return False
    _, _, qsd = principal_axes(V[flat], A[flat])
    if qsd[2] > 0.0005:
        return False
    slab = np.abs(hh - (hh.max() - 0.008)) < 0.001
    if slab.sum() < 8:
        return False
    u = np.cross(direction, [1.0, 0.0, 0.0])
    if np.linalg.norm(u) < 0.1:
        u = np.cross(direction, [0.0, 1.0, 0.0])
    u = u / np.linalg.norm(u)
    w = np.cross(direction, u)
    Q = np.column_stack([V[slab] @ u, V[slab] @ w])
    try:
        sec = ConvexHull(Q).volume                 # area in 2-D
    except QhullError:
        return False
    # below a cut the bone's sides run along the axis (a smoothed rim aside);
    # below a rounded end they turn gradually
    band = (hh < hh.max() - 0.003) & (hh > hh.max() - 0.008)
    if not band.any():
        return False
    side_cos = float(A[band] @ np.abs(cosn[band]) / A[band].sum())
    return bool(A[flat].sum() > 0.33 * sec and side_cos < 0.68)


def edge_curvature(surface: Surface) -> np.ndarray:
    r"""Mean normal curvature of the surface at each vertex (1/m; > 0 convex, < 0 concave).

    For each mesh edge :math:`(i, j)` the normal curvature along it is
    :math:`\kappa_{ij} = (n_j - n_i) \cdot (p_j - p_i) / \lVert p_j - p_i \rVert^2`
    (outward normals: positive where the surface bends away, as on a sphere
    of radius r, where it is 1/r); a vertex gets the mean over its edges,
    i.e. an estimate of the mean curvature.  Cached on the surface.
    """
    H = surface.__dict__.get("_edge_curvature")
    if H is not None:
        return H
    V, N, F = surface.vertices, surface.normals, surface.faces
    e = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
    dp = V[e[:, 1]] - V[e[:, 0]]
    k = np.einsum("ij,ij->i", dp, N[e[:, 1]] - N[e[:, 0]]) / np.maximum(np.einsum("ij,ij->i", dp, dp), 1e-18)
    ks = np.bincount(e[:, 0], k, len(V)) + np.bincount(e[:, 1], k, len(V))
    cnt = np.bincount(e[:, 0], minlength=len(V)) + np.bincount(e[:, 1], minlength=len(V))
    H = ks / np.maximum(cnt, 1)
    object.__setattr__(surface, "_edge_curvature", H)
    return H


def largest_patch(surface: Surface, mask: np.ndarray, n: int = 1) -> list[np.ndarray]:
    """The ``n`` largest (by area) edge-connected patches of the vertices in ``mask``.

    Returns a list of boolean vertex masks, largest first.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    F = surface.faces
    fm = mask[F].all(axis=1)
    Fm = F[fm]
    nv = len(surface.vertices)
    if len(Fm) == 0:
        return []
    e = np.concatenate([Fm[:, [0, 1]], Fm[:, [1, 2]], Fm[:, [2, 0]]])
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nv, nv))
    _, lab = connected_components(g, directed=False)
    used = np.zeros(nv, bool)
    used[Fm.ravel()] = True
    labs = np.unique(lab[used])
    areas = np.array([surface.areas[used & (lab == l)].sum() for l in labs])
    order = np.argsort(-areas)[:n]
    return [used & (lab == labs[i]) for i in order]
