"""Readers for bone geometry: label volumes (NIfTI, NRRD) and folders of bone meshes.

Everything leaves this module in SI units: affines map voxel indices to metres,
meshes are in metres.  The frame is the input's own (scanner) frame: NIfTI world
coordinates (RAS+) or the NRRD ``space``; nothing is re-oriented.

Unit detection for meshes compares each bone's largest bounding-box extent with
an anatomically plausible range (`PLAUSIBLE_EXTENT_M`).  The ranges are wide
(a factor >= 5 between bounds, children to large adults) yet much narrower
than the factor 1000 between millimetres and metres, so the decision is never
ambiguous; a size plausible in neither unit is refused.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from lowerlimb.bones import DEFAULT_LABEL_MAP, PREFERRED_STEMS, WHOLE_FOOT, canonical_bone_name, is_tissue_name
from lowerlimb.errors import InputError

__all__ = [
    "LabelVolume",
    "MeshInput",
    "PLAUSIBLE_EXTENT_M",
    "VOLUME_SUFFIXES",
    "MESH_SUFFIXES",
    "read_label_volume",
    "read_label_map",
    "read_tissue_label",
    "read_mesh_folder",
    "read_mesh_folder_detailed",
    "check_and_repair_mesh",
    "is_label_volume_path",
    "detect_mesh_unit",
]

VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr")
MESH_SUFFIXES = (".stl", ".ply", ".obj")
#: point-cloud files (a PLY without faces is one too)
POINT_SUFFIXES = (".pcd", ".xyz", ".xyzn", ".pts")

#: plausible largest bounding-box extent (metres) of each bone type, (low, high);
#: wide enough for children and for the real STAPLE meshes (whose ``tibia`` may
#: include the fibula and whose ``calcn`` includes the mid-foot bones)
PLAUSIBLE_EXTENT_M: dict[str, tuple[float, float]] = {
    "pelvis": (0.08, 0.50),
    "femur": (0.12, 0.75),
    "tibia": (0.10, 0.65),
    "fibula": (0.10, 0.60),
    "patella": (0.015, 0.10),
    "talus": (0.02, 0.12),
    "calcn": (0.03, 0.30),
    "toes": (0.015, 0.20),
}

_UNIT_SCALE = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "cm": 1e-2}


def _bone_type(bone: str) -> str:
    return bone[:-2] if bone.endswith(("_r", "_l")) else bone


def is_label_volume_path(path: str | os.PathLike) -> bool:
    """True if `path` names a label volume by its suffix (.nii, .nii.gz, .nrrd, .nhdr)."""
    name = Path(path).name.lower()
    return name.endswith(VOLUME_SUFFIXES)


# --------------------------------------------------------------------------- label maps
def _raw_label_map(source) -> tuple[dict, str]:
    """The label map's raw JSON object (or the given dict) and a description of its origin."""
    origin = "given"
    if not isinstance(source, dict):
        path = Path(source)
        origin = str(path)
        if not path.is_file():
            raise InputError(path, "label map file not found")
        try:
            raw = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(path, f"cannot read the label map as JSON ({exc})") from None
        if isinstance(raw, dict) and isinstance(raw.get("labels"), dict):
            raw = raw["labels"]  # tolerate {"labels": {...}, "units": ...} wrappers
        if not isinstance(raw, dict):
            raise InputError(path, "label map must be a JSON object of bone name -> integer label")
    else:
        raw = source
    return raw, origin


def _entries(raw: dict, origin: str):
    """(name, integer label) pairs of a raw label map, checked: positive integers."""
    for key, value in raw.items():
        name, label = (value, key) if isinstance(value, str) else (key, value)
        try:
            lab = int(label)
        except (TypeError, ValueError):
            raise InputError(origin, f"label of {name!r} is not an integer ({label!r})") from None
        if isinstance(label, float) and label != lab or lab <= 0:
            raise InputError(origin, f"label of {name!r} must be a positive integer ({label!r})")
        yield str(name), lab


