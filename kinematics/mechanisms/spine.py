"""Coupled spine models and a full-body mannequin (Raunhardt & Boulic 2007).

Spine model
-----------
Each vertebra's swing (flexion-extension about the anterior-lateral plane,
lateral bending) and torsion (about the vertebral axis) are split between a
two-DOF `SwingJoint` (exponential map with no component along the bone axis
``y``) and a revolute "twist" joint about ``y``, so that the two can be
coupled separately by linear constraints over the coordinates::

    inside a region r, for every swing joint j and component c in {extension, bending}:
        q[j_c] = (w_j,c / w_first,c) q[first_c]                (equalities)
    and for every twist joint t:   q[t_rotation] = (w_t / w_first) q[first_rotation]
    between regions (lumbar-thoracic, thoracic-cervical), per component c:
        | q[b_c] - k q[a_c] | <= delta                           (two inequalities)

with ``a`` the last joint of the lower region, ``b`` the first of the upper
one, ``k`` the ratio of their range spans and ``delta`` a quarter of b's span
(so q = 0 is always feasible).  Joint
limits are enforced (``Coordinate.clamped``) only on the first joint of each
region; the others follow within their ranges through the coupling ratios.

The full spine has the 24 H-Anim vertebral joints (vl5..vl1, vt12..vt1,
vc7..vc1): 17 swing and 7 twist joints (lumbar twist vl2; thoracic vt8, vt4,
vt2; cervical vc6, vc3, vc2), 41 coordinates, 32 equalities and 12
inequalities, leaving 9 free parameters (flexion, bending, torsion per region)
as in the seed.  The simplified spine has 8 swing joints (vl5, vl3, vl1,
vt10, vt6, vt1, vc7, vc4) and 5 twist joints (vl3, vt10, vt6, vc7, vc4),
12 equalities and 12 inequalities.

Ranges.  The numbers of the seed's Table 1 are not legible in its text; region
totals follow Kapandji (1982, vol. 3) - lumbar flexion 60 deg, extension 35,
lateral bending 20 per side, axial rotation 5 per side; thoracic 45 / 25 / 20
/ 35; cervical 40 / 75 / 35 / 45 - and are distributed over the joints of a
region by segmental weights after White & Panjabi (1990).  Uncoupled variants
use the same joints (``joint_style="swing_twist"``) or three-DOF
exponential-map ball joints (``"ball"``), with every range enforced by default or,
``spine_limits="first"``, the coupled spine's limit set (first joint of each region only).

Frames: y superior (bone axis), x anterior, z to the right (OpenSim
convention); metres, radians, kilograms.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from lowerlimb.errors import FitError, InputError
from kinematics.algorithms.fk import KinematicState, forward_kinematics, point_positions
from kinematics.multibody.joints import ExpMapSpherical, SwingJoint, Transform, free, revolute, spherical, universal, weld
from kinematics.multibody.model import Body, Coordinate, Marker, Model
from kinematics.algorithms.prioritized import ConstraintSet, LinearConstraint, Task

__all__ = [
    "RegionSpec", "SpineLayout", "spine_layout", "spine_constraints", "isolated_spine", "mannequin",
    "vertebral_twist", "torsion_direction_changes", "swing_components", "KinematicTasks", "REGIONS",
    "spine_solver", "isolated_spine_tasks", "balanced_posture_tasks", "FigureEight", "periodic_tasks",
    "periodic_drift", "spine_coordinates", "spine_distance", "spine_drift_bound", "posture_distance", "SPINE_LIMITS",
]

REGIONS = ("lumbar", "thoracic", "cervical")
_DEG = np.pi / 180.0
_EXT_AXIS = (0.0, 0.0, 1.0)    # extension positive about +z (flexion negative)
_BEND_AXIS = (1.0, 0.0, 0.0)   # lateral bending positive about +x (towards the right)
_TWIST_AXIS = (0.0, 1.0, 0.0)  # torsion about the vertebral axis


@dataclass(frozen=True)
class RegionSpec:
    """One spine region.

    Attributes
    ----------
    name : str
    joints : tuple of str            H-Anim joint names, caudal to cranial
    swing : dict joint -> (w_extension, w_bending)   segmental weights of the swing joints
    twist : dict joint -> w_rotation                 weights of the twist joints
    segment_length : float           joint-to-joint distance (m)
    flexion, extension, bending, rotation : float    region totals, degrees per side
    """

    name: str
    joints: tuple[str, ...]
    swing: dict
    twist: dict
    segment_length: float
    flexion: float
    extension: float
    bending: float
    rotation: float

    def joint_range(self, joint: str, component: str) -> tuple[float, float]:
        """(lower, upper) in rad of one joint's component: region total x weight share."""
        if component == "rotation":
            share = self.twist[joint] / sum(self.twist.values())
            return (-self.rotation * share * _DEG, self.rotation * share * _DEG)
        col = 0 if component == "extension" else 1
        share = self.swing[joint][col] / sum(w[col] for w in self.swing.values())
        if component == "extension":
            return (-self.flexion * share * _DEG, self.extension * share * _DEG)
        return (-self.bending * share * _DEG, self.bending * share * _DEG)

    def ball_range(self, joint: str, component: str) -> tuple[float, float]:
        """Per-joint range when every joint of the region is a ball joint (equal shares)."""
        n = len(self.joints)
        total = {"extension": (self.flexion, self.extension), "bending": (self.bending, self.bending),
                 "rotation": (self.rotation, self.rotation)}[component]
        return (-total[0] / n * _DEG, total[1] / n * _DEG)


