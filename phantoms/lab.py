"""Gait-lab frames as labs set them up: which axis is up, which way the subject walks.

The phantom's model ground follows OpenSim (X forward, Y up, Z to the
subject's right).  A `Lab` carries it into the lab's own axes:
``x_lab = lab_from_model @ x_model + origin``, with ``lab_from_model`` the
proper rotation whose columns are the lab components of forward, up and
right.  ``z-up`` is Vicon's usual set-up (Z up), ``y-up`` OpenSim's and many
Motion Analysis / Qualisys labs' (Y up); the walking direction is any
horizontal lab axis (``+x``, ``-x``, ``+y``, ``-y``, ``+z``, ``-z``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lowerlimb.errors import InputError

__all__ = ["Lab", "make_lab", "LAB_UPS"]

_AXES = {"x": 0, "y": 1, "z": 2}
LAB_UPS = ("z-up", "y-up")


def _axis(text: str) -> np.ndarray:
    t = text.strip().lower()
    sign = -1.0 if t.startswith("-") else 1.0
    t = t.lstrip("+-")
    if t not in _AXES:
        raise InputError("--walk", f"{text!r} is not one of +x, -x, +y, -y, +z, -z")
    v = np.zeros(3)
    v[_AXES[t]] = sign
    return v


@dataclass(frozen=True)
class Lab:
    """A lab frame: ``up`` and ``forward`` (walking direction) as lab unit vectors; ``origin`` (m).

    ``lab_from_model`` (3, 3): columns = lab components of model X (forward), Y (up), Z (right).
    """

    name: str
    up: np.ndarray
    forward: np.ndarray
    origin: np.ndarray

    @property
    def lab_from_model(self) -> np.ndarray:
        right = np.cross(self.forward, self.up)
        return np.column_stack([self.forward, self.up, right])

    def to_lab(self, x_model: np.ndarray) -> np.ndarray:
        """Model-ground points (..., 3) -> lab points."""
        return np.asarray(x_model, float) @ self.lab_from_model.T + self.origin

    def to_json(self) -> dict:
        R = self.lab_from_model
        return {"name": self.name, "up": self.up.tolist(), "forward": self.forward.tolist(),
                "right": R[:, 2].tolist(), "origin_m": self.origin.tolist(), "lab_from_model": R.tolist(),
                "model_ground": "X forward, Y up, Z right (OpenSim); x_lab = lab_from_model @ x_model + origin_m",
                "gravity_lab": (-9.80665 * self.up).tolist(), "units": "m"}


def make_lab(up: str = "z-up", walk: str = "+x", start: float = -1.5) -> Lab:
    """The lab with ``up`` in `LAB_UPS` and walking direction `walk` (a horizontal lab axis, ``+x`` ...).

    `start` (m) places the model origin along the walking direction (walks start before the lab origin).
    """
    key = up.strip().lower()
    if key not in LAB_UPS:
        raise InputError("--lab", f"{up!r} is not one of {', '.join(LAB_UPS)}")
    u = np.zeros(3)
    u[2 if key == "z-up" else 1] = 1.0
    f = _axis(walk)
    if abs(f @ u) > 0.5:
        raise InputError("--walk", f"{walk!r} is the vertical of a {key} lab: give a horizontal axis")
    return Lab(key, u, f, start * f)
