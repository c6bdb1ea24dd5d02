"""The personalised model beside the one a lab would otherwise use: gait2392 scaled to the subject's markers.

What MRI personalisation buys shows only against that alternative, built as an OpenSim user builds it:

1. **Scale** (`personalize.muscles.compare.scale_generic`, OpenSim's ScaleTool ModelScaler): each body of gait2392
   scaled uniformly by the mean ratio of bony-landmark marker distances, subject over model, the model's markers
   being the same landmarks found on gait2392's own bones.  Pairs as in OpenSim's example
   (``subject01_Setup_Scale.xml``): pelvis ASIS-ASIS and ASIS-PSIS, thigh trochanter-knee (ASIS-knee where the set
   has no trochanter marker, as that example does), shank knee-ankle, foot heel-metatarsal heads (the shank's
   factor where the set has no metatarsal markers).
2. **Place** (ScaleTool's MarkerPlacer): the scaled model posed on the static trial by IK of its landmark markers
   (subtalar and mtp held at zero with weight 1000, as OpenSim's example does), then every marker of the static
   trial put on its body (the personalised model's assignment) where the trial shows it.
3. **Track**: the same IK (`kinematics.algorithms.ik.solve_ik`, the same markers, weight 1 each) of every trial on
   both models.

Reported (`GenericComparison`): both models' hip, knee and ankle centres in the static pose (model ground,
m) and their distance; per trial both IKs' marker RMS and, per coordinate both models have, the RMS difference
of the angles (deg; gait2392's ``knee_angle`` taken as ``-knee_flexion``).  A phantom's truth adds each model's
centre errors and angle RMSE against it.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from lowerlimb.atomic import inside

__all__ = ["GenericComparison", "compare_with_scaled_generic", "COMPARED_ANGLES", "GENERIC_DIR"]

#: the coordinates compared, gait2392's names (the knee as the personalised model's ``knee_flexion``)
COMPARED_ANGLES = ("hip_flexion", "hip_adduction", "hip_rotation", "knee_flexion", "ankle_angle", "subtalar_angle")
#: the output folder's sub-folder of the scaled generic model, its IK set-ups and motions
GENERIC_DIR = "generic"
_JOINTS = ("hip", "knee", "ankle")
#: measurement -> pairs used when the set has none of `personalize.muscles.compare.MEASUREMENTS`' pairs
_FALLBACK_PAIRS = {"thigh": [("RASI", "RKNE"), ("LASI", "LKNE")]}
#: gait2392 landmarks left out of the placement (`_measurement_set`'s note)
_MISPLACED = ("D1M", "D5M", "TOE")


@dataclass
class GenericComparison:
    """The personalised model against gait2392 scaled to the same markers (module docstring).

    scale_factors : body -> uniform scale factor of gait2392; measurements : measurement -> marker pairs used
    centres : joint (``hip_r``...) -> {"personalised": (3,), "generic": (3,)} m, model ground, static pose
    trials : trial -> {"marker_rms_mm": {"personalised", "generic"}, "angle_rms_difference_deg": {coordinate: deg}}
    truth : {"centre_error_mm": {joint: {"personalised", "generic"}}, "angle_rmse_deg": {coordinate: {...}},
        "angle_offset_deg": {...} (the RMSE's constant part)} on a phantom, else empty; placed : markers placed on the generic model; notes : what was substituted
    """

    scale_factors: dict
    measurements: dict
    centres: dict
    trials: dict = field(default_factory=dict)
    truth: dict = field(default_factory=dict)
    placed: tuple = ()
    notes: list = field(default_factory=list)

    def to_json(self) -> dict:
        """summary.json's ``generic`` (units in the keys, frame stated)."""
        cen = {j: {"personalised_m": [float(v) for v in c["personalised"]],
                   "generic_m": [float(v) for v in c["generic"]],
                   "distance_mm": 1e3 * float(np.linalg.norm(np.subtract(c["personalised"], c["generic"])))}
               for j, c in self.centres.items()}
        return {"model": f"{GENERIC_DIR}/scaled_generic.osim", "frame": "model ground (Y up, X forward), static pose",
                "method": "gait2392 scaled by OpenSim's ScaleTool (uniform per body, bony-landmark marker pairs), "
                          "markers placed on the static pose, the same IK on every trial",
                "scale_factors": self.scale_factors, "measurements": self.measurements, "centres": cen,
                "trials": self.trials, "truth": self.truth, "placed_markers": list(self.placed), "notes": self.notes}


def _static_landmarks(static_ground, internal: dict) -> dict:
    """Landmark name -> (3,) m: the static trial's bony-landmark markers (lab label -> internal name differs, or
    the label is a landmark name itself), mean over the frames, model ground."""
    mean = np.nanmean(np.asarray(static_ground.positions, float), axis=0)
    out = {}
    for k, n in enumerate(static_ground.names):
        if np.all(np.isfinite(mean[k])):
            out[internal.get(n, n)] = mean[k]
    return out


def _measurement_set(labels) -> tuple[dict, list]:
    """`personalize.muscles.compare.MEASUREMENTS` restricted to the landmark pairs the subject has, with the
    fallbacks of the module docstring; (measurement -> (pairs, bodies), notes)."""
    from .muscles.compare import MEASUREMENTS

    have = set(labels)
    out, notes = {}, []
    for name, (pairs, bodies) in MEASUREMENTS.items():
        if name == "foot":
            continue
        use = [p for p in pairs if set(p) <= have]
        if not use and name in _FALLBACK_PAIRS:
            use = [p for p in _FALLBACK_PAIRS[name] if set(p) <= have]
            if use:
                notes.append(f"{name} scaled from {', '.join('-'.join(p) for p in use)} (no trochanter marker)")
        if use:
            out[name] = (use, list(bodies))
    if "shank" in out:
        out["shank"] = (out["shank"][0], out["shank"][1] + list(MEASUREMENTS["foot"][1]))
        notes.append("foot scaled with the shank: on gait2392's coarse foot mesh the metatarsal-head landmarks land "
                     "at the metatarsal bases, 35-45 mm proximal")
    return out, notes


def _placement_markers(landmarks: dict, factors: dict, wanted) -> tuple:
    """`kinematics.multibody.Marker`s of the scaled model at gait2392's own landmarks (`GenericModel.landmarks`,
    each location times its body's factor), named as the subject's landmarks (``RKNE`` on ``femur_r``), for the
    names in `wanted`; ``SACR`` midway between the PSIS; not the metatarsal heads and toe (misplaced, see
    `_measurement_set`)."""
    from kinematics.multibody.model import Marker

    out = []
    for body, pts in landmarks.items():
        f = factors.get(body)
        if f is None:
            continue
        named = {n if body == "pelvis" or len(n) != 3 else body[-1].upper() + n: x for n, x in pts.items()}
        if body == "pelvis" and {"RPSI", "LPSI"} <= set(named):
            named["SACR"] = 0.5 * (np.asarray(named["RPSI"]) + np.asarray(named["LPSI"]))
        for n, x in named.items():
            if n in wanted and n[1:] not in _MISPLACED:
                out.append(Marker(n, body, f * np.asarray(x, float)))
    return tuple(out)


def _scale_factors(scaled, virtual: dict, measurements: dict) -> dict:
    """body -> the uniform factor ScaleTool applied: the landmark markers' distance from their body's origin,
    scaled over generic (`virtual`: name -> (body, generic location)), each measurement's factor given to all its
    bodies."""
    ratio: dict = {}
    for m in scaled.markers:
        if m.name in virtual and virtual[m.name][0] == m.body:
            g = float(np.linalg.norm(virtual[m.name][1]))
            if g > 1e-3:
                ratio.setdefault(m.body, []).append(float(np.linalg.norm(m.offset)) / g)
    out = {}
    for _, bodies in measurements.values():
        f = [float(np.median(ratio[b])) for b in bodies if b in ratio]
        for b in bodies:
            if f:
                out[b] = f[0]
    return out


def _joint_centres(model, q, sides) -> dict:
    """joint -> (3,) m in ground: the child frame of each hip, knee and ankle joint at pose `q`."""
    from kinematics.algorithms.fk import forward_kinematics

    st = forward_kinematics(model, q)
    out = {}
    for s in sides:
        for j in _JOINTS:
            name = f"{j}_{s}"
            if name not in {jt.name for jt in model.joints}:
                continue
            jt = model.joint(name)
            b = model.body_index(jt.child)
            R, p = st.rotations[0, b], st.positions[0, b]
            out[name] = p + R @ np.asarray(jt.child_offset.translation, float)
    return out


def _as_flexion(res):
    """An IK result of gait2392 with ``knee_angle_<s>`` as the personalised model's ``knee_flexion_<s>`` (negated)."""
    names = tuple(c.replace("knee_angle_", "knee_flexion_") for c in res.coordinates)
    q = np.array(res.q, float)
    for i, c in enumerate(res.coordinates):
        if c.startswith("knee_angle_"):
            q[:, i] = -q[:, i]
    return replace(res, coordinates=names, q=q)


def _angle_rms_difference(personal, generic, sides) -> dict:
    out = {}
    for s in sides:
        for a in COMPARED_ANGLES:
            c = f"{a}_{s}"
            if c not in personal.coordinates or c not in generic.coordinates:
                continue
            d = np.degrees(personal.q[:, personal.coordinates.index(c)] - generic.q[:, generic.coordinates.index(c)])
            d = d[np.isfinite(d)]
            if len(d):
                out[c] = float(np.sqrt(np.mean(d ** 2)))
    return out


def _placed_markers(osim, scaled_path: Path, generic_model, q_static, static_ground, bodies: dict, out_path: Path):
    """The scaled model with the static trial's markers placed (ScaleTool's MarkerPlacer): written to `out_path`;
    returns the placed `kinematics.multibody.Marker`s.  bodies : lab label -> body (the personalised model's
    assignment)."""
    from kinematics.algorithms.fk import forward_kinematics
    from kinematics.io.opensim_io import write_osim
    from kinematics.multibody.model import Marker

    st = forward_kinematics(generic_model, q_static)
    mean = np.nanmean(np.asarray(static_ground.positions, float), axis=0)
    om = osim.Model(os.fspath(scaled_path))
    om.updMarkerSet().clearAndDestroy()
    placed = []
    have = set(generic_model.body_names)
    for k, n in enumerate(static_ground.names):
        body = bodies.get(n)
        if body not in have or not np.all(np.isfinite(mean[k])):
            continue
        b = generic_model.body_index(body)
        x = st.rotations[0, b].T @ (mean[k] - st.positions[0, b])
        om.addMarker(osim.Marker(n, om.getBodySet().get(body), osim.Vec3(*map(float, x))))
        placed.append(Marker(n, body, x))
    om.finalizeConnections()
    write_osim(om, out_path)
    return tuple(placed)


def compare_with_scaled_generic(pm, inputs, ik: dict, stage: Path, generic_path, say=lambda m: None,
                                truth: dict | None = None) -> GenericComparison:
    """Scale gait2392 to the subject, place its markers, track every trial, and compare (module docstring).

    Parameters
    ----------
    pm : `personalize.model_builder.PersonalModel`; inputs : `personalize.pipeline.SubjectInputs`
    ik : trial -> the personalised model's IK result (`personalize.pipeline.trials.solve_trials`)
    stage : output folder; writes ``generic/``: ``scaled_generic.osim`` with the placed markers, the ScaleTool's
        files, ``static.mot`` (the placement pose), per trial ``<trial>.mot`` (gait2392's coordinates) and an
        OpenSim IK set-up on ``../kinematics/<trial>.trc``
    generic_path : gait2392 (.osim with its ``Geometry``); truth : `evaluation.truth.truth_in_static_lab` or None
    """
    from kinematics.io.marker_sets import canonical_names, preset
    from kinematics.io.opensim_io import degree_coordinates
    from kinematics.io.storage import write_mot

    from .model_builder import trial_in_ground
    from .muscles.generic import load_generic_model

    work = inside(stage, GENERIC_DIR)
    work.mkdir(parents=True, exist_ok=True)
    static = trial_in_ground(pm, inputs.static)
    lm = _static_landmarks(static, canonical_names(inputs.marker_set or preset("pig"), static.names))
    generic = load_generic_model(generic_path)
    say("generic: gait2392 scaled to the static markers (ScaleTool)")
    g_model, factors, measurements, notes = _scaled(generic, lm, float(getattr(inputs.subject, "mass", None) or 75.0),
                                                    work)
    g_placed, q0 = _placed(g_model, generic.landmarks, factors, lm, static,
                           {m.name: m.body for m in pm.model.markers}, work)
    rot = degree_coordinates(g_placed)
    write_mot(inside(work, "static.mot"), g_placed.coordinate_names, np.array([0.0]), q0[None], rotational=rot,
              name="static pose of the scaled gait2392 (marker placement)")
    sides = tuple(inputs.sides)
    cp, cg = _joint_centres(pm.model, pm.standing_q, sides), _joint_centres(g_placed, q0, sides)
    out = GenericComparison(factors, {k: [list(p) for p in v[0]] for k, v in measurements.items()},
                            {j: {"personalised": cp[j], "generic": cg[j]} for j in cp if j in cg},
                            placed=g_placed.marker_names, notes=notes)
    g_results = {}
    for name, res in ik.items():
        if name == "static":
            continue
        say(f"generic: IK {name}")
        g_results[name] = _tracked(g_placed, q0, trial_in_ground(pm, inputs.trials[name]), res.markers, work, name)
        out.trials[name] = {
            "marker_rms_mm": {"personalised": 1e3 * float(np.nanmean(res.rms)),
                              "generic": 1e3 * float(np.nanmean(g_results[name].rms))},
            "angle_rms_difference_deg": _angle_rms_difference(res, g_results[name], sides)}
    if truth is not None:
        out.truth = _against_truth(inputs, pm, truth, ik, g_results, out.centres)
    return out


def _scaled(generic, lm: dict, mass: float, work: Path):
    """Step 1: (scaled model as a `kinematics` Model, body -> factor, measurements used, notes)."""
    from kinematics.io.opensim_io import load_osim

    from .muscles import compare as mcompare

    virtual = mcompare.generic_virtual_markers(generic)
    measurements, notes = _measurement_set(set(lm) & set(virtual))
    if not measurements:
        raise ValueError("no bony-landmark marker pair to scale gait2392 with")
    mcompare.scale_generic(generic, lm, mass, work, measurements=measurements)
    g_model = load_osim(work / "gait2392_scaled.osim")
    return g_model, _scale_factors(g_model, virtual, measurements), measurements, notes


def _placed(g_model, landmarks: dict, factors: dict, lm: dict, static, bodies: dict, work: Path):
    """Step 2: the scaled model posed on the static landmarks, its markers placed and written
    (``scaled_generic.osim``): (placed model, static pose)."""
    from kinematics.algorithms.ik import solve_ik
    from kinematics.io.ik_setup import CoordinateTask
    from kinematics.io.markers import MarkerTrial
    from kinematics.io.opensim_io import import_opensim

    g_lm = g_model.replace(markers=_placement_markers(landmarks, factors, set(lm)))
    names = g_lm.marker_names
    lt = MarkerTrial(names, np.array([[lm[n] for n in names]]), static.rate, np.array([0.0]), source="static")
    # subtalar and mtp held at zero, as OpenSim's example placement does (weight 1000): HEE alone leaves them free
    held = [CoordinateTask(c, 1000.0, 0.0) for c in g_lm.coordinate_names if c.startswith(("subtalar_angle", "mtp_angle"))]
    q = solve_ik(g_lm, lt, coordinate_tasks=held, check_units=False).q[0]
    placed = _placed_markers(import_opensim(), work / "gait2392_scaled.osim", g_lm, q, static, bodies,
                             work / "scaled_generic.osim")
    return g_model.replace(markers=placed), q


def _tracked(g_placed, q0, trial, markers, work: Path, name: str):
    """Step 3: IK of one trial (model ground) on the placed model with the personalised IK's `markers`, weight 1;
    writes ``<name>.mot`` and its OpenSim IK set-up; returns the result with ``knee_flexion`` (`_as_flexion`)."""
    from kinematics.algorithms.ik import solve_ik
    from kinematics.io.ik_setup import write_ik_setup
    from kinematics.io.opensim_io import degree_coordinates
    from kinematics.io.storage import write_mot

    from .pipeline.trials import OPENSIM_IK_ACCURACY

    w = {m: 1.0 for m in markers if m in g_placed.marker_names}
    res = solve_ik(g_placed, trial, marker_weights=w, q0=q0)
    rot = degree_coordinates(g_placed)
    write_mot(inside(work, f"{name}.mot"), g_placed.coordinate_names, res.time, res.q, rotational=rot,
              name=f"IK {name} (scaled gait2392)")
    write_ik_setup(inside(work, f"{name}_ik_setup.xml"), model_file="scaled_generic.osim",
                   marker_file=f"../kinematics/{name}.trc", output_motion_file=f"{name}_opensim_ik.mot",
                   marker_weights=w, time_range=(float(res.time[0]), float(res.time[-1])),
                   accuracy=OPENSIM_IK_ACCURACY, name=f"{name}_generic_ik")
    return _as_flexion(res)


def _against_truth(inputs, pm, truth: dict, ik: dict, generic_ik: dict, centres: dict) -> dict:
    """Both models' static joint centres (mm) and gait angles (RMSE deg) against a phantom's truth
    (`personalize.evaluation.truth`)."""
    from .evaluation.truth import angle_errors_against_truth

    G = np.asarray(pm.G, float)
    err = {}
    for j, c in centres.items():
        t = truth["centres"].get(j)
        if t is not None:
            t = G @ np.asarray(t, float)        # internal (static lab) -> model ground
            err[j] = {k: 1e3 * float(np.linalg.norm(np.asarray(c[k], float) - t)) for k in ("personalised", "generic")}
    rot_p = [c.name for c in pm.model.coordinates if c.kind == "rotational"]
    rot_g = sorted({c for r in generic_ik.values() for c in r.coordinates})
    (a_p, o_p), (a_g, o_g) = (angle_errors_against_truth(inputs, r, rot) for r, rot in ((ik, rot_p), (generic_ik, rot_g)))
    ang = {c: {"personalised": a_p[c], "generic": a_g[c]} for c in a_p if c in a_g}
    # the constant part of each RMSE (a model's joint-frame convention, e.g. gait2392's pelvis frame against ISB's)
    off = {c: {"personalised": o_p[c], "generic": o_g[c]} for c in ang}
    return {"centre_error_mm": err, "angle_rmse_deg": ang, "angle_offset_deg": off}
