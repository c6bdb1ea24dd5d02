"""`run_subject`: the whole pipeline on one subject folder, stage by stage (see `personalize.pipeline`)."""
from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path
from typing import Callable

from lowerlimb.atomic import inside
from lowerlimb.errors import FitError, InputError

from .inputs import SubjectInputs, find_inputs, label_volume
from .joints import estimate_joints, gate_registrations, pelvis_skin
from .model_checks import prior_tissue
from .summary import SubjectSummary, write_summary

__all__ = ["run_subject", "read_subject_bones", "build_model", "MUSCLES_ENV"]

#: environment variable giving `run_subject`'s default ``muscles`` (``none`` or ``gait2392``)
MUSCLES_ENV = "PERSONALIZE_MUSCLES"
#: ``run_subject``'s `patella` choices
PATELLA_CHOICES = ("fixed", "joint")


def run_subject(subject_dir: str | Path, out: str | Path, *, progress: Callable[[str], None] | None = None,
                report: bool = True, overwrite: bool = False, marker_set=None, model_check: bool = True,
                full_meshes: bool = False, muscles: str | None = None, gait2392=None,
                generic: bool | None = None, patella: str = "fixed") -> dict:
    """Run the whole pipeline on one subject folder; outputs are staged into `out`.

    Parameters
    ----------
    subject_dir : folder (`personalize.pipeline.inputs`; a `personalize phantom` folder is valid)
    out : output folder (published only when everything succeeded)
    progress : callable(str), called at each stage
    report : write report.html
    overwrite : replace a non-empty `out` whole (else it is refused before any work)
    marker_set : preset name, markers.json path or `MarkerSet` for a folder without ``markers.json``
        (default: the preset the static trial's labels fit; `personalize.pipeline.markers`)
    model_check : refuse a model that fails `model_checks.check_model` (off only for calibration studies, which
        need the estimates of every subject whatever the publication gate decides)
    full_meshes : write the bone meshes at the surfaces' full resolution (default: each decimated to at most
        `personalize.model_builder.MODEL_MESH_MAX_FACES` faces, the error stated in model.json)
    muscles : "none", "gait2392" (gait2392's leg muscles on the subject's bones, `personalize.muscles`; the
        generic model must be found) or None: ``$PERSONALIZE_MUSCLES`` when set, else gait2392 when the generic
        model is found and every side has its pelvis, femur and tibia (``muscles.json`` reports the registration
        and the re-estimated lengths)
    gait2392 : the generic gait2392 model file (None: `personalize.muscles.generic.generic_model_path`'s search)
    generic : compare with gait2392 scaled to the same markers (`personalize.generic_comparison`; ``generic/`` and
        summary.json's ``generic``); None: when the generic model is found and the muscles are not ``none``
    patella : "fixed" (the patella rides on the femur) or "joint" (a patellofemoral joint,
        `personalize.patellofemoral`, on each side whose bones give a path; not the default until the realistic
        validation and the muscle benchmark have been run with it)

    Returns
    -------
    dict, the content of ``summary.json`` (`SubjectSummary.to_json`)

    Raises
    ------
    InputError : bad subject folder or output location (one line naming the file and the
        problem); with `report`, `out` then holds only ``report.html`` stating the error
        (unless `out` itself was refused: then it is untouched)
    FitError : an estimate could not be made (same refusal report)
    """
    from ..outputs import check_output_dir
    from ..presentation.subject_report import write_refusal_report

    if patella not in PATELLA_CHOICES:
        raise InputError("--patella", f"{patella!r} is not one of {', '.join(PATELLA_CHOICES)}")
    check_output_dir(out, inputs=[subject_dir], overwrite=overwrite)
    muscles = _checked_muscles(muscles, gait2392)
    try:
        return _run_subject(subject_dir, out, progress=progress, report=report, marker_set=marker_set,
                            model_check=model_check, full_meshes=full_meshes, muscles=muscles, gait2392=gait2392,
                            generic=generic, patella=patella)
    except (InputError, FitError) as exc:
        if report:
            write_refusal_report(Path(out), subject_dir, exc)
        raise
    except OSError as exc:
        # a file-system fault met during the run (disk full, folder made read-only): the same one-line error
        err = InputError(exc.filename or out, f"{exc.strerror or exc} (file-system fault during the run)")
        if report:
            try:
                write_refusal_report(Path(out), subject_dir, err)
            except OSError:
                pass
        raise err from None
    except Exception as exc:
        if report:
            write_refusal_report(Path(out), subject_dir, exc)
        raise


