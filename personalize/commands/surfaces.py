"""``personalize surfaces INPUT --out DIR``: bone surfaces from a label volume or a mesh folder.

Reads the bones (`personalize.surface_export.bone_surface_export`) and writes
``DIR/<bone>.ply`` (binary PLY, the input's own unit and frame, stated in a
header comment) and ``DIR/surfaces.json`` (per bone: vertex and face counts,
volume, bounding box, removed islands, units; lengths in metres) through
`write_surface_export`.  The folder is staged: on any error nothing is written.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lowerlimb.bones import canonical_bone_name
from lowerlimb.errors import InputError


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
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        from ..outputs import check_output_dir
        from ..surface_export import bone_surface_export, write_surface_export

        bone_names = _bone_list(bones)
        check_output_dir(out, inputs=[input, label_map], overwrite=overwrite)
        console = Console(stderr=True, quiet=quiet)
        with Progress(TextColumn("[bold]surfaces[/bold] {task.description}"), BarColumn(),
                      TextColumn("{task.completed} bones"), TimeElapsedColumn(), console=console,
                      transient=True) as prog:
            task = prog.add_task(f"reading {input.name}", total=None)
            export = bone_surface_export(input, label_map=label_map, bones=bone_names, target_faces=faces,
                                         fix_orientation=fix_orientation, points=points,
                                         progress=lambda bone: prog.update(task, advance=1, description=f"{bone} done"),
                                         status=lambda text: prog.update(task, description=text))
        write_surface_export(export, out)
        typer.echo(f"wrote {len(export.surfaces)} bone surface(s) and surfaces.json to {out}")
