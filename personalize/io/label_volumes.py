"""Integer label volumes (NIfTI, NRRD) and the label maps that name their bones.

Affines leave this module mapping voxel indices to metres in the input's own
(scanner) frame: NIfTI world coordinates (RAS+) or the NRRD ``space``; nothing
is re-oriented.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lowerlimb.bones import DEFAULT_LABEL_MAP, canonical_bone_name, is_tissue_name
from lowerlimb.errors import InputError

from .units import UNIT_SCALE

__all__ = ["LabelVolume", "VOLUME_SUFFIXES", "is_label_volume_path", "read_label_map", "read_tissue_label",
           "read_label_volume"]

VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr")


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
    if unit not in UNIT_SCALE:
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
    affine_m[:3, :] *= UNIT_SCALE[unit]
    if not labels.any():
        raise InputError(path, "label volume is empty (no non-zero voxel)")
    return LabelVolume(labels=labels, affine_m=affine_m, label_map=lmap, source=str(path),
                       unit=unit, frame=frame, label_map_source=lmap_origin,
                       tissue_label=tissue if tissue is not None and np.any(labels == tissue) else None)
