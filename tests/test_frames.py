"""Joint frames from landmarks: conventions (Z main axis, right-handed), origins, dropped joints."""
from __future__ import annotations

import numpy as np
import pytest

from lowerlimb.geometry import frame_yz, frame_zy
from personalize.frames import closest_on_line, joints_from_landmarks
from personalize.landmarks.common import Axis, BoneLandmarks, Landmark, LandmarkSet


def _rot(seed):
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=seed).as_matrix()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_frame_zy_keeps_z_and_is_right_handed(seed):
    rng = np.random.default_rng(seed)
    z, y = rng.normal(size=3), rng.normal(size=3)
    R = frame_zy(z, y)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    assert np.allclose(R[:, 2], z / np.linalg.norm(z), atol=1e-12)
    # Y is the hint made orthogonal to Z: it stays in the plane of (y, z), on y's side
    assert abs(np.cross(y, z) @ R[:, 1]) < 1e-12
    assert R[:, 1] @ y > 0


def test_frame_yz_keeps_y():
    y, z = np.array([0.1, 1.0, 0.2]), np.array([0.0, 0.3, 1.0])
    R = frame_yz(y, z)
    assert np.allclose(R[:, 1], y / np.linalg.norm(y))
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(R[:, 0], np.cross(R[:, 1], R[:, 2]))


def test_closest_on_line():
    p = closest_on_line([0, 0, 0], [0, 0, 2.0], [1.0, 2.0, 3.0])
    assert np.allclose(p, [0, 0, 3.0])


def _lm(p, s=1e-4):
    return Landmark(np.asarray(p, float), (s * s) * np.eye(3))


def _toy_leg(R=np.eye(3), t=np.zeros(3)) -> LandmarkSet:
    """A straight right leg in body axes X anterior, Y up, Z right, moved by (R, t)."""
    P = lambda p: R @ np.asarray(p, float) + t  # noqa: E731
    D = lambda d: R @ np.asarray(d, float)  # noqa: E731
    ls = LandmarkSet()
    pel = BoneLandmarks("pelvis", None)
    pel.landmarks = {"RASI": _lm(P([0.05, 1.0, 0.12])), "LASI": _lm(P([0.05, 1.0, -0.12]))}
    pel.frames["isb"] = {"origin": P([0.05, 1.0, 0.0]), "rotation": R @ np.eye(3)}
    fem = BoneLandmarks("femur_r", "r")
    fem.landmarks = {"femoral_head_centre": _lm(P([0.0, 0.9, 0.08])),
                     "intercondylar_midpoint": _lm(P([0.0, 0.5, 0.1]))}
    fem.axes = {"knee_axis": Axis(P([0.0, 0.5, 0.1]), D([0.0, 0.0, 1.0]), 0.5),
                "shaft_axis": Axis(P([0.0, 0.7, 0.09]), D([0.0, 1.0, 0.0]), 1.0)}
    tib = BoneLandmarks("tibia_r", "r")
    tib.axes = {"shaft_axis": Axis(P([0.0, 0.3, 0.1]), D([0.0, 1.0, 0.0]), 1.0)}
    tal = BoneLandmarks("talus_r", "r")
    tal.landmarks = {"talar_dome_centre": _lm(P([0.0, 0.08, 0.1]))}
    st = np.array([0.7, 0.6, -0.3])
    tal.axes = {"ankle_axis": Axis(P([0.0, 0.08, 0.1]), D([0.2, 0.0, 1.0] / np.linalg.norm([0.2, 0, 1.0])), 1.0),
                "subtalar_axis": Axis(P([0.0, 0.05, 0.1]), D(st / np.linalg.norm(st)), 2.0)}
    tal.frames["anatomical"] = {"origin": P([0, 0.08, 0.1]), "rotation": R @ np.eye(3)}
    cal = BoneLandmarks("calcn_r", "r")
    cal.frames["foot"] = {"origin": P([-0.05, 0.0, 0.1]), "rotation": R @ np.eye(3)}
    cal.landmarks = {"met1_head_centre": _lm(P([0.15, 0.01, 0.08])), "met5_head_centre": _lm(P([0.13, 0.01, 0.13]))}
    cal.axes = {"mtp_axis": Axis(P([0.14, 0.01, 0.105]), D(np.array([-0.02, 0, 0.05]) / np.linalg.norm([-0.02, 0, 0.05])), 1.0)}
    toe = BoneLandmarks("toes_r", "r")
    ls.bones = {"pelvis": pel, "femur_r": fem, "tibia_r": tib, "talus_r": tal, "calcn_r": cal, "toes_r": toe}
    return ls


def test_joints_conventions_on_toy_leg():
    J, dropped = joints_from_landmarks(_toy_leg())
    assert set(J) == {"hip_r", "knee_r", "ankle_r", "subtalar_r", "mtp_r"}
    assert all(k.endswith("_l") for k in dropped)
    assert np.allclose(J["hip_r"].origin, [0.0, 0.9, 0.08])
    assert np.allclose(J["hip_r"].rotation, np.eye(3))
    assert np.allclose(J["knee_r"].origin, [0.0, 0.5, 0.1])
    assert np.allclose(J["knee_r"].rotation, np.eye(3), atol=1e-12)   # Y towards the hip, orthogonalised
    za = np.array([0.2, 0.0, 1.0]) / np.linalg.norm([0.2, 0.0, 1.0])
    assert np.allclose(J["ankle_r"].rotation[:, 2], za)
    # subtalar origin: point of the axis closest to the talar dome centre
    st = np.array([0.7, 0.6, -0.3]) / np.linalg.norm([0.7, 0.6, -0.3])
    o = J["subtalar_r"].origin
    assert abs((o - np.array([0.0, 0.08, 0.1])) @ st) < 1e-12
    assert np.allclose(J["subtalar_r"].rotation[:, 2], st)
    for j in J.values():
        assert np.linalg.det(j.rotation) == pytest.approx(1.0, abs=1e-9)
        assert j.axis_sd_deg >= 0 and np.all(np.linalg.eigvalsh(j.origin_cov) > 0)


def test_joints_move_with_the_input():
    R, t = _rot(5), np.array([0.3, -0.2, 1.1])
    J0, _ = joints_from_landmarks(_toy_leg())
    J1, _ = joints_from_landmarks(_toy_leg(R, t))
    for k in J0:
        assert np.allclose(J1[k].origin, R @ J0[k].origin + t, atol=1e-12)
        assert np.allclose(J1[k].rotation, R @ J0[k].rotation, atol=1e-12)
        assert np.allclose(J1[k].origin_cov, R @ J0[k].origin_cov @ R.T, atol=1e-18)


def test_missing_bone_drops_only_its_joints():
    ls = _toy_leg()
    del ls.bones["talus_r"]
    J, dropped = joints_from_landmarks(ls)
    assert set(J) == {"hip_r", "knee_r", "mtp_r"}
    assert "talus_r" in dropped["ankle_r"] and "talus_r" in dropped["subtalar_r"]
