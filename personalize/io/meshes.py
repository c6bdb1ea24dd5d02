"""Folders of bone meshes (STL, PLY, OBJ) or point clouds named after the bones.

Meshes leave this module in metres, input (scanner) frame, checked and
repaired (`personalize.io.mesh_repair`); the folder's unit is decided from the
bones' sizes (`personalize.io.units`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from lowerlimb.bones import PREFERRED_STEMS, WHOLE_FOOT, canonical_bone_name
from lowerlimb.errors import InputError

from .mesh_repair import _weld, check_and_repair_mesh, main_extent
from .units import UNIT_SCALE, detect_mesh_unit, unit_candidates

__all__ = ["MESH_SUFFIXES", "POINT_SUFFIXES", "MeshInput", "read_mesh_folder_detailed", "read_mesh_folder"]

MESH_SUFFIXES = (".stl", ".ply", ".obj")
#: point-cloud files (a PLY without faces is one too)
POINT_SUFFIXES = (".pcd", ".xyz", ".xyzn", ".pts")


@dataclass(frozen=True)
class MeshInput:
    """One bone mesh read from a folder (metres, input frame) and what was done to it."""

    name: str
    mesh: trimesh.Trimesh
    source: str
    unit: str
    report: dict = field(default_factory=dict)


def _load_mesh_file(path: Path) -> tuple[trimesh.Trimesh, dict]:
    """Triangle mesh of a mesh or point-cloud file (file units) and what reading did to it.

    A file without faces (PLY of vertices only, PCD, XYZ) is a point cloud:
    its surface is reconstructed (`personalize.io.point_clouds.reconstruct_surface`).
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


def read_mesh_folder_detailed(path: str | os.PathLike, *, bones: list[str] | None = None,
                              fix_orientation: bool = False, status: Callable[[str], None] | None = None
                              ) -> tuple[dict[str, MeshInput], dict]:
    """Read a folder of bone meshes or point clouds named after the bones.

    Files: ``<bone>.stl|ply|obj`` (``femur_r``, ``tibia_no_fib_r``,
    ``pelvis_no_sacrum``, ... see `lowerlimb.bones`), point clouds
    ``<bone>.ply|pcd|xyz`` without faces (surface reconstructed), and a whole
    foot as one mesh (``foot_r``: split into talus, calcn and toes where its
    bones are separate pieces, `personalize.io.whole_foot`).

    One bad bone does not stop the rest: a file that cannot be read, whose
    size is implausible for its name, or whose mesh cannot be repaired is left
    out and listed in the folder report's ``rejected`` (bone -> "file:
    problem"); the joints that need it are then missing.

    Returns per-bone `MeshInput` (metres) and a folder report (unit, ignored
    files, rejected bones, notes).  All meshes of a folder must share one unit.

    `status`, when given, is called before each bone's reading and repair
    with what is done and the size (``"femur_r: checking and repairing
    7,500,000 faces"``): a large mesh takes minutes, and a display shows it
    as its current description.

    Raises
    ------
    InputError
        Missing folder, no recognised bone file, no usable bone, a requested
        bone missing or unusable, mixed units.
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
        from_feet = {f"{b}_{s}" for k, s in WHOLE_FOOT.items() if k in chosen for b in ("talus", "calcn", "toes")}
        missing = [b for b in bones if b not in chosen and b not in from_feet]
        if missing:
            raise InputError(folder, f"no mesh for bone(s) {', '.join(missing)}")
        chosen = {b: f for b, f in chosen.items()
                  if b in bones or (b in WHOLE_FOOT and any(x.endswith("_" + WHOLE_FOOT[b]) for x in from_feet & set(bones)))}
    errors: dict[str, InputError] = {}
    loaded: dict[str, tuple[Path, trimesh.Trimesh, dict, float]] = {}
    say = status or (lambda message: None)
    for bone, f in chosen.items():
        say(f"{bone}: reading {f.name} ({f.stat().st_size / 1e6:.1f} MB)")
        try:
            mesh, lrep = _load_mesh_file(f)
            loaded[bone] = (f, mesh, lrep, main_extent(mesh))
        except InputError as exc:
            errors[bone] = exc
    # one unit per folder: the unit every bone of plausible size agrees with
    cands = {b: unit_candidates("calcn" if b in WHOLE_FOOT else b, ext) for b, (_, _, _, ext) in loaded.items()}
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
        mesh.apply_scale(UNIT_SCALE[use])
        say(f"{bone}: checking and repairing {len(mesh.faces):,} faces")
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

            rep["sampling_sd_m"] = sampling_sd_m(lrep, UNIT_SCALE[use])
        out[bone] = MeshInput(name=bone, mesh=mesh, source=str(f), unit=use, report=rep)
    notes: list[str] = []
    for foot, side in WHOLE_FOOT.items():
        if foot not in out:
            continue
        from .whole_foot import split_whole_foot

        mi = out.pop(foot)
        say(f"{foot}: splitting the whole foot into talus, calcn and toes")
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
