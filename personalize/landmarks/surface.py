"""The bone surface the landmark detectors work on.

`Surface` (vertices, faces, outward unit vertex normals, vertex areas, a
cached k-d tree) built from a mesh by `as_surface`, after `even_sampling`
has split long edges so that vertex counts weigh the surface evenly; plus
the vertex-level queries every detector uses (extreme vertices, connected
patches, edge curvature).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lowerlimb.errors import InputError
from lowerlimb.geometry import vertex_normals

from .common import Landmark

__all__ = ["Surface", "SUBDIVIDED_EDGE", "COARSE_EDGE_FRACTION", "even_sampling", "as_surface",
           "landmark_from_vertex", "extreme_vertex", "edge_curvature", "largest_patch", "vertex_components", "facing"]


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


def _split_long_edges(V: np.ndarray, F: np.ndarray, max_edge: float, max_iter: int = 12):
    """Bisect every edge longer than `max_edge` at one shared midpoint until none is: ``(V, F, lengths)``, with the
    unique edges' lengths (m) of the input mesh.

    The rule and the output (vertex and face order included) are trimesh's ``remesh.subdivide_to_size``: a face
    with one, two or three long edges becomes two, three (the quad cut along its shorter diagonal) or four
    faces.  Written here because a face whose edges are all short never changes again, so each pass sorts only
    the edges of the faces still being split (trimesh's sorts all): ICL_MRI's eight bones 0.22 -> 0.12 s, bit-identical on the five real sets.
    """
    from trimesh.geometry import faces_to_edges
    from trimesh.grouping import unique_rows

    V = np.array(V, dtype=np.float64)
    faces = np.asarray(F, np.int64)
    done, lengths0 = [], None
    for it in range(max_iter + 1):
        edges = np.sort(faces_to_edges(faces), axis=1)
        unique, inverse = unique_rows(edges)
        eu = edges[unique]
        lengths = np.sqrt(((V[eu[:, 0]] - V[eu[:, 1]]) ** 2).sum(axis=1))
        if lengths0 is None:
            lengths0 = lengths
        long_edge = lengths > max_edge
        if not long_edge.any():
            done.append(faces)
            break
        if it >= max_iter:
            raise ValueError("max_iter exceeded!")
        mid = np.full(len(unique), -1, dtype=np.int64)
        mid[long_edge] = np.arange(int(long_edge.sum())) + len(V)
        V = np.vstack((V, V[eu[long_edge]].mean(axis=1)))
        fm = mid[inverse].reshape((-1, 3))
        split = fm >= 0
        count = split.sum(axis=1)
        done.append(faces[count == 0])
        one = count == 1
        j = np.argmax(split[one], axis=1)
        r = np.arange(len(j))
        f1, m1 = faces[one], fm[one]
        a, b, c = f1[r, j], f1[r, (j + 1) % 3], f1[r, (j + 2) % 3]
        p = m1[r, j]
        faces_one = np.column_stack((a, p, c, p, b, c)).reshape((-1, 3))
        two = count == 2
        j = (np.argmin(split[two], axis=1) + 1) % 3
        r = np.arange(len(j))
        f2, m2 = faces[two], fm[two]
        a, b, c = f2[r, j], f2[r, (j + 1) % 3], f2[r, (j + 2) % 3]
        p, q = m2[r, j], m2[r, (j + 1) % 3]
        use_aq = (((V[a] - V[q]) ** 2).sum(axis=1) <= ((V[p] - V[c]) ** 2).sum(axis=1))[:, None]
        faces_two = np.vstack((np.column_stack((p, b, q)),
                               np.where(use_aq, np.column_stack((a, p, q)), np.column_stack((a, p, c))),
                               np.where(use_aq, np.column_stack((a, q, c)), np.column_stack((p, q, c)))))
        f3, m3 = faces[count == 3], fm[count == 3]
        v0, v1, v2 = f3.T
        e0, e1, e2 = m3.T
        faces_three = np.column_stack((v0, e0, e2, e0, v1, e1, e2, e1, v2, e0, e1, e2)).reshape((-1, 3))
        faces = np.vstack((faces_one, faces_two, faces_three)).astype(np.int64)
    return V, np.vstack(done).astype(np.int64), lengths0


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
        V, F = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
        if len(F) == 0 or not np.all(np.isfinite(V)) or F.ndim != 2 or F.shape[1] != 3:
            return obj, None                 # empty or broken: as_surface says so
        if np.median(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1)) > 0.05:
            return obj, None                 # in millimetres: as_surface says so
        v, f, edges = _split_long_edges(V, F, SUBDIVIDED_EDGE)
    except (AttributeError, ValueError, IndexError):
        return obj, None
    long = float(np.mean(edges > SUBDIVIDED_EDGE))
    if long == 0.0:
        return obj, None
    import trimesh

    out = trimesh.Trimesh(v, f, process=False)
    trimesh.grouping.merge_vertices(out)   # vertices the input held twice become one
    note = None
    if long > COARSE_EDGE_FRACTION:
        note = (f"{name}: coarse mesh ({100 * long:.0f} % of edges longer than {SUBDIVIDED_EDGE * 1e3:.0f} mm, "
                f"median {np.median(edges) * 1e3:.1f} mm): edges split before detection (surface unchanged)")
    return out, note


def _is_closed(F: np.ndarray, n_vertices: int) -> bool:
    """Every edge shared by exactly two faces (trimesh's ``is_watertight``, from one sort of integer edge keys
    instead of trimesh's row hashing and grouping: ICL_MRI's eight bones 0.07 -> 0.03 s)."""
    if len(F) == 0:
        return False
    e = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(e[:, 0] * np.int64(n_vertices) + e[:, 1], return_counts=True)
    return bool(np.all(counts == 2))


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
    fa = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    # a third of each incident face's area (bincount: an order of magnitude faster than np.add.at)
    areas = np.bincount(F.ravel(), weights=np.repeat(fa / 3.0, 3), minlength=len(V))
    vn = vertex_normals(V, F)
    closed = _is_closed(F, len(V))
    # Orient normals outwards: signed volume of a closed surface must be positive.
    vol = float(np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))) / 6.0
    if vol < 0:
        vn = -vn
    keep = areas > 0
    if keep.sum() < 50:
        raise InputError(name, "mesh has (almost) no surface area")
    return Surface(vertices=V, faces=F, normals=vn, areas=areas, closed=closed)


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
    # the unique edges in np.unique(..., axis=0)'s (lexicographic) order, from one sort of integer keys
    n = np.int64(len(V))
    e2 = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1).astype(np.int64)
    key = np.unique(e2[:, 0] * n + e2[:, 1])
    e = np.column_stack([key // n, key % n])
    dp = V[e[:, 1]] - V[e[:, 0]]
    k = np.einsum("ij,ij->i", dp, N[e[:, 1]] - N[e[:, 0]]) / np.maximum(np.einsum("ij,ij->i", dp, dp), 1e-18)
    ks = np.bincount(e[:, 0], k, len(V)) + np.bincount(e[:, 1], k, len(V))
    cnt = np.bincount(e[:, 0], minlength=len(V)) + np.bincount(e[:, 1], minlength=len(V))
    H = ks / np.maximum(cnt, 1)
    object.__setattr__(surface, "_edge_curvature", H)
    return H


def facing(surface: Surface, other: Surface, reach: float, min_cos: float = 0.3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance (m) from each vertex of `surface` to the nearest vertex of `other` (inf beyond `reach`), that
    vertex's index (``len(other.vertices)`` beyond `reach`), and whether it lies ahead of the outward normal
    (cosine above `min_cos`): an articular surface faces its partner."""
    d, j = other.tree().query(surface.vertices, distance_upper_bound=reach)
    ok = np.isfinite(d)
    ahead = np.zeros(len(d), bool)
    vec = other.vertices[j[ok]] - surface.vertices[ok]
    ahead[ok] = np.einsum("ij,ij->i", vec, surface.normals[ok]) > min_cos * np.maximum(d[ok], 1e-9)
    return d, j, ahead


def vertex_components(F: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """Number of connected components of the `n` vertices joined by the edges of faces `F`, and each one's label."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    return connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)


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
