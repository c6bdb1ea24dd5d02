"""``personalize surfaces INPUT --out DIR``: bone surfaces from a label volume or a mesh folder.

Writes ``DIR/<bone>.ply`` (binary PLY, the input's own unit and frame, stated
in a header comment) and ``DIR/surfaces.json`` (per bone: vertex and face
counts, volume, bounding box, removed islands, units; lengths in metres).
The folder is staged: on any error nothing is written.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from lowerlimb.atomic import inside

from lowerlimb.bones import canonical_bone_name
from lowerlimb.errors import InputError
from ..outputs import check_output_dir, replaced_dir

_SCALE = {"m": 1.0, "mm": 1e3, "um": 1e6, "cm": 1e2}


def ply_bytes(mesh, unit: str, comments: list[str]) -> bytes:
    """Binary PLY of `mesh` (metres) written in `unit`, with header comments."""
    import trimesh

    scaled = trimesh.Trimesh(np.asarray(mesh.vertices) * _SCALE[unit], mesh.faces, process=False)
    data = trimesh.exchange.ply.export_ply(scaled, encoding="binary", include_attributes=False)
    head, sep, body = data.partition(b"end_header\n")
    lines = head.split(b"\n")
    extra = [f"comment {c}".encode("ascii", "replace") for c in comments]
    # comments go right after the "format" line (line 2) as the PLY spec allows
    lines = lines[:2] + [e for e in extra] + [ln for ln in lines[2:] if not ln.startswith(b"comment")]
    return b"\n".join(lines) + sep + body


def _bone_list(text: Optional[str]) -> Optional[list[str]]:
    if not text:
        return None
    out = []
    for tok in text.split(","):
        tok = tok.strip()
        if not tok:
            continue
        name = canonical_bone_name(tok)
        if name is None:
            raise InputError("--bones", f"unknown bone name {tok!r}")
        out.append(name)
    return out


def run_surfaces(input: Path, out: Path, *, label_map: Optional[Path] = None, bones: Optional[str] = None,
                 faces: Optional[int] = None, fix_orientation: bool = False, points: bool = False,
                 quiet: bool = False, overwrite: bool = False) -> dict:
    """Library form of the command; returns the surfaces.json content."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from ..surfaces import load_bones

    bone_names = _bone_list(bones)
    check_output_dir(out, inputs=[input, label_map], overwrite=overwrite)
    if faces is not None and faces < 100:
        raise InputError("--faces", f"target face count must be at least 100, got {faces}")
    console = Console(stderr=True, quiet=quiet)
    with Progress(TextColumn("[bold]surfaces[/bold] {task.description}"), BarColumn(), TextColumn("{task.completed} bones"),
                  TimeElapsedColumn(), console=console, transient=True) as prog:
        task = prog.add_task(f"reading {input.name}", total=None)

        def tick(bone: str) -> None:
            prog.update(task, advance=1, description=f"{bone} done")

        surfaces = load_bones(input, label_map, bones=bone_names, target_faces=faces,
                              fix_orientation=fix_orientation, eager_points=points, progress=tick)
    summary: dict = {
        "input": str(input),
        "units": "m",
        "note": "lengths in this file are metres, volumes m^3; the PLY files are in mesh_units",
        "bones": {},
    }
    files: dict[str, bytes] = {}
    for name, s in surfaces.items():
        unit = s.report.get("units_detected", "mm")
        frame = s.report.get("frame", "input")
        m = s.mesh
        bbox = np.asarray(m.bounds)
        entry = {
            "file": f"{name}.ply",
            "source": s.source,
            "mesh_units": unit,
            "frame": frame,
            "vertices": int(len(m.vertices)),
            "faces": int(len(m.faces)),
            "volume_m3": float(m.volume),
            "area_m2": float(m.area),
            "bbox_min_m": bbox[0].tolist(),
            "bbox_max_m": bbox[1].tolist(),
            "watertight": bool(m.is_watertight),
            "islands_removed": s.report.get("islands_removed", []),
        }
        volume_level = ("ignored_files", "unmapped_labels")
        entry.update({k: v for k, v in s.report.items() if k not in entry and k not in volume_level})
        for k in volume_level:
            if k in s.report:
                summary[k] = s.report[k]
        summary["bones"][name] = entry
        comments = [f"personalize surfaces: bone {name}", f"units {unit}",
                    f"frame {frame} of input {Path(s.source).name}"]
        files[f"{name}.ply"] = ply_bytes(m, unit, comments)
        if points:
            pc = s.cloud
            files[f"{name}_points.ply"] = _points_ply(pc.points * _SCALE[unit], pc.normals,
                                                      comments + ["outward unit normals"])
            entry["points"] = int(len(pc.points))
            entry["point_outliers_removed"] = pc.outliers_removed
    summary["mesh_units"] = sorted({e["mesh_units"] for e in summary["bones"].values()})[0] \
        if summary["bones"] else None
    with replaced_dir(out) as stage:
        for rel, data in files.items():
            inside(stage, rel).write_bytes(data)
        inside(stage, "surfaces.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
    return summary


def _points_ply(points: np.ndarray, normals: np.ndarray, comments: list[str]) -> bytes:
    """Binary little-endian PLY with x y z nx ny nz vertex properties."""
    header = ["ply", "format binary_little_endian 1.0"] + [f"comment {c}" for c in comments] + [
        f"element vertex {len(points)}",
        "property float x", "property float y", "property float z",
        "property float nx", "property float ny", "property float nz",
        "end_header",
    ]
    body = np.hstack([points, normals]).astype("<f4").tobytes()
    return ("\n".join(header) + "\n").encode("ascii") + body


def register(app: typer.Typer) -> None:
    @app.command("surfaces")
    def surfaces_cmd(
        input: Path = typer.Argument(..., help="Label volume (.nii, .nii.gz, .nrrd) or folder of bone meshes (.ply, .stl, .obj)."),
        out: Path = typer.Option(..., "--out", help="Output folder: <bone>.ply and surfaces.json."),
        label_map: Optional[Path] = typer.Option(None, "--label-map", help="JSON bone -> label map (default: label_map.json beside the volume, else the built-in map)."),
        bones: Optional[str] = typer.Option(None, "--bones", help="Comma-separated bones to extract (default: all present)."),
        faces: Optional[int] = typer.Option(None, "--faces", help="Decimate each surface to about this many faces."),
        fix_orientation: bool = typer.Option(False, "--fix-orientation", help="Invert inside-out meshes instead of refusing them."),
        points: bool = typer.Option(False, "--points", help="Also write <bone>_points.ply point clouds with normals."),
        quiet: bool = typer.Option(False, "--quiet", help="No progress display."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out folder whole."),
    ) -> None:
        """Bone surfaces (PLY, input units and frame) and a surfaces.json summary."""
        summary = run_surfaces(input, out, label_map=label_map, bones=bones, faces=faces,
                               fix_orientation=fix_orientation, points=points, quiet=quiet, overwrite=overwrite)
        n = len(summary["bones"])
        typer.echo(f"wrote {n} bone surface(s) and surfaces.json to {out}")
