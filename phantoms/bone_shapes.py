"""How the phantom's bones are built: analytic solids in a local frame, placed by a chain of joint transforms.

Each bone is a smooth union of analytic solids (`phantoms.sdf`) in its LOCAL
frame (right-side construction), placed in the BODY frame (X anterior,
Y superior, Z right) by the standing pose's joint transforms; `build_bones`
builds all of them from `anatomy.PhantomParams`, the left side as the
right-side construction with the left sizes reflected through ``Z = 0``.
The landmarks, axes and joint frames each construction carries are exact
(`anatomy` explains why).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from lowerlimb.bones import mirror_name
from lowerlimb.geometry import unit

from .sdf import (
    SDF, CappedCylinder, Difference, Ellipsoid, Intersection, Offset, RoundCone, Sphere,
    SuperEllipsoid, Transformed, Union, WaistedNeck, _Oriented, rotation_from_axes, smax,
)

if TYPE_CHECKING:
    from .anatomy import PhantomParams

__all__ = ["BoneShape", "build_bones", "pose_matrix", "apply_pose", "axis_rotation", "MIRROR", "FOOT_PROGRESSION_DEG"]


#: reflection through the sagittal plane of the body frame (right <-> left)
MIRROR = np.diag([1.0, 1.0, -1.0, 1.0])


I3 = np.eye(3)


X, Y, Z = I3


def pose_matrix(t=(0, 0, 0), R=None) -> np.ndarray:
    A = np.eye(4)
    if R is not None:
        A[:3, :3] = R
    A[:3, 3] = t
    return A


def apply_pose(A: np.ndarray, p) -> np.ndarray:
    p = np.asarray(p, float)
    if p.ndim == 1:
        return A[:3, :3] @ p + A[:3, 3]
    return np.einsum("ij,kj->ik", p, A[:3, :3]) + A[:3, 3]


def axis_rotation(axis, angle) -> np.ndarray:
    """Rotation matrix about a unit axis (Rodrigues)."""
    k = unit(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _cone(axis, half_angle_deg: float, n: int = 8) -> np.ndarray:
    """Unit vectors: `axis` and two rings of `n` at half and full `half_angle_deg` around it, (2n+1, 3)."""
    a = unit(axis)
    e1 = unit(np.cross(a, X if abs(a[0]) < 0.9 else Y))
    e2 = np.cross(a, e1)
    out = [a]
    for t in np.deg2rad([0.5 * half_angle_deg, half_angle_deg]):
        for b in np.linspace(0, 2 * np.pi, n, endpoint=False):
            out.append(np.cos(t) * a + np.sin(t) * (np.cos(b) * e1 + np.sin(b) * e2))
    return np.array(out)


@dataclass(frozen=True, eq=False)
class _Condyle(_Oriented):
    """Femoral condyle: a barrel about the flexion axis (local z).

    Solid of revolution about local z of the coronal disc of radius ``rho``
    centred ``radius - rho`` from the axis, cut to ``|z| <= half_width`` (rim
    rounded by a smooth maximum of blend ``k``).  Every sagittal section is a
    circle about the axis (radius ``radius`` in the mid-plane ``z = 0``, exact
    there); the coronal curvature radius ``rho`` makes the articular surface
    broad, as real condyles are (an ellipsoid this narrow would be a ridge).
    """

    radius: float = 1.0
    rho: float = 1.0
    half_width: float = 1.0
    k: float = 0.0

    def __call__(self, p):
        q = self._local(p)
        r = np.hypot(q[:, 0], q[:, 1])
        d = np.hypot(r - (self.radius - self.rho), q[:, 2]) - self.rho
        return smax(d, np.abs(q[:, 2]) - self.half_width, self.k)

    def bounds(self):
        return self._box([self.radius, self.radius, self.half_width])


def _E(c, r, R=None) -> Ellipsoid:
    return Ellipsoid(np.asarray(c, float), np.eye(3) if R is None else np.asarray(R, float), np.asarray(r, float))


def _SE(c, r, n, R=None) -> SuperEllipsoid:
    return SuperEllipsoid(np.asarray(c, float), np.eye(3) if R is None else np.asarray(R, float), np.asarray(r, float), n)


def _S(c, r) -> Sphere:
    return Sphere(np.asarray(c, float), float(r))


def _RC(a, b, ra, rb) -> RoundCone:
    return RoundCone(np.asarray(a, float), np.asarray(b, float), float(ra), float(rb))


#: parts whose size is varied independently by `PhantomParams.variation`
_VARIED = ("pelvis_width", "pelvis_depth", "femur_length", "femoral_head", "femoral_neck", "condyles",
           "patella", "tibia_length", "plateau", "malleoli", "talus", "foot_length", "foot_width")


#: angle of the foot's long axis outwards from the sagittal plane in the standing pose, degrees
FOOT_PROGRESSION_DEG = 8.0


#: axes that point to the subject's right on both sides (negated after mirroring)
_RIGHTWARD_AXES = {"knee_axis", "ankle_axis", "mtp_axis"}


@dataclass
class BoneShape:
    sdf: SDF                       # local frame (right-side construction)
    body_from_local: np.ndarray    # standing pose, right-side construction
    landmarks: dict = field(default_factory=dict)  # body frame (right construction)
    axes: dict = field(default_factory=dict)       # name -> (point, direction)
    scalars: dict = field(default_factory=dict)
    checks: dict = field(default_factory=dict)     # extra exact surface points for tests


def _side_dims(params: PhantomParams, mult: dict, side: str) -> dict:
    f = 1.0 + (params.asymmetry / 2 if side == "r" else -params.asymmetry / 2)
    s = params.stature / 1.75 * f
    return {"s": s, **{k: s * v for k, v in mult.items()}}


def _knob(tip, direction, radii, R) -> Ellipsoid:
    """Ellipsoid (axes `R`, `radii`) placed so that its support point in `direction` is `tip`.

    The support point of ``{c + R D u : |u| = 1}`` along ``n`` is
    ``c + R D^2 R^T n / sqrt(n^T R D^2 R^T n)``.
    """
    M = R @ np.diag(np.asarray(radii, float) ** 2) @ R.T
    n = unit(direction)
    off = M @ n / np.sqrt(n @ M @ n)
    return _E(np.asarray(tip, float) - off, radii, R)


def _build_pelvis_half(d: dict, femoral_head_radius: float):
    """Right half of the pelvis in the pelvis (ISB) frame; returns parts, landmarks, cavity."""
    s = d["s"]
    pw, pd = 0.24 * d["pelvis_width"], 0.155 * d["pelvis_depth"]
    r_as, r_ps = 0.0085 * s, 0.0085 * s
    RASI = np.array([0.0, 0.0, pw / 2])
    RPSI = np.array([-pd, 0.0, 0.044 * d["pelvis_width"]])
    H = np.array([-0.19 * pw, -0.30 * pw, 0.36 * pw])          # Bell et al. regression
    R_a = femoral_head_radius + 0.0025 * s                     # cartilage gap
    asis_c = RASI - r_as * X
    psis_c = RPSI + r_ps * X
    u1 = unit(asis_c - psis_c)
    lat = unit(np.cross(u1, Y))
    yw = unit(np.cos(np.deg2rad(20)) * Y + np.sin(np.deg2rad(20)) * lat)
    Rw = rotation_from_axes(x=u1, y=yw)
    a1 = 0.5 * np.linalg.norm(asis_c - psis_c) - 0.014 * s
    wing = _E((asis_c + psis_c) / 2 - 0.015 * s * Y, [a1, 0.058 * s, 0.0085 * s], Rw)
    n_open = unit([0.35, -0.55, 0.75])
    cup = _S(H - 0.012 * s * n_open, R_a + 0.0045 * s)
    sym_c = np.array([0.0095 * d["pelvis_depth"], -0.088 * d["pelvis_width"], 0.0])
    ramus_sup = _RC(H + np.array([0.012, -0.006, -0.022]) * s, sym_c + np.array([-0.004, 0.008, 0.014]) * s,
                    0.0085 * s, 0.0075 * s)
    IT = H + np.array([-0.035, -0.058, -0.028]) * s
    ischium = _RC(H + np.array([-0.018, -0.012, -0.006]) * s, IT, 0.011 * s, 0.0105 * s)
    tuber = _E(IT, np.array([0.014, 0.018, 0.011]) * s)
    ramus_inf = _RC(IT + np.array([0.006, -0.004, -0.006]) * s, sym_c + np.array([-0.004, -0.014, 0.010]) * s,
                    0.0075 * s, 0.0065 * s)
    # ASIS / PSIS: knobs elongated along the iliac crest; the landmark is the knob's
    # support point (most anterior / most posterior), exactly on its surface
    knob_r = np.array([0.016, 0.010, 0.0095]) * s
    asis = _knob(RASI, X, knob_r, Rw)
    psis = _knob(RPSI, -X, knob_r, Rw)
    parts = (wing, asis, psis, cup, ramus_sup, ischium, tuber, ramus_inf)
    cavity = _S(H, R_a)
    lm = {"RASI": RASI, "RPSI": RPSI, "acetabulum_centre_r": H}
    return parts, lm, cavity, R_a, sym_c


def _build_leg(d: dict, params: PhantomParams, hip_body: np.ndarray, ground_y: float | None):
    """Right-side construction of femur..toes in the body frame.

    Returns ``bones`` (name without side -> `BoneShape`) and the ankle height used.
    If `ground_y` is None the leg is placed so that the ankle is at its design
    height (the floor at Y = 0); otherwise the foot rests on ``Y = ground_y``.
    """
    s = d["s"]
    kc = 0.003 * s                                     # fillet of carved (subtracted) edges
    bones: dict[str, BoneShape] = {}
    # ---------------------------------------------------------------- femur (origin: head centre)
    R_h = 0.0235 * d["femoral_head"]
    L_f = 0.43 * d["femur_length"]
    th = np.deg2rad(7.0)                               # shaft valgus from vertical
    u_s = np.array([0.0, np.cos(th), np.sin(th)])     # shaft axis, proximal
    beta = np.deg2rad(params.femoral_anteversion_deg)
    # medial direction in the plane normal to the shaft, rotated anteriorly (about the shaft) by anteversion
    med = unit(-Z + (Z @ u_s) * u_s)
    w = np.cos(beta) * med + np.sin(beta) * X
    gam = np.deg2rad(180.0 - params.neck_shaft_deg)
    u_n = np.cos(gam) * u_s + np.sin(gam) * w           # neck axis, towards the head
    # waist: narrower than the head and far enough (> blend width) from head and shaft
    r_min = 0.66 * R_h * np.sqrt(d["femoral_neck"] / d["femoral_head"])
    t0 = -(R_h + 0.0045 * s)
    L_n = max(0.052 * d["femoral_neck"], -t0 + 0.024 * s)
    Q = -L_n * u_n                                      # neck axis meets shaft axis
    r_base = r_min + 0.0045 * s
    curv = (r_base - r_min) / (L_n + t0) ** 2
    Rn = rotation_from_axes(z=u_n, y=Y)
    neck = WaistedNeck(np.zeros(3), Rn, r_min, curv, t0, -L_n, -0.010 * s)
    t_d = (-L_f - Q[1]) / u_s[1]
    Ds = Q + t_d * u_s                                  # shaft axis at knee height
    K = Ds - 0.008 * s * X                              # condyle centres lie posterior to the shaft axis
    w_c = 0.021 * d["condyles"]
    Cm, Cl = K - w_c * Z, K + w_c * Z
    # Condyles: sagittally circular and of one radius, centred on the flexion axis,
    # the "cylindrical axis" knee (Churchill et al. 1998, Eckhoff et al. 2005): the
    # posterior condyles are arcs of one cylinder about the flexion axis.  Then the
    # two conventions of the issue coincide exactly -- the cylinder through the
    # posterior condyles and the line through the condyle sphere centres are both
    # the construction axis Z through K -- so the truth is the convention's truth
    # whichever one a detector implements (with unequal medial / lateral radii they
    # differ by ~atan(dR / condyle separation), with elliptic profiles the
    # cylinder also leaves the ellipse centres).  Coronally each condyle is a
    # broad barrel (`_Condyle`), 2 * cm_r[2] wide.
    cm_r = np.array([0.025, 0.025, 0.0135]) * d["condyles"]
    cl_r = np.array([0.025, 0.025, 0.0135]) * d["condyles"]
    rho_c = 0.020 * d["condyles"]                       # coronal radius of the articular surface
    Rs = rotation_from_axes(y=u_s, z=Z)
    G = Q + np.array([-0.008, 0.006, 0.020]) * s
    g_r = np.array([0.016, 0.022, 0.012]) * s
    RTRO = G + g_r[2] * Z                               # lateral prominence of the trochanter (the TRO marker site)
    r_e = 0.010 * s
    RKNE = Cl + np.array([-0.003, 0.009, 0.0215]) * s
    RMFC = Cm + np.array([-0.002, 0.011, -0.0235]) * s
    # shaft, metaphyses and lesser trochanter blend with a wide radius (no landmark on them)
    diaphysis = Union((
        _E(Q - 0.014 * s * u_s + 0.006 * s * Z, np.array([0.017, 0.030, 0.020]) * s, Rs),
        _S(Q - 0.045 * s * u_s + np.array([-0.010, 0.0, -0.012]) * s, 0.008 * s),
        _RC(Q - 0.010 * s * u_s, Ds + 0.075 * s * u_s, 0.0160 * s, 0.0135 * s),
        _E(Ds + 0.035 * s * u_s - 0.004 * s * X, np.array([0.022, 0.045, 0.030]) * s, Rs),
    ), k=0.015 * s)
    femur_parts = (
        _S(np.zeros(3), R_h), neck, diaphysis,
        _E(G, g_r),
        _Condyle(Cm, I3, cm_r[0], rho_c, cm_r[2], 0.003 * s), _Condyle(Cl, I3, cl_r[0], rho_c, cl_r[2], 0.003 * s),
        _E(K + np.array([0.014, 0.014, 0.0]) * s, np.array([0.016, 0.022, 0.030]) * s),
        _S(RKNE - r_e * Z, r_e), _S(RMFC + r_e * Z, r_e),
    )
    femur_sdf = Union(femur_parts, k=0.005 * s)
    body_from_femur = pose_matrix(hip_body)
    fb = BoneShape(femur_sdf, body_from_femur)
    P = lambda p: apply_pose(body_from_femur, p)  # noqa: E731
    fb.landmarks = {"femoral_head_centre": P(np.zeros(3)), "RTRO": P(RTRO), "medial_condyle_centre": P(Cm),
                    "lateral_condyle_centre": P(Cl), "RKNE": P(RKNE), "RMFC": P(RMFC),
                    "intercondylar_midpoint": P(K)}
    fb.axes = {"neck_axis": (P(np.zeros(3)), u_n), "shaft_axis": (P(Q), u_s), "knee_axis": (P(K), Z.copy())}
    fb.scalars = {"femoral_head_radius": R_h, "neck_diameter_min": 2 * r_min,
                  "medial_condyle_a": cm_r[0], "medial_condyle_b": cm_r[1],
                  "lateral_condyle_a": cl_r[0], "lateral_condyle_b": cl_r[1]}
    ring = [P(t0 * u_n + r_min * (np.cos(a) * Rn[:, 0] + np.sin(a) * Rn[:, 1])) for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    # the posterior-distal arcs of both condyles in their mid-planes (distal -> posterior):
    # one cylinder of radius cm_r[0] about the knee axis
    arcs = [P(c + cm_r[0] * (-np.cos(a) * Y - np.sin(a) * X)) for c in (Cm, Cl) for a in np.deg2rad([0, 30, 60, 90])]
    fb.checks = {"neck_waist_ring": np.array(ring), "posterior_condyle_arcs": np.array(arcs)}
    bones["femur"] = fb
    knee_body = P(K)

    # ---------------------------------------------------------------- tibia (origin: knee centre)
    g_k = 0.005 * s
    y_p = -(cm_r[1] + g_k)
    L_t = 0.385 * d["tibia_length"]
    A = np.array([-0.002 * s, -L_t, 0.0])
    tau = np.deg2rad(params.tibial_torsion_deg)
    iota = np.deg2rad(8.0)
    Za = np.array([-np.sin(tau) * np.cos(iota), -np.sin(iota), np.cos(tau) * np.cos(iota)])
    Ra = rotation_from_axes(z=Za, y=Y)                  # ankle frame in tibia/body axes
    Afr = lambda q: A + Ra @ np.asarray(q, float)      # noqa: E731  ankle frame -> tibia local
    R_d = 0.0195 * d["talus"]
    h_d = 0.0135 * d["talus"]
    g_a = 0.0025 * s
    R_p = R_d + g_a
    plat_r = np.array([0.025, 0.011, 0.037]) * d["plateau"]
    plat_c = np.array([-0.003 * s, y_p - plat_r[1], 0.0])
    plateau_centre = plat_c + plat_r[1] * Y
    tub_c = np.array([0.019 * s, y_p - 0.032 * s, 0.006 * s])
    tub_r = np.array([0.009, 0.014, 0.011]) * s
    RTTB = tub_c + tub_r[0] * X
    P_top = np.array([0.003 * s, y_p - 0.055 * s, 0.002 * s])
    P_bot = A + np.array([0.0, 0.040 * s, 0.0])
    mm_r = np.array([0.011, 0.021, 0.0065]) * d["malleoli"]
    mm_c = np.array([0.006 * s, 0.0, -(h_d + g_a + mm_r[2])])
    RMMA = Afr(mm_c - mm_r[1] * Y)
    # the distal block follows the talus size: it spans the plafond arc and reaches into the malleoli
    distal_block = _SE(Afr([0.001 * s, R_p + 0.002 * s, 0.0]),
                       np.array([0.92 * R_p + 0.001 * s, 0.015 * s, h_d + g_a + 0.004 * s]), 4.0, Ra)
    med_mall = _E(Afr(mm_c), mm_r, Ra)
    diaphysis = Union((
        _E([-0.002 * s, y_p - 0.042 * s, 0.0], np.array([0.023, 0.034, 0.034]) * s),  # proximal metaphysis flares to the plateau
        _RC(P_top, P_bot, 0.0135 * s, 0.0105 * s),
        _E(A + np.array([0.0, 0.038 * s, 0.0]), np.array([0.017, 0.028, 0.018]) * s),  # distal metaphysis
    ), k=0.015 * s)
    tibia_raw = Union((
        _SE(plat_c, plat_r, 4.0), diaphysis, _E(tub_c, tub_r), distal_block, med_mall,
    ), k=0.005 * s)
    plafond_cut = CappedCylinder(A, Ra, R_p, h_d + g_a)
    tibia_sdf = Difference(tibia_raw, plafond_cut, k=kc)
    body_from_tibia = pose_matrix(knee_body)
    P = lambda p: apply_pose(body_from_tibia, p)  # noqa: E731
    tb = BoneShape(tibia_sdf, body_from_tibia)
    tb.landmarks = {"plateau_centre": P(plateau_centre), "RTTB": P(RTTB), "RMMA": P(RMMA),
                    "plafond_centre": P(Afr([0, R_p, 0]))}
    tb.axes = {"shaft_axis": (P(P_top), unit(P_top - P_bot)), "knee_axis": (P(np.zeros(3)), Z.copy()),
               "ankle_axis": (P(A), Za)}
    tb.scalars = {"plafond_radius": R_p}
    tb.checks = {"plafond_arc": np.array([P(Afr([R_p * np.sin(a), R_p * np.cos(a), z]))
                                          for a in np.deg2rad([-40, -20, 0, 20, 40]) for z in (-0.6 * h_d, 0, 0.6 * h_d)])}
    bones["tibia"] = tb
    ankle_body = P(A)

    # ---------------------------------------------------------------- fibula (tibia frame)
    fh_c = np.array([-0.020 * s, y_p - 0.017 * s, 0.034 * s])
    fh_r = 0.0105 * s
    lm_r = np.array([0.012, 0.022, 0.0075]) * d["malleoli"]
    lm_c = np.array([-0.007 * s, -0.010 * s, h_d + g_a + lm_r[2]])
    RANK = Afr(lm_c - lm_r[1] * Y)
    lat_mall = _E(Afr(lm_c), lm_r, Ra)
    fib_raw = Union((
        _S(fh_c, fh_r),
        _RC(fh_c, Afr([-0.005 * s, 0.004 * s, h_d + g_a + 0.008 * s]), 0.0065 * s, 0.0058 * s),
        lat_mall,
    ), k=0.004 * s)
    fibula_sdf = Difference(fib_raw, Offset(tibia_sdf, 0.0015 * s), k=kc)
    fib = BoneShape(fibula_sdf, body_from_tibia.copy())
    fib.landmarks = {"RHFB": P(fh_c + fh_r * Z), "RANK": P(RANK)}
    bones["fibula"] = fib

    # ---------------------------------------------------------------- patella (origin: its centre)
    pc = K + np.array([0.0415, 0.032, 0.0]) * s
    pat_r = np.array([0.0105, 0.021, 0.022]) * d["patella"]
    body_from_pat = pose_matrix(apply_pose(body_from_femur, pc))
    pb = BoneShape(_SE(np.zeros(3), pat_r, 2.5), body_from_pat)
    pb.landmarks = {"patella_centre": body_from_pat[:3, 3].copy()}
    bones["patella"] = pb

    # ---------------------------------------------------------------- talus (ankle frame, origin dome centre)
    body_from_talus = pose_matrix(ankle_body, Ra)
    # the foot points FOOT_PROGRESSION_DEG outwards whatever the tibial torsion
    phi = np.deg2rad(FOOT_PROGRESSION_DEG)
    Xf = np.array([np.cos(phi), 0.0, np.sin(phi)])
    Rf = np.column_stack([Xf, Y, np.cross(Xf, Y)])
    Rta = Ra.T @ Rf                                   # foot axes in the ankle (talus) frame
    # Subtalar geometry (Parr et al. 2012 definition, exact by construction): the
    # axis runs through the centre of the convex talar head sphere (talonavicular
    # surface) and the centre of the CONCAVE posterior talocalcaneal facet sphere
    # carved into the body's underside; direction 42 deg elevation, 23 deg medial
    # deviation in foot axes (Inman).
    el, dev = np.deg2rad(42.0), np.deg2rad(23.0)
    st_dir_f = np.array([np.cos(el) * np.cos(dev), np.sin(el), -np.cos(el) * np.sin(dev)])
    st_dir_t = Rta @ st_dir_f
    r_head = 0.0115 * d["talus"]
    head_c = Rta @ (np.array([0.028, -0.013, -0.008]) * d["talus"])        # talus frame
    r_facet = 0.022 * d["talus"]
    facet_c = head_c - 0.040 * d["talus"] * st_dir_t
    talus_body = Union((
        CappedCylinder(np.zeros(3), np.eye(3), R_d, h_d, 0.002 * s),
        _E([-0.003 * s, -0.014 * s, 0.0], np.array([0.023, 0.016, h_d / s]) * s),
        # talar neck: from the body towards the head, which points along the foot, anteromedially
        _RC(Rta @ (np.array([0.004, -0.014, -0.002]) * d["talus"]), head_c - 0.008 * d["talus"] * unit(Rta @ X),
            0.0095 * d["talus"], 0.0094 * d["talus"]),
        _S(head_c, r_head),
        _E([-0.018 * s, -0.016 * s, 0.004 * s], np.array([0.008, 0.007, 0.007]) * s),
    ), k=0.004 * s)
    talus_raw = Difference(talus_body, _S(facet_c, r_facet), k=0.0015 * s)
    talus_from_tibia = np.linalg.inv(body_from_talus) @ body_from_tibia
    # only the distal tibia and the malleoli can touch the talus (cheap to evaluate)
    distal = Union((Difference(Union((distal_block, med_mall), k=0.004 * s), plafond_cut, k=kc), lat_mall), k=0.0)
    neighbours = Transformed(distal, talus_from_tibia)
    talus_sdf = Difference(talus_raw, Offset(neighbours, 0.0010 * s), k=0.0012 * s)
    ta = BoneShape(talus_sdf, body_from_talus)
    ta.landmarks = {"talar_dome_centre": ankle_body.copy(), "talar_head_centre": apply_pose(body_from_talus, head_c),
                    "posterior_facet_centre": apply_pose(body_from_talus, facet_c)}
    ta.scalars = {"talar_dome_radius": R_d, "talar_head_radius": r_head, "posterior_facet_radius": r_facet}
    ta.checks = {"dome_arc": np.array([apply_pose(body_from_talus, [R_d * np.sin(a), R_d * np.cos(a), z])
                                       for a in np.deg2rad([-50, -25, 0, 25, 50]) for z in (-0.7 * h_d, 0, 0.7 * h_d)]),
                 # the talar head around the neck direction, the facet around its middle (both exact spheres)
                 "talar_head": apply_pose(body_from_talus, head_c + r_head * _cone(Rta @ X, 30.0)),
                 "posterior_facet": apply_pose(body_from_talus, facet_c + r_facet * _cone(
                     unit(np.array([-0.003 * s, -0.014 * s, 0.0]) - facet_c), 12.0))}
    bones["talus"] = ta

    # ---------------------------------------------------------------- foot frame (calcn local)
    h_a = 0.068 * d["foot_length"]
    floor = ankle_body[1] - h_a if ground_y is None else ground_y
    body_from_foot = pose_matrix([ankle_body[0], floor, ankle_body[2]], Rf)
    F = lambda p: apply_pose(body_from_foot, p)  # noqa: E731
    fl, fw = d["foot_length"], d["foot_width"]
    r_ht = 0.0155 * s
    heel_c = np.array([-0.047 * fl, r_ht, 0.003 * fw])
    cb_R = rotation_from_axes(x=[np.cos(np.deg2rad(12)), np.sin(np.deg2rad(12)), 0], z=Z)
    cb_c = np.array([-0.010 * fl, 0.021 * s, 0.004 * fw])
    heads = [  # (centre, radius) met1..met5, foot frame
        (np.array([0.135 * fl, 0.0105 * s, -0.027 * fw]), 0.0105 * s),
        (np.array([0.142 * fl, 0.0112 * s, -0.008 * fw]), 0.0072 * s),
        (np.array([0.137 * fl, 0.0108 * s, 0.004 * fw]), 0.0068 * s),
        (np.array([0.128 * fl, 0.0105 * s, 0.015 * fw]), 0.0065 * s),
        (np.array([0.115 * fl, 0.0078 * s, 0.027 * fw]), 0.0078 * s),
    ]
    bases = [np.array([0.078 * fl, 0.034 * s, -0.022 * fw]), np.array([0.080 * fl, 0.036 * s, -0.009 * fw]),
             np.array([0.078 * fl, 0.034 * s, 0.002 * fw]), np.array([0.074 * fl, 0.030 * s, 0.013 * fw]),
             np.array([0.066 * fl, 0.024 * s, 0.024 * fw])]
    shaft_r = [(0.0085, 0.0065), (0.0065, 0.0045), (0.0062, 0.0043), (0.006, 0.0042), (0.0065, 0.005)]
    calcn_parts = [
        _S(heel_c, r_ht),
        _E(cb_c, np.array([0.042 * fl, 0.016 * s, 0.017 * fw]), cb_R),
        _E([-0.036 * fl, 0.034 * s, 0.003 * fw], np.array([0.013, 0.018, 0.014]) * s),
        _E([0.0, 0.030 * s, -0.020 * fw], np.array([0.012, 0.006, 0.008]) * s),
        _E([0.046 * fl, 0.021 * s, 0.012 * fw], np.array([0.021, 0.014, 0.016]) * s),  # cuboid
        _E([0.050 * fl, 0.038 * s, -0.014 * fw], np.array([0.010, 0.015, 0.018]) * s),
        _SE([0.068 * fl, 0.035 * s, -0.008 * fw], np.array([0.012, 0.015, 0.022]) * s, 3.0),
    ]
    for (hc, hr), b, (ra, rb) in zip(heads, bases, shaft_r):
        # the shaft ends above and behind the head centre so the head's plantar pole stays exact
        calcn_parts += [_S(hc, hr), _RC(b, hc + hr * np.array([-0.3, 0.25, 0.0]), ra * s, rb * s)]
    foot_from_talus = np.linalg.inv(body_from_foot) @ body_from_talus
    # convex posterior facet of the calcaneus, concentric with the talar one (trimmed below by
    # the dilated talus, so the cartilage gap is >= 1.2 mm)
    fc_f = apply_pose(foot_from_talus, facet_c)
    up_f = foot_from_talus[:3, :3] @ Y
    calcn_parts.append(Intersection((_S(fc_f, r_facet - 0.0008 * s),
                                     _E(fc_f + (r_facet - 0.007 * s) * up_f, np.array([0.014, 0.009, 0.011]) * s))))
    calcn_sdf = Difference(Union(tuple(calcn_parts), k=0.003 * s), Offset(Transformed(talus_raw, foot_from_talus), 0.0012 * s), k=kc)
    cb = BoneShape(calcn_sdf, body_from_foot)
    (m1, r1), (m5, r5) = heads[0], heads[4]
    dd = unit([1.0, 1.0, 0.0])
    cb.landmarks = {"RHEE": F(heel_c - r_ht * X), "RD1M": F(m1 + r1 * dd), "RD5M": F(m5 + r5 * dd),
                    "heel_contact": F(heel_c - r_ht * Y), "met1_contact": F(m1 - r1 * Y),
                    "met5_contact": F(m5 - r5 * Y)}
    cb.axes = {"hindfoot_axis": (F(cb_c), Rf @ cb_R[:, 0]),
               "forefoot_axis": (F(bases[1]), Rf @ unit(heads[1][0] - bases[1]))}
    bones["calcn"] = cb
    # subtalar axis: through the posterior facet and talar head centres, anterior
    ta.axes = {"ankle_axis": (ankle_body.copy(), Za),
               "subtalar_axis": (apply_pose(body_from_talus, facet_c), body_from_talus[:3, :3] @ st_dir_t)}

    # ---------------------------------------------------------------- toes (foot axes, origin mtp centre)
    # the mtp as the detector defines it: the least-squares line through the five head centres, at their mean
    hcs = np.array([hc for hc, _ in heads])
    mtp_mid = hcs.mean(axis=0)
    mtp_dir = np.linalg.svd(hcs - mtp_mid)[2][0]
    mtp_dir = mtp_dir if mtp_dir @ (m5 - m1) > 0 else -mtp_dir
    toe_parts = []
    lengths = [(0.030, 0.026), (0.024, 0.020), (0.022, 0.018), (0.020, 0.016), (0.018, 0.015)]
    for (hc, hr), (l1, l2) in zip(heads, lengths):
        rb = 0.62 * hr
        base = hc + (hr + 0.004 * s) * X - 0.001 * s * Y
        d1 = unit([np.cos(np.deg2rad(8)), -np.sin(np.deg2rad(8)), 0.0])
        mid = base + l1 * fl * d1
        tip_r = 0.55 * rb
        tip = mid + l2 * fl * X
        tip[1] = max(tip[1], tip_r + 0.002 * s)
        toe_parts += [_RC(base, mid, rb, 0.75 * rb), _RC(mid, tip, 0.75 * rb, tip_r)]
    heads_u = Union(tuple(_S(hc, hr) for hc, hr in heads), k=0.0)
    toes_sdf_f = Difference(Union(tuple(toe_parts), k=0.002 * s), Offset(heads_u, 0.0012 * s), k=kc)
    toes_sdf = Transformed(toes_sdf_f, pose_matrix(-mtp_mid))
    tob = BoneShape(toes_sdf, body_from_foot @ pose_matrix(mtp_mid))
    tob.axes = {"mtp_axis": (F(mtp_mid), Rf @ mtp_dir)}
    bones["toes"] = tob
    return bones, floor


def build_bones(params: PhantomParams, rng: np.random.Generator):
    """Construct all bones (body frame, standing) for both sides; returns dict name -> BoneShape."""
    # log-normal part scaling, clipped at 2 sd so that no part combination becomes implausible
    mult = {k: float(np.exp(params.variation * np.clip(rng.normal(), -2.0, 2.0))) for k in _VARIED}
    dims = {side: _side_dims(params, mult, side) for side in ("r", "l")}
    tilt = np.deg2rad(-12.0)                      # ASIS-PSIS plane: PSIS higher (anterior pelvic tilt)
    R_pel = axis_rotation(Z, tilt)
    halves = {}
    legs_tmp = {}
    for side in ("r", "l"):
        d = dims[side]
        R_h = 0.0235 * d["femoral_head"]
        halves[side] = _build_pelvis_half(d, R_h)
    # pelvis height: the right ankle sits at its design height above the floor Y = 0
    H_r_local = halves["r"][1]["acetabulum_centre_r"]
    probe, _ = _build_leg(dims["r"], params, R_pel @ H_r_local, None)
    floor0 = probe["calcn"].body_from_local[1, 3]
    body_from_pelvis = pose_matrix([0.0, -floor0, 0.0], R_pel)
    bones: dict[str, BoneShape] = {}
    for side in ("r", "l"):
        H_local = halves[side][1]["acetabulum_centre_r"]
        hip_rc = apply_pose(body_from_pelvis, H_local)          # right-construction coordinates
        legs_tmp[side], _ = _build_leg(dims[side], params, hip_rc, None)
    # ------------------------------------------------ pelvis: right half + mirrored left half + midline parts
    pr, lmr, cav_r, Ra_r, sym_c_r = halves["r"]
    pl, lml, cav_l, Ra_l, sym_c_l = halves["l"]
    s_mid = 0.5 * (dims["r"]["s"] + dims["l"]["s"])
    sym_c = 0.5 * (sym_c_r + sym_c_l)
    SYMP = sym_c + 0.0075 * s_mid * X
    k_p = 0.008 * s_mid
    # sacrum between the PSIS: its position and width follow them, its back stays >= 15 mm in front
    psis_x = 0.5 * (lmr["RPSI"][0] + lml["RPSI"][0])
    psis_z = 0.5 * (lmr["RPSI"][2] + lml["RPSI"][2])
    sacrum = Union((
        _E([psis_x + 0.033 * s_mid, -0.002 * s_mid, 0.0], [0.020 * s_mid, 0.035 * s_mid, psis_z + 0.006 * s_mid],
           axis_rotation(Z, np.deg2rad(-25))),
        _E([psis_x + 0.015 * s_mid, -0.050 * s_mid, 0.0], np.array([0.013, 0.032, 0.024]) * s_mid, axis_rotation(Z, np.deg2rad(-35))),
    ), k=0.015 * s_mid)
    midline = (_E(sym_c, np.array([0.0075, 0.019, 0.012]) * s_mid), sacrum)
    raw = Union((Union(pr, k=k_p), Transformed(Union(pl, k=k_p), MIRROR)) + midline, k=k_p)
    kc = 0.003 * s_mid
    pelvis_sdf = Difference(Difference(raw, cav_r, k=kc), Transformed(cav_l, MIRROR), k=kc)
    pel = BoneShape(pelvis_sdf, body_from_pelvis)
    Pp = lambda p: apply_pose(body_from_pelvis, p)  # noqa: E731
    M3 = MIRROR[:3, :3]
    pel.landmarks = {"RASI": Pp(lmr["RASI"]), "LASI": Pp(M3 @ lml["RASI"]), "RPSI": Pp(lmr["RPSI"]),
                     "LPSI": Pp(M3 @ lml["RPSI"]), "SYMP": Pp(SYMP),
                     "acetabulum_centre_r": Pp(lmr["acetabulum_centre_r"]),
                     "acetabulum_centre_l": Pp(M3 @ lml["acetabulum_centre_r"])}
    pel.scalars = {"acetabulum_radius_r": Ra_r, "acetabulum_radius_l": Ra_l}
    n_open = unit([0.35, -0.55, 0.75])
    cup_pts = []
    for side, lm, Ra in (("r", lmr, Ra_r), ("l", lml, Ra_l)):
        Hc = lm["acetabulum_centre_r"]
        Rn = rotation_from_axes(z=-n_open, x=X)
        for a in np.deg2rad([0, 20, 35]):
            for b in np.linspace(0, 2 * np.pi, 6, endpoint=False):
                u = Rn @ np.array([np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)])
                p = Hc + Ra * u
                cup_pts.append(Pp(p if side == "r" else M3 @ p))
    pel.checks = {"acetabular_cup": np.array(cup_pts)}
    bones["pelvis"] = pel
    for side in ("r", "l"):
        for b, bone in legs_tmp[side].items():
            name = f"{b}_{side}"
            if side == "l":
                bone = _mirror_bone(bone)
            bones[name] = bone
    return bones, dims, mult


def _mirror_bone(b: BoneShape) -> BoneShape:
    M3 = MIRROR[:3, :3]
    out = BoneShape(b.sdf, MIRROR @ b.body_from_local)
    out.landmarks = {mirror_name(k): M3 @ v for k, v in b.landmarks.items()}
    out.axes = {}
    for k, (p, dvec) in b.axes.items():
        dm = M3 @ dvec
        out.axes[mirror_name(k)] = (M3 @ p, -dm if k in _RIGHTWARD_AXES else dm)
    out.scalars = {mirror_name(k): v for k, v in b.scalars.items()}
    out.checks = {k: v @ M3 for k, v in b.checks.items()}
    return out
