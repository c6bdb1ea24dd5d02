"""``personalize phantom``: write a synthetic subject with exactly known anatomy.

Outputs (in ``--out``): ``labels.nii.gz`` (int16 labels, affine in mm, scanner
frame), ``label_map.json`` (bone -> label), ``meshes/<bone>.ply`` (exact
surfaces, mm, scanner frame) and ``truth.json`` (every landmark, axis, scalar
and joint frame, metres, scanner frame).

``--anatomy DIR --reference MODEL.osim`` builds the phantom on a real subject's
bone meshes with the expert model as truth (`phantoms.real_subject`): any
``--marker-set`` (pig, ior, cast, opensim or a markers.json), ``--tissue``
child/adult/obese, plus ``markers.json``, ``truth_model.osim`` (ground = lab,
the placed markers) and ``subject.json``.  ``--lab``, ``--walk``, ``--format``,
``--static-name``, ``--static-frames`` and ``--no-functional`` write the trials
as a given lab does, for both anatomies.
"""
from __future__ import annotations

from pathlib import Path

import typer

from lowerlimb.errors import InputError

NOISE_LEVELS = {"none": 0.0, "low": 0.25, "medium": 0.5, "high": 1.0}


def parse_noise(text: str) -> float:
    """Noise level from ``none|low|medium|high`` or a number in [0, 1]."""
    key = text.strip().lower()
    if key in NOISE_LEVELS:
        return NOISE_LEVELS[key]
    try:
        val = float(key)
    except ValueError:
        raise InputError("--noise", f"{text!r} is not a number in 0..1 nor one of {', '.join(NOISE_LEVELS)}") from None
    if not (0.0 <= val <= 1.0):
        raise InputError("--noise", f"{val} is outside 0..1")
    return val


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

    from phantoms import make_phantom
    from phantoms.subject import write_subject

    from ..outputs import check_output_dir, replaced_dir

    side_key = side.strip().lower()
    if side_key not in ("both", "r", "l"):
        raise InputError("--side", f"{side!r} is not one of both, r, l")
    if any(not (0.05 <= v <= 20.0) for v in voxel):
        raise InputError("--voxel", f"spacing {list(voxel)} mm must be within 0.05-20 mm per axis")
    if placement not in ("random", "identity"):
        raise InputError("--placement", f"{placement!r} is not one of random, identity")
    level = parse_noise(noise)
    if not (0.0 <= growth_plates <= 10.0):
        raise InputError("--growth-plates", f"{growth_plates} mm is outside 0-10 mm")
    check_output_dir(out, overwrite=overwrite)
    if anatomy is not None or reference is not None:
        _real_phantom(out, anatomy, reference, seed=seed, voxel=voxel, noise=level, marker_set=marker_set, lab=lab,
                      walk=walk, tissue=tissue, trial_format=trial_format, static_name=static_name,
                      static_frames=static_frames, functional=functional, fibula_mesh=fibula_mesh, sta=sta,
                      marker_noise=marker_noise, motion=motion, force_plates=force_plates)
        return
    if force_plates:
        raise InputError("--force-plates", "force platforms are written for real-anatomy phantoms (--anatomy)")
    if marker_set.strip().lower() != "pig":
        raise InputError("--marker-set", "the analytic phantom carries the Plug-in-Gait set: use "
                                         "--anatomy/--reference for other marker sets")
    from phantoms.lab import make_lab

    lab_ = make_lab(lab, walk)
    if not (1 <= static_frames <= 100000):
        raise InputError("--static-frames", f"{static_frames} is outside 1-100000")
    trials = {"lab": None if (lab_.name == "z-up" and walk == "+x") else lab_, "static_name": static_name,
              "trial_format": trial_format, "static_duration": static_frames / 100.0,
              "sta": sta, "noise_sd": marker_noise / 1000.0}
    if not functional:
        trials["functional_ranges"] = ()
    if trial_format not in ("c3d", "trc", "both"):
        raise InputError("--format", f"{trial_format!r} is not one of c3d, trc, both")
    if not static_name or any(c in static_name for c in "/\\."):
        raise InputError("--static-name", f"{static_name!r} is not a file stem")
    ph = make_phantom(seed=seed, side=side_key, stature=stature, placement=placement)
    subset = None
    if bones.strip():
        subset = [b.strip() for b in bones.split(",") if b.strip()]
        unknown = [b for b in subset if b not in ph.bone_names]
        if unknown:
            raise InputError("--bones", f"unknown bone(s) {', '.join(unknown)} (this phantom has {', '.join(ph.bone_names)})")
    if motion and side_key != "both":
        raise InputError("--side", "motion trials need both legs: use --side both or --no-motion")
    n_steps = 2 * len(subset or ph.bone_names) + 1
    console = Console(stderr=True)
    with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), console=console,
                  transient=True) as prog:
        task = prog.add_task("phantom", total=n_steps)

        def report(msg: str) -> None:
            prog.update(task, description=msg, advance=1)

        with replaced_dir(out) as stage:
            write_subject(stage, ph, voxel=tuple(v / 1000.0 for v in voxel), noise=level, seed=seed,
                          bones=subset, motion=motion, progress=report, physes=growth_plates / 1000.0, trials=trials)
    typer.echo(f"wrote phantom (seed {seed}, {len(subset or ph.bone_names)} bones, voxel {list(voxel)} mm, noise {level}) to {out}")


def _real_phantom(out: Path, anatomy: Path | None, reference: Path | None, *, seed, voxel, noise, marker_set, lab,
                  walk, tissue, trial_format, static_name, static_frames, functional, fibula_mesh, sta,
                  marker_noise, motion, force_plates=False) -> None:
    """``--anatomy DIR --reference MODEL.osim``: a phantom on real bones (`phantoms.real_subject`)."""
    from rich.console import Console

    from kinematics.io.marker_sets import resolve_marker_set
    from phantoms.lab import make_lab
    from phantoms.real_anatomy import load_real_anatomy
    from phantoms.real_subject import write_real_subject

    from ..outputs import replaced_dir

    if anatomy is None or reference is None:
        raise InputError("--anatomy" if anatomy is None else "--reference", "--anatomy and --reference go together")
    if not motion:
        raise InputError("--no-motion", "real-anatomy phantoms always write their trials")
    if not (0.0 <= marker_noise <= 10.0):
        raise InputError("--marker-noise", f"{marker_noise} mm is outside 0-10 mm")
    lab_ = make_lab(lab, walk)
    ms = resolve_marker_set(marker_set)
    console = Console(stderr=True)
    anat = load_real_anatomy(anatomy, reference)        # bad input fails here, before any progress line
    with replaced_dir(out) as stage:
        write_real_subject(stage, anat, marker_set=ms, lab=lab_, build=tissue, seed=seed,
                           voxel=tuple(v / 1000.0 for v in voxel), noise=noise, fibula_mesh=fibula_mesh,
                           functional=functional, static_frames=static_frames, static_name=static_name,
                           trial_format=trial_format, sta=sta, noise_sd=marker_noise / 1000.0,
                           force_plates=force_plates, progress=lambda m: console.print(m))
    typer.echo(f"wrote real-anatomy phantom ({anat.name}, marker set {ms.name}, lab {lab_.name} walking {walk}, "
               f"{tissue} tissue, seed {seed}) to {out}")


def register(app: typer.Typer) -> None:
    app.command("phantom")(phantom)