@dataclass(frozen=True)
class SpineLayout:
    """A spine: ``kind`` ('full' or 'simplified') and its three regions, caudal to cranial."""

    kind: str
    regions: tuple[RegionSpec, ...]

    @property
    def joints(self) -> tuple[str, ...]:
        return tuple(j for r in self.regions for j in r.joints)

    def region_of(self, joint: str) -> RegionSpec:
        for r in self.regions:
            if joint in r.joints:
                return r
        raise KeyError(joint)


def _segment(joint: str) -> str:
    """H-Anim segment driven by a vertebral joint: vl5 -> l5."""
    return joint[1:]


def spine_layout(kind: str = "full") -> SpineLayout:
    """Joint layout, weights and ranges of the 'full' (24 vertebrae) or 'simplified' spine."""
    if kind == "full":
        lumbar = RegionSpec(
            "lumbar", ("vl5", "vl4", "vl3", "vl2", "vl1"),
            {"vl5": (17, 3), "vl4": (16, 6), "vl3": (15, 8), "vl1": (12, 6)}, {"vl2": 1.0},
            0.036, 60, 35, 20, 5)
        thoracic = RegionSpec(
            "thoracic", tuple(f"vt{i}" for i in range(12, 0, -1)),
            {"vt12": (12, 8), "vt11": (12, 8), "vt10": (6, 8), "vt9": (6, 6), "vt7": (6, 6), "vt6": (6, 6),
             "vt5": (4, 6), "vt3": (4, 6), "vt1": (4, 6)},
            {"vt8": 8.0, "vt4": 9.0, "vt2": 9.0}, 0.022, 45, 25, 20, 35)
        cervical = RegionSpec(
            "cervical", tuple(f"vc{i}" for i in range(7, 0, -1)),
            {"vc7": (9, 4), "vc5": (17, 11), "vc4": (17, 11), "vc1": (10, 5)},
            {"vc6": 6.0, "vc3": 7.0, "vc2": 30.0}, 0.016, 40, 75, 35, 45)
    elif kind == "simplified":
        lumbar = RegionSpec("lumbar", ("vl5", "vl3", "vl1"), {"vl5": (1, 1), "vl3": (1, 1), "vl1": (1, 1)},
                            {"vl3": 1.0}, 0.06, 60, 35, 20, 5)
        thoracic = RegionSpec("thoracic", ("vt10", "vt6", "vt1"), {"vt10": (1, 1), "vt6": (1, 1), "vt1": (1, 1)},
                              {"vt10": 1.0, "vt6": 1.0}, 0.088, 45, 25, 20, 35)
        cervical = RegionSpec("cervical", ("vc7", "vc4"), {"vc7": (1, 1), "vc4": (1, 1)},
                              {"vc7": 1.0, "vc4": 1.0}, 0.055, 40, 75, 35, 45)
    else:
        raise InputError("spine", f"unknown spine kind {kind!r} (use 'full' or 'simplified')")
    return SpineLayout(kind, (lumbar, thoracic, cervical))


def _coord(joint: str, component: str) -> str:
    return f"{joint}_{component}"


def spine_constraints(layout: SpineLayout) -> list[LinearConstraint]:
    """Equalities inside each region, then the 12 inter-region inequalities (see module docstring)."""
    eqs, ineqs = [], []
    for reg in layout.regions:
        swing = [j for j in reg.joints if j in reg.swing]
        twist = [j for j in reg.joints if j in reg.twist]
        for comp, col in (("extension", 0), ("bending", 1)):
            first = swing[0]
            for j in swing[1:]:
                k = reg.swing[j][col] / reg.swing[first][col]
                eqs.append(LinearConstraint.ratio(_coord(j, comp), _coord(first, comp), k,
                                                  f"{reg.name}: {j} {comp} = {k:.3g} x {first}"))
        for j in twist[1:]:
            k = reg.twist[j] / reg.twist[twist[0]]
            eqs.append(LinearConstraint.ratio(_coord(j, "rotation"), _coord(twist[0], "rotation"), k,
                                              f"{reg.name}: {j} rotation = {k:.3g} x {twist[0]}"))
    for lower, upper in zip(layout.regions[:-1], layout.regions[1:]):
        for comp in ("extension", "bending", "rotation"):
            pool_lo = [j for j in lower.joints if j in (lower.twist if comp == "rotation" else lower.swing)]
            pool_up = [j for j in upper.joints if j in (upper.twist if comp == "rotation" else upper.swing)]
            a, b = pool_lo[-1], pool_up[0]
            ra, rb = lower.joint_range(a, comp), upper.joint_range(b, comp)
            k = (rb[1] - rb[0]) / (ra[1] - ra[0])
            delta = 0.25 * (rb[1] - rb[0])
            ineqs.extend(LinearConstraint.band(_coord(b, comp), _coord(a, comp), k, delta,
                                               f"{lower.name}-{upper.name} {comp}: |{b} - {k:.3g} x {a}| <= {delta:.3g}"))
    return eqs + ineqs


# ----------------------------------------------------------------------------- model building
class _Builder:
    def __init__(self):
        self.bodies, self.joints, self.coords, self.markers = [], [], [], []

    def body(self, name, mass=0.0, com=(0, 0, 0), length=0.0):
        # slender-segment inertia (uniform rod along y), enough for COM and dynamics smoke use
        I = np.diag([1.0, 0.1, 1.0]) * mass * max(length, 0.05) ** 2 / 12.0
        self.bodies.append(Body(name, mass, np.asarray(com, float), I))

    def coordinate(self, name, rng=(-np.inf, np.inf), clamped=True, default=0.0, kind="rotational"):
        self.coords.append(Coordinate(name, kind, default, rng, False, clamped))


SPINE_LIMITS = ("all", "first", "none")


