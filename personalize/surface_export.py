"""Bone surfaces of a label volume or a mesh folder as PLY files with a summary, in the input's unit and frame.

`bone_surface_export` reads the bones (`personalize.surfaces.load_bones`:
surfaces extracted from a label volume, or a mesh folder read and repaired),
optionally decimated and with point clouds.  `write_surface_export` writes,
staged (nothing is written on error):

``<bone>.ply``
    binary PLY in the input's own unit and frame, stated in header comments;
``<bone>_points.ply``
    with points: the point cloud with outward unit normals (x y z nx ny nz);
``surfaces.json``
    `surfaces_document`: per bone vertex and face counts, volume, area,
    bounding box, removed islands, units (lengths in metres).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from lowerlimb.errors import InputError

__all__ = ["MIN_FACES", "SurfaceExport", "bone_surface_export", "mesh_ply_bytes", "points_ply_bytes",
           "surfaces_document", "write_surface_export"]

MIN_FACES = 100
_VOLUME_LEVEL = ("ignored_files", "unmapped_labels")


def _per_metre(unit: str) -> float:
    """How many `unit` make a metre (the readers' `personalize.io.units.UNIT_SCALE` is metres per unit)."""
    from personalize.io.units import UNIT_SCALE

    return 1.0 / UNIT_SCALE[unit]


def mesh_ply_bytes(mesh, unit: str, comments: Sequence[str]) -> bytes:
    """Binary PLY of `mesh` (metres) written in `unit`, with header comments right after the format line."""
    import trimesh

    scaled = trimesh.Trimesh(np.asarray(mesh.vertices) * _per_metre(unit), mesh.faces, process=False)
    data = trimesh.exchange.ply.export_ply(scaled, encoding="binary", include_attributes=False)
    head, sep, body = data.partition(b"end_header\n")
    lines = head.split(b"\n")
    extra = [f"comment {c}".encode("ascii", "replace") for c in comments]
    # comments go right after the "format" line (line 2) as the PLY spec allows
    lines = lines[:2] + extra + [ln for ln in lines[2:] if not ln.startswith(b"comment")]
    return b"\n".join(lines) + sep + body


def points_ply_bytes(points: np.ndarray, normals: np.ndarray, comments: Sequence[str]) -> bytes:
    """Binary little-endian PLY of points (N, 3) with normals (N, 3): x y z nx ny nz vertex properties."""
    header = ["ply", "format binary_little_endian 1.0"] + [f"comment {c}" for c in comments] + [
        f"element vertex {len(points)}",
        "property float x", "property float y", "property float z",
        "property float nx", "property float ny", "property float nz",
        "end_header",
    ]
    body = np.hstack([points, normals]).astype("<f4").tobytes()
    return ("\n".join(header) + "\n").encode("ascii") + body


@dataclass(frozen=True, eq=False)
class SurfaceExport:
    """The bone surfaces of one input.

    Attributes
    ----------
    input : the label volume or mesh folder
    surfaces : canonical bone name -> `personalize.surfaces.BoneSurface` (metres, input frame)
    points : whether the point clouds are exported
    """

    input: Path
    surfaces: dict
    points: bool = False


def bone_surface_export(input: str | os.PathLike, *, label_map: str | os.PathLike | None = None,
                        bones: Sequence[str] | None = None, target_faces: int | None = None,
                        fix_orientation: bool = False, points: bool = False,
                        progress: Callable[[str], None] | None = None,
                        status: Callable[[str], None] | None = None) -> SurfaceExport:
    """Bone surfaces of a label volume (.nii, .nii.gz, .nrrd) or a folder of bone meshes (.ply, .stl, .obj).

    Parameters
    ----------
    input : label volume or mesh folder
    label_map : JSON bone -> label map (default: label_map.json beside the volume, else the built-in map)
    bones : canonical bone names to extract (default: all present)
    target_faces : decimate each surface to about this many faces (at least `MIN_FACES`)
    fix_orientation : invert inside-out meshes instead of refusing them
    points : also sample the point clouds with normals
    progress : called with each bone's name when it is done
    status : called before each bone's reading, repair, surfacing and decimation with what it does
        (sizes, expected time of a large decimation)

    Raises
    ------
    InputError
        `target_faces` below `MIN_FACES`, or the input cannot be read.
    """
    from .surfaces import load_bones

    if target_faces is not None and target_faces < MIN_FACES:
        raise InputError("--faces", f"target face count must be at least {MIN_FACES}, got {target_faces}")
    surfaces = load_bones(input, label_map, bones=None if bones is None else list(bones), target_faces=target_faces,
                          fix_orientation=fix_orientation, eager_points=points, progress=progress,
                          status=status)
    return SurfaceExport(Path(input), surfaces, points)


def _unit(s) -> str:
    return s.report.get("units_detected", "mm")


def surfaces_document(export: SurfaceExport) -> dict:
    """The ``surfaces.json`` document (lengths in metres; the PLY files in each bone's ``mesh_units``)."""
    summary: dict = {
        "input": str(export.input),
        "units": "m",
        "note": "lengths in this file are metres, volumes m^3; the PLY files are in mesh_units",
        "bones": {},
    }
    for name, s in export.surfaces.items():
        m = s.mesh
        bbox = np.asarray(m.bounds)
        entry = {
            "file": f"{name}.ply",
            "source": s.source,
            "mesh_units": _unit(s),
            "frame": s.report.get("frame", "input"),
            "vertices": int(len(m.vertices)),
            "faces": int(len(m.faces)),
            "volume_m3": float(m.volume),
            "area_m2": float(m.area),
            "bbox_min_m": bbox[0].tolist(),
            "bbox_max_m": bbox[1].tolist(),
            "watertight": bool(m.is_watertight),
            "islands_removed": s.report.get("islands_removed", []),
        }
        entry.update({k: v for k, v in s.report.items() if k not in entry and k not in _VOLUME_LEVEL})
        for k in _VOLUME_LEVEL:
            if k in s.report:
                summary[k] = s.report[k]
        summary["bones"][name] = entry
        if export.points:
            entry["points"] = int(len(s.cloud.points))
            entry["point_outliers_removed"] = s.cloud.outliers_removed
    summary["mesh_units"] = sorted({e["mesh_units"] for e in summary["bones"].values()})[0] \
        if summary["bones"] else None
    return summary


def write_surface_export(export: SurfaceExport, out: str | os.PathLike) -> dict:
    """Write the PLY files and surfaces.json into ``out``, replacing it whole; returns the surfaces.json document.

    Check ``out`` first with `personalize.outputs.check_output_dir` (an existing folder is replaced).
    """
    from lowerlimb.atomic import inside

    from .outputs import replaced_dir

    summary = surfaces_document(export)
    files: dict[str, bytes] = {}
    for name, s in export.surfaces.items():
        unit, frame = _unit(s), s.report.get("frame", "input")
        comments = [f"personalize surfaces: bone {name}", f"units {unit}",
                    f"frame {frame} of input {Path(s.source).name}"]
        files[f"{name}.ply"] = mesh_ply_bytes(s.mesh, unit, comments)
        if export.points:
            pc = s.cloud
            files[f"{name}_points.ply"] = points_ply_bytes(pc.points * _per_metre(unit), pc.normals,
                                                           comments + ["outward unit normals"])
    with replaced_dir(out) as stage:
        for rel, data in files.items():
            inside(stage, rel).write_bytes(data)
        inside(stage, "surfaces.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
    return summary