def _run_subject(subject_dir, out, *, progress=None, report: bool = True, marker_set=None,
                 model_check: bool = True, full_meshes: bool = False, muscles: str | None = None,
                 gait2392=None, generic: bool | None = None, patella: str = "fixed") -> dict:
    """`run_subject` without the refusal report."""
    from ..bone_set import write_bone_files
    from ..evaluation.truth import chain_angle_errors, compare_with_truth, truth_in_static_lab
    from ..model_builder import MODEL_MESH_MAX_FACES, save_model_json, save_model_osim, write_meshes
    from ..outputs import replaced_dir
    from ..parameter_fusion import fuse_segment_lengths
    from .marker_assignment import model_markers
    from .model import (bone_landmarks_lab, bone_meshes_lab, joints_on_bones, patella_geometries, pelvis_bone_frame,
                        segment_placements)
    from .model_checks import bone_segment_lengths, check_model
    from .dynamics_setups import write_dynamics_setups
    from .trials import chain_blend, solve_trials

    say = progress or (lambda m: None)
    say("reading inputs")
    inputs = find_inputs(subject_dir, marker_set)
    say(f"lab: {inputs.lab.describe()}")
    volume = label_volume(inputs)        # read once: the bone surfaces and the soft-tissue measurement use it
    inputs, bones = read_subject_bones(inputs, volume, say)
    say("measuring the soft tissue over the pelvic landmarks")
    skin = pelvis_skin(inputs, bones.surfaces, bones.landmarks, volume)
    del volume
    # the MRI covariance scales were calibrated on phantoms: without the real-bone model-error term
    joints = {k: j.without_model_error() for k, j in bones.joints.items()}
    est = estimate_joints(inputs, bones.surfaces, bones.landmarks, joints, say, bones.dropped, skin=skin)
    gate_registrations(inputs, est, say)
    placements = segment_placements(est, joints)
    est.pelvis_bone = pelvis_bone_frame(placements.get("pelvis"), bones.landmarks.bones.get("pelvis"))
    meshes_lab = bone_meshes_lab(bones.surfaces, placements, inputs.sides)
    markers = model_markers(inputs, meshes_lab)
    say("building the model")
    patellae = patella_geometries(bones.surfaces, bones.landmarks, placements, inputs.sides) if patella == "joint" else {}
    try:
        pm, intercepts = build_model(inputs, est, joints, say, markers, patellae)
    except InputError as exc:
        if exc.source != "model":
            raise
        raise InputError(inputs.folder, f"model refused: {exc.problem}") from None   # name the subject, not "model"
    _patella_bodies(patellae, pm, meshes_lab, est.notes)
    centres = ("hip", "knee", "ankle")
    lengths = fuse_segment_lengths({f"{j}_{s}": joints[f"{j}_{s}"].centre for s in inputs.sides for j in centres},
                                   {f"{j}_{s}": est.centres[s][j].motion for s in inputs.sides for j in centres},
                                   inputs.sides)
    notes = list(est.notes) + [f"landmarks of {b}: {', '.join(r.flags)} ({'; '.join(r.notes) or 'see landmarks.json'})"
                               for b, r in bones.landmarks.bones.items() if r.flags]
    summary = SubjectSummary(inputs.folder.name, str(inputs.folder), list(inputs.sides), sorted(inputs.trials),
                             inputs.functional, bones.dropped, notes, pm.parameters.sources, est, lengths, intercepts,
                             lab=inputs.lab.to_json(), measurements=_measurements_json(inputs))
    summary.markers = markers.to_json()
    summary.patellofemoral = {s: t.to_json() for s, t in pm.patellar_tracks.items()}
    summary.joints_on_bones = joints_on_bones(pm, placements, inputs.sides, joints,
                                              ((inputs.truth or {}).get("joints") or {}).get("joints"))
    say("checking the model against the bones")
    ms = inputs.marker_set
    bony = frozenset(k for k, v in ms.markers.items() if v.landmark) if ms is not None else frozenset()
    if model_check:
        check_model(pm, meshes_lab, inputs.folder,
                    {**prior_tissue(est, ms, [m.name for m in pm.model.markers]), **(skin or {})},
                    bone_segment_lengths(joints, inputs.sides), bony)
    truth = truth_in_static_lab(inputs)
    add_muscles, muscle_report = _muscle_step(
        muscles, gait2392, pm, meshes_lab, inputs.sides, notes=summary.notes,
        landmarks_lab=bone_landmarks_lab(bones.landmarks, placements, inputs.sides))
    with replaced_dir(out) as stage:
        write_bone_files(stage, bones, fits=False)
        say("writing meshes and model")
        mesh_files = write_meshes(pm, meshes_lab, inside(stage, "meshes"),
                                  max_faces=None if full_meshes else MODEL_MESH_MAX_FACES, source=str(inputs.bones))
        save_model_json(pm, inside(stage, "model.json"), mesh_files)
        if add_muscles is not None:
            say("muscles: gait2392 onto the subject's bones")
        try:
            save_model_osim(pm, inside(stage, "model.osim"), mesh_files, extend=add_muscles)
        except Exception as exc:    # noqa: BLE001 - the default muscles are an addition: the model goes without them
            if add_muscles is None or muscles == "gait2392":
                raise
            say(f"warning: no muscles ({type(exc).__name__}: {exc})")
            summary.notes.append(f"no muscles: carrying gait2392's muscles onto these bones failed "
                                 f"({type(exc).__name__}: {exc}); the model is written without them")
            muscle_report.clear()
            save_model_osim(pm, inside(stage, "model.osim"), mesh_files)
        if muscle_report:
            from lowerlimb.atomic import write_text

            write_text(inside(stage, "muscles.json"), json.dumps(muscle_report, indent=1) + "\n")
        ik, summary.ik = solve_trials(pm, inputs, stage, say, summary.notes)
        summary.dynamics_setups = write_dynamics_setups(pm, inputs, stage, ik, say, summary.notes)
        summary.chain_blend, chains = chain_blend(inputs, stage, summary.notes)
        summary.generic = _generic_step(generic, muscles, gait2392, pm, inputs, ik, stage, say, truth, summary.notes)
        if truth is not None:
            summary.chain_blend.update(chain_angle_errors(inputs, chains))
            rot = [c.name for c in pm.model.coordinates if c.kind == "rotational"]
            summary.truth = compare_with_truth(inputs, truth, est, ik, rot)
        if report:
            from ..presentation.subject_report import write_subject_report

            say("writing report.html")
            write_subject_report(inside(stage, "report.html"), summary, ik, bones)
        write_summary(inside(stage, "summary.json"), summary)
    return summary.to_json()