def read_label_map(source: str | os.PathLike | dict | None) -> tuple[dict[str, int], str]:
    """Bone -> integer label map from a dict, a JSON file, or the default.

    The JSON may map bone names to labels (``{"femur_r": 2}``) or labels to bone
    names (``{"2": "femur_r"}``); aliases such as ``pelvis_no_sacrum`` are
    accepted.  The optional body/skin label (``skin``, ``body`` or
    ``soft_tissue``; `read_tissue_label`) is not a bone and is left out.
    Returns the canonical map and a description of its origin.

    Raises
    ------
    InputError
        Unreadable JSON, unknown bone names, non-integer or duplicate labels.
    """
    if source is None:
        return dict(DEFAULT_LABEL_MAP), "default"
    raw, origin = _raw_label_map(source)
    out: dict[str, int] = {}
    tissue: list[int] = []
    for name, lab in _entries(raw, origin):
        if is_tissue_name(name):
            tissue.append(lab)
            continue
        bone = canonical_bone_name(name)
        if bone is None:
            raise InputError(origin, f"unknown bone name {name!r} in the label map")
        if bone in out:
            raise InputError(origin, f"bone {bone!r} appears twice in the label map")
        if lab in out.values():
            raise InputError(origin, f"label {lab} is used for two bones in the label map")
        out[bone] = lab
    if len(tissue) > 1:
        raise InputError(origin, f"the body/skin label appears {len(tissue)} times in the label map (skin, body, soft_tissue)")
    if tissue and tissue[0] in out.values():
        raise InputError(origin, f"label {tissue[0]} is used for the skin and for a bone in the label map")
    if not out:
        raise InputError(origin, "label map is empty")
    return out, origin


def read_tissue_label(source: str | os.PathLike | dict | None) -> int | None:
    """Integer label of the body/skin envelope in a label map (key ``skin``, ``body`` or ``soft_tissue``), or None.

    The default label map has none: a volume's soft tissue is only used when the label map names it.
    """
    if source is None:
        return None
    raw, origin = _raw_label_map(source)
    labs = [lab for name, lab in _entries(raw, origin) if is_tissue_name(name)]
    return labs[0] if labs else None


# --------------------------------------------------------------------------- volumes
@dataclass(frozen=True)
class LabelVolume:
    """An integer label map on a voxel grid.

    Attributes
    ----------
    labels : (I, J, K) ndarray of int
        Label of each voxel; 0 is background.
    affine_m : (4, 4) ndarray
        Voxel index (i, j, k, 1) -> physical position in metres, input frame.
        May contain flips (negative determinant), permutations and obliquity.
    label_map : dict[str, int]
        Canonical bone name -> label.
    source : str
        The file read (or a description).
    unit : str
        Physical unit of the file's own coordinates ("mm" for NIfTI/NRRD usually).
    frame : str
        The file's world frame ("RAS" for NIfTI, the NRRD ``space``).
    label_map_source : str
        Where the label map came from ("default", a JSON path, ...).
    tissue_label : int or None
        Label of the body/skin envelope (soft tissue inside the skin that is not
        bone; bones are labelled over it), None when the volume has none.
    """

    labels: np.ndarray
    affine_m: np.ndarray
    label_map: dict[str, int]
    source: str
    unit: str = "mm"
    frame: str = "RAS"
    label_map_source: str = "default"
    tissue_label: int | None = None

    @property
    def spacing_m(self) -> np.ndarray:
        """(3,) voxel size along the array axes, metres."""
        return np.linalg.norm(self.affine_m[:3, :3], axis=0)


def _as_integer_labels(data: np.ndarray, path: Path) -> np.ndarray:
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise InputError(path, f"a label volume must be 3-D, got shape {data.shape}")
    if data.size == 0:
        raise InputError(path, "label volume has no voxels")
    if np.issubdtype(data.dtype, np.bool_):
        return data.astype(np.uint8)
    if np.issubdtype(data.dtype, np.integer):
        return data
    if np.issubdtype(data.dtype, np.floating):
        # float-stored label maps are common (ITK-SNAP, Slicer exports); accept
        # them only if every value is a finite whole number
        finite = np.isfinite(data)
        if not finite.all() or not np.array_equal(data, np.round(data)):
            raise InputError(path, "not an integer label map (the volume holds non-integer values, e.g. an intensity image)")
        lo, hi = float(data.min()), float(data.max())
        dtype = np.uint8 if lo >= 0 and hi < 256 else np.int32
        return data.astype(dtype)
    raise InputError(path, f"not an integer label map (voxel type {data.dtype})")


