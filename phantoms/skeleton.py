"""The phantom's skeleton as an engine `Model`, with exactly known anatomical frames.

Lab frame (every trial of the motion phantoms): X forward (walking
direction), Y to the subject's left, Z up, metres.  The phantom's body frame
(X anterior, Y superior, Z right; `phantoms.anatomy`) maps to it by the
constant rotation `LAB_FROM_BODY`.

Bodies (one per segment, both sides): ``pelvis`` (free joint to the ground),
``femur_r`` (hip: 3 rotations about the femoral head centre), ``tibia_r``
(knee: 3 rotations and 3 translations, the translations a known linear law of
the rotations, see `knee_law`), ``talus_r`` (ankle: revolute about the true
talocrural axis), ``calcn_r`` (subtalar: revolute about the true subtalar
axis), same on the left.  The fibula is rigid with the tibia, the toes with
the calcaneus.

Each body frame of pelvis, femur and tibia IS its anatomical frame in the
Plug-in-Gait convention (x anterior, y left, z proximal):

* pelvis: origin mid-ASIS, y = LASI - RASI, x towards the ASIS from the PSIS
  mid-point (from the STA-free marker sites, as Plug-in-Gait would see them);
* femur: origin knee centre K, z = unit(H - K) (H femoral head centre),
  y = the knee axis (pointing left) made orthogonal to z;
* tibia: origin ankle centre A (talar dome centre), z = unit(K - A), y the
  knee axis made orthogonal to z (Plug-in-Gait's "untorsioned" tibia).

and the hip and knee rotations are the Plug-in-Gait Y-X'-Z'' Cardan angles
(``kinematics.gait.pig.joint_angles``) of these frames, signed as Nexus reports
them: ``hip_flexion_r`` etc. ARE the true Plug-in-Gait hip/knee angles.
The true ankle angles use the torsioned tibia (y along the true ankle axis)
and a calcaneus-fixed foot frame (z from the toe to the heel marker sites).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.mechanisms.correlative import CorrelativeLaw
from kinematics.algorithms.fk import forward_kinematics, point_positions
from kinematics.multibody.joints import CustomJoint, Transform, TransformAxis, free, revolute
from kinematics.multibody.functions import Linear
from kinematics.multibody.model import Body, Coordinate, Marker, Model
from kinematics.gait.pig import SegmentPose, joint_angles, pelvis_frame
from kinematics.gait.soft_tissue import draw_thickness
from kinematics.gait.subject import SubjectMeasurements
from lowerlimb.geometry import DEFAULT_MARKER_DIAMETER, DEFAULT_MARKER_RADIUS, frame_zy, unit
from lowerlimb.topology import (JOINT_COORDINATES, KNEE_ROTATIONS, KNEE_TRANSLATIONS, PELVIS_TRANSLATIONS, coordinate_def,
                                leg_coordinates, sided)

__all__ = ["LAB_FROM_BODY", "Site", "PhantomSkeleton", "phantom_skeleton", "pelvis_tissue_thickness", "pelvis_skin_sites", "SIDES",
           "PIG_MARKERS", "EXTRA_MARKERS", "DEVICE_MARKERS"]

#: body frame (X anterior, Y superior, Z right) -> lab frame (X forward, Y left, Z up)
LAB_FROM_BODY = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
SIDES = ("r", "l")
#: Plug-in-Gait lower-body markers (right; left twins start with L)
PIG_MARKERS = ("ASI", "PSI", "THI", "KNE", "TIB", "ANK", "HEE", "TOE")
#: optional markers: medial knee and ankle, thigh cluster (wand) markers
EXTRA_MARKERS = ("KNEM", "ANKM", "THIP", "THIA")
#: the seed's validation device: two markers on a tibia-fixed bow and one skin marker (distal medial tibia)
DEVICE_MARKERS = ("TIBM1", "TIBM2", "TIBM3")

_X, _Y, _Z = np.eye(3)


def _ortho(v, z):
    """Unit component of v orthogonal to unit z."""
    return unit(v - np.dot(v, z) * z)


@dataclass(frozen=True)
class Site:
    """A point fixed on a body: ``offset`` (3,) m in the body frame."""

    body: str
    offset: np.ndarray


@dataclass(frozen=True)
class PhantomSkeleton:
    """The phantom skeleton: model, standing pose, anatomy and knee laws (immutable).

    Attributes
    ----------
    model : kinematics.multibody.model.Model
        Bodies, joints, 28 coordinates, the STA-free marker sites as markers,
        and the knee laws as linear couplings.
    standing_q : ndarray (n_q,)
        Coordinates of the constructed (standing) pose, pelvis at its lab position.
    sites : dict marker name -> Site
        STA-free marker centres (bone landmark + soft tissue + marker radius).
    skin_normals : dict marker name -> (3,) outward unit normal in the body frame
    centres : dict ``hip_r``/``knee_r``/``ankle_r``... -> Site (true joint centres)
    frame_offsets : dict ``tibia_torsioned_r``, ``foot_r`` -> (body, R (3,3), origin (3,))
        Anatomical frames not equal to a body frame (axes in the body frame).
    knee_laws : dict side -> CorrelativeLaw
        Translations (knee_tx anterior, knee_ty proximal, knee_tz lateral; metres,
        femur frame) as linear functions of (knee_flexion, knee_adduction, knee_rotation) (rad).
    subject : SubjectMeasurements
        What a gait lab would measure on this subject (tape and calliper on the skin).
    tibial_torsion : dict side -> rad, in Plug-in-Gait's convention (`kinematics.gait.pig.tibia_frame`).
    tissue_thickness : dict site (``ASI``, ``PSI``, ``KNE``...) -> m, this subject's skin-to-bone distance
        under the marker (pelvis: drawn around `kinematics.gait.soft_tissue`, along the bone's outward normal).
    """

    model: Model
    standing_q: np.ndarray
    sites: dict
    skin_normals: dict
    centres: dict
    frame_offsets: dict
    knee_laws: dict
    subject: SubjectMeasurements
    tibial_torsion: dict
    seed: int = 0
    tissue_thickness: dict = field(default_factory=dict)
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    # ---------------------------------------------------------------- coordinates
    @property
    def coordinate_names(self) -> tuple[str, ...]:
        return self.model.coordinate_names

    def complete(self, q: np.ndarray) -> np.ndarray:
        """Copy of q (N, n_q) with the knee translations set by the knee laws."""
        q = np.array(q, float, copy=True)
        idx = self.model.coordinate_index
        for s, law in self.knee_laws.items():
            a = q[:, [idx(n) for n in law.independent]]
            q[:, [idx(n) for n in law.dependent]] = law.predict(a)
        return q

    # ---------------------------------------------------------------- evaluation
    def state(self, q):
        return forward_kinematics(self.model, np.atleast_2d(q))

    def sites_lab(self, state, names) -> np.ndarray:
        """Lab positions (N, M, 3) of the STA-free sites `names`."""
        b = np.array([self.model.body_index(self.sites[n].body) for n in names], int)
        o = np.array([self.sites[n].offset for n in names])
        return point_positions(self.model, state, b, o)

    def centres_lab(self, state) -> dict:
        """True joint centres: name -> (N, 3) m."""
        out = {}
        for k, s in self.centres.items():
            out[k] = point_positions(self.model, state, np.array([self.model.body_index(s.body)]), s.offset[None])[:, 0]
        return out

    def segment_poses(self, state) -> dict:
        """True anatomical frames (Plug-in-Gait convention) as `SegmentPose`: pelvis, femur_r, tibia_r
        (untorsioned), tibia_torsioned_r, foot_r, ..., plus raw body poses talus_r, calcn_r."""
        m = self.model
        out = {}
        for name in m.body_names[1:]:
            b = m.body_index(name)
            out[name] = SegmentPose(state.positions[:, b], state.rotations[:, b])
        for name, (body, R, o) in self.frame_offsets.items():
            b = m.body_index(body)
            Rw = state.rotations[:, b]
            out[name] = SegmentPose(state.positions[:, b] + Rw @ o, Rw @ R)
        return out

    def angles(self, state) -> dict:
        """True Plug-in-Gait joint angles (rad): ``hip_r``, ``knee_r``, ``ankle_r``, ... -> (N, 3)."""
        seg = self.segment_poses(state)
        out = {}
        for s in SIDES:
            S = s.upper()
            out[f"hip_{s}"] = joint_angles(seg["pelvis"], seg[f"femur_{s}"], "hip", S)
            out[f"knee_{s}"] = joint_angles(seg[f"femur_{s}"], seg[f"tibia_{s}"], "knee", S)
            out[f"ankle_{s}"] = joint_angles(seg[f"tibia_torsioned_{s}"], seg[f"foot_{s}"], "ankle", S)
        return out


# --------------------------------------------------------------------------- construction
def _knee_law(side: str, rng: np.random.Generator, standing: np.ndarray) -> CorrelativeLaw:
    """A plausible knee law: slopes (m/rad) drawn within published ranges.

    * knee_tx (anterior translation of the tibia under the femur): femoral
      roll-back of the knee centre (mid-condyles) of about 8-17 mm over 0-120 deg
      of weight-bearing flexion, i.e. 4-8 mm/rad (Johal et al. 2005, J Biomech
      38:269, MRI squat: lateral condyle ~20 mm, medial a few mm; Moro-oka et al.
      2008, J Orthop Res 26:428; Qi et al. 2013, J Biomech 46:1576), plus the
      lateral-condyle roll-back that comes with tibial internal rotation
      (a few mm per 10 deg, signs either way across knees: -4..4 mm/rad);
    * knee_ty (proximal): the tibia sinks slightly with flexion (1-3 mm/rad);
    * knee_tz (lateral): ab/adduction lifts a condyle and shifts the centre
      medio-laterally by a few mm per radian (condylar lift-off), rotation
      likewise.

    The constant term makes the translations zero standing.
    """
    u = rng.uniform
    slopes = 1e-3 * np.array([
        [u(4.0, 8.0), u(-3.0, 3.0), u(-4.0, 4.0)],    # knee_tx (anterior)
        [u(-3.0, -1.0), u(-2.0, 2.0), u(-2.0, 2.0)],  # knee_ty (proximal)
        [u(-2.0, 2.0), u(3.0, 8.0), u(-6.0, -2.0)],   # knee_tz (lateral)
    ])
    c0 = -slopes @ standing
    return CorrelativeLaw(
        joint=f"knee_{side}",
        independent=tuple(sided(c, side) for c in KNEE_ROTATIONS),
        dependent=tuple(sided(c, side) for c in KNEE_TRANSLATIONS),
        coefficients=np.column_stack([slopes, c0]),
        independent_units=("rad",) * 3, dependent_units=("m",) * 3,
    )


def _pose_frame(origin, z, y_hint) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(origin, float), frame_zy(z, y_hint)


def _sdf_normal_body(ph, bone: str, p_body: np.ndarray, h: float = 2e-4) -> np.ndarray:
    """Outward unit normal (body frame) of `bone` at `p_body`: the phantom SDF's central-difference gradient."""
    A = np.asarray(ph.placement, float)
    ps = A[:3, :3] @ p_body + A[:3, 3]
    E = h * np.eye(3)
    g = (ph.sdf(bone, ps + E) - ph.sdf(bone, ps - E)) / (2 * h)
    return unit(A[:3, :3].T @ g)


def pelvis_tissue_thickness(seed: int) -> dict:
    """The subject's soft tissue (m) over the ASIS and PSIS (``{"ASI": t, "PSI": t}``, both sides share it).

    Drawn around the population table (`kinematics.gait.soft_tissue.draw_thickness`) from the stream
    ``default_rng([seed, 7])``: the same numbers for the markers (`phantom_skeleton`) and for the
    skin envelope of the label volume (`phantoms.imaging.label_volume`).
    """
    rng_t = np.random.default_rng([int(seed), 7])
    return {site: draw_thickness(rng_t, site) for site in ("ASI", "PSI")}


def pelvis_skin_sites(ph, seed: int) -> dict:
    """Scanner-frame pelvic marker sites of `ph`: name -> (bony landmark (3,), outward unit normal (3,), thickness).

    The landmark is the phantom's exact RASI/LASI/RPSI/LPSI, the normal the pelvis SDF's gradient there
    (as `phantom_skeleton` places the markers), the thickness `pelvis_tissue_thickness(seed)` (m).
    """
    A = np.asarray(ph.placement, float)
    plm = ph.body_truth()["bones"]["pelvis"]["landmarks"]
    t = pelvis_tissue_thickness(seed)
    out = {}
    for S in ("R", "L"):
        for site in ("ASI", "PSI"):
            p_body = np.asarray(plm[f"{S}{site}"], float)
            out[f"{S}{site}"] = (A[:3, :3] @ p_body + A[:3, 3], A[:3, :3] @ _sdf_normal_body(ph, "pelvis", p_body), t[site])
    return out


def phantom_skeleton(ph, seed: int | None = None) -> PhantomSkeleton:
    """Build the skeleton model of a `phantoms.anatomy.Phantom` (both legs needed).

    Parameters
    ----------
    ph : Phantom
    seed : int, optional
        Seeds the knee-law coefficients (default: the phantom's seed).

    Returns
    -------
    PhantomSkeleton
    """
    from lowerlimb.errors import InputError

    if "femur_r" not in ph.bone_names or "femur_l" not in ph.bone_names:
        raise InputError("phantom", "the motion phantoms need both legs (make_phantom(side='both'))")
    seed = ph.seed if seed is None else int(seed)
    rng = np.random.default_rng([seed, 2])
    bt = ph.body_truth()["bones"]
    L = LAB_FROM_BODY
    lab = lambda p: L @ np.asarray(p, float)  # noqa: E731
    s_ = ph.params.stature / 1.75
    r = DEFAULT_MARKER_RADIUS

    # ---- anatomical points and axes in the lab at the standing pose (pelvis at its built position)
    plm = bt["pelvis"]["landmarks"]
    normals = {}           # lab outward normals of skin sites
    body_of = {}
    tissue = {"ASI": 0.006, "PSI": 0.008, "KNE": 0.005, "KNEM": 0.005, "ANK": 0.003, "ANKM": 0.003,
              "HEE": 0.006, "TOE": 0.003}
    sites_lab: dict[str, np.ndarray] = {}
    skin_lab: dict[str, np.ndarray] = {}

    def put(name, body, landmark, normal, t):
        n = unit(normal)
        skin_lab[name] = landmark + t * n
        sites_lab[name] = landmark + (t + r) * n
        normals[name] = n
        body_of[name] = body

    # Pelvis markers: soft tissue measured along the bone's outward normal (as CT/MRI/ultrasound measure it),
    # one thickness per site and subject drawn around the population table (kinematics.gait.soft_tissue; both
    # sides share it), from its own stream so the knee laws do not change with it.
    tissue.update(pelvis_tissue_thickness(seed))
    for S in ("R", "L"):
        for site in ("ASI", "PSI"):
            p_body = np.asarray(plm[f"{S}{site}"], float)
            put(f"{S}{site}", "pelvis", lab(p_body), lab(_sdf_normal_body(ph, "pelvis", p_body)), tissue[site])
    joints = {}
    for s in SIDES:
        S = s.upper()
        lat = -_Y if s == "r" else _Y                 # lateral direction in the lab (standing)
        f, t, fi, ta, ca = (bt[f"{b}_{s}"] for b in ("femur", "tibia", "fibula", "talus", "calcn"))
        H = lab(f["landmarks"]["femoral_head_centre"])
        K = lab(f["landmarks"]["intercondylar_midpoint"])
        A = lab(ta["landmarks"]["talar_dome_centre"])
        k_ax = unit(lab(f["axes"]["knee_axis"][1]))
        k_lat = k_ax if k_ax @ lat > 0 else -k_ax
        a_ax = unit(lab(ta["axes"]["ankle_axis"][1]))
        a_lat = a_ax if a_ax @ lat > 0 else -a_ax
        st_p, st_d = ta["axes"]["subtalar_axis"]
        st_p, st_d = lab(st_p), unit(lab(st_d))
        if st_d @ _X < 0:
            st_d = -st_d
        Sub = st_p + np.dot(A - st_p, st_d) * st_d
        joints[s] = dict(H=H, K=K, A=A, k_lat=k_lat, a_lat=a_lat, st_d=st_d, Sub=Sub)
        # knee markers on the epicondyles at the flexion axis (Plug-in-Gait: "on the flexion axis")
        on_kaxis = lambda p: K + np.dot(p - K, k_lat) * k_lat  # noqa: E731
        put(f"{S}KNE", f"femur_{s}", on_kaxis(lab(f["landmarks"][f"{S}KNE"])), k_lat, tissue["KNE"])
        put(f"{S}KNEM", f"femur_{s}", on_kaxis(lab(f["landmarks"][f"{S}MFC"])), -k_lat, tissue["KNEM"])
        # malleolar markers on the transmalleolar (ankle) axis, the Plug-in-Gait placement
        on_axis = lambda p: A + np.dot(p - A, a_lat) * a_lat  # noqa: E731
        put(f"{S}ANK", f"tibia_{s}", on_axis(lab(fi["landmarks"][f"{S}ANK"])), a_lat, tissue["ANK"])
        put(f"{S}ANKM", f"tibia_{s}", on_axis(lab(t["landmarks"][f"{S}MMA"])), -a_lat, tissue["ANKM"])
        hee = lab(ca["landmarks"][f"{S}HEE"])
        toe_b = 0.5 * (lab(ca["landmarks"][f"{S}D1M"]) + lab(ca["landmarks"][f"{S}D5M"]))
        put(f"{S}HEE", f"calcn_{s}", hee, unit(hee - toe_b) * np.array([1, 1, 0]), tissue["HEE"])
        put(f"{S}TOE", f"calcn_{s}", toe_b, _Z, tissue["TOE"])
        # femur frame axes (standing) for wand placement
        zf = unit(H - K)
        yl = _ortho(k_lat, zf)                         # lateral, orthogonal to the femur axis
        left = -k_lat if s == "r" else k_lat
        xf = unit(np.cross(_ortho(left, zf), zf))     # anterior
        # THI: lower third of the thigh, in the plane of hip, knee and knee axis (Plug-in-Gait placement)
        for name, frac, rad in ((f"{S}THI", 0.33, 0.062),):
            base = K + frac * (H - K)
            sites_lab[name] = base + (rad * s_ + r) * yl
            normals[name], body_of[name] = yl, f"femur_{s}"
        # thigh cluster markers (optional wands): proximal antero-lateral, distal anterior
        for name, frac, d in ((f"{S}THIP", 0.62, unit(0.6 * xf + 0.8 * yl)), (f"{S}THIA", 0.30, unit(xf + 0.2 * yl))):
            base = K + frac * (H - K)
            sites_lab[name] = base + (0.068 * s_ + r) * d
            normals[name], body_of[name] = d, f"femur_{s}"
        # TIB: lower third of the shank, in the plane through K and the ANK site containing the knee axis
        zt = unit(K - A)
        ank = sites_lab[f"{S}ANK"]
        npl = unit(np.cross(ank - K, k_lat))
        base = A + 0.33 * (K - A)
        base = base - np.dot(base - K, npl) * npl
        lat_pl = unit(k_lat - np.dot(k_lat, npl) * npl - np.dot(k_lat, zt) * zt)
        sites_lab[f"{S}TIB"] = base + (0.048 * s_ + r) * lat_pl
        normals[f"{S}TIB"], body_of[f"{S}TIB"] = lat_pl, f"tibia_{s}"
        # validation device: bow on a tibia-fixed plate (TIBM1, TIBM2) and a distal medial skin marker (TIBM3)
        xt = unit(np.cross(_ortho(left, zt), zt))      # anterior
        med = -lat_pl
        for name, frac, d in ((f"{S}TIBM1", 0.62, 0.085 * xt + 0.025 * med), (f"{S}TIBM2", 0.42, 0.085 * xt + 0.040 * med),
                              (f"{S}TIBM3", 0.16, 0.022 * xt + 0.028 * med)):
            sites_lab[name] = A + frac * (K - A) + d * s_
            normals[name], body_of[name] = unit(d), f"tibia_{s}"

    # ---- anatomical frames (standing, lab)
    ps = 0.5 * (sites_lab["RPSI"] + sites_lab["LPSI"])
    pf = pelvis_frame(sites_lab["RASI"][None], sites_lab["LASI"][None], ps[None])
    frames = {"pelvis": (pf.origin[0], pf.axes[0])}
    tors = {}
    for s in SIDES:
        j = joints[s]
        left = -j["k_lat"] if s == "r" else j["k_lat"]
        frames[f"femur_{s}"] = _pose_frame(j["K"], j["H"] - j["K"], left)
        frames[f"tibia_{s}"] = _pose_frame(j["A"], j["K"] - j["A"], left)
        aleft = -j["a_lat"] if s == "r" else j["a_lat"]
        frames[f"tibia_torsioned_{s}"] = _pose_frame(j["A"], j["K"] - j["A"], aleft)
        Rt, Rtt = frames[f"tibia_{s}"][1], frames[f"tibia_torsioned_{s}"][1]
        xa = Rt.T @ Rtt[:, 0]                       # torsioned x in the untorsioned frame
        tors[s] = float(np.arctan2(-xa[1], xa[0]))  # x' = cos t x - sin t y (kinematics.gait.pig.tibia_frame)
        S = s.upper()
        toe, hee = sites_lab[f"{S}TOE"], sites_lab[f"{S}HEE"]
        zfo = unit(hee - toe)
        xfo = unit(np.cross(Rtt[:, 1], zfo))
        frames[f"foot_{s}"] = (toe, np.column_stack([xfo, np.cross(zfo, xfo), zfo]))

    # ---- bodies: pelvis, femur, tibia frames = anatomical; talus/calcn axes = torsioned tibia axes
    body_frames = {"pelvis": frames["pelvis"]}
    for s in SIDES:
        j = joints[s]
        body_frames[f"femur_{s}"] = frames[f"femur_{s}"]
        body_frames[f"tibia_{s}"] = frames[f"tibia_{s}"]
        body_frames[f"talus_{s}"] = (j["A"], frames[f"tibia_{s}"][1])
        body_frames[f"calcn_{s}"] = (j["Sub"], frames[f"tibia_{s}"][1])

    def local(body, p):
        o, R = body_frames[body]
        return R.T @ (np.asarray(p) - o)

    # the free joint's rotations in its ZXY sequence (heading, list, tilt about the Z-up lab axes)
    coords = [Coordinate(n, coordinate_def(n).kind, range=coordinate_def(n).range)
              for n in ("pelvis_rotation", "pelvis_list", "pelvis_tilt") + PELVIS_TRANSLATIONS]
    jl = [free("ground_pelvis", "ground", "pelvis", [c.name for c in coords], sequence="ZXY")]
    bodies = [Body("pelvis", 11.0)]
    for s in SIDES:
        j = joints[s]
        sg = 1.0 if s == "r" else -1.0
        hc = [sided(c, s) for c in JOINT_COORDINATES["hip"]]
        kc = [sided(c, s) for c in KNEE_ROTATIONS]
        kt = [sided(c, s) for c in KNEE_TRANSLATIONS]
        # the toes ride on the calcaneus (no mtp joint)
        coords += [Coordinate(n, d.kind, range=d.range) for n, d in leg_coordinates(s, ("hip", "knee", "ankle", "subtalar"))]
        bodies += [Body(f"femur_{s}", 8.0), Body(f"tibia_{s}", 3.5), Body(f"talus_{s}", 0.1), Body(f"calcn_{s}", 1.2)]
        ax = lambda v, c: TransformAxis(np.asarray(v, float), Linear(), (c,))  # noqa: E731
        jl.append(CustomJoint(
            f"hip_{s}", "pelvis", f"femur_{s}", tuple(hc),
            Transform(np.eye(3), local("pelvis", j["H"])), Transform(np.eye(3), local(f"femur_{s}", j["H"])),
            rotations=(ax(-_Y, hc[0]), ax(sg * _X, hc[1]), ax(sg * _Z, hc[2])), kind_name="custom"))
        jl.append(CustomJoint(
            f"knee_{s}", f"femur_{s}", f"tibia_{s}", tuple(kc + kt),
            Transform(np.eye(3), local(f"femur_{s}", j["K"])), Transform(np.eye(3), local(f"tibia_{s}", j["K"])),
            rotations=(ax(_Y, kc[0]), ax(sg * _X, kc[1]), ax(sg * _Z, kc[2])),
            translations=(ax(_X, kt[0]), ax(_Z, kt[1]), ax(-sg * _Y, kt[2])), kind_name="custom"))
        Rt = body_frames[f"tibia_{s}"][1]
        aleft = -j["a_lat"] if s == "r" else j["a_lat"]
        # dorsiflexion positive: rotation about the right-pointing ankle axis
        jl.append(revolute(f"ankle_{s}", f"tibia_{s}", f"talus_{s}", f"ankle_angle_{s}", axis=Rt.T @ (-aleft),
                           parent_offset=Transform(np.eye(3), local(f"tibia_{s}", j["A"]))))
        st = j["st_d"] if s == "r" else -j["st_d"]     # inversion positive on both sides
        jl.append(revolute(f"subtalar_{s}", f"talus_{s}", f"calcn_{s}", f"subtalar_angle_{s}", axis=Rt.T @ st,
                           parent_offset=Transform(np.eye(3), local(f"talus_{s}", j["Sub"]))))
    sites = {n: Site(body_of[n], local(body_of[n], p)) for n, p in sites_lab.items()}
    sk_normals = {n: body_frames[body_of[n]][1].T @ normals[n] for n in sites}
    markers = [Marker(n, s.body, s.offset) for n, s in sites.items()]
    centres = {}
    for s in SIDES:
        j = joints[s]
        centres[f"hip_{s}"] = Site(f"femur_{s}", local(f"femur_{s}", j["H"]))
        centres[f"knee_{s}"] = Site(f"tibia_{s}", local(f"tibia_{s}", j["K"]))
        centres[f"ankle_{s}"] = Site(f"talus_{s}", local(f"talus_{s}", j["A"]))
    frame_offsets = {}
    for s in SIDES:
        for name, body in ((f"tibia_torsioned_{s}", f"tibia_{s}"), (f"foot_{s}", f"calcn_{s}")):
            o, R = frames[name]
            bo, bR = body_frames[body]
            frame_offsets[name] = (body, bR.T @ R, bR.T @ (o - bo))
    base = Model(tuple(bodies), tuple(jl), tuple(coords), tuple(markers), name=f"phantom_{ph.seed}")

    # ---- standing pose: pelvis from its frame, joint angles from the anatomical frames
    q0 = np.zeros(base.n_q)
    ix = base.coordinate_index
    o, R = frames["pelvis"]
    q0[[ix("pelvis_rotation"), ix("pelvis_list"), ix("pelvis_tilt")]] = Rotation.from_matrix(R).as_euler("ZXY")
    q0[[ix("pelvis_tx"), ix("pelvis_ty"), ix("pelvis_tz")]] = o
    seg = {k: SegmentPose(v[0][None], v[1][None]) for k, v in frames.items()}
    laws = {}
    for s in SIDES:
        S = s.upper()
        h = joint_angles(seg["pelvis"], seg[f"femur_{s}"], "hip", S)[0]
        k = joint_angles(seg[f"femur_{s}"], seg[f"tibia_{s}"], "knee", S)[0]
        q0[[ix(sided(c, s)) for c in JOINT_COORDINATES["hip"]]] = h
        q0[[ix(sided(c, s)) for c in KNEE_ROTATIONS]] = k
        laws[s] = _knee_law(s, rng, k)
    coupling = laws["r"].to_coupling(base.coordinate_names).stack(laws["l"].to_coupling(base.coordinate_names))
    model = base.with_couplings(coupling.over(base.coordinate_names))

    # ---- what the lab measures (skin, tape, calliper)
    def dist(a, b):
        return float(np.linalg.norm(skin_lab[a] - skin_lab[b]))
    leg = {}
    for s in SIDES:
        S = s.upper()
        j = joints[s]
        leg[s] = float(np.linalg.norm(skin_lab[f"{S}ASI"] - j["K"]) + np.linalg.norm(j["K"] - skin_lab[f"{S}ANKM"]))
    subject = SubjectMeasurements(
        left_leg_length=leg["l"], right_leg_length=leg["r"],
        left_knee_width=dist("LKNE", "LKNEM"), right_knee_width=dist("RKNE", "RKNEM"),
        left_ankle_width=dist("LANK", "LANKM"), right_ankle_width=dist("RANK", "RANKM"),
        inter_asis_distance=dist("RASI", "LASI"), marker_diameter=DEFAULT_MARKER_DIAMETER,
        height=float(ph.params.stature), mass=float(round(70.0 * s_**2, 1)),
        left_tibial_torsion=tors["l"], right_tibial_torsion=tors["r"], source=f"phantom seed {ph.seed}")
    return PhantomSkeleton(model, q0, sites, sk_normals, centres, frame_offsets, laws, subject, tors, seed,
                           tissue_thickness=dict(tissue))
