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
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kinematics.algorithms.constraints import ConstraintSet, LinearConstraint
from kinematics.multibody.joints import ExpMapSpherical, SwingJoint, Transform, free, revolute, spherical, universal, weld
from kinematics.multibody.model import Body, Coordinate, Marker, Model
from lowerlimb.errors import InputError

__all__ = [
    "RegionSpec", "SpineLayout", "spine_layout", "spine_layout_of", "spine_constraints", "isolated_spine", "mannequin",
    "vertebra_body", "component_coordinate", "SPINE_LIMITS",
]

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


def vertebra_body(joint: str) -> str:
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


def spine_layout_of(model: Model) -> SpineLayout:
    """Layout of a model built by this module (full spine when it has the l4 vertebra)."""
    kind = "full" if "l4" in model.body_names else "simplified"
    return spine_layout(kind)


def component_coordinate(joint: str, component: str) -> str:
    """Coordinate of one component ('extension', 'bending', 'rotation') of a vertebral joint."""
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
                eqs.append(LinearConstraint.ratio(component_coordinate(j, comp), component_coordinate(first, comp), k,
                                                  f"{reg.name}: {j} {comp} = {k:.3g} x {first}"))
        for j in twist[1:]:
            k = reg.twist[j] / reg.twist[twist[0]]
            eqs.append(LinearConstraint.ratio(component_coordinate(j, "rotation"), component_coordinate(twist[0], "rotation"), k,
                                              f"{reg.name}: {j} rotation = {k:.3g} x {twist[0]}"))
    for lower, upper in zip(layout.regions[:-1], layout.regions[1:]):
        for comp in ("extension", "bending", "rotation"):
            pool_lo = [j for j in lower.joints if j in (lower.twist if comp == "rotation" else lower.swing)]
            pool_up = [j for j in upper.joints if j in (upper.twist if comp == "rotation" else upper.swing)]
            a, b = pool_lo[-1], pool_up[0]
            ra, rb = lower.joint_range(a, comp), upper.joint_range(b, comp)
            k = (rb[1] - rb[0]) / (ra[1] - ra[0])
            delta = 0.25 * (rb[1] - rb[0])
            ineqs.extend(LinearConstraint.band(component_coordinate(b, comp), component_coordinate(a, comp), k, delta,
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
            seg = vertebra_body(jn)
            po = Transform(np.eye(3), prev_offset)
            first_swing = [j for j in reg.joints if j in reg.swing][:1]
            first_twist = [j for j in reg.joints if j in reg.twist][:1]
            if joint_style == "ball":
                names = [component_coordinate(jn, c) for c in ("bending", "rotation", "extension")]   # rotation vector x, y, z
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
                        b.coordinate(component_coordinate(jn, comp), reg.joint_range(jn, comp), clamped=clamp)
                    if has_twist:
                        b.body(child_swing)   # massless link between the swing and the twist joint
                    b.joints.append(SwingJoint(jn, prev, child_swing, (component_coordinate(jn, "extension"), component_coordinate(jn, "bending")),
                                               po, Transform(), axes=(_EXT_AXIS, _BEND_AXIS)))
                if has_twist:
                    clamp = limits == "all" or (limits == "first" and jn in first_twist)
                    b.coordinate(component_coordinate(jn, "rotation"), reg.joint_range(jn, "rotation"), clamped=clamp)
                    parent_twist = child_swing if has_swing else prev
                    po_twist = Transform() if has_swing else po
                    b.joints.append(revolute(jn + ("_twist" if has_swing else ""), parent_twist, seg,
                                             component_coordinate(jn, "rotation"), _TWIST_AXIS, po_twist))
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
    thoracic_top = vertebra_body(layout.regions[1].joints[-1])
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

