"""Multibody kinematics: models, joints, transmission elements, FK/IK, correlative and coupled joints, marker data.

This package never imports `personalize`.
"""
from .errors import FitError, InputError
from .model import Body, Coordinate, Frame, Marker, Model
from .joints import CustomJoint, ExpMapSpherical, SwingJoint, Transform, TransformAxis
from .coupling import CoordinateCoupler, LinearCoupling, LinearInequalities
from .fk import forward_kinematics, marker_jacobian, marker_positions
from .ik import IKResult, solve_ik
from .opensim_io import load_osim, save_osim

__all__ = ["InputError", "FitError", "Body", "Coordinate", "Frame", "Marker", "Model", "CustomJoint",
           "ExpMapSpherical", "SwingJoint", "Transform", "TransformAxis", "CoordinateCoupler", "LinearCoupling",
           "LinearInequalities", "forward_kinematics", "marker_jacobian", "marker_positions", "IKResult", "solve_ik",
           "load_osim", "save_osim"]
