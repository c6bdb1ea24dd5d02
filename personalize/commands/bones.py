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

import json
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from lowerlimb.atomic import inside

from lowerlimb.errors import InputError
from ..outputs import check_output_dir, replaced_dir


def run_bones(input: Path, out: Path, *, label_map: Optional[Path] = None, png: bool = True,
              quiet: bool = False, overwrite: bool = False, trust_names: bool = False) -> dict:
    """Library form of the command; returns ``{"landmarks": ..., "joints": ...}`` (JSON-ready)."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from ..frames import joints_document, joints_from_landmarks
    from ..landmarks import detect_landmarks
    from ..point_clouds import add_sampling_uncertainty
    from ..surfaces import load_bones

    check_output_dir(out, inputs=[input, label_map], overwrite=overwrite)
    console = Console(stderr=True, quiet=quiet)
    with Progress(TextColumn("[bold]bones[/bold] {task.description}"), BarColumn(), TextColumn("{task.completed} bones"),
                  TimeElapsedColumn(), console=console, transient=True) as prog:
        task = prog.add_task(f"reading {input.name}", total=None)

        def tick(bone: str) -> None:
            prog.update(task, advance=1, description=f"{bone} done")

        surfaces = load_bones(input, label_map, progress=tick)
        if not surfaces:
            raise InputError(input, "no recognisable bone surfaces")
        prog.update(task, completed=0, description="detecting landmarks")
        ls = detect_landmarks(surfaces, progress=tick, trust_names=True)
    _check_names(ls, surfaces, trust_names)
    add_sampling_uncertainty(ls, surfaces)
    joints, dropped = joints_from_landmarks(ls)
    rejected = dict(getattr(surfaces, "rejected", {}))
    for b, why in rejected.items():
        ls.rejected.setdefault(b, why)
    for j, why in dropped.items():
        bad = [b for b in rejected if b in why]
        if bad:
            dropped[j] = why + "; " + "; ".join(f"{b} left out ({rejected[b]})" for b in bad)
    lm_json = ls.to_json()
    lm_json["input"] = str(input)
    lm_json["missing_bones"] = list(ls.missing)
    lm_json["input_notes"] = list(getattr(surfaces, "notes", []))
    lm_json["inputs"] = {b: {"source": s.source, "repairs": list(s.report.get("repairs", [])),
                             **({"whole_foot": s.report["whole_foot"]} if "whole_foot" in s.report else {})}
                         for b, s in surfaces.items()}
    j_json = joints_document(joints, dropped, input=str(input))
    fits = ls.fits_json()
    with replaced_dir(out) as stage:
        for name, payload in (("landmarks.json", lm_json), ("joints.json", j_json), ("fits.json", fits)):
            inside(stage, name).write_text(json.dumps(payload, indent=1), encoding="utf-8")
        if png:
            from ..landmarks.plot import plot_bone

            for name, res in ls.bones.items():
                s = surfaces.get(name)
                if s is None:
                    continue
                plot_bone(s.mesh if hasattr(s, "mesh") else s, res, inside(stage, f"{name}.png"))
    if not quiet:
        n_low = sum("low_confidence" in b.flags for b in ls.bones.values())
        console.print(f"[bold]bones[/bold]: {len(ls.bones)} bones, {len(joints)} joints -> {out}"
                      + (f" ({n_low} low-confidence bone(s), see flags)" if n_low else "")
                      + (f"; dropped: {', '.join(sorted(dropped))}" if dropped else ""))
    return {"landmarks": lm_json, "joints": j_json}


def _check_names(ls, surfaces, trust_names: bool) -> None:
    """Refuse (unless `trust_names`) a bone whose shape says it is another bone or the other side.

    Bones reconstructed from point clouds are only flagged: the smoothed
    surface can round an articular end enough to pass for a femoral head (the
    ICL tibia sampled at 20-50 % of its vertices does), so their shape is no
    proof against the name.
    """
    from ..landmarks import LandmarkSet, name_problems
    from ..landmarks import _refuse_names as refuse

    cloud = {b for b, s in surfaces.items() if s.report.get("input") == "point cloud"}
    for b, why in name_problems(ls).items():
        if b in cloud:
            ls.bones[b].notes.append(f"{b}: not refused ({why}): its surface is reconstructed from points; "
                                     "check the name")
    if not trust_names:
        refuse(LandmarkSet(bones={k: v for k, v in ls.bones.items() if k not in cloud}), surfaces)


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
        run_bones(input, out, label_map=label_map, png=png, quiet=quiet, overwrite=overwrite, trust_names=trust_names)


_ = np