def _patella_bodies(patellae: dict, pm, meshes_lab: dict, notes: list) -> None:
    """Each patella mesh onto its ``patella_<s>`` body where the model has the joint, else a note of why not."""
    from ..patellofemoral import TENDON_RANGE

    for s in patellae:
        if s in pm.patellar_tracks:
            meshes_lab[f"patella_{s}"] = (meshes_lab[f"patella_{s}"][0], f"patella_{s}")
        else:
            notes.append(f"patella_{s} rides on the femur: no patellar path on these bones (tendon length outside "
                         f"{', '.join(f'{1e3 * v:.0f}' for v in TENDON_RANGE)} mm or no converged pose)")


def _generic_step(generic: bool | None, muscles, gait2392, pm, inputs, ik, stage, say, truth, notes) -> dict | None:
    """summary.json's ``generic``: the model against gait2392 scaled to the same markers
    (`personalize.generic_comparison`), or None when not asked for (see `run_subject`'s `generic`).  Asked for
    explicitly, a failure stops the run; by default it is noted and the run goes on without it."""
    from ..generic_comparison import GENERIC_DIR, compare_with_scaled_generic
    from ..muscles.generic import generic_model_path

    if generic is False or (generic is None and muscles == "none"):
        return None
    path = generic_model_path(gait2392, required=bool(generic))
    if path is None:
        return None
    try:
        return compare_with_scaled_generic(pm, inputs, ik, stage, path, say, truth).to_json()
    except (InputError, FitError, ValueError, RuntimeError) as exc:
        if generic:
            raise InputError(path, f"gait2392 scaled to the subject's markers: {exc}") from None
        import shutil

        shutil.rmtree(inside(stage, GENERIC_DIR), ignore_errors=True)       # no partial comparison is published
        notes.append(f"no comparison with the scaled generic model: {exc}")
        return None


