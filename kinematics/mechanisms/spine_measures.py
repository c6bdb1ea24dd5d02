"""Measures of spine postures: vertebral twist and swing, parametrisation-free distances, drift bound.

For models built by `kinematics.mechanisms.spine` (H-Anim vertebral joints;
y the vertebral axis).  Angles in radians.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.algorithms.constraints import ConstraintSet
from kinematics.algorithms.fk import forward_kinematics
from kinematics.mechanisms.spine import component_coordinate, spine_layout_of, vertebra_body
from kinematics.multibody.joints import ExpMapSpherical, SwingJoint
from kinematics.multibody.model import Model
from lowerlimb.errors import FitError

__all__ = ["vertebral_twist", "torsion_direction_changes", "swing_components", "spine_coordinates",
           "spine_distance", "posture_distance", "spine_drift_bound"]


def vertebral_twist(model: Model, q: np.ndarray) -> dict[str, np.ndarray]:
    """Torsion of each vertebra relative to the one below (rad), per region, caudal to cranial.

    The relative rotation R = R_below^T R_vertebra is split into swing and
    twist about the vertebral axis y (swing-twist decomposition): with the
    quaternion (w, x, y, z) of R, twist = 2 atan2(y, w), wrapped to (-pi, pi].
    """
    out = {}
    for region, rel in _relative_rotations_by_region(model, q).items():
        tw = []
        for R in rel:
            x, y, z, w = Rotation.from_matrix(R).as_quat()
            t = 2.0 * np.arctan2(y, w)
            tw.append((t + np.pi) % (2 * np.pi) - np.pi)
        out[region] = np.array(tw)
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
    layout = spine_layout_of(model)
    st = forward_kinematics(model, np.asarray(q, float))
    joints = layout.joints
    out = []
    for i, jn in enumerate(joints):
        below = vertebra_body(joints[i - 1]) if i else model.joint(jn).parent
        out.append(st.rotations[0, model.body_index(below)].T @ st.rotations[0, model.body_index(vertebra_body(jn))])
    return np.array(out)


def _relative_rotations_by_region(model: Model, q: np.ndarray) -> dict[str, np.ndarray]:
    """`_relative_rotations` split per region: name -> (k, 3, 3), caudal to cranial."""
    rel = _relative_rotations(model, q)
    out, k = {}, 0
    for reg in spine_layout_of(model).regions:
        out[reg.name] = rel[k:k + len(reg.joints)]
        k += len(reg.joints)
    return out


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
    for jn in spine_layout_of(model).joints:
        comps = {c: s_of[component_coordinate(jn, c)] for c in ("extension", "bending", "rotation") if component_coordinate(jn, c) in s_of}
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
    out = {}
    for region, rel in _relative_rotations_by_region(model, q).items():
        rows = []
        for R in rel:
            x, y, z, w = Rotation.from_matrix(R).as_quat()
            tw = Rotation.from_quat([0.0, y, 0.0, w]) if (y * y + w * w) > 0 else Rotation.identity()
            sw = (Rotation.from_matrix(R) * tw.inv()).as_rotvec()
            rows.append((sw[2], sw[0]))
        out[region] = np.array(rows)
    return out


def spine_coordinates(model: Model) -> tuple[str, ...]:
    """Coordinates of the vertebral joints of a model built by this module."""
    joints = set(spine_layout_of(model).joints)
    return tuple(n for n in model.coordinate_names if n.split("_")[0] in joints)
