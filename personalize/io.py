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

from .bones import DEFAULT_LABEL_MAP, canonical_bone_name, is_tissue_name
from .errors import InputError

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
        present, else `personalize.bones.DEFAULT_LABEL_MAP`.

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


def _load_mesh_file(path: Path) -> trimesh.Trimesh:
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:
        raise InputError(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputError(path, "file holds no triangle faces")
    if not np.all(np.isfinite(loaded.vertices)):
        raise InputError(path, "mesh has non-finite vertex coordinates")
    # merge duplicated vertices (STL has none shared) so topology is meaningful
    mesh = trimesh.Trimesh(loaded.vertices, loaded.faces, process=True, validate=False)
    mesh.remove_unreferenced_vertices()
    return mesh


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
    return trimesh.Trimesh(m.vertex_matrix(), m.face_matrix(), process=True)


def check_and_repair_mesh(mesh: trimesh.Trimesh, bone: str, source: str | os.PathLike, *,
                          fix_orientation: bool = False, min_island_fraction: float = 0.01,
                          max_hole_fraction: float = 0.1) -> tuple[trimesh.Trimesh, dict]:
    """Validate a bone mesh; repair what is unambiguous, refuse the rest.

    * non-manifold edges (shared by > 2 faces): refused.
    * islands with area < `min_island_fraction` x the largest component: removed.
    * open components: holes whose boundary loop is shorter than
      `max_hole_fraction` x the bone's largest extent are closed (pymeshlab);
      larger holes (missing anatomy) -> refused,
      except ``toes_*`` (open in the real data), which are flagged.
    * components whose winding is inconsistent: re-wound and oriented outward.
    * a mesh whose faces consistently point inward (negative volume): refused
      unless `fix_orientation`, then inverted.

    Returns the repaired mesh and a report dict.
    """
    report: dict = {"islands_removed": [], "winding_repaired_components": 0, "inverted": False,
                    "holes_closed": False, "open": False}
    edges = mesh.edges_sorted
    _, counts = np.unique(edges, axis=0, return_counts=True)
    n_nonmanifold = int(np.sum(counts > 2))
    if n_nonmanifold and not bone.startswith("toes"):
        raise InputError(source, f"non-manifold mesh ({n_nonmanifold} edges shared by more than two faces)")
    report["nonmanifold_edges"] = n_nonmanifold
    parts = mesh.split(only_watertight=False)
    if len(parts) == 0:
        raise InputError(source, "mesh has no connected faces")
    areas = np.array([p.area for p in parts])
    keep = areas >= min_island_fraction * areas.max()
    for p, a, k in zip(parts, areas, keep):
        if not k:
            report["islands_removed"].append({"faces": int(len(p.faces))})
    kept = []
    scale = float(np.max(mesh.extents))
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
                raise InputError(source, "open mesh (not watertight) with holes too large to close "
                                 f"(largest boundary loop {_largest_hole_perimeter(p):.3g} m)")
        if not p.is_winding_consistent:
            trimesh.repair.fix_winding(p)
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
    out = trimesh.util.concatenate(kept) if len(kept) > 1 else kept[0]
    return out, report


def _bone_files(folder: Path) -> tuple[dict[str, Path], list[str]]:
    files: dict[str, list[Path]] = {}
    ignored: list[str] = []
    for f in sorted(folder.iterdir()):
        if not f.is_file() or f.name.startswith("."):
            continue
        if f.suffix.lower() not in MESH_SUFFIXES:
            continue
        bone = canonical_bone_name(f.stem)
        if bone is None:
            ignored.append(f.name)
            continue
        files.setdefault(bone, []).append(f)
    chosen: dict[str, Path] = {}
    for bone, cands in files.items():
        if len(cands) > 1:
            # the naming: prefer the exact STAPLE names, and for the
            # pelvis prefer `pelvis_no_sacrum` (the hip bones) over `pelvis`
            pref = [c for c in cands if c.stem.lower() == "pelvis_no_sacrum"] or \
                   [c for c in cands if c.stem.lower() == bone] or cands
            pick = pref[0]
            ignored.extend(c.name for c in cands if c != pick)
            chosen[bone] = pick
        else:
            chosen[bone] = cands[0]
    return chosen, ignored


def read_mesh_folder_detailed(path: str | os.PathLike, *, bones: list[str] | None = None,
                              fix_orientation: bool = False) -> tuple[dict[str, MeshInput], dict]:
    """Read a folder of bone meshes (STL, PLY, OBJ) named after the bones.

    Returns per-bone `MeshInput` (metres) and a folder report (unit, ignored files).
    All meshes of a folder must share one unit.

    Raises
    ------
    InputError
        Missing folder, no recognised bone file, requested bone missing,
        unreadable/non-manifold/inside-out mesh, implausible or mixed units.
    """
    folder = Path(path)
    if not folder.exists():
        raise InputError(folder, "folder not found")
    if not folder.is_dir():
        raise InputError(folder, "not a folder of bone meshes")
    chosen, ignored = _bone_files(folder)
    if not chosen:
        raise InputError(folder, "no bone mesh found (expected files like femur_r.ply, tibia_r.stl, pelvis_no_sacrum.obj)")
    if bones is not None:
        missing = [b for b in bones if b not in chosen]
        if missing:
            raise InputError(folder, f"no mesh for bone(s) {', '.join(missing)}")
        chosen = {b: chosen[b] for b in bones}
    out: dict[str, MeshInput] = {}
    units: dict[str, str] = {}
    for bone, f in chosen.items():
        mesh = _load_mesh_file(f)
        unit = detect_mesh_unit(bone, float(np.max(mesh.extents)), f)
        units[bone] = unit
        mesh.apply_scale(_UNIT_SCALE[unit])
        mesh, rep = check_and_repair_mesh(mesh, bone, f, fix_orientation=fix_orientation)
        rep["units_detected"] = unit
        out[bone] = MeshInput(name=bone, mesh=mesh, source=str(f), unit=unit, report=rep)
    if len(set(units.values())) > 1:
        odd = min(units, key=lambda b: list(units.values()).count(units[b]))
        raise InputError(chosen[odd], f"units differ within the folder ({units[odd]} here, "
                         f"{'m' if units[odd] == 'mm' else 'mm'} for the other bones)")
    return out, {"unit": next(iter(units.values())), "ignored_files": ignored}


def read_mesh_folder(path: str | os.PathLike) -> dict[str, trimesh.Trimesh]:
    """Bone meshes of a folder, canonical name -> trimesh in metres (input frame).

    See `read_mesh_folder_detailed` for the checks and repairs.
    """
    meshes, _ = read_mesh_folder_detailed(path)
    return {k: v.mesh for k, v in meshes.items()}
