"""Multibody kinematics: models, joints, transmission elements, FK/IK, correlative and coupled joints, marker data.

This package never imports `personalize`.
"""
from .errors import FitError, InputError

__all__ = ["InputError", "FitError"]
