"""Bone surfaces and point clouds from label volumes or mesh folders.

Surface model
-------------
For a bone mask ``M`` (binary, voxel grid with affine ``A``: index -> metres)
the surface is the iso-surface

    S = { x : (G_sigma * 1_M)(A^-1 x) = 1/2 }

of the mask's indicator blurred by an anisotropy-aware Gaussian (``sigma`` in
metres, i.e. ``sigma / spacing_k`` voxels along array axis ``k``), extracted by
marching cubes in index space and mapped through ``A``.  The blur removes the
voxel staircase of a binary mask (plain marching cubes on it is off by up to
half a voxel).  A few Taubin (lambda|mu) smoothing passes (pymeshlab) follow;
unlike Laplacian smoothing they do not shrink the bone.  The blur still moves
the 1/2 level inward by about ``sigma^2 H`` (H: mean curvature), so finally
every vertex is moved along its outward normal by the constant

    d = (V_mask - V_mesh) / area,     V_mask = n_voxels * |det A|,

which restores the voxel-count volume (an unbiased estimate of the bone
volume) and removes that bias to first order.

Orientation: marching cubes works in index space; when ``det A < 0`` (an axis
flip) the mapped triangles turn inside out, so faces are re-oriented until the
signed volume is positive.  Permutations and oblique affines need nothing else.
"""
from __future__ import annotations

import functools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import scipy.ndimage as ndi
import trimesh

from lowerlimb.errors import InputError
from .io import (LabelVolume, is_label_volume_path, read_label_volume, read_mesh_folder_detailed,
                 PLAUSIBLE_EXTENT_M)

__all__ = [
    "BoneSurface",
    "BoneSurfaces",
    "PointCloud",
    "clean_mask",
    "extract_surface",
    "point_cloud",
    "surface_distance",
    "surfaces_from_labels",
    "load_bones",
    "taubin_smooth",
    "decimate",
]


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class PointCloud:
    """Points on a bone surface with outward unit normals.

    Attributes
    ----------
    points : (N, 3) ndarray, metres
    normals : (N, 3) ndarray, unit, outward
    outliers_removed : int
        Points dropped by the statistical outlier filter.
    """

    points: np.ndarray
    normals: np.ndarray
    outliers_removed: int = 0


@dataclass(frozen=True)
class BoneSurface:
    """One bone's closed surface and its point cloud.

    Attributes
    ----------
    name : str
        Canonical bone name (``femur_r``...).
    mesh : trimesh.Trimesh
        Metres, input (scanner) frame, outward normals, positive volume.
    source : str
        File it came from.
    report : dict
        What was done: removed islands, holes filled, units detected, ...
    """

    name: str
    mesh: trimesh.Trimesh
    source: str
    report: dict = field(default_factory=dict)
    point_spacing: float = 2e-3
    seed: int = 0

    @functools.cached_property
    def cloud(self) -> PointCloud:
        """Point cloud sampled on `mesh` (see `point_cloud`)."""
        return point_cloud(self.mesh, spacing=self.point_spacing, seed=self.seed)

    @property
    def points(self) -> np.ndarray:
        """(N, 3) surface points, metres."""
        return self.cloud.points

    @property
    def normals(self) -> np.ndarray:
        """(N, 3) outward unit normals at `points`."""
        return self.cloud.normals

    @property
    def volume(self) -> float:
        """Enclosed volume, m^3."""
        return signed_volume(self.mesh.vertices, self.mesh.faces)


# --------------------------------------------------------------------------- masks
def _fill_cavities(mask: np.ndarray) -> np.ndarray:
    """Fill enclosed cavities: background not 6-connected to the array border becomes bone.

    Same result as `scipy.ndimage.binary_fill_holes`, but one labelling pass
    instead of an iterated dilation (several times faster on a bone's box).
    """
    bg, n = ndi.label(~mask)
    if n <= 1:
        return mask if n == 1 else np.ones_like(mask)
    border = np.zeros(n + 1, bool)
    for ax in range(3):
        for idx in (0, -1):
            border[np.unique(np.take(bg, idx, axis=ax))] = True
    border[0] = False  # label 0 is the bone itself
    return ~border[bg]  # bone, or background enclosed by it