def _add_spine(b: _Builder, layout: SpineLayout, parent: str, offset: np.ndarray, coupled: bool,
               joint_style: str, trunk_mass: float, neck_mass: float, limits: str | None = None) -> str:
    """Append vertebral bodies/joints; returns the name of the top vertebra body.

    ``limits`` selects the clamped vertebral coordinates: 'first' (the first swing and the first
    twist joint of each region, as the seed does for the coupled spine; ball joints: the first
    joint of each region), 'all' or 'none'.  Default: 'first' when coupled, else 'all'.
    """
    limits = limits or ("first" if coupled else "all")
    if limits not in SPINE_LIMITS:
        raise InputError("spine", f"spine limits must be one of {SPINE_LIMITS}, not {limits!r}")
    if joint_style not in ("swing_twist", "ball"):
        raise InputError("spine", f"joint_style must be 'swing_twist' or 'ball', not {joint_style!r}")
    if coupled and joint_style != "swing_twist":
        raise InputError("spine", "only the swing/twist spine can be coupled (ball joints mix swing and twist)")
    prev, prev_offset = parent, np.asarray(offset, float)
    lengths = {r.name: r.segment_length * len(r.joints) for r in layout.regions}
    for reg in layout.regions:
        region_mass = neck_mass if reg.name == "cervical" else trunk_mass * lengths[reg.name] / (
            lengths["lumbar"] + lengths["thoracic"])
        m = region_mass / len(reg.joints)
        L = reg.segment_length
        for jn in reg.joints:
            seg = _segment(jn)
            po = Transform(np.eye(3), prev_offset)
            first_swing = [j for j in reg.joints if j in reg.swing][:1]
            first_twist = [j for j in reg.joints if j in reg.twist][:1]
            if joint_style == "ball":
                names = [_coord(jn, c) for c in ("bending", "rotation", "extension")]   # rotation vector x, y, z
                clamp = limits == "all" or (limits == "first" and jn == reg.joints[0])
                for nm, comp in zip(names, ("bending", "rotation", "extension")):
                    b.coordinate(nm, reg.ball_range(jn, comp), clamped=clamp)
                b.body(seg, m, (0, L / 2, 0), L)
                b.joints.append(ExpMapSpherical(jn, prev, seg, tuple(names), po, Transform()))
            else:
                has_swing, has_twist = jn in reg.swing, jn in reg.twist
                child_swing = seg if not has_twist else f"{seg}_link"
                if has_swing:
                    for comp in ("extension", "bending"):
                        clamp = limits == "all" or (limits == "first" and jn in first_swing)
                        b.coordinate(_coord(jn, comp), reg.joint_range(jn, comp), clamped=clamp)
                    if has_twist:
                        b.body(child_swing)   # massless link between the swing and the twist joint
                    b.joints.append(SwingJoint(jn, prev, child_swing, (_coord(jn, "extension"), _coord(jn, "bending")),
                                               po, Transform(), axes=(_EXT_AXIS, _BEND_AXIS)))
                if has_twist:
                    clamp = limits == "all" or (limits == "first" and jn in first_twist)
                    b.coordinate(_coord(jn, "rotation"), reg.joint_range(jn, "rotation"), clamped=clamp)
                    parent_twist = child_swing if has_swing else prev
                    po_twist = Transform() if has_swing else po
                    b.joints.append(revolute(jn + ("_twist" if has_swing else ""), parent_twist, seg,
                                             _coord(jn, "rotation"), _TWIST_AXIS, po_twist))
                b.body(seg, m, (0, L / 2, 0), L)
            prev, prev_offset = seg, np.array([0.0, L, 0.0])
    return prev


def _finish(b: _Builder, layout: SpineLayout, coupled: bool, name: str) -> Model:
    model = Model(tuple(b.bodies), tuple(b.joints), tuple(b.coords), tuple(b.markers), name=name)
    if not coupled:
        return model
    cons = ConstraintSet.build(model.coordinate_names, spine_constraints(layout), source=f"spine model {name!r}")
    eq, ineq = cons.as_linear()
    return model.replace(couplings=eq, inequalities=ineq)


def isolated_spine(kind: str = "full", coupled: bool = True, joint_style: str = "swing_twist") -> Model:
    """A spine standing on a sacrum welded to the ground (origin at the sacrum, y up).

    The skull is welded on the top vertebra (frame 'skull', body 'skull').
    """
    layout = spine_layout(kind)
    b = _Builder()
    b.body("sacrum", 0.5, (0, 0, 0), 0.05)
    b.joints.append(weld("sacrum_ground", "ground", "sacrum"))
    top = _add_spine(b, layout, "sacrum", np.zeros(3), coupled, joint_style, trunk_mass=25.0, neck_mass=1.0)
    b.body("skull", 4.5, (0.02, 0.10, 0), 0.2)
    b.joints.append(weld("skullbase", top, "skull", Transform(np.eye(3), np.array([0.0, layout.regions[-1].segment_length, 0.0]))))
    b.markers.append(Marker("head_top", "skull", np.array([0.0, 0.2, 0.0])))
    return _finish(b, layout, coupled, f"spine_{kind}_{'coupled' if coupled else 'uncoupled'}")


