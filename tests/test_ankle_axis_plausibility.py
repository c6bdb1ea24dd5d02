"""The ankle axis: a talar dome axis far from the bimalleolar line is not used as the talocrural axis
(personalize.frames, ANKLE_AXIS_MALLEOLAR_MAX_DEG)."""
from __future__ import annotations

import numpy as np
import pytest

from personalize.frames import ANKLE_AXIS_MALLEOLAR_MAX_DEG, _ankle_centre
from personalize.landmarks import Axis, BoneLandmarks, Landmark


def _bones(dome_deg: float):
    """Right ankle: dome centre at the origin, malleolus tips 70 mm apart along +Z (right), the dome axis turned
    `dome_deg` from that line about the vertical Y."""
    cov = (0.0005 ** 2) * np.eye(3)
    a = np.radians(dome_deg)
    u = np.array([np.sin(a), 0.0, np.cos(a)])
    tal = BoneLandmarks(bone="talus_r", side="r", landmarks={"talar_dome_centre": Landmark(np.zeros(3), cov)},
                        axes={"ankle_axis": Axis(np.zeros(3), u, 1.0)}, scalars={"talar_dome_radius": 0.021})
    tib = BoneLandmarks(bone="tibia_r", side="r",
                        landmarks={"medial_malleolus_tip": Landmark(np.array([0.0, -0.01, -0.035]), cov)})
    fib = BoneLandmarks(bone="fibula_r", side="r",
                        landmarks={"lateral_malleolus_tip": Landmark(np.array([0.0, -0.01, 0.035]), cov)})
    return tal, tib, fib


def _angle(u, v) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(np.dot(u, v)) / np.linalg.norm(u) / np.linalg.norm(v))))))


@pytest.mark.parametrize("dome_deg", [5.0, 20.0])
def test_a_plausible_dome_axis_is_the_ankle_axis(dome_deg):
    _, _, _, u, sd, _, flags = _ankle_centre(*_bones(dome_deg), "r")
    a = np.radians(dome_deg)
    assert _angle(u, [np.sin(a), 0.0, np.cos(a)]) < 0.5 and sd < 5.0


def test_a_dome_axis_far_from_the_malleoli_gives_way_to_them():
    assert ANKLE_AXIS_MALLEOLAR_MAX_DEG < 78.0
    _, _, _, u, sd, info, flags = _ankle_centre(*_bones(78.0), "r")
    assert _angle(u, [0.0, 0.0, 1.0]) < 0.5                      # the malleolar line
    assert "low_confidence" in flags and info["axis"]["used"] == ["malleoli"]
    # the dome's disagreement is reported (its spread enters the joint's stated sd downstream, joints_from_landmarks)
    assert info["axis"]["disagreeing"] == ["talar_dome"] and info["axis"]["spread_deg"] == pytest.approx(78.0, abs=0.5)
