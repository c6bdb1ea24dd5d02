"""Muscles on the subject's bones (issue M1): gait2392's leg muscle-tendon paths carried onto the personalised
bones, their optimal fibre and tendon slack lengths re-estimated.

`personalise_muscles` runs the steps on a personalised opensim model:

1. the generic model (`generic.load_generic_model`: gait2392, the user's copy);
2. each leg body's generic bone registered to the subject's (`bone_registration.register_bodies`: start from the
   anatomical landmarks both bones show (the same detectors on gait2392's bones and the subject's), the tibia
   twisted by its torsion, then similarity ICP anchored on the landmarks, affine ICP when it fits measurably
   better; the femur from its joint centres and surface);
3. the two models' equivalent postures (`poses.joint_offsets`);
4. the muscles' paths mapped body by body (`transfer.add_muscles`);
5. l_o and l_s re-estimated so that normalised fibre lengths over the range of motion stay the generic model's
   (`calibration.calibrate_lengths`, Modenese et al. 2016).

gait2392's six trunk muscles (erector spinae, internal and external obliques) ride on ``torso``, which the
personalised model does not have: the 86 leg muscles are carried (43 a side).
"""
from __future__ import annotations

__all__ = ["MUSCLE_CHOICES", "personalise_muscles", "subject_body_meshes", "subject_body_landmarks"]

#: values of ``--muscles``
MUSCLE_CHOICES = ("none", "gait2392")


def subject_body_meshes(meshes: dict, body_frames: dict) -> dict:
    """body -> trimesh.Trimesh of the body's bones in its body frame (m).

    meshes : bone -> (trimesh.Trimesh in the internal frame, body) (`pipeline.model.bone_meshes_lab`);
    body_frames : body -> (origin (3,), rotation (3, 3)) internal frame (`PersonalModel.body_frames`):
    x_body = Rᵀ (x - o).  The patella rides on the femur in the personalised model but on no gait2392 body: left
    out.
    """
    import numpy as np
    import trimesh

    parts: dict = {}
    for bone, (mesh, body) in sorted(meshes.items()):
        if body not in body_frames or bone.startswith("patella"):
            continue
        o, R = (np.asarray(v, float) for v in body_frames[body])
        m = mesh.copy()
        m.vertices = (np.asarray(m.vertices, float) - o) @ R
        parts.setdefault(body, []).append(m)
    return {b: (p[0] if len(p) == 1 else trimesh.util.concatenate(p)) for b, p in parts.items()}


def subject_body_landmarks(landmarks: dict, body_frames: dict) -> dict:
    """body -> {landmark name (`generic.side_free`): (3,) m in the body frame}.

    landmarks : bone -> ({name: (3,) internal frame}, body) (`pipeline.model.bone_landmarks_lab`); body_frames :
    as `subject_body_meshes` (x_body = Rᵀ (x - o)).  The patella's are left out (no gait2392 body).
    """
    import numpy as np

    from .generic import side_free

    out: dict = {}
    for bone, (pts, body) in sorted(landmarks.items()):
        if body not in body_frames or bone.startswith("patella"):
            continue
        o, R = (np.asarray(v, float) for v in body_frames[body])
        for n, x in pts.items():
            out.setdefault(body, {})[side_free(n, body)] = (np.asarray(x, float) - o) @ R
    return out


def personalise_muscles(om, subject_meshes: dict, sides, generic_path=None, *, affine: bool = True,
                        subject_landmarks: dict | None = None) -> dict:
    """Add gait2392's leg muscles to the personalised opensim model `om` (module docstring); `om` is left
    finalised with the muscles.

    om : opensim.Model of the personalised model (`kinematics.io.opensim_io.to_opensim`, bodies named as
        gait2392's); subject_meshes : body -> trimesh in the body's frame (`subject_body_meshes`); sides : 'r'/'l'
    generic_path : the generic model file (None: `generic.generic_model_path`'s search)
    subject_landmarks : body -> {name: (3,) m, body frame} (`subject_body_landmarks`): matched by name with the
        same detectors' landmarks on gait2392's bones, the registration's anatomical correspondences (None: joint
        centres only)

    Returns the report (JSON-ready): generic model file, per-body registration, coordinate map, muscles added /
    skipped, per-muscle lengths.

    Raises
    ------
    InputError
        The generic model or its meshes cannot be read.
    """
    from .bone_registration import register_bodies
    from .calibration import calibrate_lengths
    from .generic import body_poses, joint_points, load_generic_model, zero_state
    from .poses import joint_offsets
    from .transfer import add_muscles

    generic = load_generic_model(generic_path)
    om.finalizeConnections()
    state = zero_state(om)
    maps = register_bodies(generic, subject_meshes, joint_points(om, state), body_poses(om, state), affine=affine,
                           subject_landmarks=subject_landmarks)
    cmap = joint_offsets(generic, om, maps, sides)
    added = add_muscles(om, generic, maps, cmap, sides)
    om.finalizeConnections()
    om.initSystem()
    lengths = calibrate_lengths(generic.model, om, added["muscles"], cmap, sides)
    om.finalizeConnections()
    return {"generic_model": str(generic.path), "source": "gait2392 (opensim-models, Apache-2.0)",
            "method": "per-body registration of the generic bones (anatomical-landmark start and anchors, tibial "
                      "torsion, similarity then affine ICP; femur: joint-centre start); path points mapped; l_o and "
                      "l_s after Modenese et al. 2016",
            "units": "m, mm for distances, rad",
            "bodies": {b: m.to_json() for b, m in maps.items()}, "coordinates": cmap.to_json(),
            "muscles": added["muscles"], "skipped": added["skipped"], "wrap_objects": added["wrap_objects"],
            "lengths": lengths}