def _read_nifti(path: Path) -> tuple[np.ndarray, np.ndarray, str, str]:
    import nibabel as nib

    try:
        img = nib.load(str(path))
        dataobj = img.dataobj
        slope = getattr(dataobj, "slope", 1.0)
        inter = getattr(dataobj, "inter", 0.0)
        if (slope in (1.0, None) or np.isnan(slope)) and (inter in (0.0, None) or np.isnan(inter)):
            # native dtype: no float64 copy of a 100M-voxel label map
            data = np.asarray(dataobj.get_unscaled()) if hasattr(dataobj, "get_unscaled") else np.asarray(dataobj)
        else:
            data = np.asarray(img.get_fdata(dtype=np.float32))
        affine = np.array(img.affine, dtype=float)
        unit = img.header.get_xyzt_units()[0]
    except InputError:
        raise
    except Exception as exc:  # nibabel raises many types for corrupt files
        raise InputError(path, f"cannot read NIfTI file ({type(exc).__name__}: {exc})") from None
    unit = {"meter": "m", "mm": "mm", "micron": "um", "unknown": "mm"}.get(unit, "mm")
    return data, affine, unit, "RAS"


def _read_nrrd(path: Path) -> tuple[np.ndarray, np.ndarray, str, str]:
    import nrrd

    try:
        data, header = nrrd.read(str(path))
    except Exception as exc:
        raise InputError(path, f"cannot read NRRD file ({type(exc).__name__}: {exc})") from None
    dirs = header.get("space directions")
    if dirs is None:
        spacing = header.get("spacings", [1.0, 1.0, 1.0])
        rot = np.diag(np.asarray(spacing, float)[:3])
    else:
        rows = [np.asarray(d, float) for d in dirs if d is not None and not np.all(np.isnan(np.asarray(d, float)))]
        if len(rows) != 3:
            raise InputError(path, "NRRD 'space directions' must define three spatial axes")
        rot = np.stack(rows, axis=1)  # column k = step of array axis k
    origin = np.asarray(header.get("space origin", np.zeros(3)), float)
    affine = np.eye(4)
    affine[:3, :3] = rot
    affine[:3, 3] = origin
    units = header.get("space units")
    unit = str(units[0]).strip().lower() if units else "mm"
    unit = {"millimeter": "mm", "millimeters": "mm", "meter": "m", "meters": "m", "micron": "um"}.get(unit, unit)
    if unit not in _UNIT_SCALE:
        raise InputError(path, f"unsupported NRRD space unit {unit!r}")
    return data, affine, unit, str(header.get("space", "unknown"))