def mannequin(spine: str = "simplified", coupled: bool = True, joint_style: str | None = None,
              limit_spine: bool = True, spine_limits: str | None = None) -> Model:
    """Full-body mannequin: pelvis (free joint), legs, spine, arms, head; 1.75 m, 75 kg.

    Legs: hip (ZXY Cardan), knee (revolute, flexion positive), ankle
    (universal: ankle angle then subtalar).  Arms: shoulder (exponential-map
    ball joint), elbow (revolute).  Head welded on the top vertebra.
    Markers: ``{r,l}_heel``, ``{r,l}_toe``, ``{r,l}_toe_lat`` (sole, y = 0 at the default pose),
    ``{r,l}_hand``, ``head_top``.  Segment masses after de Leva (1996).

    Parameters
    ----------
    spine : {'simplified', 'full'}
    coupled : bool
        Coupled swing/twist spine; otherwise ``joint_style`` ('ball' by default
        for the simplified spine as in the seed, 'swing_twist' for the full one).
    limit_spine : bool
        Enforce the vertebral ranges (False: a generic mannequin whose uncoupled
        spine joints are unbounded; ranges stay in the model, not clamped).
    spine_limits : {'first', 'all', 'none'}, optional
        Which vertebral coordinates are clamped to their ranges: the first joint of each
        region only (the seed's coupled spine; default when coupled), every joint (default
        when uncoupled) or none (same as ``limit_spine=False``).  ``mannequin(coupled=False,
        joint_style='swing_twist', spine_limits='first')`` is the coupled spine without its
        coupling constraints: same joints, same limit set.
    """
    layout = spine_layout(spine)
    style = joint_style or ("swing_twist" if coupled or spine == "full" else "ball")
    b = _Builder()
    b.body("pelvis", 8.4, (-0.03, 0.0, 0.0), 0.2)
    pel = ("pelvis_tilt", "pelvis_list", "pelvis_rotation", "pelvis_tx", "pelvis_ty", "pelvis_tz")
    for c in pel[:3]:
        b.coordinate(c)
    for c, d in zip(pel[3:], (0.0, 0.95, 0.0)):
        b.coordinate(c, kind="translational", default=d)
    b.joints.append(free("ground_pelvis", "ground", "pelvis", pel, "ZXY"))
    for s, sign in (("r", 1.0), ("l", -1.0)):
        b.body(f"femur_{s}", 10.6, (0, -0.18, 0), 0.43)
        for c, rng in ((f"hip_flexion_{s}", (-0.5, 2.0)), (f"hip_adduction_{s}", (-0.8, 0.5)),
                       (f"hip_rotation_{s}", (-0.8, 0.8))):
            b.coordinate(c, rng)
        b.joints.append(spherical(f"hip_{s}", "pelvis", f"femur_{s}",
                                  (f"hip_flexion_{s}", f"hip_adduction_{s}", f"hip_rotation_{s}"), "ZXY",
                                  Transform(np.eye(3), np.array([-0.02, -0.07, sign * 0.085]))))
        b.body(f"tibia_{s}", 3.2, (0, -0.17, 0), 0.38)
        b.coordinate(f"knee_angle_{s}", (0.0, 2.3), default=0.15)
        b.joints.append(revolute(f"knee_{s}", f"femur_{s}", f"tibia_{s}", f"knee_angle_{s}", (0, 0, -1),
                                 Transform(np.eye(3), np.array([0.0, -0.43, 0.0]))))
        b.body(f"foot_{s}", 1.0, (0.05, -0.03, 0), 0.2)
        b.coordinate(f"ankle_angle_{s}", (-0.8, 0.6))
        b.coordinate(f"subtalar_angle_{s}", (-0.4, 0.4))
        b.joints.append(universal(f"ankle_{s}", f"tibia_{s}", f"foot_{s}", (f"ankle_angle_{s}", f"subtalar_angle_{s}"),
                                  ((0, 0, 1), (1, 0, 0)), Transform(np.eye(3), np.array([0.0, -0.38, 0.0]))))
        b.markers.append(Marker(f"{s}_heel", f"foot_{s}", np.array([-0.05, -0.07, 0.0])))
        b.markers.append(Marker(f"{s}_toe", f"foot_{s}", np.array([0.17, -0.07, 0.0])))
        # lateral forefoot (fifth metatarsal head): with heel and toe, the sole cannot roll
        b.markers.append(Marker(f"{s}_toe_lat", f"foot_{s}", np.array([0.13, -0.07, sign * 0.04])))
    limits = spine_limits or ("none" if not limit_spine else ("first" if coupled else "all"))
    top = _add_spine(b, layout, "pelvis", np.array([-0.03, 0.05, 0.0]), coupled, style,
                     trunk_mass=24.2, neck_mass=1.0, limits=limits)
    thoracic_top = _segment(layout.regions[1].joints[-1])
    t_len = layout.regions[1].segment_length
    for s, sign in (("r", 1.0), ("l", -1.0)):
        b.body(f"humerus_{s}", 2.0, (0, -0.14, 0), 0.30)
        names = tuple(f"shoulder_{c}_{s}" for c in ("x", "y", "z"))
        for c in names:
            b.coordinate(c, (-2.5, 2.5))
        b.joints.append(ExpMapSpherical(f"shoulder_{s}", thoracic_top, f"humerus_{s}", names,
                                        Transform(np.eye(3), np.array([-0.01, t_len - 0.02, sign * 0.18]))))
        b.body(f"forearm_{s}", 1.65, (0, -0.16, 0), 0.35)
        b.coordinate(f"elbow_flexion_{s}", (0.0, 2.5), default=0.3)
        b.joints.append(revolute(f"elbow_{s}", f"humerus_{s}", f"forearm_{s}", f"elbow_flexion_{s}", (0, 0, 1),
                                 Transform(np.eye(3), np.array([0.0, -0.30, 0.0]))))
        b.markers.append(Marker(f"{s}_hand", f"forearm_{s}", np.array([0.0, -0.34, 0.0])))
    b.body("skull", 4.5, (0.02, 0.10, 0), 0.2)
    b.joints.append(weld("skullbase", top, "skull",
                         Transform(np.eye(3), np.array([0.0, layout.regions[-1].segment_length, 0.0]))))
    b.markers.append(Marker("head_top", "skull", np.array([0.0, 0.2, 0.0])))
    suffix = {"all": "", "first": "_first_limited", "none": "_unlimited"}[limits] if not coupled else (
        "" if limits == "first" else f"_{limits}_limited")
    return _finish(b, layout, coupled, f"mannequin_{spine}_{'coupled' if coupled else style}{suffix}")


