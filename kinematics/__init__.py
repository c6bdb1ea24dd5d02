"""Multibody kinematics: models, joints, transmission elements, FK/IK, correlative and coupled joints, marker data.

Subpackages: `multibody` (the model), `algorithms` (FK, marker and prioritized IK, loops),
`io` (files), `gait` (reconstruction from marker trials, kinetics), `mechanisms`
(correlative joints, transmission, chords, spines).  This package imports `lowerlimb`
and never `personalize`, `phantoms` or matplotlib (tables and figures live in
`personalize.presentation`).
"""
from kinematics.multibody.model import Body, Coordinate, Frame, Marker, Model
from kinematics.multibody.joints import CustomJoint, ExpMapSpherical, SwingJoint, Transform, TransformAxis
from kinematics.multibody.coupling import CoordinateCoupler, LinearCoupling, LinearInequalities
from kinematics.algorithms.fk import forward_kinematics, marker_jacobian, marker_positions
from kinematics.algorithms.ik import IKResult, solve_ik
from kinematics.io.opensim_io import load_osim, save_osim

__all__ = ["Body", "Coordinate", "Frame", "Marker", "Model", "CustomJoint",
           "ExpMapSpherical", "SwingJoint", "Transform", "TransformAxis", "CoordinateCoupler", "LinearCoupling",
           "LinearInequalities", "forward_kinematics", "marker_jacobian", "marker_positions", "IKResult", "solve_ik",
           "load_osim", "save_osim"]