def read_label_volume(path: str | os.PathLike, label_map: str | os.PathLike | dict | None = None) -> LabelVolume:
    """Read an integer label volume (NIfTI ``.nii``/``.nii.gz`` or NRRD ``.nrrd``/``.nhdr``).

    Parameters
    ----------
    path : path-like
        The label volume.
    label_map : dict, path to JSON, or None
        Bone -> label map.  None uses ``label_map.json`` beside the volume if
        present, else `lowerlimb.bones.DEFAULT_LABEL_MAP`.

    Returns
    -------
    LabelVolume
        Labels, the voxel -> metres affine (input frame) and the label map.

    Raises
    ------
    InputError
        Missing/unreadable file, non-integer voxels, a volume without any
        non-zero label, a bad label map or voxel sizes that are not finite and
        positive.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    if not path.is_file():
        raise InputError(path, "not a file")
    if not is_label_volume_path(path):
        raise InputError(path, f"unsupported label volume type (expected one of {', '.join(VOLUME_SUFFIXES)})")
    if label_map is None and (path.parent / "label_map.json").is_file():
        label_map = path.parent / "label_map.json"
    lmap, lmap_origin = read_label_map(label_map)
    tissue = read_tissue_label(label_map)
    if path.name.lower().endswith((".nrrd", ".nhdr")):
        data, affine, unit, frame = _read_nrrd(path)
    else:
        data, affine, unit, frame = _read_nifti(path)
    labels = _as_integer_labels(data, path)
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise InputError(path, "the voxel-to-world affine is singular or not finite")
    affine_m = affine.copy()
    affine_m[:3, :] *= _UNIT_SCALE[unit]
    if not labels.any():
        raise InputError(path, "label volume is empty (no non-zero voxel)")
    return LabelVolume(labels=labels, affine_m=affine_m, label_map=lmap, source=str(path),
                       unit=unit, frame=frame, label_map_source=lmap_origin,
                       tissue_label=tissue if tissue is not None and np.any(labels == tissue) else None)


# --------------------------------------------------------------------------- meshes
def detect_mesh_unit(bone: str, extent: float, source: str | os.PathLike) -> str:
    """Decide whether a bone mesh is in metres or millimetres from its size.

    Parameters
    ----------
    bone : str
        Canonical bone name (the type sets the plausible range).
    extent : float
        Largest bounding-box extent in the file's units.
    source : path-like
        File named in the error.

    Returns
    -------
    str
        "m" or "mm".

    Raises
    ------
    InputError
        If the size is plausible in neither unit.
    """
    lo, hi = PLAUSIBLE_EXTENT_M[_bone_type(bone)]
    if lo <= extent <= hi:
        return "m"
    if lo <= extent * 1e-3 <= hi:
        return "mm"
    raise InputError(source, f"implausible size for a {bone}: largest extent {extent:.4g} is neither "
                     f"{lo:g}-{hi:g} m nor {lo * 1e3:g}-{hi * 1e3:g} mm; check the units")


@dataclass(frozen=True)
class MeshInput:
    """One bone mesh read from a folder (metres, input frame) and what was done to it."""

    name: str
    mesh: trimesh.Trimesh
    source: str
    unit: str
    report: dict = field(default_factory=dict)


def _weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """Merge coincident vertices, then drop the faces the merge collapsed and repeated faces.

    Merging two coincident vertices is an edge collapse when they are joined
    by an edge (the phantom's marching-cubes meshes have a few such
    zero-length edges): the two faces on that edge lose a corner.  Keeping
    them, as a plain vertex merge does, leaves each of their edges on three
    faces (non-manifold).  Repeated faces (same corners, any winding; real
    segmentations hold 8-fold copies of one triangle) are kept once.
    STL files store every corner separately: the merge gives them topology.
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    uniq, inv = np.unique(v, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    f = inv[f]
    collapsed = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    f = f[~collapsed]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    n_rep = len(f) - len(first)
    f = f[np.sort(first)]
    used = np.unique(f)
    remap = np.full(len(uniq), -1, np.int64)
    remap[used] = np.arange(len(used))
    rep = {"merged_vertices": int(len(v) - len(uniq)), "collapsed_faces_removed": int(collapsed.sum()),
           "duplicate_faces_removed": int(n_rep)}
    return uniq[used], remap[f], rep


def _load_mesh_file(path: Path) -> tuple[trimesh.Trimesh, dict]:
    """Triangle mesh of a mesh or point-cloud file (file units) and what reading did to it.

    A file without faces (PLY of vertices only, PCD, XYZ) is a point cloud:
    its surface is reconstructed (`personalize.point_clouds.reconstruct_surface`).
    """
    if path.suffix.lower() in POINT_SUFFIXES:
        from .point_clouds import read_point_cloud, reconstruct_surface

        pts, nrm = read_point_cloud(path)
        return reconstruct_surface(pts, nrm, source=path)
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:
        raise InputError(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
        loaded = trimesh.util.concatenate(geoms) if geoms else None
    if isinstance(loaded, trimesh.PointCloud) or (isinstance(loaded, trimesh.Trimesh) and len(loaded.faces) == 0
                                                  and len(loaded.vertices)):
        from .point_clouds import read_point_cloud, reconstruct_surface

        pts, nrm = read_point_cloud(path)
        return reconstruct_surface(pts, nrm, source=path)
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputError(path, "file holds no triangle faces")
    if not np.all(np.isfinite(loaded.vertices)):
        raise InputError(path, "mesh has non-finite vertex coordinates")
    fi = np.asarray(loaded.faces)
    if fi.ndim != 2 or fi.shape[1] != 3 or fi.min() < 0 or fi.max() >= len(loaded.vertices):
        raise InputError(path, f"corrupt mesh: face corner indices outside its {len(loaded.vertices)} vertices")
    v, f, rep = _weld(loaded.vertices, loaded.faces)
    if len(f) == 0:
        raise InputError(path, "file holds no triangle faces with three distinct corners")
    return trimesh.Trimesh(v, f, process=False, validate=False), rep


def _centroid_volume(mesh: trimesh.Trimesh) -> float:
    """Signed volume about the vertex centroid (exact if closed, an orientation cue if open)."""
    v = np.asarray(mesh.vertices, float)
    t = (v - v.mean(axis=0))[np.asarray(mesh.faces)]
    return float(np.einsum("ij,ij->", t[:, 0], np.cross(t[:, 1], t[:, 2])) / 6.0)


def _largest_hole_perimeter(mesh: trimesh.Trimesh) -> float:
    edges = mesh.edges_sorted
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = uniq[counts == 1]
    if len(boundary) == 0:
        return 0.0
    # boundary loops = connected components of the boundary-edge graph
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = len(mesh.vertices)
    g = sp.coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    lengths = np.linalg.norm(mesh.vertices[boundary[:, 0]] - mesh.vertices[boundary[:, 1]], axis=1)
    return float(np.bincount(comp[boundary[:, 0]], weights=lengths).max())


def _close_holes(mesh: trimesh.Trimesh, max_hole_edges: int = 200) -> trimesh.Trimesh:
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int32)))
    try:
        ms.meshing_close_holes(maxholesize=max_hole_edges, newfaceselected=False)
    except pymeshlab.PyMeshLabException:  # e.g. non-manifold edges: leave it open
        return mesh
    m = ms.current_mesh()
    v, f, _ = _weld(m.vertex_matrix(), m.face_matrix())
    return trimesh.Trimesh(v, f, process=False, validate=False)