# ----------------------------------------------------------------------------- spine measures
def _spine_layout_of(model: Model) -> SpineLayout:
    kind = "full" if "l4" in model.body_names else "simplified"
    return spine_layout(kind)


def vertebral_twist(model: Model, q: np.ndarray) -> dict[str, np.ndarray]:
    """Torsion of each vertebra relative to the one below (rad), per region, caudal to cranial.

    The relative rotation R = R_below^T R_vertebra is split into swing and
    twist about the vertebral axis y (swing-twist decomposition): with the
    quaternion (w, x, y, z) of R, twist = 2 atan2(y, w), wrapped to (-pi, pi].
    """
    layout = _spine_layout_of(model)
    st = forward_kinematics(model, np.asarray(q, float))
    out = {}
    joints = layout.joints
    for reg in layout.regions:
        tw = []
        for jn in reg.joints:
            i = joints.index(jn)
            below = _segment(joints[i - 1]) if i else model.joint(jn).parent
            Rb = st.rotations[0, model.body_index(below)]
            Rv = st.rotations[0, model.body_index(_segment(jn))]
            x, y, z, w = Rotation.from_matrix(Rb.T @ Rv).as_quat()
            t = 2.0 * np.arctan2(y, w)
            tw.append((t + np.pi) % (2 * np.pi) - np.pi)
        out[reg.name] = np.array(tw)
    return out


def torsion_direction_changes(model: Model, q: np.ndarray, threshold: float = 1e-4) -> dict[str, int]:
    """Number of sign changes of the vertebral torsion between successive twisting vertebrae of a region.

    Vertebrae whose |twist| is below `threshold` (rad) do not twist and are skipped.
    """
    out = {}
    for region, tw in vertebral_twist(model, q).items():
        s = np.sign(tw[np.abs(tw) > threshold])
        out[region] = int(np.sum(s[1:] != s[:-1]))
    return out


def _relative_rotations(model: Model, q: np.ndarray) -> np.ndarray:
    """Rotation of each vertebra relative to the one below, (V, 3, 3), caudal to cranial."""
    layout = _spine_layout_of(model)
    st = forward_kinematics(model, np.asarray(q, float))
    joints = layout.joints
    out = []
    for i, jn in enumerate(joints):
        below = _segment(joints[i - 1]) if i else model.joint(jn).parent
        out.append(st.rotations[0, model.body_index(below)].T @ st.rotations[0, model.body_index(_segment(jn))])
    return np.array(out)


def spine_distance(model: Model, q: np.ndarray, q_ref: np.ndarray) -> float:
    """Joint-space distance of two spine postures, independent of the joint parametrisation (rad).

    ``sqrt(sum_v theta_v^2)`` with theta_v the angle of ``R_v(q) R_v(q_ref)^T`` and R_v the
    rotation of vertebra v relative to the one below (geodesic distance on SO(3)^V).
    """
    A, B = _relative_rotations(model, q), _relative_rotations(model, q_ref)
    angles = Rotation.from_matrix(A @ np.transpose(B, (0, 2, 1))).magnitude()
    return float(np.sqrt(np.sum(angles ** 2)))


def posture_distance(model: Model, q: np.ndarray, q_ref: np.ndarray) -> float:
    """Joint-space distance of two whole postures, independent of the joint parametrisation (rad).

    ``sqrt(sum_b theta_b^2)`` over every body b with mass (massless links between a swing and
    a twist joint are merged into the next body), theta_b the angle of ``R_b(q) R_b(q_ref)^T``
    and R_b the rotation of b relative to its nearest massive ancestor (the ground for the
    pelvis).  Translations (pelvis position) are not included.
    """
    parent_of = {j.child: j.parent for j in model.joints}
    mass = {bd.name: bd.mass for bd in model.bodies}

    def anchor(name):
        while name != "ground" and mass[name] == 0.0:
            name = parent_of[name]
        return name
    pairs = [(model.body_index(b.name), anchor(parent_of[b.name])) for b in model.bodies if b.mass > 0.0]
    sa = forward_kinematics(model, np.asarray(q, float))
    sb = forward_kinematics(model, np.asarray(q_ref, float))

    def rel(st, i, par):
        R = st.rotations[0, i]
        return R if par == "ground" else st.rotations[0, model.body_index(par)].T @ R
    A = np.array([rel(sa, i, par) for i, par in pairs])
    B = np.array([rel(sb, i, par) for i, par in pairs])
    angles = Rotation.from_matrix(A @ np.transpose(B, (0, 2, 1))).magnitude()
    return float(np.sqrt(np.sum(angles ** 2)))


