"""Error types (shared with `kinematics`, which owns them)."""
from kinematics.errors import FitError, InputError

__all__ = ["InputError", "FitError"]