def _checked_muscles(muscles: str | None, gait2392) -> str | None:
    """The ``muscles`` choice (``$PERSONALIZE_MUSCLES`` when not given; None: the default), refusing a bad one or a
    missing ``gait2392`` file before any work (InputError)."""
    from ..muscles import MUSCLE_CHOICES

    choice = muscles if muscles is not None else os.environ.get(MUSCLES_ENV) or None
    if choice is not None and choice not in MUSCLE_CHOICES:
        raise InputError("--muscles" if muscles is not None else MUSCLES_ENV,
                         f"{choice!r} is not one of {', '.join(MUSCLE_CHOICES)}")
    if gait2392 is not None and choice != "none" and not Path(gait2392).is_file():
        raise InputError(gait2392, "the generic gait2392 model (.osim) is not there")
    return choice


def _muscle_step(muscles: str | None, gait2392, pm, meshes_lab: dict, sides, notes: list, landmarks_lab=None):
    """(callable(opensim.Model) adding the muscles or None, the report dict it fills).

    Muscles asked for (``gait2392`` given or in ``$PERSONALIZE_MUSCLES``) that cannot be added stop the run; the
    default ones are left out with a note (`_run_subject`).

    muscles : the choice `_checked_muscles` returned; meshes_lab : `model.bone_meshes_lab`; landmarks_lab :
    `model.bone_landmarks_lab` (the registration's anatomical correspondences) or None

    Raises
    ------
    InputError : gait2392 asked for and the generic model or the bones it needs not found
    """
    from ..muscles import personalise_muscles, subject_body_landmarks, subject_body_meshes
    from ..muscles.generic import generic_model_path

    if muscles == "none":
        return None, {}
    path = generic_model_path(gait2392, required=muscles == "gait2392")
    body_meshes = subject_body_meshes(meshes_lab, pm.body_frames)
    body_landmarks = subject_body_landmarks(landmarks_lab or {}, pm.body_frames)
    missing = [b for s in sides for b in ("pelvis", f"femur_{s}", f"tibia_{s}") if b not in body_meshes]
    if path is None or missing:
        if muscles == "gait2392":
            raise InputError("--muscles", f"gait2392's muscles need the bones {', '.join(missing)}")
        notes.append("no muscles: " + ("the generic gait2392 model was not found (--gait2392 FILE)" if path is None
                                       else f"bones {', '.join(missing)} missing"))
        return None, {}
    report: dict = {}

    def add(om):
        report.update(personalise_muscles(om, body_meshes, tuple(sides), path, subject_landmarks=body_landmarks))

    return add, report