def spine_drift_bound(model: Model) -> dict:
    """A-priori upper bound of the spine drift allowed by the model's limits and couplings (rad).

    Every spine coordinate i can only reach ``[min q_i, max q_i]`` over the polytope
    ``{l_j <= q_j <= u_j for clamped j, C q = b, G q <= h}`` (spine coordinates and the
    constraint rows supported on them only; one linear programme per bound, scipy ``linprog``),
    of span ``s_i`` (inf when unbounded).  Since exp: R^3 -> SO(3) is 1-Lipschitz for the
    geodesic angle and the metric is bi-invariant, a vertebra with swing s and twist t moves by
    at most ``d_v = |s_swing| + s_twist`` (swing/twist joints) or ``|s_ball|`` (rotation-vector
    ball joints), so for any two reachable postures

        spine_distance(q, q')  <=  sqrt(sum_v d_v^2)       ('geodesic_rad')
        |q_spine - q'_spine|    <=  sqrt(sum_i s_i^2)       ('coordinate_rad').

    Returns dict with those two floats (inf when some spine coordinate is unbounded) and
    'span_rad' (coordinate name -> s_i).
    """
    from scipy.optimize import linprog
    names = model.coordinate_names
    spine_names = spine_coordinates(model)
    idx = np.array([names.index(n) for n in spine_names])
    other = np.setdiff1d(np.arange(model.n_q), idx)
    cons = ConstraintSet.from_model(model)
    eq_rows = np.all(cons.C[:, other] == 0.0, axis=1) if len(cons.b) else np.zeros(0, bool)
    in_rows = np.all(cons.G[:, other] == 0.0, axis=1) if len(cons.h) else np.zeros(0, bool)
    A_eq, b_eq = cons.C[eq_rows][:, idx], cons.b[eq_rows]
    A_ub, b_ub = cons.G[in_rows][:, idx], cons.h[in_rows]
    bounds = [(model.lower[i], model.upper[i]) if model.coordinates[i].clamped else (None, None) for i in idx]
    span = np.empty(len(idx))
    for k in range(len(idx)):
        ext = []
        for sign in (1.0, -1.0):
            c = np.zeros(len(idx))
            c[k] = sign
            r = linprog(c, A_ub=A_ub if len(b_ub) else None, b_ub=b_ub if len(b_ub) else None,
                        A_eq=A_eq if len(b_eq) else None, b_eq=b_eq if len(b_eq) else None,
                        bounds=bounds, method="highs")
            if r.status == 3:          # unbounded
                ext = None
                break
            if r.status != 0:
                raise FitError(f"spine drift bound: linear programme failed ({r.message})")
            ext.append(sign * r.fun)     # min q_k, then max q_k
        span[k] = np.inf if ext is None else ext[1] - ext[0]
    s_of = dict(zip(spine_names, span.tolist()))
    d = []
    for jn in _spine_layout_of(model).joints:
        comps = {c: s_of[_coord(jn, c)] for c in ("extension", "bending", "rotation") if _coord(jn, c) in s_of}
        if isinstance(model.joint(jn), SwingJoint):
            d.append(np.hypot(comps["extension"], comps["bending"]) + comps.get("rotation", 0.0))
        elif isinstance(model.joint(jn), ExpMapSpherical):
            d.append(np.sqrt(sum(v * v for v in comps.values())))
        else:
            d.append(sum(comps.values()))
    return {"geodesic_rad": float(np.sqrt(np.sum(np.square(d)))),
            "coordinate_rad": float(np.sqrt(np.sum(span ** 2))), "span_rad": s_of}


def swing_components(model: Model, q: np.ndarray) -> dict[str, np.ndarray]:
    """Swing (s_x: extension about z, s_y: bending about x) of each vertebra relative to the one below.

    Returns per region an array (k, 2) in rad: the swing rotation vector of
    the swing-twist decomposition, components about z and x.
    """
    layout = _spine_layout_of(model)
    st = forward_kinematics(model, np.asarray(q, float))
    out = {}
    joints = layout.joints
    for reg in layout.regions:
        rows = []
        for jn in reg.joints:
            i = joints.index(jn)
            below = _segment(joints[i - 1]) if i else model.joint(jn).parent
            R = (st.rotations[0, model.body_index(below)].T @ st.rotations[0, model.body_index(_segment(jn))])
            x, y, z, w = Rotation.from_matrix(R).as_quat()
            tw = Rotation.from_quat([0.0, y, 0.0, w]) if (y * y + w * w) > 0 else Rotation.identity()
            sw = (Rotation.from_matrix(R) * tw.inv()).as_rotvec()
            rows.append((sw[2], sw[0]))
        out[reg.name] = np.array(rows)
    return out


# ----------------------------------------------------------------------------- tasks on a Model
class KinematicTasks:
    """Factory of IK tasks on a `Model` sharing one forward-kinematics evaluation per configuration.

    Every task returned is a `Task` whose function maps q (n_q,) to
    (error, Jacobian); all of them read the same cached `KinematicState`
    (FK with column screws) for the last q, so a step costs one FK.
    """

    def __init__(self, model: Model):
        self.model = model
        self._key = None
        self._state: KinematicState | None = None
        K = model.column_coordinate.size
        self._scatter = np.zeros((K, model.n_q))
        self._scatter[np.arange(K), model.column_coordinate] = 1.0
        self._mass = np.array([bd.mass for bd in model.bodies])
        self._com = np.array([bd.com for bd in model.bodies])

    def state(self, q) -> KinematicState:
        q = np.asarray(q, float)
        key = q.tobytes()
        if key != self._key:
            self._state = forward_kinematics(self.model, q, jacobian=True)
            self._key = key
        return self._state

    def ancestors(self, body: str | None) -> tuple[str, ...]:
        """Coordinates moving `body` (all coordinates for None)."""
        names = self.model.coordinate_names
        if body is None:
            return names
        cols = self.model.body_columns[self.model.body_index(body)]
        return tuple(names[i] for i in sorted(set(self.model.column_coordinate[cols].tolist())))

    def _point_jac(self, st, b: int, x: np.ndarray) -> np.ndarray:
        mask = self.model.body_columns[b]
        cols = np.cross(st.omega[0], x) + st.v0[0]         # (K, 3)
        return (cols * mask[:, None]).T @ self._scatter      # (3, n_q)

    def position(self, name: str, body: str, point, target, priority: int, recruited=None,
                 max_error: float | None = 0.05, axes=(0, 1, 2)) -> Task:
        """Point `point` (body frame, m) of `body` to `target` (callable t() or array, ground, m)."""
        b = self.model.body_index(body)
        p = np.asarray(point, float).reshape(1, 3)
        ax = list(axes)
        target_fn = target if callable(target) else (lambda t=np.asarray(target, float): t)

        def f(q):
            st = self.state(q)
            x = point_positions(self.model, st, np.array([b]), p)[0, 0]
            return (target_fn() - x)[ax], self._point_jac(st, b, x)[ax]
        return Task(name, f, priority, recruited, self.ancestors(body), max_error)

    def orientation(self, name: str, body: str, target_rotation, priority: int, recruited=None,
                    max_error: float | None = 0.1) -> Task:
        """Orientation of `body` to `target_rotation` (3x3, ground): error log(R_t R^T) (rad, ground)."""
        b = self.model.body_index(body)
        Rt = np.asarray(target_rotation, float)

        def f(q):
            st = self.state(q)
            R = st.rotations[0, b]
            e = Rotation.from_matrix(Rt @ R.T).as_rotvec()
            Jw = (st.omega[0] * self.model.body_columns[b][:, None]).T @ self._scatter
            return e, Jw
        return Task(name, f, priority, recruited, self.ancestors(body), max_error)

    def com(self, name: str, target, priority: int, recruited=None, axes=(0, 2),
            max_error: float | None = 0.02) -> Task:
        """Whole-body centre of mass (components `axes`, default horizontal x, z) to `target` (m)."""
        ax = list(axes)
        target = np.asarray(target, float)
        w = self._mass / self._mass.sum()
        nb = self.model.n_bodies

        def f(q):
            st = self.state(q)
            x = point_positions(self.model, st, np.arange(nb), self._com)[0]        # (B, 3)
            c = w @ x
            mask = self.model.body_columns.astype(float)                          # (B, K)
            # sum_b w_b (omega_k x x_b + v0_k) mask_bk
            wx = np.einsum("b,bk,bi->ki", w, mask, x)
            v = np.einsum("b,bk->k", w, mask)[:, None] * st.v0[0]
            cols = np.cross(st.omega[0], wx) + v
            J = cols.T @ self._scatter
            return (target - c[ax]), J[ax]
        return Task(name, f, priority, recruited, self.model.coordinate_names, max_error)


