"""The personalised model of a subject: the model builder's parameters from the joint estimates, the bone meshes."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..model_builder import SideParameters, SubjectParameters
from .inputs import SubjectInputs
from .joint_estimates import JointEstimates
from .marker_assignment import MarkerAssignment

__all__ = ["subject_parameters", "patella_geometries", "bone_meshes_lab", "bone_landmarks_lab", "segment_placements", "joints_on_bones", "pelvis_bone_frame"]


def subject_parameters(inputs: SubjectInputs, est: JointEstimates, static: dict,
                       markers: MarkerAssignment | None = None) -> SubjectParameters:
    """The model builder's input: fused centres and axes with their covariances, static markers, provenance.

    `static` : label -> `Gaussian` static marker positions (the trial's own labels); `markers`: their bodies
    (`marker_assignment.assign_markers`), None: the Plug-in-Gait name table of the builder.
    """

    sides = {}
    for s in inputs.sides:
        c, a, p = est.centres[s], est.axes[s], est.lines[s]
        sides[s] = SideParameters(
            hip=c["hip"].fused.mean, knee=c["knee"].fused.mean, knee_axis=a["knee"].fused.direction,
            ankle=c["ankle"].fused.mean, ankle_axis=a["ankle"].fused.direction,
            subtalar=p["subtalar"].point, subtalar_axis=p["subtalar"].direction, mtp=p["mtp"].point,
            mtp_axis=p["mtp"].direction, centre_cov={j: c[j].fused.cov for j in ("hip", "knee", "ankle")},
            axis_sd_deg={j: a[j].fused.sd_deg for j in ("knee", "ankle")})
    subj = inputs.subject
    mass = float(subj.mass) if subj.mass else 70.0
    height = float(subj.height) if subj.height else 1.75
    motion_centre = {j: (f"motion ({j}_centre_<side>_motion)" if any(k.startswith(f"{j}_centre_") for k in est.sources)
                         else "Plug-in-Gait static") for j in ("knee", "ankle")}
    sources = {"hip centres": "fused: MRI (pelvis registration) x motion (hip_<side>_motion)",
               "knee centres": f"fused: MRI (femur registration) x {motion_centre['knee']}",
               "knee axes": "fused: MRI (femur registration) x motion (knee_axis_<side>_motion)",
               "ankle centres": f"fused: MRI (shank registration) x {motion_centre['ankle']}",
               "ankle axes": "fused: MRI (shank registration) x motion (ankle_axis_<side>_motion)",
               "knee law": "default (model_builder.DEFAULT_KNEE_SLOPES); not fitted",
               "markers": "median static-trial positions",
               "mass": "subject.json" if subj.mass else "70 kg default (subject.json has no mass)"}
    if inputs.marker_set is not None:
        sources["marker set"] = inputs.marker_set_source or inputs.marker_set.name
    sources.update({k: v for k, v in est.sources.items()})
    if est.pelvis_bone is not None:
        sources["pelvis frame"] = ("ISB frame of the MRI pelvis (the bone's ASIS-PSIS plane), as the model places the "
                                   "bone on the fused hip centres")
    else:
        sources["pelvis frame"] = "Plug-in-Gait frame of the static pelvis markers"
    origin, axes = est.pelvis_bone if est.pelvis_bone is not None else est.pelvis
    return SubjectParameters(origin, axes, sides, {n: v.mean for n, v in static.items()},
                             mass, height, sources, name=inputs.folder.name or "subject",
                             marker_bodies=None if markers is None else dict(markers.bodies))




def patella_geometries(surfaces: dict, landmarks, placements: dict, sides) -> dict:
    """side -> `personalize.patellofemoral.PatellaGeometry` in the static lab frame: femur, patella and the MRI's
    tibial tuberosity moved with the femur's placement (their MRI relation), the tuberosity also with the shank's.
    Sides without a patella, a confidently oriented one (`FLAG_LOW_CONFIDENCE`) or a tuberosity are left out."""
    from trimesh.transformations import transform_points

    from ..landmarks.common import FLAG_LOW_CONFIDENCE
    from ..patellofemoral import PatellaGeometry

    out = {}
    for s in sides:
        pat, tib = landmarks.bones.get(f"patella_{s}"), landmarks.bones.get(f"tibia_{s}")
        tt = None if tib is None else tib.landmarks.get(f"{s.upper()}TTB")
        T_f, T_t = placements.get(f"femur_{s}"), placements.get(f"tibia_{s}")
        if (pat is None or tt is None or T_f is None or T_t is None or FLAG_LOW_CONFIDENCE in pat.flags
                or "articular" not in pat.frames or f"femur_{s}" not in surfaces or f"patella_{s}" not in surfaces):
            continue
        fm, pm_ = surfaces[f"femur_{s}"].mesh, surfaces[f"patella_{s}"].mesh
        R = T_f[:3, :3]
        out[s] = PatellaGeometry(transform_points(fm.vertices, T_f), np.asarray(fm.vertex_normals) @ R.T,
                                 transform_points(pm_.vertices, T_f), np.asarray(pm_.vertex_normals) @ R.T,
                                 transform_points([pat.landmarks["patella_centre"].position], T_f)[0],
                                 R @ pat.frames["articular"]["rotation"], transform_points([tt.position], T_f)[0],
                                 transform_points([tt.position], T_t)[0])
    return out


def _placed_on_joints(reg, mri_prox, lab_prox, mri_dist=None, lab_dist=None) -> np.ndarray:
    """4x4 scanner -> lab map of a segment's meshes: its registration turned and shifted onto the model's joints.

    The registration alone leaves the bone where its markers put it, up to its joint anchor's residual (a femoral
    head 9 mm off the model's hip).  The turn is the least that aligns the registered hip-knee (knee-ankle) line
    with the model's (fused) one, the shift puts the mid-point of the MRI joint centres on the mid-point of the
    model's: the two centres' length difference is then shared by both ends.  Without a distal joint the
    proximal MRI centre goes onto the model's.
    """
    R = reg.R
    mri_mid, lab_mid = np.asarray(mri_prox, float), np.asarray(lab_prox, float)
    if mri_dist is not None and lab_dist is not None:
        mri_dist, lab_dist = np.asarray(mri_dist, float), np.asarray(lab_dist, float)
        u, v = R @ (mri_dist - mri_mid), lab_dist - lab_mid
        axis = np.cross(u, v)
        s, c = float(np.linalg.norm(axis)), float(u @ v)
        if s > 1e-12:
            R = Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix() @ R
        mri_mid, lab_mid = 0.5 * (mri_mid + mri_dist), 0.5 * (lab_mid + lab_dist)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, lab_mid - R @ mri_mid
    if not np.all(np.isfinite(T)):
        T = reg.as_matrix()
    return T


def _bone_segments(sides) -> dict:
    """Bone -> (segment whose placement moves it, model body it belongs to)."""
    seg_of = {"pelvis": ("pelvis", "pelvis")}
    for s in sides:
        seg_of.update({f"femur_{s}": (f"femur_{s}", f"femur_{s}"), f"patella_{s}": (f"femur_{s}", f"femur_{s}"),
                       f"tibia_{s}": (f"tibia_{s}", f"tibia_{s}"), f"fibula_{s}": (f"tibia_{s}", f"tibia_{s}"),
                       f"talus_{s}": (f"calcn_{s}", f"talus_{s}"), f"calcn_{s}": (f"calcn_{s}", f"calcn_{s}"),
                       f"toes_{s}": (f"calcn_{s}", f"toes_{s}")})
    return seg_of


def segment_placements(est: JointEstimates, joints: dict | None = None) -> dict:
    """Segment -> 4x4 scanner -> static lab map of its bones in the model.

    With `joints` (joint name -> `personalize.frames.Joint`, scanner) the pelvis is placed on the model's two
    hip centres, the femur on its hip and knee centres, the shank on its knee and ankle centres
    (`_placed_on_joints`): the fused centres say where the bones are, so the bones follow them rather than the
    joints leaving the bones (a pelvis registered from palpated markers 10 mm off left the model's hips up to
    27 mm from the acetabula).  The foot's registration is already anchored on the fused ankle
    (`foot.estimate_foot_axes`).
    """
    placed = {}
    for seg, reg in est.registrations.items():
        T = reg.as_matrix()
        bone, _, s = seg.partition("_")
        ends = {"femur": (("hip", s), ("knee", s)), "tibia": (("knee", s), ("ankle", s)),
                "pelvis": tuple(("hip", side) for side in sorted(est.centres))}.get(bone, ())
        ends = [(f"{j}_{side}", side, j) for j, side in ends
                if joints is not None and f"{j}_{side}" in joints and j in est.centres.get(side, {})]
        if ends:
            pts = [(joints[n].origin, est.centres[side][j].fused.mean) for n, side, j in ends[:2]]
            T = _placed_on_joints(reg, *pts[0], *(pts[1] if len(pts) > 1 else ()))
        placed[seg] = T
    return placed


def bone_meshes_lab(surfaces: dict, placements: dict, sides) -> dict:
    """Bone meshes moved into the static lab frame by their segment's placement (`segment_placements`):
    bone -> (mesh, body)."""
    seg_of = _bone_segments(sides)
    out = {}
    for bone, surf in surfaces.items():
        if bone not in seg_of or seg_of[bone][0] not in placements:
            continue
        m = surf.mesh.copy()
        m.apply_transform(placements[seg_of[bone][0]])
        out[bone] = (m, seg_of[bone][1])
    return out


def bone_landmarks_lab(landmarks, placements: dict, sides) -> dict:
    """Bone landmarks moved into the static lab frame as `bone_meshes_lab` moves the meshes: bone -> ({name: (3,)
    m}, body).  landmarks : `personalize.landmarks.LandmarkSet` (scanner frame); the points are
    `personalize.muscles.generic.anatomical_points` (the landmarks and the points the bone's axes define)."""
    from ..muscles.generic import anatomical_points

    seg_of = _bone_segments(sides)
    out = {}
    for bone, res in landmarks.bones.items():
        if bone not in seg_of or seg_of[bone][0] not in placements or not res.landmarks:
            continue
        T = placements[seg_of[bone][0]]
        out[bone] = ({n: T[:3, :3] @ x + T[:3, 3] for n, x in anatomical_points(res).items()}, seg_of[bone][1])
    return out


def pelvis_bone_frame(placement: np.ndarray | None, pelvis) -> tuple | None:
    """The pelvis's ISB frame from its bone, as the model places it: (origin (3,), axes (3, 3)) in the static lab,
    axes as `JointEstimates.pelvis` (x anterior, y left, z up), or None without the bone's ASIS and PSIS.

    The skin markers' ASIS-PSIS plane departs from the bone's with the tissue under them and their palpation
    (a realistic phantom with 6 mm over the ASIS and 22 mm over the PSIS: 1.5 deg of tilt, 2 deg overall); an
    expert-built model's pelvis frame is the bone's.

    placement : 4x4 scanner -> lab map of the pelvis (`segment_placements`); pelvis : the pelvis's
    `personalize.landmarks.BoneLandmarks` (its ``isb`` frame: X anterior, Y superior, Z right; scanner)
    """
    fr = None if pelvis is None else pelvis.frames.get("isb")
    if placement is None or fr is None or not all(k in pelvis.landmarks for k in ("RASI", "LASI", "RPSI", "LPSI")):
        return None
    R = placement[:3, :3] @ np.asarray(fr["rotation"], float)
    origin = placement[:3, :3] @ np.asarray(fr["origin"], float) + placement[:3, 3]
    return origin, np.column_stack([R[:, 0], -R[:, 2], R[:, 1]])


def joints_on_bones(pm, placements: dict, sides, joints: dict, truth_joints: dict | None = None) -> dict:
    """Where the model's joint centres sit on its bones: each joint's parent- and child-side centre carried back
    into its bone's scanner frame, against the MRI joint (``*_vs_mri_mm``) and the phantom truth (``*_vs_truth_mm``).

    What an expert comparing the model with the bones (or with an expert-built model) measures; fusion moves a
    centre off the bones' own estimate by at most its disagreement with the motion estimate.

    pm : `personalize.model_builder.PersonalModel`; placements : `segment_placements`; joints : joint name ->
    `personalize.frames.Joint` (scanner, m); truth_joints : joint name -> {"origin": (3,) m} (truth.json, scanner)
    """
    seg_of = _bone_segments(sides)
    out = {}
    for j in pm.model.joints:
        if j.name not in joints:
            continue
        row = {}
        for end, body, off in (("parent", j.parent, j.parent_offset), ("child", j.child, j.child_offset)):
            if body not in seg_of or seg_of[body][0] not in placements or body not in pm.body_frames:
                continue
            o, R = pm.body_frames[body]
            T = placements[seg_of[body][0]]
            x = T[:3, :3].T @ (o + R @ off.translation - T[:3, 3])
            row[f"{end}_vs_mri_mm"] = round(1e3 * float(np.linalg.norm(x - joints[j.name].origin)), 2)
            if truth_joints and j.name in truth_joints:
                row[f"{end}_vs_truth_mm"] = round(1e3 * float(np.linalg.norm(x - np.asarray(truth_joints[j.name]["origin"]))), 2)
        if row:
            out[j.name] = row
    return out
