"""detect_lab on the real trials of ../shared/data: the vertical, progression and floor read from the data."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.gait.lab_frame import detect_lab
from kinematics.io.trials import read_trial
from lowerlimb.errors import InputError


@pytest.fixture(scope="module")
def gait2392(shared_data):
    d = shared_data / "opensim_gait2392"
    return read_trial(d / "subject01_static.trc"), read_trial(d / "subject01_walk1.trc")


@pytest.fixture(scope="module")
def pig(shared_data):
    d = shared_data / "mocap_pig"
    return read_trial(d / "Static_trial.c3d"), read_trial(d / "Movement_trial.c3d")


def _rotated(trial, rot: np.ndarray):
    return replace(trial, positions=trial.positions @ rot.T)


def _anonymous(trial):
    return replace(trial, names=tuple(f"M{i}" for i in range(len(trial.names))))


def _check_opensim_rotation(lab):
    r = lab.rotation_to_opensim
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ lab.up, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(r @ lab.forward, [1, 0, 0], atol=1e-12)


def test_gait2392_is_y_up_facing_x(gait2392):
    static, walk = gait2392
    lab = detect_lab(static, [walk])
    np.testing.assert_array_equal(lab.up, [0, 1, 0])
    # walk1 is walking in place (pelvis moves < 0.3 m): forward from the feet, +X within 5 deg
    assert not lab.walking
    assert lab.forward @ [1, 0, 0] > np.cos(np.radians(5))
    assert abs(lab.forward @ lab.up) < 1e-12
    # heel and toe marker centres sit 20-60 mm above the floor of OpenSim's ground (Y = 0)
    assert 0.02 < lab.floor_height < 0.06
    assert lab.describe().startswith("Y up, facing +X")
    assert any("R.ASIS" in e and "R.Heel" in e for e in lab.evidence)
    _check_opensim_rotation(lab)
    # the walking trial alone gives the same lab
    alone = detect_lab(None, [walk])
    np.testing.assert_array_equal(alone.up, [0, 1, 0])
    assert alone.forward @ [1, 0, 0] > np.cos(np.radians(5))  # 2.7 deg off +X (the static: 2.9 deg the other way)


def test_pig_is_z_up_walking_minus_x(pig):
    static, walk = pig
    lab = detect_lab(static, [walk])
    np.testing.assert_array_equal(lab.up, [0, 0, 1])
    # the movement trial's pelvis travels 1.3 m along -X (stairs down); the static pose faces +X
    assert lab.walking
    assert lab.forward @ [-1, 0, 0] > np.cos(np.radians(5))
    assert lab.describe().startswith("Z up, walking -X")
    assert any("LASI" in e and "LHEE" in e for e in lab.evidence)
    assert -0.17 < lab.floor_height < -0.14
    _check_opensim_rotation(lab)
    standing = detect_lab(static, [])
    np.testing.assert_array_equal(standing.up, [0, 0, 1])
    assert standing.forward @ [1, 0, 0] > np.cos(np.radians(5))
    assert standing.describe().startswith("Z up, facing +X")


def test_pig_without_names_uses_geometry(pig):
    static, walk = pig
    lab = detect_lab(_anonymous(static), [_anonymous(walk)])
    np.testing.assert_array_equal(lab.up, [0, 0, 1])
    assert lab.forward @ [-1, 0, 0] > np.cos(np.radians(5))
    assert any("geometry" in e for e in lab.evidence)
    # a standing trial alone without names cannot tell the feet from the (T-pose) hands and head
    with pytest.raises(InputError, match="cannot tell the feet from the head"):
        detect_lab(_anonymous(static), [])


@pytest.mark.parametrize("k", range(24))
def test_pig_rotated_by_every_axis_permutation(pig, k):
    static, walk = pig
    base = detect_lab(static, [walk])
    rot = np.rint(Rotation.create_group("O")[k].as_matrix())
    lab = detect_lab(_rotated(static, rot), [_rotated(walk, rot)])
    np.testing.assert_array_equal(lab.up, rot @ base.up)
    np.testing.assert_allclose(lab.forward, rot @ base.forward, atol=1e-9)
    assert lab.floor_height == pytest.approx(base.floor_height, abs=1e-9)
    _check_opensim_rotation(lab)


@pytest.mark.parametrize("rotvec_deg", [(30, 0, 0), (0, 30, 0), (30, 30, 30)])
def test_tilted_lab_is_refused(pig, rotvec_deg):
    static, walk = pig
    rot = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    with pytest.raises(InputError, match=r"Static_trial.c3d: ambiguous lab: the pelvis-to-feet direction is \d+\.\d deg"):
        detect_lab(_rotated(static, rot), [_rotated(walk, rot)])


def test_tilt_angle_is_reported(pig):
    static, _ = pig
    rot = Rotation.from_rotvec(np.radians([30, 0, 0])).as_matrix()
    with pytest.raises(InputError) as err:
        detect_lab(_rotated(static, rot), [])
    # the static pelvis-to-feet offset is 1.2 deg off +Z; tilted by 30 deg it is 28-32 deg off
    ang = float(str(err.value).split(" is ")[1].split(" deg")[0])
    assert 28.0 < ang < 32.0


def test_no_trial_is_refused():
    with pytest.raises(InputError, match="no marker trial"):
        detect_lab(None, [])