# ----------------------------------------------------------------------------- experiments of the seed (section 5)
def spine_solver(model: Model, tasks: Sequence[Task], damping: float = 0.05, check: bool = True):
    """`PrioritizedIK` over a model: its couplings/inequalities and the ranges of clamped coordinates."""
    from kinematics.algorithms.prioritized import PrioritizedIK
    cons = ConstraintSet.from_model(model)
    clamped = np.array([c.clamped for c in model.coordinates])
    lower = np.where(clamped, model.lower, -np.inf)
    upper = np.where(clamped, model.upper, np.inf)
    return PrioritizedIK(model.coordinate_names, tasks, cons, lower, upper, damping=damping, check=check)


def isolated_spine_tasks(model: Model, kt: KinematicTasks | None = None,
                         orientation_rotvec=(0.15, 0.35, -0.3), position=(0.15, 0.70, 0.10)) -> list[Task]:
    """Experiment 5.1: head orientation (priority 0, rotation vector in rad) and head-top position (priority 1, m)."""
    kt = kt or KinematicTasks(model)
    Rt = Rotation.from_rotvec(orientation_rotvec).as_matrix()
    return [kt.orientation("head orientation", "skull", Rt, 0),
            kt.position("head position", "skull", (0.0, 0.2, 0.0), np.asarray(position, float), 1)]


def _marker_point(model: Model, name: str):
    mk = model.marker(name)
    return mk.body, mk.offset


def spine_coordinates(model: Model) -> tuple[str, ...]:
    """Coordinates of the vertebral joints of a model built by this module."""
    joints = set(_spine_layout_of(model).joints)
    return tuple(n for n in model.coordinate_names if n.split("_")[0] in joints)


def _hand_recruits(model: Model, kt: KinematicTasks, body: str, pelvis: bool = True) -> tuple[str, ...]:
    """A hand recruits its ancestors (without the pelvis when ``pelvis`` is False) and the whole
    spine: the cervical joints are coupled to the thoracic ones (inter-region inequalities), so
    eq. (4) requires the hand to recruit them too whenever a lower-priority task (the head) moves them."""
    anc = tuple(c for c in kt.ancestors(body) if pelvis or not c.startswith("pelvis_"))
    return anc + tuple(c for c in spine_coordinates(model) if c not in anc)


def balanced_posture_tasks(model: Model, kt: KinematicTasks | None = None, q0=None) -> list[Task]:
    """Experiment 5.2.1 on a mannequin (targets relative to the posture q0, metres).

    priority 0: centre of mass (x, z) over the middle of the left foot;
    priority 1: left heel, toe and lateral forefoot stay where they are (the seed uses heel and
    toe only, which leaves the foot free to roll about the heel-toe line);
    priority 2: right toe 0.35 m backwards and 0.15 m up, both hands reach forward-left;
    priority 3: head keeps looking forward (identity orientation).
    """
    kt = kt or KinematicTasks(model)
    q0 = model.default_q if q0 is None else np.asarray(q0, float)
    from kinematics.algorithms.fk import marker_positions
    x0 = dict(zip(model.marker_names, marker_positions(model, q0)))
    support = 0.5 * (x0["l_heel"] + x0["l_toe"])
    tasks = [kt.com("centre of mass over left foot", support[[0, 2]], 0)]
    for m in ("l_heel", "l_toe", "l_toe_lat"):
        body, off = _marker_point(model, m)
        tasks.append(kt.position(f"{m} on the ground", body, off, x0[m], 1))
    body, off = _marker_point(model, "r_toe")
    tasks.append(kt.position("right toe backwards", body, off, x0["r_toe"] + np.array([-0.35, 0.15, 0.0]), 2))
    for m, dz in (("r_hand", -0.25), ("l_hand", -0.15)):
        body, off = _marker_point(model, m)
        target = np.array([0.45, 1.15, x0[m][2] + dz])
        tasks.append(kt.position(f"{m} reaching", body, off, target, 2, recruited=_hand_recruits(model, kt, body)))
    tasks.append(kt.orientation("head looking forward", "skull", np.eye(3), 3))
    return tasks


