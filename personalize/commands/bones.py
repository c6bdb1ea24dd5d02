"""``personalize bones INPUT --out DIR``: landmarks, joint centres and axes from bone surfaces.

INPUT is a label volume (.nii, .nii.gz, .nrrd) or a folder of bone meshes.
Writes, all in the input's coordinates (metres):

* ``landmarks.json`` - per bone: landmarks (position, 3x3 covariance), axes
  (point, direction, sd_deg), scalars, frames and flags;
* ``joints.json`` - hip, knee, ankle, subtalar, mtp per side: origin,
  origin_cov, rotation (columns X, Y, Z; Z = main rotation axis), axis_sd_deg,
  plus the joints that could not be built and why;
* ``fits.json`` - every fitted primitive;
* ``<bone>.png`` - the surface, fitted primitives and landmarks, two views.

The folder is staged: on any error nothing is written.  Exit code 2 for
unusable input (no recognisable bone, no usable mesh, mixed units, a bone
whose shape says it is another bone or the other side - unless
``--trust-names``).  A single bone that cannot be used (unreadable,
implausible size, mesh beyond repair) is left out: ``landmarks.json``
``rejected`` and the ``dropped`` joints say why; ``inputs`` lists the
repairs made to each mesh.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("bones")
    def bones_cmd(
        input: Path = typer.Argument(..., help="label volume (.nii/.nii.gz/.nrrd) or folder of bone meshes"),
        out: Path = typer.Option(..., "--out", "-o", help="output folder"),
        label_map: Optional[Path] = typer.Option(None, "--label-map", help="JSON {bone: label} for label volumes"),
        png: bool = typer.Option(True, "--png/--no-png", help="write a picture per bone"),
        quiet: bool = typer.Option(False, "--quiet", "-q"),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out folder whole."),
        trust_names: bool = typer.Option(False, "--trust-names",
                                         help="Use a bone whose shape says it is another bone or the other side "
                                              "under its file/label name (flagged) instead of refusing the set."),
    ) -> None:
        """Landmarks, joint centres and axes (with uncertainties) from bone surfaces."""
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        from ..bone_set import read_bone_set, write_bone_files
        from ..outputs import check_output_dir, replaced_dir

        check_output_dir(out, inputs=[input, label_map], overwrite=overwrite)
        console = Console(stderr=True, quiet=quiet)
        with Progress(TextColumn("[bold]bones[/bold] {task.description}"), BarColumn(),
                      TextColumn("{task.completed} steps"), TimeElapsedColumn(), console=console, transient=True) as prog:
            task = prog.add_task(f"reading {input.name}", total=None)
            bs = read_bone_set(input, label_map, trust_names=trust_names,
                               progress=lambda m: prog.update(task, advance=1, description=f"{m} done"),
                               status=lambda m: prog.update(task, description=m))
        with replaced_dir(out) as stage:
            write_bone_files(stage, bs, pictures=png)
        n_low = sum("low_confidence" in b.flags for b in bs.landmarks.bones.values())
        console.print(f"[bold]bones[/bold]: {len(bs.landmarks.bones)} bones, {len(bs.joints)} joints -> {out}"
                      + (f" ({n_low} low-confidence bone(s), see flags)" if n_low else "")
                      + (f"; dropped: {', '.join(sorted(bs.dropped))}" if bs.dropped else ""))