#: widest unlabelled gap (m) across which a separate piece of a bone is joined back
#: to it: a child's open growth plate (physis, 1-3 mm of cartilage in MRI)
PHYSIS_GAP = 0.004
#: a piece is an epiphysis (joined) rather than noise or a sesamoid (removed) when it
#: holds at least this fraction of the main component's voxels ...
EPIPHYSIS_MIN_FRACTION = 0.005
#: ... and this fraction of its boundary faces the main component within PHYSIS_GAP
#: (a growth plate spans the bone's cross-section; a fibula labelled with its tibia
#: touches it only at the two tibiofibular joints)
EPIPHYSIS_MIN_CONTACT = 0.1


def clean_mask(mask: np.ndarray, keep_fraction: float = 0.1, spacing=None,
               physis_gap: float = PHYSIS_GAP) -> tuple[np.ndarray, dict]:
    r"""Keep the largest 26-connected component of a bone mask, join its epiphyses, fill its cavities.

    Components with at least `keep_fraction` of the largest one's voxels are kept
    too (a pelvis label may hold two hip bones that touch nowhere).  With the
    voxel `spacing` given, a smaller piece separated from the largest
    component by an unlabelled gap of at most `physis_gap` across a broad
    face (an epiphysis behind a child's open growth plate, see
    ``EPIPHYSIS_MIN_FRACTION`` and ``EPIPHYSIS_MIN_CONTACT``) is joined back:
    the gap voxels ``x`` with :math:`d_{main}(x) + d_{piece}(x) \le g + h_{max}`
    (``g`` the piece's distance from the main component, ``d`` Euclidean
    distances in metres) whose nearest main and piece voxels lie on opposite
    sides (angle over 135 degrees: inside the plate, not beside its rim) are
    set, so the bone is surfaced as one rigid body.
    Other small islands are segmentation noise and removed.

    Returns
    -------
    mask : ndarray of bool
    report : dict
        ``islands_removed`` (list of voxel counts), ``epiphyses_joined`` (voxels,
        gap in m), ``holes_filled_voxels``, ``components_kept``.
    """
    lab, n = ndi.label(mask, structure=np.ones((3, 3, 3), bool))
    removed: list[int] = []
    joined: list[dict] = []
    if n > 1:
        sizes = np.bincount(lab.ravel())[1:]
        keep = sizes >= keep_fraction * sizes.max()
        main = int(np.argmax(sizes)) + 1
        bridges = np.zeros(mask.shape, bool)
        if spacing is not None:
            h = np.asarray(spacing, float)
            for c in np.flatnonzero(sizes < 0.5 * sizes.max()) + 1:
                if sizes[c - 1] < EPIPHYSIS_MIN_FRACTION * sizes.max():
                    continue
                out = _join_piece(lab, main, int(c), h, physis_gap)
                if out is not None:
                    bridges |= out[0]
                    keep[c - 1] = True
                    joined.append({"voxels": int(sizes[c - 1]), "gap_m": out[1]})
        removed = sorted((int(s) for s in sizes[~keep]), reverse=True)
        mask = (keep[np.maximum(lab - 1, 0)] & (lab > 0)) | bridges
    else:
        mask = lab > 0
    filled = _fill_cavities(mask)
    return filled, {"islands_removed": [{"voxels": v} for v in removed], "epiphyses_joined": joined,
                    "holes_filled_voxels": int(filled.sum() - mask.sum()),
                    "components_kept": int(n - len(removed)) if n else 0}


