"""Small engine-built models shared by the kinematics tests (not a test module)."""
from __future__ import annotations

import numpy as np

from kinematics.multibody.functions import Linear, Multiplier, SimmSpline
from kinematics.multibody.joints import (CustomJoint, ExpMapSpherical, SwingJoint, Transform, TransformAxis, free, prismatic,
                               revolute, spherical, universal, weld)
from kinematics.multibody.model import Body, Coordinate, Marker, Model

KNEE_X = SimmSpline([-2.0944, -1.74533, -1.39626, -1.0472, -0.698132, -0.349066, -0.174533, 0.197344, 0.337395],
                    [-0.0032, 0.00179, 0.00411, 0.0041, 0.00212, -0.001, -0.0031, -0.005227, -0.005435])
KNEE_Y = SimmSpline([-2.0944, -1.22173, -0.523599, -0.349066, -0.174533, 0.159149, 2.0944],
                    [-0.4226, -0.4082, -0.399, -0.3976, -0.3966, -0.395264, -0.396])


def _markers(body, pts):
    return [Marker(f"{body}_{i}", body, p) for i, p in enumerate(pts)]


def leg_model(exportable: bool = True) -> Model:
    """Pelvis (free) - thigh (spherical ZXY hip) - shank (OpenSim-like spline knee) - foot (universal) - toe (pin)
    - heel pad (weld) and a sled on a slider; with ``exportable=False`` also a swing joint and an exp-map arm."""
    rad = "rotational"
    tr = "translational"
    deg = np.pi / 180
    coords = [
        Coordinate("pelvis_tilt", rad, 0.0, (-90 * deg, 90 * deg)),
        Coordinate("pelvis_list", rad, 0.0, (-90 * deg, 90 * deg)),
        Coordinate("pelvis_rotation", rad, 0.0, (-90 * deg, 90 * deg)),
        Coordinate("pelvis_tx", tr, 0.0, (-2, 2)),
        Coordinate("pelvis_ty", tr, 0.95, (0, 2)),
        Coordinate("pelvis_tz", tr, 0.0, (-2, 2)),
        Coordinate("hip_flexion", rad, 0.0, (-40 * deg, 120 * deg)),
        Coordinate("hip_adduction", rad, 0.0, (-30 * deg, 30 * deg)),
        Coordinate("hip_rotation", rad, 0.0, (-40 * deg, 40 * deg)),
        Coordinate("knee_angle", rad, 0.0, (-120 * deg, 10 * deg)),
        Coordinate("ankle_angle", rad, 0.0, (-40 * deg, 30 * deg)),
        Coordinate("subtalar_angle", rad, 0.0, (-20 * deg, 20 * deg)),
        Coordinate("mtp_angle", rad, 0.0, (-30 * deg, 30 * deg)),
        Coordinate("sled", tr, 0.0, (-0.1, 0.1)),
    ]
    knee = CustomJoint(
        "knee", "thigh", "shank", ("knee_angle",),
        parent_offset=Transform.from_euler_xyz((0.0, 0.0, 0.05), (0.0, -0.02, 0.0)),
        child_offset=Transform(),
        rotations=(TransformAxis((0, 0, 1), Linear(1.0, 0.0), ("knee_angle",)),),
        translations=(TransformAxis((1, 0, 0), Multiplier(KNEE_X, 1.1), ("knee_angle",)),
                      TransformAxis((0, 1, 0), Multiplier(KNEE_Y, 1.1), ("knee_angle",))),
    )
    joints = [
        free("ground_pelvis", "ground", "pelvis",
             ("pelvis_tilt", "pelvis_list", "pelvis_rotation", "pelvis_tx", "pelvis_ty", "pelvis_tz"), sequence="ZXY"),
        spherical("hip", "pelvis", "thigh", ("hip_flexion", "hip_adduction", "hip_rotation"), sequence="ZXY",
                  parent_offset=Transform((np.eye(3)), (-0.07, -0.07, 0.08))),
        knee,
        universal("ankle", "shank", "foot", ("ankle_angle", "subtalar_angle"), axes=((0, 0, 1), (0.8, 0.6, 0.0)),
                  parent_offset=Transform.from_euler_xyz((0.1, -0.05, 0.02), (0.0, -0.43, 0.0)),
                  child_offset=Transform.from_euler_xyz((0.0, 0.2, 0.0), (-0.05, 0.04, 0.0))),
        revolute("mtp", "foot", "toes", "mtp_angle", axis=(0.3, 0.0, 0.95),
                 parent_offset=Transform((np.eye(3)), (0.18, -0.002, 0.001))),
        weld("heel_pad", "foot", "pad", parent_offset=Transform.from_euler_xyz((0.0, 0.3, 0.0), (-0.02, -0.03, 0.0))),
        prismatic("sled_joint", "pelvis", "sled", "sled", axis=(0.0, 0.6, 0.8)),
    ]
    bodies = [
        Body("pelvis", 10.0, (-0.07, 0.0, 0.0), np.diag([0.1, 0.08, 0.05])),
        Body("thigh", 8.0, (0.0, -0.17, 0.0), np.diag([0.11, 0.03, 0.12])),
        Body("shank", 3.5, (0.0, -0.18, 0.0), np.diag([0.05, 0.005, 0.05])),
        Body("foot", 1.2, (0.1, 0.03, 0.0), np.diag([0.002, 0.005, 0.005])),
        Body("toes", 0.2, (0.03, 0.0, 0.0), np.diag([1e-4, 2e-4, 1e-4])),
        Body("pad", 0.05, (0.0, 0.0, 0.0), np.diag([1e-5, 1e-5, 1e-5])),
        Body("sled", 0.5, (0.0, 0.0, 0.0), np.diag([1e-3, 1e-3, 1e-3])),
    ]
    markers = (
        _markers("pelvis", [(0.02, 0.03, 0.13), (0.02, 0.03, -0.13), (-0.17, 0.05, 0.0), (-0.1, 0.12, 0.05)])
        + _markers("thigh", [(0.06, -0.2, 0.05), (0.0, -0.3, 0.08), (-0.05, -0.25, 0.0), (0.0, -0.39, 0.05)])
        + _markers("shank", [(0.05, -0.15, 0.03), (0.0, -0.25, 0.06), (-0.04, -0.2, 0.0), (0.0, -0.4, 0.05)])
        + _markers("foot", [(-0.02, 0.02, 0.0), (0.1, 0.04, 0.04), (0.15, 0.01, -0.03), (0.08, 0.06, 0.0)])
        + _markers("toes", [(0.05, 0.0, 0.0), (0.03, 0.01, 0.03)])
        + _markers("pad", [(0.0, -0.01, 0.02)])
        + _markers("sled", [(0.1, 0.0, 0.0), (0.0, 0.1, 0.0), (0.0, 0.0, 0.1)])
    )
    if not exportable:
        coords += [Coordinate("swing_a", rad, 0.0, (-1, 1)), Coordinate("swing_b", rad, 0.0, (-1, 1)),
                   Coordinate("arm_x", rad, 0.0, (-1, 1)), Coordinate("arm_y", rad, 0.0, (-1, 1)),
                   Coordinate("arm_z", rad, 0.0, (-1, 1))]
        joints += [
            SwingJoint("swing", "pelvis", "tail", ("swing_a", "swing_b"),
                       Transform.from_euler_xyz((0.2, 0.0, 0.1), (-0.2, 0.0, 0.0)), Transform(),
                       axes=((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))),
            ExpMapSpherical("shoulder", "pelvis", "arm", ("arm_x", "arm_y", "arm_z"),
                            Transform((np.eye(3)), (0.0, 0.4, 0.2)), Transform((np.eye(3)), (0.0, 0.05, 0.0))),
        ]
        bodies += [Body("tail", 0.1, (0, -0.05, 0), np.eye(3) * 1e-4), Body("arm", 2.0, (0, -0.15, 0), np.eye(3) * 0.01)]
        markers += _markers("tail", [(0.0, -0.1, 0.01), (0.02, -0.05, 0.0), (0.0, 0.0, 0.05)])
        markers += _markers("arm", [(0.03, -0.1, 0.0), (0.0, -0.25, 0.04), (-0.03, -0.2, 0.0)])
    return Model(tuple(bodies), tuple(joints), tuple(coords), tuple(markers), name="leg")
