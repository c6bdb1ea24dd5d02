"""Every bone's surface from a label volume or a mesh folder (`load_bones`), as `BoneSurface` values.

A label volume's bones are cropped to their boxes, cleaned
(`personalize.surfaces.masks`) and surfaced (`personalize.surfaces.extraction`)
in a thread pool; a mesh folder's are read and repaired by `personalize.io`.
"""
from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from lowerlimb.errors import InputError
from lowerlimb.geometry import signed_volume
from personalize.io import LabelVolume, is_label_volume_path, read_label_volume, read_mesh_folder_detailed
from personalize.io.units import PLAUSIBLE_EXTENT_M

from .extraction import decimate, decimation_message, extract_surface
from .masks import BONE_PIECE_MIN_VOLUME, clean_mask, split_fibula
from .sampling import PointCloud, point_cloud

__all__ = ["BoneSurface", "BoneSurfaces", "surfaces_from_labels", "load_bones"]


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


#: labels that hold several bones (`personalize.surfaces.masks.BONE_PIECE_MIN_VOLUME`): the foot without its
#: talus, the phalanges, a whole foot
MULTI_BONE_LABELS = ("calcn_", "toes_", "foot_")


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
                         progress: Callable[[str], None] | None = None,
                         status: Callable[[str], None] | None = None) -> dict[str, BoneSurface]:
    """Extract every (or the requested) bone of a label volume.

    Each bone is cropped to its bounding box before any filtering, cleaned
    (`clean_mask`), and surfaced (`extract_surface`); bones run in a thread pool.
    `progress` is called with each bone's name when it is done, `status`
    (see `load_bones`) before each bone's surfacing and decimation.

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

    say = status or (lambda message: None)

    def extract(bone: str) -> tuple[trimesh.Trimesh, dict]:
        label = present[bone]
        sl = boxes[label]
        say(f"{bone}: surfacing label {label}")
        crop = volume.labels[sl] == label
        several = bone.startswith(MULTI_BONE_LABELS)
        mask, rep = clean_mask(crop, keep_fraction, spacing=volume.spacing_m,
                               min_piece_volume=BONE_PIECE_MIN_VOLUME if several else None)
        start = np.array([s.start for s in sl], float)
        aff = volume.affine_m.copy()
        aff[:3, 3] = aff[:3, :3] @ start + aff[:3, 3]
        parts = None
        if bone.startswith("tibia_") and f"fibula_{bone[-1]}" not in lmap:
            # a fibula labelled with its tibia touches it at both tibiofibular joints: surfaced as a second
            # component, so the landmark detectors find it (`landmarks.tibia.detect_tibia`)
            parts = split_fibula(mask, volume.spacing_m)
        if parts is None:
            mesh = extract_surface(mask, aff, sigma=sigma, smoothing_iterations=smoothing_iterations)
        else:
            tib, fib, info = parts
            mesh = trimesh.util.concatenate([extract_surface(m, aff, sigma=sigma, smoothing_iterations=smoothing_iterations)
                                             for m in (tib, fib)])
            rep["fibula_split"] = {**info, "note": f"fibula_{bone[-1]} parted from the {bone} label at the tibiofibular "
                                   f"joints (erosion by {info['erosion_m'] * 1e3:.1f} mm) and surfaced as its second component"}
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
        decimated = []
        for b, (m, r) in zip(names, meshes):
            if target_faces < len(m.faces):
                say(decimation_message(b, len(m.faces), target_faces))
            decimated.append((decimate(m, target_faces), r))
        meshes = decimated
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
               progress: Callable[[str], None] | None = None,
               status: Callable[[str], None] | None = None) -> dict[str, BoneSurface]:
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
    progress : callable(str), optional
        Called with each bone's name when its surface is done (one step per bone).
    status : callable(str), optional
        Called before each long step of a bone (reading, repair, surfacing,
        decimation) with what is done and the mesh size, for decimation with
        its expected time (``"femur_r: decimating 7,500,000 faces to 500,000
        (about 5 min)"``): a display's current description, not a step.

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
        meshes, folder_rep = read_mesh_folder_detailed(p, bones=bones, fix_orientation=fix_orientation,
                                                       status=status)
        out = BoneSurfaces(rejected=folder_rep["rejected"], notes=folder_rep["notes"])
        for name, mi in meshes.items():
            mesh = mi.mesh
            if target_faces and target_faces < len(mesh.faces):
                if status is not None:
                    status(decimation_message(name, len(mesh.faces), target_faces))
                mesh = decimate(mesh, target_faces)
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
                                progress=progress, status=status)
