"""The personalised engine model from fused subject parameters, in OpenSim's conventions (issue P1, item 3; R1).

Every parameter is given in ONE frame, the INTERNAL frame of the static
trial (X = the static pose's facing direction, Y = left, Z = up, metres; the
subject standing still).  The model is written in OpenSim's conventions:

* ground: Y up, X along the static pose's facing direction, Z to the right,
  ``x_ground = G x_internal`` with ``G = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]``
  (`GROUND_FROM_INTERNAL`); gravity -9.80665 m/s² along -Y;
* body frames as ISB recommends (Wu et al. 2002; X anterior, Y superior,
  Z to the right):

  - ``pelvis``: origin mid-ASIS, Z = unit(RASI - LASI), X anterior in the
    ASIS-PSIS plane (the Plug-in-Gait pelvis frame's x), Y = Z x X;
  - ``femur_s``: origin knee centre K, Y = unit(H - K) (H the fused hip
    centre), Z = the knee axis (pointing right) made orthogonal to Y;
  - ``tibia_s``: origin ankle centre A, Y = unit(K - A), Z as the femur's;
  - ``talus_s`` (origin A), ``calcn_s`` (origin on the subtalar axis),
    ``toes_s`` (origin on the metatarsophalangeal axis): axes of the tibia;

* coordinates with gait2392's names, axes and signs
  (``subject01_simbody_adjusted.osim`` read with the opensim API):

  - ``ground_pelvis``: rotation1 ``pelvis_tilt`` about ground Z, rotation2
    ``pelvis_list`` about X, rotation3 ``pelvis_rotation`` about Y (body-fixed
    Z-X-Y), translations ``pelvis_tx/ty/tz`` along ground X, Y, Z, so that
    ``pelvis_ty`` is the height of the pelvis origin;
  - hip: flexion about the pelvis-side Z, adduction about ±X, internal
    rotation about ±Y (``+`` right, ``-`` left, gait2392's signs), about the
    fused hip centre, from the pelvis axes to the femur axes;
  - knee: a correlative knee (Pronost et al. 2010) with six coordinates,
    flexion about -Z_k (``knee_flexion`` positive in flexion: the deliberate
    difference from gait2392's ``knee_angle``, see `lowerlimb.topology`),
    ab/adduction about ±X_k, rotation about ±Y_k (Z_k the fused knee axis to
    the right, Y_k the femur's long axis made orthogonal to it), from the
    femur's knee frame to the tibia frame, and translations knee_tx
    (anterior, X_k), knee_ty (proximal, Y_k), knee_tz (lateral, ±Z_k) that are
    a linear law of the three rotations
    (`kinematics.mechanisms.correlative.CorrelativeLaw`, enforced as linear
    couplings; OpenSim CoordinateCouplerConstraints in ``model.osim``).  A
    law's constant term is the translation at the STANDING pose (zero: the
    fused knee centre is the standing one); the builder re-expresses it in
    the model's coordinates, c_0' = c_0 - S q_standing;
  - ankle, subtalar and metatarsophalangeal: revolute joints about the fused
    axes with gait2392's signs (dorsiflexion, inversion, toe extension
    positive on both sides); the mtp coordinate is locked unless the toes
    carry markers.

The hip and knee angles are anatomical (zero when the frames are aligned),
so the standing pose carries its own (``standing_q``; a standing knee is
typically a few degrees from straight).  A subject standing upright facing +X
has the pelvis list and rotation and the knee and ankle angles near zero; the
pelvis tilt is the ISB frame's, the ASIS-PSIS plane's tilt (posterior tilt
positive: an anteriorly tilted pelvis reads about -10 to -15 deg, -12 deg on
the phantoms; gait2392's own pelvis frame is within 2.4 deg of its ASIS-sacral
line, so it reads the same), and the hip flexion of a vertical femur about as
much positive.  The leg's rotational coordinates are clamped to their
`lowerlimb.topology` ranges (IK keeps them inside, as OpenSim's IK does for
clamped coordinates).

`PersonalModel.body_frames` stays in the internal frame:
x_internal = o + R x_body.  Markers are placed from the static trial:
offset = Rᵀ (m - o) with m the median static position.

Mass properties: de Leva (1996, J Biomech 29:1223) segment mass fractions,
centre-of-mass positions and radii of gyration of the adult male, scaled by
the subject's mass and the model's own segment lengths.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.mechanisms.correlative import CorrelativeLaw
from lowerlimb.errors import InputError
from lowerlimb.geometry import frame_yz, frame_zy, unit
from lowerlimb.topology import (GROUND_JOINT, JOINT_COORDINATES, KNEE_ROTATIONS, KNEE_TRANSLATIONS, PELVIS_ROTATIONS,
                                PELVIS_TRANSLATIONS, coordinate_def, leg_coordinates, sided)
from kinematics.multibody.functions import Linear
from kinematics.multibody.joints import CustomJoint, Transform, TransformAxis, free, revolute
from kinematics.multibody.model import Body, Coordinate, Marker, Model

__all__ = ["SideParameters", "SubjectParameters", "PersonalModel", "build_personal_model", "default_knee_law",
           "MARKER_BODIES", "DE_LEVA", "GROUND_FROM_INTERNAL", "GRAVITY", "trial_in_ground", "save_model_json",
           "save_model_osim", "write_meshes", "MeshFile", "MODEL_MESH_MAX_FACES", "decimation_error", "model_credits"]

_X, _Y, _Z = np.eye(3)

#: OpenSim ground from the internal frame: x_ground = G x_internal (X forward, Y up, Z right)
GROUND_FROM_INTERNAL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: gravity in ground (m/s², standard gravity along -Y)
GRAVITY = np.array([0.0, -9.80665, 0.0])
#: ISB axes (X anterior, Y up, Z right) of a frame given by its Plug-in-Gait axes (x anterior, y left, z up):
#: R_isb = R_pig @ _PIG_TO_ISB
_PIG_TO_ISB = GROUND_FROM_INTERNAL.T

#: marker name (without side letter) -> segment kind; pelvis markers keep their full names
MARKER_BODIES = {
    "pelvis": ("RASI", "LASI", "RPSI", "LPSI", "SACR", "SYMP"),
    "femur": ("THI", "KNE", "KNEM", "THIP", "THIA", "TRO", "MFC"),
    "tibia": ("TIB", "ANK", "ANKM", "TIBM1", "TIBM2", "TIBM3", "TTB", "HFB", "MMA"),
    "calcn": ("HEE", "TOE", "D1M", "D5M"),
    "toes": ("HLX",),
}

#: de Leva (1996), males: mass fraction, com from the proximal end (fraction of length),
#: radii of gyration (sagittal, transverse, longitudinal; fraction of length)
DE_LEVA = {
    "pelvis": (0.1117, None, (0.615, 0.551, 0.587)),     # "lower trunk"
    "thigh": (0.1416, 0.4095, (0.329, 0.329, 0.149)),
    "shank": (0.0433, 0.4459, (0.255, 0.249, 0.103)),
    "foot": (0.0137, 0.4415, (0.257, 0.245, 0.124)),
}
#: share of the foot's mass given to talus, calcaneus (+ mid-foot) and toes
FOOT_SPLIT = {"talus": 0.10, "calcn": 0.75, "toes": 0.15}

#: default knee law slopes (m/rad) of (knee_tx anterior, knee_ty proximal, knee_tz lateral) on
#: (flexion, adduction, rotation): the centres of the published ranges the phantoms draw from
#: (femoral roll-back 2-6 mm/rad, tibial sinking 1-3 mm/rad, ab/adduction and rotation coupling)
DEFAULT_KNEE_SLOPES = 1e-3 * np.array([[4.0, 0.0, 0.0], [-2.0, 0.0, 0.0], [0.0, 5.5, -4.0]])


@dataclass(frozen=True)
class SideParameters:
    """One leg's joint parameters, internal frame of the static trial (m, unit vectors; any sense for axes).

    hip : (3,) hip centre; knee : (3,) knee centre; knee_axis : (3,)
    ankle : (3,) ankle centre; ankle_axis : (3,)
    subtalar : (3,) point on the subtalar axis; subtalar_axis : (3,) (anterior-pointing after orientation)
    mtp : (3,) point on the metatarsophalangeal axis; mtp_axis : (3,)
    knee_law : CorrelativeLaw of this side's knee (default: `default_knee_law`); its constant term is the
        knee translation at the standing pose (m; zero when the fused knee centre is the standing one)
    centre_cov : {"hip" | "knee" | "ankle": (3, 3) m²}, the stated covariance of each centre
    axis_sd_deg : {"knee" | "ankle": deg}, the 1-sd angle of each axis; both written to model.json
    patella : `personalize.patellofemoral.PatellaGeometry` (static lab) for a patellofemoral joint, or None (the
        patella then rides on the femur)
    """

    hip: np.ndarray
    knee: np.ndarray
    knee_axis: np.ndarray
    ankle: np.ndarray
    ankle_axis: np.ndarray
    subtalar: np.ndarray
    subtalar_axis: np.ndarray
    mtp: np.ndarray
    mtp_axis: np.ndarray
    knee_law: CorrelativeLaw | None = None
    centre_cov: dict = field(default_factory=dict)
    axis_sd_deg: dict = field(default_factory=dict)
    patella: object = None


@dataclass(frozen=True)
class SubjectParameters:
    """Everything the model builder needs, internal frame of the static trial (X facing, Y left, Z up; m).

    pelvis_origin : (3,), pelvis_rotation : (3, 3) Plug-in-Gait pelvis frame (columns x anterior, y left, z up;
        the builder turns it into the ISB pelvis frame)
    sides : dict 'r'/'l' -> SideParameters
    markers : dict marker name -> (3,) median static position
    mass : kg; height : m
    sources : dict parameter -> provenance text (written to model.json)
    name : model name
    marker_bodies : dict marker name -> body it rides on (from the marker set); None: Plug-in-Gait names
        (`MARKER_BODIES`)
    """

    pelvis_origin: np.ndarray
    pelvis_rotation: np.ndarray
    sides: dict
    markers: dict
    mass: float
    height: float
    sources: dict = field(default_factory=dict)
    name: str = "personalised"
    marker_bodies: dict | None = None


@dataclass(frozen=True)
class PersonalModel:
    """The built model and what it was built from.

    model : kinematics.multibody.model.Model in OpenSim's ground (X forward, Y up, Z right; gravity along -Y)
    standing_q : (n_q,) coordinates of the static pose
    body_frames : dict body -> (origin (3,), rotation (3, 3)), the body's static pose in the INTERNAL frame
        (x_internal = origin + rotation @ x_body; ISB body axes)
    parameters : SubjectParameters (internal frame)
    knee_laws : dict side -> CorrelativeLaw
    G : (3, 3) ground from internal, x_ground = G x_internal (`GROUND_FROM_INTERNAL`); map every marker trial
        of the internal frame by it (`trial_in_ground`) before IK on `model`
    patellar_tracks : side -> `personalize.patellofemoral.PatellarTrack` of the sides with a patellofemoral joint
        (their ``patella_<s>`` body frame is the femur's knee frame at the MRI's patella pose, the frame its mesh is
        written in)
    """

    model: Model
    standing_q: np.ndarray
    body_frames: dict
    parameters: SubjectParameters
    knee_laws: dict
    G: np.ndarray = field(default_factory=lambda: GROUND_FROM_INTERNAL.copy())
    patellar_tracks: dict = field(default_factory=dict)


def trial_in_ground(pm: PersonalModel, trial):
    """A marker trial of the internal frame (`kinematics.io.markers.MarkerTrial`) in the model's ground (x' = G x)."""
    return replace(trial, positions=np.asarray(trial.positions, float) @ np.asarray(pm.G, float).T)


def default_knee_law(side: str) -> CorrelativeLaw:
    """The generic knee law (`DEFAULT_KNEE_SLOPES`), zero translation at zero angles (the standing pose)."""
    return CorrelativeLaw(
        joint=f"knee_{side}",
        independent=tuple(sided(c, side) for c in KNEE_ROTATIONS),
        dependent=tuple(sided(c, side) for c in KNEE_TRANSLATIONS),
        coefficients=np.column_stack([DEFAULT_KNEE_SLOPES, np.zeros(3)]),
        independent_units=("rad",) * 3, dependent_units=("m",) * 3,
    )


def _body_of_marker(name: str, sides, marker_bodies: dict | None = None) -> str | None:
    """The body marker `name` rides on: `marker_bodies` (`SubjectParameters.marker_bodies`) when given, else the
    Plug-in-Gait name table `MARKER_BODIES`; None: not placed on the model."""
    if marker_bodies is not None:
        return marker_bodies.get(name)
    if name in MARKER_BODIES["pelvis"]:
        return "pelvis"
    s = name[:1].lower()
    if s not in sides:
        return None
    for kind in ("femur", "tibia", "calcn", "toes"):
        if name[1:] in MARKER_BODIES[kind]:
            return f"{kind}_{s}"
    return None


def _inertia(mass: float, length: float, radii) -> np.ndarray:
    """Principal inertia (kg m²) in ISB body axes: X anterior (transverse), Y long, Z medio-lateral (sagittal)."""
    r_sag, r_tr, r_long = radii
    return mass * length**2 * np.diag([r_tr**2, r_long**2, r_sag**2])


def build_personal_model(p: SubjectParameters) -> PersonalModel:
    """Build the personalised model (see the module docstring).

    Raises
    ------
    InputError
        Degenerate geometry (coincident centres, an axis along a bone) or no markers.
    """
    G = GROUND_FROM_INTERNAL
    o_p = np.asarray(p.pelvis_origin, float)
    R_p = np.asarray(p.pelvis_rotation, float) @ _PIG_TO_ISB         # ISB pelvis axes (internal frame)
    frames = {"pelvis": (o_p, R_p)}
    laws = {}
    # gait2392's ground_pelvis: tilt about ground Z, list about X, rotation about Y (body-fixed), then X, Y, Z
    coords = [Coordinate(n, coordinate_def(n).kind, range=coordinate_def(n).range)
              for n in PELVIS_ROTATIONS + PELVIS_TRANSLATIONS]
    joints = [free(GROUND_JOINT, "ground", "pelvis", [c.name for c in coords], sequence="ZXY")]
    length_pelvis = 0.0833 * p.height                       # de Leva lower-trunk length / stature
    bodies = [Body("pelvis", DE_LEVA["pelvis"][0] * p.mass, np.zeros(3),
                   _inertia(DE_LEVA["pelvis"][0] * p.mass, length_pelvis, DE_LEVA["pelvis"][2]))]
    toes_bodies = {_body_of_marker(n, p.sides, p.marker_bodies) for n in p.markers}

    def local(body, x):
        o, R = frames[body]
        return R.T @ (np.asarray(x, float) - o)

    def offset(body, origin, R_joint) -> Transform:
        o, R = frames[body]
        return Transform(R.T @ R_joint, R.T @ (np.asarray(origin, float) - o))

    ax = lambda v, c: TransformAxis(np.asarray(v, float), Linear(), (c,))  # noqa: E731
    knee_frames = {}
    for s, sp in p.sides.items():
        sg = 1.0 if s == "r" else -1.0
        H, K, A = (np.asarray(v, float) for v in (sp.hip, sp.knee, sp.ankle))
        if min(np.linalg.norm(H - K), np.linalg.norm(K - A)) < 0.05:
            raise InputError("model", f"side {s}: hip, knee and ankle centres are closer than 5 cm")
        right = R_p[:, 2]                                   # subject's right (internal frame)
        k_right = unit(sp.knee_axis, where="model") if np.dot(sp.knee_axis, right) > 0 else -unit(sp.knee_axis, where="model")
        a_right = unit(sp.ankle_axis, where="model") if np.dot(sp.ankle_axis, right) > 0 else -unit(sp.ankle_axis, where="model")
        fwd = R_p[:, 0]
        st = unit(sp.subtalar_axis, where="model") if np.dot(sp.subtalar_axis, fwd) > 0 else -unit(sp.subtalar_axis, where="model")
        m_right = unit(sp.mtp_axis, where="model") if np.dot(sp.mtp_axis, right) > 0 else -unit(sp.mtp_axis, where="model")
        R_f = frame_yz(H - K, k_right, where="model")
        R_t = frame_yz(K - A, k_right, where="model")
        sub = np.asarray(sp.subtalar, float)                # the MRI's subtalar centre (as expert models place it)
        frames.update({f"femur_{s}": (K, R_f), f"tibia_{s}": (A, R_t), f"talus_{s}": (A, R_t),
                       f"calcn_{s}": (sub, R_t), f"toes_{s}": (np.asarray(sp.mtp, float), R_t)})
        hc = [sided(c, s) for c in JOINT_COORDINATES["hip"]]
        kc = [sided(c, s) for c in KNEE_ROTATIONS]
        kt = [sided(c, s) for c in KNEE_TRANSLATIONS]
        toes_tracked = f"toes_{s}" in toes_bodies
        # the leg's rotations are clamped to their ranges (IK keeps them inside); the knee translations follow the law
        coords += [Coordinate(n, d.kind, range=d.range, locked=(d.joint == "mtp" and not toes_tracked),
                              clamped=d.kind == "rotational")
                   for n, d in leg_coordinates(s)]
        L_th, L_sh = float(np.linalg.norm(H - K)), float(np.linalg.norm(K - A))
        L_ft = float(np.linalg.norm(np.asarray(sp.mtp, float) - A)) * 1.35   # heel-to-toe ~ 1.35 x ankle-to-mtp
        m_th, m_sh, m_ft = (DE_LEVA[k][0] * p.mass for k in ("thigh", "shank", "foot"))
        bodies += [
            Body(f"femur_{s}", m_th, local(f"femur_{s}", H + DE_LEVA["thigh"][1] * (K - H)), _inertia(m_th, L_th, DE_LEVA["thigh"][2])),
            Body(f"tibia_{s}", m_sh, local(f"tibia_{s}", K + DE_LEVA["shank"][1] * (A - K)), _inertia(m_sh, L_sh, DE_LEVA["shank"][2])),
            Body(f"talus_{s}", FOOT_SPLIT["talus"] * m_ft, np.zeros(3), _inertia(FOOT_SPLIT["talus"] * m_ft, 0.3 * L_ft, DE_LEVA["foot"][2])),
            Body(f"calcn_{s}", FOOT_SPLIT["calcn"] * m_ft, local(f"calcn_{s}", 0.5 * (A + np.asarray(sp.mtp, float))),
                 _inertia(FOOT_SPLIT["calcn"] * m_ft, L_ft, DE_LEVA["foot"][2])),
            Body(f"toes_{s}", FOOT_SPLIT["toes"] * m_ft, np.zeros(3), _inertia(FOOT_SPLIT["toes"] * m_ft, 0.25 * L_ft, DE_LEVA["foot"][2])),
        ]
        # hip: parent frame = pelvis axes, child frame = femur axes at the hip centre, so that the angles are the
        # anatomical (Plug-in-Gait / ISB) ones: zero when the femur frame is aligned with the pelvis frame, and the
        # standing pose has its own hip angles (e.g. flexion = the pelvic tilt of a subject with a vertical femur)
        joints.append(CustomJoint(
            f"hip_{s}", "pelvis", f"femur_{s}", tuple(hc), offset("pelvis", H, R_p), offset(f"femur_{s}", H, R_f),
            rotations=(ax(_Z, hc[0]), ax(sg * _X, hc[1]), ax(sg * _Y, hc[2])), kind_name="custom"))
        # knee: flexion exactly about the fused axis; child frame = the tibia frame, so that the standing angles
        # are the anatomical ones (flexion and varus between the femoral and tibial mechanical axes)
        R_k = frame_zy(k_right, H - K, where="model")
        knee_frames[s] = R_k
        laws[s] = sp.knee_law or default_knee_law(s)
        # the law's standing translation (its constant term; e.g. a fused intercept) moves the tibia's joint point
        # from the femur's, so that the tibia stays at its static pose in the standing pose
        t_st = np.asarray(laws[s].coefficients, float)[:, -1]
        K_tib = K + R_k @ np.array([t_st[0], t_st[1], sg * t_st[2]])
        joints.append(CustomJoint(
            f"knee_{s}", f"femur_{s}", f"tibia_{s}", tuple(kc + kt), offset(f"femur_{s}", K, R_k), offset(f"tibia_{s}", K_tib, R_t),
            rotations=(ax(-_Z, kc[0]), ax(sg * _X, kc[1]), ax(sg * _Y, kc[2])),
            translations=(ax(_X, kt[0]), ax(_Y, kt[1]), ax(sg * _Z, kt[2])), kind_name="custom"))
        joints.append(revolute(f"ankle_{s}", f"tibia_{s}", f"talus_{s}", f"ankle_angle_{s}", axis=R_t.T @ a_right,
                               parent_offset=offset(f"tibia_{s}", A, R_t), child_offset=offset(f"talus_{s}", A, R_t)))
        st_inv = st if s == "r" else -st                    # inversion positive on both sides
        joints.append(revolute(f"subtalar_{s}", f"talus_{s}", f"calcn_{s}", f"subtalar_angle_{s}", axis=R_t.T @ st_inv,
                               parent_offset=offset(f"talus_{s}", sub, R_t), child_offset=offset(f"calcn_{s}", sub, R_t)))
        joints.append(revolute(f"mtp_{s}", f"calcn_{s}", f"toes_{s}", f"mtp_angle_{s}", axis=R_t.T @ m_right,
                               parent_offset=offset(f"calcn_{s}", sp.mtp, R_t), child_offset=offset(f"toes_{s}", sp.mtp, R_t)))
    markers = []
    for n in sorted(p.markers):
        body = _body_of_marker(n, p.sides, p.marker_bodies)
        x = np.asarray(p.markers[n], float)
        if body is None or body not in frames or not np.all(np.isfinite(x)):
            continue
        markers.append(Marker(n, body, local(body, x)))
    if not markers:
        raise InputError("model", "no static marker could be placed on the model")
    base = Model(tuple(bodies), tuple(joints), tuple(coords), tuple(markers), gravity=GRAVITY.copy(), name=p.name)
    knee_q = {}
    for s in p.sides:
        # static knee angles: R_kᵀ R_t = Rz(-flexion) Rx(±adduction) Ry(±rotation), body-fixed
        sg = 1.0 if s == "r" else -1.0
        phi, psi, chi = Rotation.from_matrix(knee_frames[s].T @ frames[f"tibia_{s}"][1]).as_euler("ZXY")
        knee_q[s] = np.array([-phi, sg * psi, sg * chi])
        law = laws[s]
        C = np.array(law.coefficients, float)
        C[:, -1] = C[:, -1] - C[:, :-1] @ knee_q[s]        # the law's constant term is the standing translation
        laws[s] = replace(law, coefficients=C)
    coupling = None
    for s in p.sides:
        c = laws[s].to_coupling(base.coordinate_names)
        coupling = c if coupling is None else coupling.stack(c)
    tracks = {s: t for s, sp in p.sides.items() if sp.patella is not None
              and (t := _patellar_track(base, s, sp, knee_frames[s], laws[s], knee_q[s], frames)) is not None}
    if tracks:
        base, coupling = _with_patellae(base, coupling, tracks, knee_frames, p, offset)
        frames.update({f"patella_{s}": (np.asarray(p.sides[s].knee, float), knee_frames[s]) for s in tracks})
    model = base.with_couplings(coupling.over(base.coordinate_names)) if coupling is not None else base
    q0 = np.zeros(model.n_q)
    ix = model.coordinate_index
    # the pelvis' static pose in ground: G R_p = Rz(tilt) Rx(list) Ry(rotation), origin G o_p
    q0[[ix(n) for n in PELVIS_ROTATIONS]] = Rotation.from_matrix(G @ R_p).as_euler("ZXY")
    q0[[ix(n) for n in PELVIS_TRANSLATIONS]] = G @ o_p
    for s in p.sides:
        # static hip angles: R_pᵀ R_f = Rz(flexion) Rx(±adduction) Ry(±rotation), body-fixed
        sg = 1.0 if s == "r" else -1.0
        R_f = frames[f"femur_{s}"][1]
        phi, psi, chi = Rotation.from_matrix(R_p.T @ R_f).as_euler("ZXY")
        q0[[ix(sided(c, s)) for c in JOINT_COORDINATES["hip"]]] = (phi, sg * psi, sg * chi)
        q0[[ix(sided(c, s)) for c in KNEE_ROTATIONS]] = knee_q[s]
        law = laws[s]
        q0[[ix(n) for n in law.dependent]] = law.predict(knee_q[s][None])[0]
        if s in tracks:
            q0[ix(f"{sided('knee_flexion', s)}_beta")] = knee_q[s][0]
    # default pose = static pose (IK's cold start and OpenSim's default state)
    coords_def = tuple(Coordinate(c.name, c.kind, float(q0[i]), c.range, c.locked, c.clamped)
                       for i, c in enumerate(model.coordinates))
    model = model.replace(coordinates=coords_def)
    return PersonalModel(model, q0, frames, p, laws, G.copy(), tracks)


#: kg, the patella body's mass (Rajagopal et al. 2016's patella: about 0.1 kg); inertia of a 45 x 45 x 22 mm box
PATELLA_MASS = 0.1


def _patellar_track(base: Model, s: str, sp: SideParameters, R_k: np.ndarray, law, knee_q: np.ndarray, frames: dict):
    """`personalize.patellofemoral.patellar_track` of side `s` on the model's knee: the tibial tuberosity moved
    by the knee joint (flexion swept, adduction and rotation at their standing values, translations by `law`)."""
    from .patellofemoral import patellar_track

    geo = sp.patella
    K = np.asarray(sp.knee, float)
    jt = base.joint(f"knee_{s}")
    o_t, R_t = frames[f"tibia_{s}"]
    tt_body = R_t.T @ (np.asarray(geo.tuberosity_on_tibia, float) - o_t)
    tt_m = jt.child_offset.inverse().apply(tt_body)

    def tuberosity_at(q: float) -> np.ndarray:
        ang = np.array([q, knee_q[1], knee_q[2]])
        R, t = jt.transform(np.concatenate([ang, law.predict(ang[None])[0]])[None])
        return R[0] @ tt_m + t[0]

    return patellar_track(geo, (K, R_k), tuberosity_at, start_deg=float(np.degrees(knee_q[0])))


def _with_patellae(base: Model, coupling, tracks: dict, knee_frames: dict, p, offset):
    """`base` with, per side in `tracks`, a patella body on a CustomJoint ``patellofemoral_<s>`` from the femur
    whose coordinate ``knee_flexion_<s>_beta`` equals knee flexion (one coupling row): rotation about the knee
    frame's Z and the joint frame's x, y translation, SimmSplines of it (`personalize.patellofemoral`)."""
    from kinematics.multibody.coupling import LinearCoupling
    from kinematics.multibody.functions import SimmSpline

    bodies, joints, coords = list(base.bodies), list(base.joints), list(base.coordinates)
    for s, tr in tracks.items():
        K = np.asarray(p.sides[s].knee, float)
        flex = sided("knee_flexion", s)
        beta = f"{flex}_beta"
        box = np.array([0.045, 0.045, 0.022])
        inertia = PATELLA_MASS / 12.0 * np.diag([box[1] ** 2 + box[2] ** 2, box[0] ** 2 + box[2] ** 2,
                                                box[0] ** 2 + box[1] ** 2])
        bodies.append(Body(f"patella_{s}", PATELLA_MASS, np.asarray(tr.centre, float), inertia))
        spline = lambda y: SimmSpline(tr.flexion, y)            # noqa: E731
        joints.append(CustomJoint(
            f"patellofemoral_{s}", f"femur_{s}", f"patella_{s}", (beta,), offset(f"femur_{s}", K, knee_frames[s]),
            Transform(), rotations=(TransformAxis(_Z, spline(tr.rotation), (beta,)),),
            translations=(TransformAxis(_X, spline(tr.translation[:, 0]), (beta,)),
                          TransformAxis(_Y, spline(tr.translation[:, 1]), (beta,))), kind_name="custom"))
        d = coordinate_def("knee_flexion")
        coords.append(Coordinate(beta, "rotational", range=d.range))
        row = LinearCoupling((beta, flex), np.array([[1.0, -1.0]]), np.zeros(1), (beta,))
        coupling = row if coupling is None else coupling.stack(row)
    return base.replace(bodies=tuple(bodies), joints=tuple(joints), coordinates=tuple(coords)), coupling


# --------------------------------------------------------------------------- export
#: default face budget of each exported bone mesh (``personalize run --full-meshes`` keeps them whole): a 1 mm
#: MRI femur has ~0.5 M faces; 20,000 keep its shape within a fraction of the voxel (`MeshFile` states the error)
MODEL_MESH_MAX_FACES = 20_000
#: surface samples of the decimation error (each way)
_ERROR_SAMPLES = 20_000


@dataclass(frozen=True)
class MeshFile:
    """One bone mesh written for the model (binary STL, metres, in its body's frame).

    body : body it is attached to; file : path relative to the model file (``meshes/<bone>.stl``)
    faces : faces written; source_faces : faces of the bone surface it was made from
    hausdorff_mm : symmetric Hausdorff distance between the written and the source surface (mm; every source vertex
        to the written surface and `_ERROR_SAMPLES` surface samples each way); 0 when written whole
    mean_mm : mean absolute surface distance, both ways (mm); watertight : (source, written) watertightness
    source : where the surface came from (the subject's label volume or mesh folder, and the bone)
    """

    body: str
    file: str
    faces: int
    source_faces: int
    hausdorff_mm: float = 0.0
    mean_mm: float = 0.0
    watertight: tuple[bool, bool] = (True, True)
    source: str = ""

    @property
    def decimated(self) -> bool:
        return self.faces < self.source_faces

    def to_json(self) -> dict:
        return {"body": self.body, "file": self.file, "units": "m", "frame": f"body {self.body} (ISB axes)",
                "faces": self.faces, "source_faces": self.source_faces, "decimated": self.decimated,
                "decimation": "quadric edge collapse (pymeshlab), topology kept" if self.decimated else "none",
                "hausdorff_mm": self.hausdorff_mm, "mean_distance_mm": self.mean_mm,
                "watertight": {"source": self.watertight[0], "written": self.watertight[1]}, "source": self.source}


def decimation_error(source, written) -> tuple[float, float]:
    """(Hausdorff, mean) distance between two surfaces in mm (meshes in metres).

    The Hausdorff distance is the largest of every `source` vertex's distance to `written` and the sampled
    distances both ways (`personalize.surfaces.surface_distance`); the mean is that function's two-way mean.
    """
    import igl

    from .surfaces import surface_distance

    d = surface_distance(written, source, n=_ERROR_SAMPLES, seed=0)
    dv = np.sqrt(igl.point_mesh_squared_distance(np.asarray(source.vertices, float), np.asarray(written.vertices, float),
                                                 np.asarray(written.faces, np.int64))[0])
    return 1e3 * max(d["max"], float(dv.max())), 1e3 * d["mean"]


def write_meshes(pm: PersonalModel, meshes: dict, folder: Path, *, max_faces: int | None = MODEL_MESH_MAX_FACES,
                 source: str = "") -> dict:
    """Write bone meshes in their body frames as binary STL (metres) into `folder`, decimated to `max_faces`.

    meshes : dict bone name -> (trimesh.Trimesh in the internal frame of the static trial, m; body name)
    max_faces : face budget per bone (quadric edge collapse, `personalize.surfaces.extraction.decimate` without
        planar quadrics, topology kept); None: written whole
    source : where the surfaces came from (stated in model.json and the .osim's credits)

    Returns dict bone -> `MeshFile` (the decimation's measured error included).
    """
    from lowerlimb.atomic import atomic_path, inside

    from .surfaces.extraction import decimate

    out = {}
    for bone, (mesh, body) in sorted(meshes.items()):
        if body not in pm.body_frames:
            continue
        o, R = pm.body_frames[body]
        m = mesh.copy()
        T = np.eye(4)
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ o
        m.apply_transform(T)
        n_src = len(m.faces)
        h_mm = mean_mm = 0.0
        tight = bool(m.is_watertight)
        if max_faces is not None and n_src > max_faces:
            full = m
            m = decimate(full, int(max_faces), planar_quadric=False)     # curvature-led: 5x smaller error
            h_mm, mean_mm = decimation_error(full, m)
        path = inside(folder, f"{bone}.stl")
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            data = m.export(file_type="stl")
            # the binary STL header (80 bytes) states units, frame and decimation
            what = f"{len(m.faces)}/{n_src} faces, Hausdorff {h_mm:.2f} mm" if len(m.faces) < n_src else "full"
            head = f"m; body {body} frame; {bone} {what}; personalize".encode()[:80].ljust(80, b" ")
            tmp.write_bytes(head + data[80:])
        out[bone] = MeshFile(body, f"{folder.name}/{bone}.stl", len(m.faces), n_src, h_mm, mean_mm,
                             (tight, bool(m.is_watertight)), f"{source}: {bone}" if source else bone)
    return out


def model_credits(pm: PersonalModel, mesh_files: dict | None = None) -> str:
    """The .osim's ``credits``: what made the model, from what, in which units and frames."""
    from . import __version__

    files = list((mesh_files or {}).values())
    text = (f"Subject-specific lower-limb model '{pm.model.name}' built by personalize {__version__} from the "
            "subject's MRI bone surfaces and motion capture (joint centres and axes fused from both; de Leva 1996 "
            "mass properties). Units: m, kg, N, rad. Ground: X the static pose's facing, Y up, Z right; ISB body "
            "frames (X anterior, Y superior, Z right).")
    if files:
        dec = [f for f in files if f.decimated]
        src = sorted({f.source.rsplit(": ", 1)[0] for f in files if ": " in f.source})
        text += (f" Bone meshes: binary STL in metres, each in its body's frame, from {', '.join(src) or 'the bone surfaces'}; ")
        if dec:
            text += (f"{len(dec)} of {len(files)} decimated by quadric edge collapse to at most "
                     f"{max(f.faces for f in dec)} faces (largest Hausdorff distance to the source surface "
                     f"{max(f.hausdorff_mm for f in dec):.2f} mm; per bone in model.json).")
        else:
            text += "full resolution."
    return text


def save_model_osim(pm: PersonalModel, path: Path, mesh_files: dict | None = None, extend=None) -> Path:
    """Export to OpenSim (``kinematics.io.opensim_io.to_opensim``) with the bone meshes attached to their bodies.

    mesh_files : bone -> `MeshFile` (`write_meshes`); the model states its units (``length_units`` meters,
    ``force_units`` N) and, in ``credits``, its source, frames and the meshes' decimation (`model_credits`).
    extend : callable(opensim.Model) run on the finalised model before it is written (the muscles,
        `personalize.muscles.personalise_muscles`), or None
    """
    import os

    from lowerlimb.atomic import atomic_path
    from kinematics.io.opensim_io import to_opensim

    om = to_opensim(pm.model)
    import opensim as osim

    for bone, mf in (mesh_files or {}).items():
        b = om.updBodySet().get(mf.body)
        g = osim.Mesh(mf.file)
        g.setName(f"{bone}_geometry")
        b.attachGeometry(g)
    om.set_length_units("meters")
    om.set_force_units("N")
    om.set_credits(model_credits(pm, mesh_files))
    om.finalizeConnections()
    if extend is not None:
        extend(om)
    with atomic_path(path) as tmp:
        if not om.printToXML(os.fspath(tmp)):
            raise InputError(path, "OpenSim could not write the model")
    return Path(path)


def model_json(pm: PersonalModel, mesh_files: dict | None = None) -> dict:
    """JSON description of the model (SI units, frames stated)."""
    m = pm.model
    G = np.asarray(pm.G, float)
    bodies = []
    for b in m.bodies[1:]:
        o, R = pm.body_frames[b.name]
        bodies.append({"name": b.name, "mass": b.mass, "com": b.com.tolist(), "inertia": b.inertia.tolist(),
                       "static_origin": (G @ o).tolist(), "static_rotation": (G @ R).tolist(),
                       "meshes": [mf.file for bone, mf in sorted((mesh_files or {}).items()) if mf.body == b.name]})
    joints = []
    for j in m.joints:
        joints.append({"name": j.name, "type": j.kind_name if hasattr(j, "kind_name") else j.kind,
                       "parent": j.parent, "child": j.child, "coordinates": list(j.coordinates),
                       "parent_offset": {"rotation": j.parent_offset.rotation.tolist(), "translation": j.parent_offset.translation.tolist()},
                       "child_offset": {"rotation": j.child_offset.rotation.tolist(), "translation": j.child_offset.translation.tolist()},
                       "rotation_axes": [a.axis.tolist() for a in getattr(j, "rotations", ())],
                       "translation_axes": [a.axis.tolist() for a in getattr(j, "translations", ())]})
    return {
        "units": "m, kg, kg m^2, rad",
        "frame": "OpenSim ground (X = the static pose's facing direction, Y up, Z right; gravity along -Y); "
                 "ISB body frames (X anterior, Y superior, Z right); body offsets in body frames; static_origin and "
                 "static_rotation: each body's pose in ground at the standing pose",
        "ground_from_internal": G.tolist(),
        "internal_frame": "the static trial's internal frame (X facing, Y left, Z up) of summary.json and "
                          "'uncertainty': x_ground = ground_from_internal @ x_internal",
        "gravity": m.gravity.tolist(),
        "name": m.name,
        "mass_properties": "de Leva (1996) male segment fractions scaled by the subject's mass and segment lengths",
        "bodies": bodies, "joints": joints,
        "coordinates": [{"name": c.name, "kind": c.kind, "default": c.default, "range": list(c.range), "locked": c.locked}
                        for c in m.coordinates],
        "markers": [{"name": mk.name, "body": mk.body, "offset": mk.offset.tolist()} for mk in m.markers],
        "mesh_files": {bone: mf.to_json() for bone, mf in sorted((mesh_files or {}).items())},
        "knee_laws": {s: law.to_json() for s, law in pm.knee_laws.items()},
        "patellofemoral": {s: {**t.to_json(), "joint": f"patellofemoral_{s}", "coordinate": f"knee_flexion_{s}_beta",
                               "note": "patella_<s>'s static_origin / static_rotation: the knee frame, its mesh's "
                                       "frame (the MRI patella pose); the joint moves it with knee flexion"}
                           for s, t in pm.patellar_tracks.items()},
        "uncertainty": _uncertainty_json(pm.parameters),
        "sources": pm.parameters.sources,
        "standing_q": dict(zip(m.coordinate_names, pm.standing_q.tolist())),
    }


def _uncertainty_json(p: SubjectParameters) -> dict:
    """The joint parameters the model was built from with their stated uncertainty (internal frame)."""
    joints = {}
    for s, sp in p.sides.items():
        for j in ("hip", "knee", "ankle"):
            e = {"centre": np.asarray(getattr(sp, j), float).tolist()}
            if j in sp.centre_cov:
                e["centre_cov"] = np.asarray(sp.centre_cov[j], float).tolist()
            if j != "hip":
                e["axis"] = np.asarray(getattr(sp, f"{j}_axis"), float).tolist()
                if j in sp.axis_sd_deg:
                    e["axis_sd_deg"] = float(sp.axis_sd_deg[j])
            joints[f"{j}_{s}"] = e
    return {"units": "centre m, centre_cov m^2, axis unit vector, axis_sd_deg deg",
            "frame": "internal frame of the static trial (X facing, Y left, Z up; x_ground = ground_from_internal "
                     "@ x_internal)", "joints": joints}


def save_model_json(pm: PersonalModel, path: Path, mesh_files: dict | None = None) -> Path:
    from lowerlimb.atomic import write_text

    return write_text(path, json.dumps(model_json(pm, mesh_files), indent=1) + "\n")