def _fix_winding(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Faces wound coherently (pymeshlab's re-orientation, C++; trimesh's networkx walk takes ~0.3 s a part)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int32)))
    try:
        ms.meshing_re_orient_faces_coherently()
    except pymeshlab.PyMeshLabException:
        trimesh.repair.fix_winding(mesh)
        return mesh
    m = ms.current_mesh()
    out = trimesh.Trimesh(m.vertex_matrix(), m.face_matrix(), process=False, validate=False)
    if len(out.vertices) != len(mesh.vertices) or not out.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
        return mesh
    return out


def _nonmanifold_edge_count(faces: np.ndarray) -> int:
    e = np.sort(np.asarray(faces)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int(np.sum(counts > 2))


def _repair_nonmanifold(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Remove the faces that make edges non-manifold (pymeshlab, then its vertex split), re-weld."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int32)))
    ms.meshing_repair_non_manifold_edges(method="Remove Faces")
    ms.meshing_repair_non_manifold_vertices()
    m = ms.current_mesh()
    v, f, _ = _weld(m.vertex_matrix(), m.face_matrix())
    return trimesh.Trimesh(v, f, process=False, validate=False)


def _islands(mesh: trimesh.Trimesh, min_island_fraction: float):
    """Connected parts (by edges) and which are kept (area >= fraction x the largest)."""
    parts = mesh.split(only_watertight=False)
    if len(parts) == 0:
        return [], np.zeros(0, bool)
    areas = np.array([p.area for p in parts])
    return parts, areas >= min_island_fraction * areas.max()


def main_extent(mesh: trimesh.Trimesh, min_island_fraction: float = 0.01) -> float:
    """Largest bounding-box extent of a mesh without its small islands (file units).

    Stray specks far from the bone (a segmentation's mislabelled voxels) must
    not decide the unit or the plausibility of the bone's size.
    """
    parts, keep = _islands(mesh, min_island_fraction)
    if not len(parts):
        return float(np.max(mesh.extents))
    v = np.concatenate([p.vertices for p, k in zip(parts, keep) if k])
    return float(np.max(v.max(axis=0) - v.min(axis=0)))


def check_and_repair_mesh(mesh: trimesh.Trimesh, bone: str, source: str | os.PathLike, *,
                          fix_orientation: bool = False, min_island_fraction: float = 0.01,
                          max_hole_fraction: float = 0.1) -> tuple[trimesh.Trimesh, dict]:
    """Validate a bone mesh; repair what is unambiguous, refuse the rest.

    * coincident vertices merged, the faces this collapses and repeated
      faces removed (`_weld`; also done on reading);
    * non-manifold edges (shared by > 2 faces): the offending faces removed
      (pymeshlab), the holes this opens closed below;
    * islands with area < `min_island_fraction` x the largest component: removed;
    * open components: holes whose boundary loop is shorter than
      `max_hole_fraction` x the bone's largest extent are closed (pymeshlab);
      larger holes (missing anatomy) -> refused,
      except ``toes_*`` (open in the real data), which are flagged;
    * components whose winding is inconsistent: re-wound and oriented outward;
    * a mesh whose faces consistently point inward (negative volume): refused
      unless `fix_orientation`, then inverted.

    Returns the repaired mesh and a report dict; ``report["repairs"]`` lists
    in words what was changed.

    Raises
    ------
    InputError
        What could not be repaired (the bone cannot be used).
    """
    report: dict = {"islands_removed": [], "winding_repaired_components": 0, "inverted": False,
                    "holes_closed": False, "open": False, "repairs": []}
    v, f, wrep = _weld(mesh.vertices, mesh.faces)
    if wrep["collapsed_faces_removed"] or wrep["duplicate_faces_removed"] or wrep["merged_vertices"]:
        mesh = trimesh.Trimesh(v, f, process=False, validate=False)
    n_nonmanifold = _nonmanifold_edge_count(mesh.faces)
    report["nonmanifold_edges"] = n_nonmanifold
    nm_note = ""
    if n_nonmanifold:
        n0 = len(mesh.faces)
        mesh = _repair_nonmanifold(mesh)
        left = _nonmanifold_edge_count(mesh.faces)
        report["nonmanifold_faces_removed"] = int(n0 - len(mesh.faces))
        nm_note = f"non-manifold mesh ({n_nonmanifold} edges shared by more than two faces)"
        if left:
            raise InputError(source, f"{nm_note}: {left} remain after repair")
        report["repairs"].append(f"{n_nonmanifold} non-manifold edges repaired "
                                 f"({report['nonmanifold_faces_removed']} faces removed)")
    parts, keep = _islands(mesh, min_island_fraction)
    if len(parts) == 0:
        raise InputError(source, "mesh has no connected faces")
    for p, k in zip(parts, keep):
        if not k:
            report["islands_removed"].append({"faces": int(len(p.faces))})
    if report["islands_removed"]:
        report["repairs"].append(f"{len(report['islands_removed'])} small islands removed "
                                 f"({sum(i['faces'] for i in report['islands_removed'])} faces)")
    kept = []
    scale = main_extent(mesh, min_island_fraction)
    inverted_parts = 0
    for p in (p for p, k in zip(parts, keep) if k):
        if not p.is_watertight:
            q = _close_holes(p) if _largest_hole_perimeter(p) <= max_hole_fraction * scale else p
            if q.is_watertight:
                p = q
                report["holes_closed"] = True
            elif bone.startswith("toes"):
                report["open"] = True
            else:
                raise InputError(source, (f"{nm_note}, open after repair: " if nm_note else "open mesh (not watertight) ")
                                 + "with holes too large to close "
                                 f"(largest boundary loop {_largest_hole_perimeter(p):.3g} m)")
        if not p.is_winding_consistent:
            p = _fix_winding(p)
            if _centroid_volume(p) < 0:
                p.invert()
            report["winding_repaired_components"] += 1
        elif not p.is_watertight:
            # open (toes): no inside to test; orient by the volume about the centroid
            if _centroid_volume(p) < 0:
                p.invert()
        elif _centroid_volume(p) < 0:
            inverted_parts += 1
            if fix_orientation:
                p.invert()
        kept.append(p)
    if inverted_parts:
        if not fix_orientation:
            raise InputError(source, f"inside-out mesh (faces of {inverted_parts} of {len(kept)} closed parts point "
                             "inward); re-export with outward normals or pass --fix-orientation")
        report["inverted"] = True
        report["repairs"].append("inside-out mesh inverted")
    if report["holes_closed"]:
        report["repairs"].append("small holes closed")
    if report["winding_repaired_components"]:
        report["repairs"].append(f"winding made consistent in {report['winding_repaired_components']} part(s)")
    out = trimesh.util.concatenate(kept) if len(kept) > 1 else kept[0]
    return out, report


def _bone_files(folder: Path) -> tuple[dict[str, Path], list[str]]:
    """Bone (or whole-foot stem ``foot_r``) -> file chosen in `folder`, and the file names not read.

    Several files for one bone: a preferred stem (`lowerlimb.bones.PREFERRED_STEMS`),
    then the canonical stem, then a mesh over a point cloud.
    """
    files: dict[str, list[Path]] = {}
    ignored: list[str] = []
    for f in sorted(folder.iterdir()):
        if not f.is_file() or f.name.startswith("."):
            continue
        if f.suffix.lower() not in MESH_SUFFIXES + POINT_SUFFIXES:
            continue
        stem = f.stem.strip().lower().replace("-", "_").replace(" ", "_")
        bone = stem if stem in WHOLE_FOOT else canonical_bone_name(f.stem)
        if bone is None:
            ignored.append(f.name)
            continue
        files.setdefault(bone, []).append(f)
    chosen: dict[str, Path] = {}

    def rank(c: Path, bone: str) -> tuple:
        stem = c.stem.lower()
        return (stem not in PREFERRED_STEMS, stem != bone, c.suffix.lower() in POINT_SUFFIXES, c.name)

    for bone, cands in files.items():
        pick = min(cands, key=lambda c: rank(c, bone))
        ignored.extend(c.name for c in cands if c != pick)
        chosen[bone] = pick
    for foot, side in WHOLE_FOOT.items():
        if foot in chosen and any(f"{b}_{side}" in chosen for b in ("talus", "calcn", "toes")):
            ignored.append(chosen.pop(foot).name)      # the foot's own bones are given: read those
    return chosen, ignored


def _unit_candidates(bone: str, extent: float) -> list[str]:
    lo, hi = PLAUSIBLE_EXTENT_M[_bone_type(bone)]
    return [u for u, k in (("mm", 1e-3), ("m", 1.0)) if lo <= extent * k <= hi]


def read_mesh_folder_detailed(path: str | os.PathLike, *, bones: list[str] | None = None,
                              fix_orientation: bool = False) -> tuple[dict[str, MeshInput], dict]:
    """Read a folder of bone meshes or point clouds named after the bones.

    Files: ``<bone>.stl|ply|obj`` (``femur_r``, ``tibia_no_fib_r``,
    ``pelvis_no_sacrum``, ... see `lowerlimb.bones`), point clouds
    ``<bone>.ply|pcd|xyz`` without faces (surface reconstructed), and a whole
    foot as one mesh (``foot_r``: split into talus, calcn and toes where its
    bones are separate pieces, `personalize.whole_foot`).

    One bad bone does not stop the rest: a file that cannot be read, whose
    size is implausible for its name, or whose mesh cannot be repaired is left
    out and listed in the folder report's ``rejected`` (bone -> "file:
    problem"); the joints that need it are then missing.

    Returns per-bone `MeshInput` (metres) and a folder report (unit, ignored
    files, rejected bones, notes).  All meshes of a folder must share one unit.

    Raises
    ------
    InputError
        Missing folder, no recognised bone file, no usable bone, a requested
        bone missing or unusable, mixed units.
    """
    from lowerlimb.bones import WHOLE_FOOT

    folder = Path(path)
    if not folder.exists():
        raise InputError(folder, "folder not found")
    if not folder.is_dir():
        raise InputError(folder, "not a folder of bone meshes")
    chosen, ignored = _bone_files(folder)
    if not chosen:
        raise InputError(folder, "no bone mesh found (expected files like femur_r.ply, tibia_r.stl, pelvis_no_sacrum.obj)")
    if bones is not None:
        from_feet = {f"{b}_{s}" for k, s in WHOLE_FOOT.items() if k in chosen for b in ("talus", "calcn", "toes")}
        missing = [b for b in bones if b not in chosen and b not in from_feet]
        if missing:
            raise InputError(folder, f"no mesh for bone(s) {', '.join(missing)}")
        chosen = {b: f for b, f in chosen.items()
                  if b in bones or (b in WHOLE_FOOT and any(x.endswith("_" + WHOLE_FOOT[b]) for x in from_feet & set(bones)))}
    errors: dict[str, InputError] = {}
    loaded: dict[str, tuple[Path, trimesh.Trimesh, dict, float]] = {}
    for bone, f in chosen.items():
        try:
            mesh, lrep = _load_mesh_file(f)
            loaded[bone] = (f, mesh, lrep, main_extent(mesh))
        except InputError as exc:
            errors[bone] = exc
    # one unit per folder: the unit every bone of plausible size agrees with
    cands = {b: _unit_candidates("calcn" if b in WHOLE_FOOT else b, ext) for b, (_, _, _, ext) in loaded.items()}
    votes = [c[0] for c in cands.values() if len(c) == 1]
    unit = max(set(votes), key=votes.count) if votes else None
    for bone, c in cands.items():
        f = loaded[bone][0]
        if unit is not None and c and unit not in c:
            raise InputError(f, f"units differ within the folder ({c[0]} here, {unit} for the other bones)")
        if not c:
            try:
                detect_mesh_unit("calcn" if bone in WHOLE_FOOT else bone, loaded[bone][3], f)
            except InputError as exc:
                errors[bone] = exc
    out: dict[str, MeshInput] = {}
    for bone, (f, mesh, lrep, _) in loaded.items():
        if bone in errors:
            continue
        use = unit or cands[bone][0]
        mesh.apply_scale(_UNIT_SCALE[use])
        try:
            mesh, rep = check_and_repair_mesh(mesh, "calcn" if bone in WHOLE_FOOT else bone, f,
                                              fix_orientation=fix_orientation)
        except InputError as exc:
            errors[bone] = exc
            continue
        for k in ("merged_vertices", "collapsed_faces_removed", "duplicate_faces_removed"):
            rep[k] = lrep.get(k, 0) + rep.get(k, 0)
        words = {"collapsed_faces_removed": "faces collapsed by merging coincident vertices removed",
                 "duplicate_faces_removed": "repeated faces removed"}
        rep["repairs"] = [f"{rep[k]} {w}" for k, w in words.items() if rep[k]] + rep["repairs"]
        rep["repairs"] += lrep.get("repairs", [])
        rep.update({k: v for k, v in lrep.items() if k not in rep})
        rep["units_detected"] = use
        if lrep.get("input") == "point cloud":
            from .point_clouds import sampling_sd_m

            rep["sampling_sd_m"] = sampling_sd_m(lrep, _UNIT_SCALE[use])
        out[bone] = MeshInput(name=bone, mesh=mesh, source=str(f), unit=use, report=rep)
    notes: list[str] = []
    for foot, side in WHOLE_FOOT.items():
        if foot not in out:
            continue
        from .whole_foot import split_whole_foot

        mi = out.pop(foot)
        tib = out.get(f"tibia_{side}")
        pieces, note = split_whole_foot(mi.mesh, side, tibia=tib.mesh if tib is not None else None)
        notes.append(f"{Path(mi.source).name}: {note}")
        for b, m in pieces.items():
            rep = dict(mi.report, whole_foot=note,
                       repairs=[f"{Path(mi.source).name}: {r}" for r in mi.report.get("repairs", [])])
            out[b] = MeshInput(name=b, mesh=m, source=mi.source, unit=mi.unit, report=rep)
    if bones is not None:
        bad = [b for b in bones if b in errors]
        if bad:
            raise errors[bad[0]]
        out = {b: m for b, m in out.items() if b in bones}
    if not out:
        if errors:
            raise next(iter(errors.values()))
        raise InputError(folder, "no usable bone mesh")
    rejected = {b: str(e) for b, e in errors.items()}
    return out, {"unit": unit or next(iter(out.values())).unit, "ignored_files": ignored, "rejected": rejected,
                 "notes": notes}


def read_mesh_folder(path: str | os.PathLike, bones: list[str] | None = None) -> dict[str, trimesh.Trimesh]:
    """Bone meshes of a folder, canonical name -> trimesh in metres (input frame).

    See `read_mesh_folder_detailed` for the checks, repairs and the bones left out.
    """
    meshes, _ = read_mesh_folder_detailed(path, bones=bones)
    return {k: v.mesh for k, v in meshes.items()}
