"""One synthetic subject with exactly known anatomy, built from an options object and written as a subject folder.

`build_phantom` checks the `PhantomOptions` and builds the subject: the
analytic phantom (`phantoms.make_phantom`) or, with ``anatomy`` and
``reference``, a phantom on a real subject's bone meshes with the expert model
as truth (`phantoms.real_anatomy.load_real_anatomy`).  `write_phantom` writes
it into a folder, replaced whole when complete:

``labels.nii.gz`` (int16 labels, affine in mm, scanner frame), ``label_map.json``
(bone -> label), ``meshes/<bone>.ply`` (exact surfaces, mm, scanner frame) and
``truth.json`` (every landmark, axis, scalar and joint frame, metres, scanner
frame); with motion the trials (static, gait, crouch, functional hip; C3D or
TRC as the lab writes them), ``subject.json`` and ``truth/*.mot``; for a real
anatomy also ``markers.json`` and ``truth_model.osim`` (ground = lab, the
placed markers).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

from lowerlimb.errors import InputError

__all__ = ["NOISE_LEVELS", "PhantomOptions", "PhantomSubject", "build_phantom", "noise_level", "write_phantom"]

#: named segmentation noise levels (0: exact labels, 1: the strongest noise of `phantoms.imaging`)
NOISE_LEVELS = {"none": 0.0, "low": 0.25, "medium": 0.5, "high": 1.0}


def noise_level(text: str | float) -> float:
    """Noise level from ``none|low|medium|high`` or a number in [0, 1]."""
    key = str(text).strip().lower()
    if key in NOISE_LEVELS:
        return NOISE_LEVELS[key]
    try:
        val = float(key)
    except ValueError:
        raise InputError("--noise", f"{text!r} is not a number in 0..1 nor one of {', '.join(NOISE_LEVELS)}") from None
    if not (0.0 <= val <= 1.0):
        raise InputError("--noise", f"{val} is outside 0..1")
    return val


@dataclass(frozen=True)
class PhantomOptions:
    """What to build (lengths in the units of their names; the defaults are ``personalize phantom``'s).

    Attributes
    ----------
    seed : subject seed: size variation, scanner placement and noise
    voxel_mm : voxel spacing (3,) mm; noise : segmentation noise, a name of `NOISE_LEVELS` or 0..1
    side : 'both', 'r' or 'l'; stature : standing height (m); placement : 'random' (from the seed) or 'identity'
    bones : subset of bones to write (None: all); growth_plates_mm : open growth plates left unlabelled (0: adult)
    motion : also write the motion trials (needs both legs)
    anatomy, reference : a real subject's mesh folder and its expert ``.osim`` (together)
    marker_set : pig, ior, cast, opensim or a markers.json path (the analytic phantom carries pig)
    lab : 'z-up' or 'y-up'; walk : walking direction, a horizontal lab axis (+x ...)
    tissue : child, adult or obese soft-tissue prior (real anatomy)
    trial_format : c3d, trc or both; static_name : file stem of the static; static_frames : its frames (100 Hz)
    functional : write the functional hip trial; fibula_mesh : fibula as its own bone (real anatomy)
    sta : soft-tissue artefact; marker_noise_mm : marker noise sd (mm)
    force_plates : force platforms under the stance phases (real anatomy)
    """

    seed: int = 0
    voxel_mm: tuple[float, float, float] = (1.0, 1.0, 1.0)
    noise: str | float = "none"
    side: str = "both"
    stature: float = 1.75
    placement: str = "random"
    bones: Optional[tuple[str, ...]] = None
    growth_plates_mm: float = 0.0
    motion: bool = True
    anatomy: Optional[Path] = None
    reference: Optional[Path] = None
    marker_set: str = "pig"
    lab: str = "z-up"
    walk: str = "+x"
    tissue: str = "adult"
    trial_format: str = "c3d"
    static_name: str = "static"
    static_frames: int = 200
    functional: bool = True
    fibula_mesh: bool = True
    sta: bool = True
    marker_noise_mm: float = 0.5
    force_plates: bool = False

    @property
    def real(self) -> bool:
        """Built on a real subject's bones."""
        return self.anatomy is not None or self.reference is not None


@dataclass(frozen=True, eq=False)
class PhantomSubject:
    """A built phantom, ready to write.

    Attributes
    ----------
    options : PhantomOptions
    noise : segmentation noise level 0..1
    phantom : `phantoms.anatomy.Phantom` (analytic) or `phantoms.real_anatomy.RealAnatomy`
    bones : bones written (the analytic phantom's subset or all of them; a real anatomy's meshes)
    lab : `phantoms.lab.Lab`; marker_set : `kinematics.io.marker_sets.MarkerSet` (real anatomy)
    trials : options of the analytic phantom's trials (`phantoms.subject.write_subject`)
    """

    options: PhantomOptions
    noise: float
    phantom: Any
    bones: tuple[str, ...]
    lab: Any = None
    marker_set: Any = None
    trials: Optional[dict] = None

    @property
    def steps(self) -> Optional[int]:
        """About how many progress messages `write_phantom` sends (two per bone and one more; None: not known)."""
        return None if self.options.real else 2 * len(self.bones) + 1

    def summary(self) -> str:
        """One line: what was built."""
        o = self.options
        if o.real:
            return (f"real-anatomy phantom ({self.phantom.name}, marker set {self.marker_set.name}, lab {self.lab.name} "
                    f"walking {o.walk}, {o.tissue} tissue, seed {o.seed})")
        return f"phantom (seed {o.seed}, {len(self.bones)} bones, voxel {list(o.voxel_mm)} mm, noise {self.noise})"


def _real(o: PhantomOptions, level: float) -> PhantomSubject:
    from kinematics.io.marker_sets import resolve_marker_set
    from phantoms.lab import make_lab
    from phantoms.real_anatomy import load_real_anatomy

    if o.anatomy is None or o.reference is None:
        raise InputError("--anatomy" if o.anatomy is None else "--reference", "--anatomy and --reference go together")
    if not o.motion:
        raise InputError("--no-motion", "real-anatomy phantoms always write their trials")
    if not (0.0 <= o.marker_noise_mm <= 10.0):
        raise InputError("--marker-noise", f"{o.marker_noise_mm} mm is outside 0-10 mm")
    lab = make_lab(o.lab, o.walk)
    ms = resolve_marker_set(o.marker_set)
    anat = load_real_anatomy(o.anatomy, o.reference)
    return PhantomSubject(o, level, anat, tuple(anat.meshes), lab, ms)


def _analytic(o: PhantomOptions, level: float, side: str) -> PhantomSubject:
    from phantoms import make_phantom
    from phantoms.lab import make_lab

    if o.force_plates:
        raise InputError("--force-plates", "force platforms are written for real-anatomy phantoms (--anatomy)")
    if o.marker_set.strip().lower() != "pig":
        raise InputError("--marker-set", "the analytic phantom carries the Plug-in-Gait set: use "
                                         "--anatomy/--reference for other marker sets")
    lab = make_lab(o.lab, o.walk)
    if not (1 <= o.static_frames <= 100000):
        raise InputError("--static-frames", f"{o.static_frames} is outside 1-100000")
    trials = {"lab": None if (lab.name == "z-up" and o.walk == "+x") else lab, "static_name": o.static_name,
              "trial_format": o.trial_format, "static_duration": o.static_frames / 100.0,
              "sta": o.sta, "noise_sd": o.marker_noise_mm / 1000.0}
    if not o.functional:
        trials["functional_ranges"] = ()
    if o.trial_format not in ("c3d", "trc", "both"):
        raise InputError("--format", f"{o.trial_format!r} is not one of c3d, trc, both")
    if not o.static_name or any(c in o.static_name for c in "/\\."):
        raise InputError("--static-name", f"{o.static_name!r} is not a file stem")
    ph = make_phantom(seed=o.seed, side=side, stature=o.stature, placement=o.placement)
    if o.bones:
        unknown = [b for b in o.bones if b not in ph.bone_names]
        if unknown:
            raise InputError("--bones", f"unknown bone(s) {', '.join(unknown)} (this phantom has {', '.join(ph.bone_names)})")
    if o.motion and side != "both":
        raise InputError("--side", "motion trials need both legs: use --side both or --no-motion")
    return PhantomSubject(o, level, ph, tuple(o.bones or ph.bone_names), lab, trials=trials)


def build_phantom(options: PhantomOptions) -> PhantomSubject:
    """Check `options` and build the phantom (nothing is written).

    Raises
    ------
    InputError
        An option out of its range or inconsistent with another (named as the
        command's option), unreadable anatomy or reference files.
    """
    o = options
    side = o.side.strip().lower()
    if side not in ("both", "r", "l"):
        raise InputError("--side", f"{o.side!r} is not one of both, r, l")
    if any(not (0.05 <= v <= 20.0) for v in o.voxel_mm):
        raise InputError("--voxel", f"spacing {list(o.voxel_mm)} mm must be within 0.05-20 mm per axis")
    if o.placement not in ("random", "identity"):
        raise InputError("--placement", f"{o.placement!r} is not one of random, identity")
    level = noise_level(o.noise)
    if not (0.0 <= o.growth_plates_mm <= 10.0):
        raise InputError("--growth-plates", f"{o.growth_plates_mm} mm is outside 0-10 mm")
    return _real(o, level) if o.real else _analytic(o, level, side)


def write_phantom(subject: PhantomSubject, out: str | os.PathLike,
                  progress: Callable[[str], None] | None = None) -> Path:
    """Write the subject folder into ``out``, replacing it whole when complete.

    Check ``out`` first with `personalize.outputs.check_output_dir` (an existing folder is replaced).
    `progress` is called with a message at each step (about `PhantomSubject.steps` of them).
    """
    from personalize.outputs import replaced_dir

    o, voxel_m = subject.options, tuple(v / 1000.0 for v in subject.options.voxel_mm)
    with replaced_dir(out) as stage:
        if o.real:
            from phantoms.real_subject import write_real_subject

            write_real_subject(stage, subject.phantom, marker_set=subject.marker_set, lab=subject.lab, build=o.tissue,
                               seed=o.seed, voxel=voxel_m, noise=subject.noise, fibula_mesh=o.fibula_mesh,
                               functional=o.functional, static_frames=o.static_frames, static_name=o.static_name,
                               trial_format=o.trial_format, sta=o.sta, noise_sd=o.marker_noise_mm / 1000.0,
                               force_plates=o.force_plates, progress=progress)
        else:
            from phantoms.subject import write_subject

            write_subject(stage, subject.phantom, voxel=voxel_m, noise=subject.noise, seed=o.seed,
                          bones=list(o.bones) if o.bones else None, motion=o.motion, progress=progress,
                          physes=o.growth_plates_mm / 1000.0, trials=subject.trials)
    return Path(out)