def _join_piece(lab: np.ndarray, main: int, piece: int, h: np.ndarray, gap: float):
    """Bridge voxels joining component `piece` to `main` across a growth-plate gap, or None."""
    pad = np.ceil(gap / h).astype(int) + 1
    idx = np.argwhere(lab == piece)
    lo = np.maximum(idx.min(0) - pad, 0)
    hi = np.minimum(idx.max(0) + pad + 1, lab.shape)
    sl = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    sub = lab[sl]
    m, p = sub == main, sub == piece
    if not m.any():
        return None
    d_main, i_main = ndi.distance_transform_edt(~m, sampling=h, return_indices=True)
    boundary = p & ~ndi.binary_erosion(p, structure=np.ones((3, 3, 3), bool))
    near = boundary & (d_main <= gap + h.max())
    if near.sum() < EPIPHYSIS_MIN_CONTACT * boundary.sum():
        return None
    g = float(d_main[p].min())
    d_piece, i_piece = ndi.distance_transform_edt(~p, sampling=h, return_indices=True)
    bridge = (sub == 0) & (d_main + d_piece <= g + h.max()) & (d_main <= gap + h.max()) & (d_piece <= gap + h.max())
    # inside the plate the nearest main and piece voxels lie on opposite sides; beside
    # its rim they do not (the bridge must not bulge out of the bone's outline)
    x = np.argwhere(bridge)
    to_main = (i_main[(slice(None), *x.T)].T - x) * h
    to_piece = (i_piece[(slice(None), *x.T)].T - x) * h
    cos = np.einsum("ij,ij->i", to_main, to_piece) / np.maximum(
        np.linalg.norm(to_main, axis=1) * np.linalg.norm(to_piece, axis=1), 1e-12)
    bridge[tuple(x[cos > -0.7].T)] = False
    out = np.zeros(lab.shape, bool)
    out[sl] = bridge
    return out, g


# --------------------------------------------------------------------------- meshes
def _to_pymeshlab(mesh: trimesh.Trimesh):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)))
    return ms


def _from_pymeshlab(ms) -> trimesh.Trimesh:
    m = ms.current_mesh()
    return trimesh.Trimesh(m.vertex_matrix(), m.face_matrix(), process=False)


def taubin_smooth(mesh: trimesh.Trimesh, iterations: int = 5, lamb: float = 0.5, mu: float = -0.53) -> trimesh.Trimesh:
    """Taubin lambda|mu smoothing: a low-pass filter that, unlike Laplacian smoothing, does not shrink.

    Each of the `iterations` passes applies ``x += lamb * L x`` then
    ``x += mu * L x`` (``mu < -lamb < 0``) with the umbrella Laplacian
    ``L x_i = mean_{j ~ i} x_j - x_i`` (trimesh, sparse; thread-safe, unlike pymeshlab).
    """
    if iterations <= 0:
        return mesh
    from trimesh.smoothing import filter_taubin, laplacian_calculation

    out = trimesh.Trimesh(np.array(mesh.vertices, float), mesh.faces, process=False)
    # trimesh counts half-steps (lambda on even, mu on odd ones)
    filter_taubin(out, lamb=lamb, nu=-mu, iterations=2 * int(iterations),
                  laplacian_operator=laplacian_calculation(out, equal_weight=True))
    return out


_PYMESHLAB_LOCK = threading.Lock()  # pymeshlab is not thread-safe


def decimate(mesh: trimesh.Trimesh, target_faces: int) -> trimesh.Trimesh:
    """Quadric edge-collapse decimation (pymeshlab) to about `target_faces`, topology kept.

    Call from the main thread only: pymeshlab used from other threads corrupts
    the heap (crash at interpreter exit), even when serialised.
    """
    if target_faces is None or target_faces >= len(mesh.faces):
        return mesh
    with _PYMESHLAB_LOCK:
        ms = _to_pymeshlab(mesh)
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(target_faces), preservetopology=True,
                                                    preservenormal=True, planarquadric=True, qualitythr=0.5)
        out = _from_pymeshlab(ms)
    if signed_volume(out.vertices, out.faces) < 0:
        out.invert()
    return out