def read_subject_bones(inputs: SubjectInputs, volume, say) -> tuple[SubjectInputs, object]:
    """The subject's bone surfaces, landmarks and joints (`personalize.bone_set.BoneSet`), and the inputs
    restricted to the sides with both bones (femur, tibia) and markers.

    Raises
    ------
    InputError : no pelvis, or no side with both bones and markers
    """
    from ..bone_set import analyse_bones
    from ..surfaces import load_bones, surfaces_from_labels

    say(f"bone surfaces from {inputs.bones.name}")
    if volume is not None:
        surfaces = surfaces_from_labels(volume, eager_points=False, progress=lambda b: say(f"surface {b}"))
    else:
        surfaces = load_bones(inputs.bones, inputs.label_map, eager_points=False, progress=lambda b: say(f"surface {b}"))
    bone_sides = {s for s in ("r", "l") if f"femur_{s}" in surfaces and f"tibia_{s}" in surfaces}
    if "pelvis" not in surfaces:
        raise InputError(inputs.bones, "no pelvis among the bones: the hip centres cannot be registered")
    sides = tuple(s for s in inputs.sides if s in bone_sides)
    if not sides:
        raise InputError(inputs.folder, f"the bones are of side(s) {', '.join(sorted(bone_sides)) or 'none'} but the markers "
                                        f"of side(s) {', '.join(inputs.sides)}: no side with both femur/tibia and markers")
    say("detecting landmarks")
    bones = analyse_bones(surfaces, input=inputs.bones, progress=lambda b: say(f"landmarks {b}"))
    subject, sources = _subject_measurements(inputs, bones)
    for k, v in sources.items():
        if v != "subject file":
            say(f"{k} measured on the bones: {v}")
    return replace(inputs, sides=sides, subject=subject, subject_sources=sources), bones


def _measurements_json(inputs: SubjectInputs) -> dict:
    """summary.json's ``subject_measurements``: the Plug-in-Gait lengths used (m) and where each came from."""
    return {k: {"value": getattr(inputs.subject, k), "source": v} for k, v in (inputs.subject_sources or {}).items()}


def _subject_measurements(inputs: SubjectInputs, bones) -> tuple[object, dict]:
    """The subject's Plug-in-Gait measurements, those subject.json leaves out measured on the bones
    (`kinematics.gait.subject.measure_from_bones`), and each one's source."""
    from kinematics.gait.subject import BONE_MEASURABLE, measure_from_bones

    given = inputs.subject_given or {}
    if inputs.subject is not None:
        return inputs.subject, {k: "subject file" for k in BONE_MEASURABLE}
    points = {n: lm.position for b in bones.landmarks.bones.values() for n, lm in b.landmarks.items()}
    for s in ("r", "l"):
        if f"knee_{s}" in bones.joints:
            points[f"{s.upper()}KJC"] = bones.joints[f"knee_{s}"].centre.mean
    return measure_from_bones(given, points, source=inputs.folder / "subject.json")


def build_model(inputs: SubjectInputs, est, joints: dict, say, markers=None, patellae=None) -> tuple[object, dict]:
    """The personalised model (`personalize.model_builder.PersonalModel`) with fitted and fused knee laws.

    Built once from the joint estimates to fit the knee laws (`knee_law.fit_knee_laws` on the
    non-functional trials), then again with the laws.  Returns the model and side -> `KneeIntercept`.
    `markers` : the static markers' bodies (`marker_assignment.MarkerAssignment`), None: Plug-in-Gait names;
    `patellae` : side -> `personalize.patellofemoral.PatellaGeometry` (`model.patella_geometries`), the sides that
    get a patellofemoral joint.
    """
    from ..model_builder import build_personal_model
    from ..registration import static_marker_positions
    from .knee_law import fit_knee_laws, fuse_knee_intercepts
    from .model import subject_parameters

    # the first model only fits the knee laws: no patellar path yet (it follows the laws' knee)
    params = subject_parameters(inputs, est, static_marker_positions(inputs.static), markers)
    pm = build_personal_model(params)
    standing: dict = {}
    laws = fit_knee_laws(pm, [t for k, t in sorted(inputs.trials.items()) if not k.startswith("functional")], say,
                         standing=standing)
    laws, intercepts, law_sources = fuse_knee_intercepts(laws, standing, joints)
    sources = dict(params.sources)
    sources.pop("knee law", None)
    sources.update(law_sources)
    sides = {s: replace(sp, knee_law=laws[s][0], patella=(patellae or {}).get(s)) for s, sp in params.sides.items()}
    return build_personal_model(replace(params, sides=sides, sources=sources)), intercepts
