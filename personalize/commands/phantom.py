"""``personalize phantom``: write a synthetic subject with exactly known anatomy.

Builds the subject from the options (`personalize.evaluation.phantom_builder.build_phantom`)
and writes it into ``--out`` (`write_phantom`): ``labels.nii.gz`` (int16
labels, affine in mm, scanner frame), ``label_map.json``, ``meshes/<bone>.ply``
(exact surfaces, mm) and ``truth.json`` (metres, scanner frame), with the motion
trials.  ``--anatomy DIR --reference MODEL.osim`` builds it on a real subject's
bone meshes with the expert model as truth (any ``--marker-set``, ``--tissue``;
plus ``markers.json``, ``truth_model.osim`` and ``subject.json``).  ``--lab``,
``--walk``, ``--format``, ``--static-name``, ``--static-frames`` and
``--no-functional`` write the trials as a given lab does, for both anatomies.
"""
from __future__ import annotations

from pathlib import Path

import typer


def phantom(
    out: Path = typer.Option(..., "--out", help="Output folder (created; published whole when complete)."),
    seed: int = typer.Option(0, "--seed", help="Subject seed: size variation, scanner placement and noise."),
    voxel: tuple[float, float, float] = typer.Option((1.0, 1.0, 1.0), "--voxel", help="Voxel spacing SX SY SZ in mm."),
    noise: str = typer.Option("none", "--noise", help="Segmentation noise: none, low, medium, high or a level 0..1."),
    side: str = typer.Option("both", "--side", help="Legs to include: both, r or l."),
    stature: float = typer.Option(1.75, "--stature", help="Standing height in metres."),
    placement: str = typer.Option("random", "--placement", help="Scanner placement: random (from the seed) or identity."),
    bones: str = typer.Option("", "--bones", help="Comma-separated subset of bones to write (default: all)."),
    growth_plates: float = typer.Option(0.0, "--growth-plates",
                                        help="Width in mm of a child's open growth plates, left unlabelled (0: adult bones)."),
    motion: bool = typer.Option(True, "--motion/--no-motion",
                                help="Also write motion trials (static, gait, crouch, functional hip C3Ds, truth/*.mot); needs --side both."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out folder whole."),
    anatomy: Path = typer.Option(None, "--anatomy", help="Folder of a real subject's bone meshes (mm; STAPLE names): "
                                                         "build the phantom on them (needs --reference)."),
    reference: Path = typer.Option(None, "--reference", help="Expert .osim of the --anatomy bones (bodies in the "
                                                             "scanner frame): the truth skeleton."),
    marker_set: str = typer.Option("pig", "--marker-set", help="pig, ior (bony landmarks), cast, opensim (gait2392 "
                                                               "names) or a markers.json file."),
    lab: str = typer.Option("z-up", "--lab", help="Lab vertical: z-up or y-up."),
    walk: str = typer.Option("+x", "--walk", help="Walking direction: a horizontal lab axis (+x, -x, +y, -y, +z, -z)."),
    tissue: str = typer.Option("adult", "--tissue", help="Body build of the soft-tissue prior: child, adult or obese."),
    trial_format: str = typer.Option("c3d", "--format", help="Trial files: c3d, trc or both."),
    static_name: str = typer.Option("static", "--static-name", help="File stem of the static trial (e.g. Static)."),
    static_frames: int = typer.Option(200, "--static-frames", help="Frames of the static trial (100 Hz)."),
    functional: bool = typer.Option(True, "--functional/--no-functional", help="Write the functional hip trial."),
    fibula_mesh: bool = typer.Option(True, "--fibula-mesh/--no-fibula-mesh",
                                     help="Fibula as its own bone, or as the tibia mesh's second component."),
    sta: bool = typer.Option(True, "--sta/--no-sta", help="Soft-tissue artefact on the markers."),
    marker_noise: float = typer.Option(0.5, "--marker-noise", help="Marker noise sd in mm."),
    force_plates: bool = typer.Option(False, "--force-plates", help="With --anatomy: force platforms under the "
                                                                    "stance phases of the gait C3Ds."),
) -> None:
    """Write a synthetic subject: label volume, exact meshes, motion trials (C3D) and ground truth."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from ..evaluation.phantom_builder import PhantomOptions, build_phantom, write_phantom
    from ..outputs import check_output_dir

    subset = tuple(b.strip() for b in bones.split(",") if b.strip()) or None
    options = PhantomOptions(
        seed=seed, voxel_mm=tuple(voxel), noise=noise, side=side, stature=stature, placement=placement, bones=subset,
        growth_plates_mm=growth_plates, motion=motion, anatomy=anatomy, reference=reference, marker_set=marker_set,
        lab=lab, walk=walk, tissue=tissue, trial_format=trial_format, static_name=static_name,
        static_frames=static_frames, functional=functional, fibula_mesh=fibula_mesh, sta=sta,
        marker_noise_mm=marker_noise, force_plates=force_plates)
    # the anatomy folder and reference model are inputs: --out inside them (or equal) would delete them
    check_output_dir(out, inputs=[p for p in (anatomy, reference) if p is not None], overwrite=overwrite)
    subject = build_phantom(options)           # bad input fails here, before any progress line
    console = Console(stderr=True)
    if subject.steps is None:
        write_phantom(subject, out, progress=lambda m: console.print(m))
    else:
        with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), console=console,
                      transient=True) as prog:
            task = prog.add_task("phantom", total=subject.steps)
            write_phantom(subject, out, progress=lambda m: prog.update(task, description=m, advance=1))
    typer.echo(f"wrote {subject.summary()} to {out}")


def register(app: typer.Typer) -> None:
    app.command("phantom")(phantom)