class FigureEight:
    """Moving goal on a figure eight in the frontal (y-z) plane: z = a sin(phase), y = b sin(2 phase).

    ``phase`` (rad) is set by the caller; `target(offset)` returns a callable for a task.
    """

    def __init__(self, centre, a: float = 0.15, b: float = 0.08):
        self.centre = np.asarray(centre, float)
        self.a, self.b = float(a), float(b)
        self.phase = 0.0

    def point(self, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
        p = self.phase
        return self.centre + np.asarray(offset, float) + np.array([0.0, self.b * np.sin(2 * p), self.a * np.sin(p)])

    def target(self, offset=(0.0, 0.0, 0.0)):
        off = np.asarray(offset, float)
        return lambda: self.point(off)


def periodic_tasks(model: Model, eight: FigureEight, kt: KinematicTasks | None = None, q0=None,
                   recruit_pelvis: bool = True) -> list[Task]:
    """Experiment 5.2.2: COM between the feet (0), three sole points per foot fixed (1), hands on the
    figure eight (2), head looking forward (3).

    Deviations from the seed, applied to both models: a third sole point per foot (heel and toe
    alone let the foot roll about their line, a null-space motion that drifts freely) and the
    head task (without it the head, moved only through the centre of mass, drifts freely).
    """
    kt = kt or KinematicTasks(model)
    q0 = model.default_q if q0 is None else np.asarray(q0, float)
    from kinematics.algorithms.fk import marker_positions
    x0 = dict(zip(model.marker_names, marker_positions(model, q0)))
    feet = ("l_heel", "l_toe", "l_toe_lat", "r_heel", "r_toe", "r_toe_lat")
    support = np.mean([x0[m] for m in feet], axis=0)
    tasks = [kt.com("centre of mass between the feet", support[[0, 2]], 0)]
    for m in feet:
        body, off = _marker_point(model, m)
        tasks.append(kt.position(f"{m} on the ground", body, off, x0[m], 1))
    for m, dz in (("r_hand", 0.08), ("l_hand", -0.08)):
        body, off = _marker_point(model, m)
        tasks.append(kt.position(f"{m} on the figure eight", body, off, eight.target((0.0, 0.0, dz)), 2,
                                 recruited=_hand_recruits(model, kt, body, pelvis=recruit_pelvis), max_error=0.1))
    # the head keeps looking forward (as in 5.2.1): without it the head, moved only through the
    # centre of mass, would drift freely in both models
    head = tuple(c for c in kt.ancestors("skull") if recruit_pelvis or not c.startswith("pelvis_"))
    tasks.append(kt.orientation("head looking forward", "skull", np.eye(3), 3, recruited=head))
    return tasks


def periodic_drift(model: Model, cycles: int = 2000, steps_per_cycle: int = 24,
                   checkpoints: Sequence[int] = (5, 50, 100, 200, 600, 2000), settle: int = 60,
                   centre=(0.40, 1.15, 0.0), progress=None) -> dict:
    """Run the figure-eight task for `cycles` cycles; joint-space drift at the checkpoints.

    One IK step per goal sample, `steps_per_cycle` samples per cycle.  Drift
    after c cycles is |q(c) - q(1)| over the rotational coordinates (rad) with
    q(c) the posture at the end of cycle c; also the geodesic distances of the
    spine (`spine_distance`) and of the whole posture (`posture_distance`).
    ``settle`` steps first converge on the goal at phase 0.

    Returns dict with 'drift_rad' (Euclidean over rotational coordinates), 'drift_spine_rad'
    (`spine_distance`), 'drift_posture_rad' (`posture_distance`) (checkpoint -> rad),
    'postures' (checkpoint -> q), 'max_task_error' per level (m), 'max_equality_residual'
    (after every cycle), 'max_inequality_or_limit_excess' (after every step; <= 0 when never violated).
    """
    eight = FigureEight(centre)
    kt = KinematicTasks(model)
    ik = spine_solver(model, periodic_tasks(model, eight, kt))
    q = model.default_q.copy()
    for _ in range(settle):
        q = ik.step(q).q
    rot = model.rotational
    ref = None
    drift, drift_spine, drift_posture, postures = {}, {}, {}, {}
    max_err = np.zeros(len(ik.levels))
    cons = ik.constraints
    max_res = 0.0
    max_excess = -np.inf
    wanted = set(int(c) for c in checkpoints if c <= cycles)
    for c in range(1, cycles + 1):
        for k in range(steps_per_cycle):
            eight.phase = 2 * np.pi * (k + 1) / steps_per_cycle
            r = ik.step(q)
            q = r.q
            max_err = np.maximum(max_err, r.errors)
            max_excess = max(max_excess, float(np.max(cons.inequality_excess(q), initial=0.0)),
                             float(np.max(ik.lower - q)), float(np.max(q - ik.upper)))
        if len(cons.b):
            max_res = max(max_res, float(np.max(np.abs(cons.equality_residual(q)))))
        if c == 1:
            ref = q.copy()
            postures[1] = ref
        if c in wanted:
            drift[c] = float(np.linalg.norm((q - ref)[rot]))
            drift_spine[c] = spine_distance(model, q, ref)
            drift_posture[c] = posture_distance(model, q, ref)
            postures[c] = q.copy()
        if progress is not None:
            progress(c)
    return {"drift_rad": drift, "drift_spine_rad": drift_spine, "drift_posture_rad": drift_posture,
            "postures": postures,
            "max_task_error": max_err.tolist(), "max_equality_residual": max_res,
            "max_inequality_or_limit_excess": max_excess}