def extract_surface(mask: np.ndarray, affine_m: np.ndarray, *, sigma: float | None = None,
                    smoothing_iterations: int = 5, volume_match: bool = True,
                    target_faces: int | None = None) -> trimesh.Trimesh:
    """Closed surface of a binary mask, in physical coordinates.

    Parameters
    ----------
    mask : (I, J, K) ndarray of bool
        The bone (already cleaned; cropped with a margin is fine and fast).
    affine_m : (4, 4) ndarray
        Index -> metres; flips, permutations, obliquity and anisotropy allowed.
    sigma : float, optional
        Gaussian blur (metres) before marching cubes; default 0.75 x the largest
        voxel size.  0 gives plain marching cubes of the binary mask.
    smoothing_iterations : int
        Taubin lambda|mu passes (0 to skip).
    volume_match : bool
        Offset the surface along its normals so its volume equals the voxel
        count volume (see the module docstring).
    target_faces : int, optional
        Decimate to about this many faces.

    Returns
    -------
    trimesh.Trimesh
        Watertight, outward normals, positive volume, metres.
    """
    from skimage.measure import marching_cubes

    mask = np.asarray(mask, bool)
    if not mask.any():
        raise ValueError("empty mask")
    affine_m = np.asarray(affine_m, float)
    spacing = np.linalg.norm(affine_m[:3, :3], axis=0)
    if sigma is None:
        sigma = 0.75 * float(spacing.max())
    pad_vox = np.ceil(3.0 * sigma / spacing).astype(int) + 2
    padded = np.pad(mask, [(p, p) for p in pad_vox])
    shift = affine_m[:3, :3] @ (-pad_vox.astype(float))
    if sigma > 0:
        field_ = ndi.gaussian_filter(padded.astype(np.float32), sigma / spacing, mode="constant", truncate=3.0)
    else:
        field_ = padded.astype(np.float32)
    verts, faces, _, _ = marching_cubes(field_, 0.5, allow_degenerate=False)
    del field_, padded
    verts = verts.astype(float) @ affine_m[:3, :3].T + (affine_m[:3, 3] + shift)
    faces = np.asarray(faces, np.int64)
    if signed_volume(verts, faces) < 0:  # det(A) < 0: the mapping mirrored the triangles
        faces = faces[:, ::-1].copy()
    mesh = trimesh.Trimesh(verts, faces, process=False)
    mesh = taubin_smooth(mesh, smoothing_iterations)
    if volume_match:
        v_mask = float(np.count_nonzero(mask)) * abs(np.linalg.det(affine_m[:3, :3]))
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        d = (v_mask - signed_volume(v, f)) / mesh.area
        mesh = trimesh.Trimesh(v + d * _vertex_normals(v, f), f, process=False)
    if target_faces:
        mesh = decimate(mesh, target_faces)
    return mesh


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed enclosed volume ``sum_f v0 . (v1 x v2) / 6`` (positive for outward faces).

    Taken about the vertex centroid: exact for closed meshes (any origin), and a
    stable orientation measure for open ones.
    """
    vv = np.asarray(vertices, float)
    v = (vv - vv.mean(axis=0))[np.asarray(faces)]
    return float(np.einsum("ij,ij->", v[:, 0], np.cross(v[:, 1], v[:, 2])) / 6.0)


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # |fn| = 2 area
    vn = np.zeros_like(vertices)
    for k in range(3):
        for c in range(3):
            vn[:, c] += np.bincount(faces[:, k], weights=fn[:, c], minlength=len(vertices))
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


# --------------------------------------------------------------------------- point clouds
def point_cloud(mesh: trimesh.Trimesh, n: int | None = None, *, spacing: float = 2e-3, seed: int = 0,
                outlier_neighbours: int = 12, outlier_std: float = 3.0) -> PointCloud:
    """Area-uniform point cloud on a closed mesh, outward normals, outliers removed.

    Points are drawn uniformly by area (seeded), each taking its triangle's
    outward normal, so normals are consistent by construction (no sign guessing
    as with normal estimation on raw points).  open3d's statistical filter then
    drops points whose mean distance to their `outlier_neighbours` nearest
    neighbours exceeds the global mean by `outlier_std` standard deviations
    (spikes, stray fragments).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Metres, outward normals.
    n : int, optional
        Number of points; default ``area / spacing**2``.
    spacing : float
        Mean point spacing (metres) when `n` is not given.
    seed : int
        Seed of the numpy Generator; the cloud is reproducible.
    """
    import open3d as o3d

    if n is None:
        n = max(100, int(round(mesh.area / spacing**2)))
    rng = np.random.default_rng(seed)
    pts, face_idx = trimesh.sample.sample_surface(mesh, int(n), seed=rng)
    normals = np.asarray(mesh.face_normals)[face_idx]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(pts, float)))
    k = min(outlier_neighbours, max(2, len(pts) - 1))
    _, keep = pcd.remove_statistical_outlier(nb_neighbors=k, std_ratio=outlier_std)
    keep = np.asarray(keep, dtype=np.int64)
    return PointCloud(points=np.asarray(pts)[keep], normals=normals[keep],
                      outliers_removed=int(len(pts) - len(keep)))


def surface_distance(a: trimesh.Trimesh, b: trimesh.Trimesh, n: int = 20000, seed: int = 0) -> dict:
    """Mean absolute surface distance between two meshes, sampled both ways.

    ``d(a->b) = mean_{p ~ U(a)} min_{q in b} |p - q|`` (point-to-triangle, libigl),
    likewise ``d(b->a)``; ``mean = (d(a->b) + d(b->a)) / 2``.  Units of the meshes.

    Returns
    -------
    dict
        ``mean``, ``a_to_b``, ``b_to_a``, ``max`` (largest sampled distance), ``rms``.
    """
    import igl

    rng = np.random.default_rng(seed)
    pa, _ = trimesh.sample.sample_surface(a, n, seed=rng)
    pb, _ = trimesh.sample.sample_surface(b, n, seed=rng)
    dab = np.sqrt(igl.point_mesh_squared_distance(np.asarray(pa, float), np.asarray(b.vertices, float),
                                                  np.asarray(b.faces, np.int64))[0])
    dba = np.sqrt(igl.point_mesh_squared_distance(np.asarray(pb, float), np.asarray(a.vertices, float),
                                                  np.asarray(a.faces, np.int64))[0])
    both = np.concatenate([dab, dba])
    return {"mean": float((dab.mean() + dba.mean()) / 2), "a_to_b": float(dab.mean()),
            "b_to_a": float(dba.mean()), "max": float(both.max()), "rms": float(np.sqrt(np.mean(both**2)))}


class BoneSurfaces(dict):
    """Bone name -> `BoneSurface`, plus what reading left out.

    Attributes
    ----------
    rejected : dict[str, str]
        Bone -> "file: problem" for each bone whose file could not be used;
        the joints that need it are missing.
    notes : list[str]
        What was done to the input as a whole (a whole foot split, ...).
    """

    def __init__(self, *args, rejected: dict | None = None, notes: list | None = None, **kw):
        super().__init__(*args, **kw)
        self.rejected = dict(rejected or {})
        self.notes = list(notes or [])


# --------------------------------------------------------------------------- pipelines
def _bone_boxes(labels: np.ndarray, label_values: list[int], slab: int = 16,
                present_out: set | None = None) -> dict[int, tuple[slice, ...] | None]:
    """Bounding box (slices) of each label value, None if absent; `present_out` collects all labels seen.

    One pass over the volume in slabs, touching only non-zero voxels: much
    faster than `scipy.ndimage.find_objects` on a mostly-background volume
    and with memory bounded by one slab.
    """
    arr, flipped = (labels.T, True) if labels.flags.f_contiguous and not labels.flags.c_contiguous else (labels, False)
    wanted = np.asarray(sorted(set(int(v) for v in label_values)))
    lo = {v: np.full(3, np.iinfo(np.int64).max) for v in wanted}
    hi = {v: np.full(3, -1) for v in wanted}
    for s0 in range(0, arr.shape[0], slab):
        block = np.ascontiguousarray(arr[s0:s0 + slab])
        nz = np.flatnonzero(block)
        if nz.size == 0:
            continue
        vals = block.reshape(-1)[nz]
        seen = np.unique(vals) if vals.dtype.itemsize > 1 else np.flatnonzero(np.bincount(vals))
        if present_out is not None:
            present_out.update(int(x) for x in seen)
        present = np.intersect1d(seen, wanted)
        for v in present:
            idx = np.unravel_index(nz[vals == v], block.shape)
            mins = np.array([i.min() for i in idx]) + [s0, 0, 0]
            maxs = np.array([i.max() for i in idx]) + [s0, 0, 0]
            lo[v] = np.minimum(lo[v], mins)
            hi[v] = np.maximum(hi[v], maxs)
    out: dict[int, tuple[slice, ...] | None] = {}
    for v in label_values:
        if hi[v][0] < 0:
            out[v] = None
            continue
        a, b = lo[v], hi[v]
        if flipped:
            a, b = a[::-1], b[::-1]
        out[v] = tuple(slice(int(x), int(y) + 1) for x, y in zip(a, b))
    return out


def _check_plausible_size(bone: str, box: tuple[slice, ...], affine_m: np.ndarray, source: str) -> None:
    """Refuse a bone whose box is wrong by a unit factor (e.g. a header saying mm for metres).

    Label volumes can be legitimately cropped (a knee scan shows part of a
    femur), so only sizes far outside the plausible range are refused.
    """
    size = np.array([s.stop - s.start for s in box], float)
    ext = float(np.max(np.abs(affine_m[:3, :3]) @ size))
    lo, hi = PLAUSIBLE_EXTENT_M[bone[:-2] if bone.endswith(("_r", "_l")) else bone]
    if ext > 3 * hi or ext < lo / 10:
        raise InputError(source, f"implausible size for {bone}: {ext * 1e3:.4g} mm across; "
                         "check the voxel size and its unit in the header")


def surfaces_from_labels(volume: LabelVolume, *, bones: list[str] | None = None, sigma: float | None = None,
                         smoothing_iterations: int = 5, target_faces: int | None = None,
                         keep_fraction: float = 0.1, workers: int = 2, point_spacing: float = 2e-3,
                         seed: int = 0, eager_points: bool = True,
                         progress: Callable[[str], None] | None = None) -> dict[str, BoneSurface]:
    """Extract every (or the requested) bone of a label volume.

    Each bone is cropped to its bounding box before any filtering, cleaned
    (`clean_mask`), and surfaced (`extract_surface`); bones run in a thread pool.

    Raises
    ------
    InputError
        A requested bone absent from the label map, or whose label is empty;
        a volume where no mapped label occurs.
    """
    src = volume.source
    lmap = volume.label_map
    if bones is not None:
        for b in bones:
            if b not in lmap:
                raise InputError(src, f"bone {b!r} is absent from the label map ({volume.label_map_source})")
        wanted = {b: lmap[b] for b in bones}
    else:
        wanted = dict(lmap)
    seen: set[int] = set()
    boxes = _bone_boxes(volume.labels, list(wanted.values()), present_out=seen)
    unmapped = sorted(seen - set(lmap.values()))
    present = {b: v for b, v in wanted.items() if boxes[v] is not None}
    if bones is not None:
        for b in bones:
            if b not in present:
                raise InputError(src, f"label {lmap[b]} ({b}) is empty: no voxel carries it")
    if not present:
        raise InputError(src, f"none of the labels of the label map ({volume.label_map_source}) occurs in the volume")

    for b, v in present.items():
        _check_plausible_size(b, boxes[v], volume.affine_m, src)

    def extract(bone: str) -> tuple[trimesh.Trimesh, dict]:
        label = present[bone]
        sl = boxes[label]
        crop = volume.labels[sl] == label
        mask, rep = clean_mask(crop, keep_fraction, spacing=volume.spacing_m)
        start = np.array([s.start for s in sl], float)
        aff = volume.affine_m.copy()
        aff[:3, 3] = aff[:3, :3] @ start + aff[:3, 3]
        mesh = extract_surface(mask, aff, sigma=sigma, smoothing_iterations=smoothing_iterations)
        rep.update({"label": int(label), "voxels": int(mask.sum()),
                    "voxel_size_m": [float(x) for x in volume.spacing_m], "units_detected": volume.unit,
                    "frame": volume.frame, "label_map": volume.label_map_source, "unmapped_labels": unmapped,
                    "mask_volume_m3": float(mask.sum()) * abs(float(np.linalg.det(volume.affine_m[:3, :3])))})
        if progress is not None and not target_faces:
            progress(bone)
        return mesh, rep

    names = list(present)
    meshes = _map(extract, names, workers)
    if target_faces:
        # pymeshlab corrupts the heap when used from worker threads: main thread only
        meshes = [(decimate(m, target_faces), r) for m, r in meshes]
        if progress is not None:
            for b in names:
                progress(b)
    out = {b: BoneSurface(name=b, mesh=m, source=src, report=r, point_spacing=point_spacing, seed=seed)
           for b, (m, r) in zip(names, meshes)}
    if eager_points:
        _map(lambda surf: surf.cloud, list(out.values()), workers)  # fills each cached cloud
    return out


def _map(fn, items: list, workers: int) -> list:
    """``[fn(x) for x in items]``, in a thread pool when `workers` > 1 (numpy/scipy/skimage/open3d release the GIL)."""
    if workers > 1 and len(items) > 1:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            return list(pool.map(fn, items))
    return [fn(x) for x in items]


def load_bones(path: str | os.PathLike, label_map: str | os.PathLike | dict | None = None, *,
               bones: list[str] | None = None, target_faces: int | None = None, fix_orientation: bool = False,
               workers: int = 2, point_spacing: float = 2e-3, seed: int = 0, eager_points: bool = True,
               progress: Callable[[str], None] | None = None) -> dict[str, BoneSurface]:
    """Bone surfaces from a label volume (.nii, .nii.gz, .nrrd) or a folder of meshes.

    Parameters
    ----------
    path : path-like
        Label volume file or folder of ``<bone>.ply|stl|obj``.
    label_map : dict or JSON path, optional
        For label volumes (see `personalize.io.read_label_volume`).
    bones : list of str, optional
        Only these bones (each must be present).
    target_faces : int, optional
        Decimate each surface to about this many faces.
    fix_orientation : bool
        For meshes: invert inside-out meshes instead of refusing them.
    eager_points : bool
        Build the point clouds now (in the worker threads) rather than on first use.

    Returns
    -------
    BoneSurfaces
        Canonical bone name -> surface, metres, input frame; for a mesh
        folder, ``rejected`` lists the bones left out (bone -> "file: problem")
        and ``notes`` what was done to the folder (a whole foot split, ...).
    """
    p = Path(path)
    if not p.exists():
        raise InputError(p, "file or folder not found")
    if p.is_dir():
        meshes, folder_rep = read_mesh_folder_detailed(p, bones=bones, fix_orientation=fix_orientation)
        out = BoneSurfaces(rejected=folder_rep["rejected"], notes=folder_rep["notes"])
        for name, mi in meshes.items():
            mesh = decimate(mi.mesh, target_faces) if target_faces else mi.mesh
            rep = dict(mi.report, frame="input", ignored_files=folder_rep["ignored_files"])
            out[name] = BoneSurface(name=name, mesh=mesh, source=mi.source, report=rep,
                                    point_spacing=point_spacing, seed=seed)
            if progress is not None:
                progress(name)
        if eager_points:
            _map(lambda surf: surf.cloud, list(out.values()), workers)
        return out
    if not is_label_volume_path(p):
        raise InputError(p, "expected a label volume (.nii, .nii.gz, .nrrd, .nhdr) or a folder of bone meshes")
    vol = read_label_volume(p, label_map)
    return surfaces_from_labels(vol, bones=bones, target_faces=target_faces, workers=workers,
                                point_spacing=point_spacing, seed=seed, eager_points=eager_points,
                                progress=progress)
