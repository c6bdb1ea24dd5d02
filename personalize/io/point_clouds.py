"""Bone point clouds (points without faces) as segmentation tools export them, and their surfaces.

A point cloud file (PLY with vertices only, PCD, XYZ) holds points on one
bone's surface, optionally with normals.  The detectors need a closed
surface, so reading reconstructs one:

1. normals: read if present, else estimated by open3d (PCA of the
   ``k`` nearest neighbours, `estimate_normals`) and each turned outward
   by the cloud's filled occupancy (`_outward`);
2. surface: screened Poisson reconstruction (Kazhdan & Hoppe 2013, open3d),
   the indicator function ``chi`` minimising

       || grad chi - V ||^2 + alpha sum_i chi(p_i)^2

   with ``V`` the normal field; its octree depth is set so the finest cell
   is half the point spacing ``h`` (median nearest-neighbour distance).
   Projecting the vertices on the local planes of their nearest points was
   tried: where the sampling is sparse (ICL shafts at 20 % of the vertices,
   gaps of 10-20 mm) it pulls the surface inward (femur volume -5 %).

The reconstruction is only as good as the sampling: ``report["sampling_sd_m"]``
is the rms distance of the points to the reconstructed surface combined with
the chordal error of a surface sampled every ``h`` (``h^2 / (8 R)``, R = 10 mm,
a typical articular radius); it is added to the stated
covariance of every landmark of such a bone (`add_sampling_uncertainty`).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import trimesh

from lowerlimb.errors import InputError

__all__ = ["read_point_cloud", "reconstruct_surface", "sampling_sd_m", "add_sampling_uncertainty", "MIN_POINTS",
           "ARTICULAR_RADIUS_M"]

#: octree levels beyond the one whose cell matches the point spacing (finer cells follow the points closer)
POISSON_EXTRA_DEPTH = 1
#: fewest points of a bone cloud
MIN_POINTS = 200
#: curvature radius for the chordal term of the sampling error (articular surfaces: 10-25 mm)
ARTICULAR_RADIUS_M = 0.010


def read_point_cloud(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) in the file's units and their normals (N, 3) or None.

    ``.xyz``/``.xyzn``/``.pts``: text, one point per line, ``x y z`` or
    ``x y z nx ny nz`` (``#`` comments; a leading count line is skipped).
    ``.ply``/``.pcd``: open3d.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".xyz", ".xyzn", ".pts"):
        try:
            rows = [ln.split() for ln in path.read_text(encoding="utf-8", errors="strict").splitlines()
                    if ln.strip() and not ln.lstrip().startswith(("#", "//"))]
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(path, f"cannot read point cloud as text ({exc})") from None
        if rows and len(rows[0]) == 1:
            rows = rows[1:]  # a count line
        ncol = {len(r) for r in rows}
        if not rows or len(ncol) != 1 or ncol.pop() not in (3, 6, 7):
            raise InputError(path, "point cloud lines must all hold x y z (or x y z nx ny nz)")
        try:
            a = np.asarray(rows, float)
        except ValueError:
            raise InputError(path, "point cloud holds a non-numeric value") from None
        pts, nrm = a[:, :3], (a[:, 3:6] if a.shape[1] >= 6 else None)
    else:
        import open3d as o3d

        try:
            pc = o3d.io.read_point_cloud(str(path))
        except Exception as exc:  # open3d raises RuntimeError on bad headers
            raise InputError(path, f"cannot read point cloud ({type(exc).__name__}: {exc})") from None
        pts = np.asarray(pc.points, float)
        nrm = np.asarray(pc.normals, float) if pc.has_normals() else None
    if len(pts) < MIN_POINTS:
        raise InputError(path, f"point cloud holds {len(pts)} points (at least {MIN_POINTS} needed)")
    if not np.all(np.isfinite(pts)) or (nrm is not None and not np.all(np.isfinite(nrm))):
        raise InputError(path, "point cloud has non-finite coordinates or normals")
    if nrm is not None:
        n = np.linalg.norm(nrm, axis=1)
        nrm = None if np.any(n < 1e-12) else nrm / n[:, None]
    return pts, nrm


def reconstruct_surface(points: np.ndarray, normals: np.ndarray | None = None, *, source=None,
                        seed: int = 0) -> tuple[trimesh.Trimesh, dict]:
    """Closed surface through a bone's points (units of `points`) and a report.

    Parameters
    ----------
    points : (N, 3) ndarray
    normals : (N, 3) ndarray, optional
        Outward unit normals; estimated when absent (or turned outward when
        they point in on the whole).
    source : path-like, optional
        Named in errors.
    seed : int
        open3d's random state (Poisson runs on one thread and is then
        deterministic; kept for the normal orientation's tie-breaks).

    Returns
    -------
    mesh : trimesh.Trimesh
        Watertight where Poisson closes it (always for a cloud around a bone).
    report : dict
        ``input``, ``points``, ``normals`` (read / estimated), ``point_spacing``
        and ``points_to_surface_rms`` (file units), ``poisson_depth``,
        ``repairs`` (words).
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    o3d.utility.random.seed(seed)
    pts = np.asarray(points, float)
    tree = cKDTree(pts)
    d, _ = tree.query(pts, k=2)
    h = float(np.median(d[:, 1]))
    if not h > 0:
        raise InputError(source, "point cloud points coincide")
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    estimated = normals is None
    if estimated:
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=20))
        nrm = _outward(pts, np.asarray(pc.normals), h, tree)
    else:
        nrm = np.asarray(normals, float)
        if np.mean(np.einsum("ij,ij->i", _outward(pts, nrm, h, tree), nrm) < 0) > 0.5:
            nrm = -nrm  # read normals pointing inward on the whole: turn them all
    pc.normals = o3d.utility.Vector3dVector(nrm)
    extent = float(np.max(pts.max(axis=0) - pts.min(axis=0)))
    depth = int(np.clip(np.ceil(np.log2(1.1 * extent / h)) + POISSON_EXTRA_DEPTH, 6, 11))
    # one thread: open3d's threaded Poisson emits its vertices in a run-dependent order (and the detectors
    # thin by index), so identical input gave landmarks mm apart; single-threaded it is also no slower here
    mesh, _dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=depth, scale=1.1,
                                                                             linear_fit=True, n_threads=1)
    v, f = np.asarray(mesh.vertices, float), np.asarray(mesh.triangles, np.int64)
    if len(f) == 0:
        raise InputError(source, "no surface could be reconstructed from the point cloud")
    out = trimesh.Trimesh(v, f, process=False, validate=False)
    # Poisson may add a far-off shell; the bone is the component nearest the points
    parts = out.split(only_watertight=False)
    if len(parts) > 1:
        out = max(parts, key=lambda p: p.area)
    if out.volume < 0:
        out.invert()
    _, dist, _ = trimesh.proximity.closest_point(out, pts[:: max(1, len(pts) // 5000)])
    rms = float(np.sqrt(np.mean(dist ** 2)))
    rep = {"input": "point cloud", "points": int(len(pts)), "normals": "estimated" if estimated else "read",
           "point_spacing": h, "poisson_depth": depth, "points_to_surface_rms": rms,
           "repairs": [f"surface reconstructed from {len(pts)} points (normals {'estimated' if estimated else 'read'}"
                       f", screened Poisson depth {depth})"]}
    return out, rep



def sampling_sd_m(report: dict, metres_per_unit: float) -> float:
    """1-sd surface error (m) of a reconstructed cloud: ``hypot(rms to points, h^2 / (8 R))``."""
    h = report["point_spacing"] * metres_per_unit
    return float(np.hypot(report["points_to_surface_rms"] * metres_per_unit, h ** 2 / (8 * ARTICULAR_RADIUS_M)))


def _outward(points: np.ndarray, normals: np.ndarray, h: float, tree) -> np.ndarray:
    """`normals` (unoriented) each turned outward, from a filled occupancy of the cloud.

    The points are rasterised on voxels of size ``h``; the shell is closed by
    dilating it ``k`` times, filled (``binary_fill_holes``) and eroded back
    (a morphological closing that keeps the interior); ``k`` is the smallest
    of 1-10 whose filled interior reaches half the largest over ``k`` (the
    shell has closed; a larger ``k`` fills concavities and thin parts).  A
    normal points outward when the blurred solid is lower 2.5 h along it than
    2.5 h against it.  Then, five times, a normal is turned when its
    neighbours (12 nearest, weighted by their own solid contrast) disagree
    with it on the whole.  open3d's `orient_normals_consistent_tangent_plane`
    (spanning-tree propagation) was tried first: on the ICL tibia, pelvis and
    calcaneus sampled at 20 % of their vertices it flips whole regions (34-67 %
    of the normals wrong), this rule 0.1-2 % (calcaneus, toes: 16-24 %).
    """
    import scipy.ndimage as ndi

    # at most 400 voxels along the bone: a 0.2 mm cloud of a femur would otherwise need ~5e8 voxels
    h = max(h, float(np.ptp(points, axis=0).max()) / 400.0)
    K = 10
    lo = points.min(axis=0) - (K + 4) * h
    idx = np.floor((points - lo) / h).astype(int)
    occ = np.zeros(idx.max(axis=0) + K + 5, bool)
    occ[tuple(idx.T)] = True
    interior = []
    ks = (1, 2, 3, 4, 6, 8, 10)
    for k in ks:
        d = ndi.binary_dilation(occ, iterations=k)
        interior.append(int((ndi.binary_fill_holes(d) & ~d).sum()))
    iv = np.asarray(interior)
    k = ks[int(np.argmax(iv >= 0.5 * iv.max()))]
    solid = ndi.binary_erosion(ndi.binary_fill_holes(ndi.binary_dilation(occ, iterations=k)), iterations=k,
                               border_value=0) | occ
    blur = ndi.gaussian_filter(solid.astype(float), 1.0)

    def at(q):
        return ndi.map_coordinates(blur, ((q - lo) / h - 0.5).T, order=1)

    s = at(points - 2.5 * h * normals) - at(points + 2.5 * h * normals)
    n = np.where((s < 0)[:, None], -normals, normals)
    _, j = tree.query(points, k=13)
    j = j[:, 1:]
    w = np.abs(s)[j]
    for _ in range(5):
        agree = np.einsum("ijk,ik->ij", n[j], n) * w
        n = np.where((agree.sum(axis=1) < 0)[:, None], -n, n)
    return n


def add_sampling_uncertainty(ls, surfaces) -> dict[str, float]:
    """Add each point-cloud bone's sampling sd to the covariance of its landmarks (in place).

    ``cov <- cov + sd^2 I`` for every landmark of a bone whose surface was
    reconstructed from points (``report["sampling_sd_m"]``): the fitted
    primitives see the reconstructed surface, whose error the fits' own
    residuals cannot show.  Returns bone -> sd (m) for the bones changed.
    """
    from ..landmarks.common import Landmark

    done = {}
    for name, res in ls.bones.items():
        s = surfaces.get(name)
        sd = (getattr(s, "report", None) or {}).get("sampling_sd_m")
        if not sd:
            continue
        for k, lm in list(res.landmarks.items()):
            res.landmarks[k] = Landmark(position=lm.position, cov=np.asarray(lm.cov) + sd ** 2 * np.eye(3))
        res.notes.append(f"{name}: surface reconstructed from a point cloud; landmark covariances include its "
                         f"sampling sd {sd * 1e3:.2f} mm")
        done[name] = float(sd)
    return done
