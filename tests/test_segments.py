"""Rigid cluster poses (Söderkvist-Wedin) against known rotations."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lowerlimb.errors import InputError
from kinematics.algorithms.segments import cluster_reference, rigid_pose

REF = np.array([[0.05, 0.0, 0.0], [0.0, 0.06, 0.01], [-0.04, -0.02, 0.03], [0.01, 0.02, -0.05]])


def _move(rot, t, ref=REF):
    return np.transpose(rot.as_matrix() @ ref.T, (0, 2, 1)) + t[:, None]


def test_exact_poses_recovered():
    rng = np.random.default_rng(0)
    rot = Rotation.random(40, random_state=rng)
    t = rng.normal(0, 1, (40, 3))
    R, tt, rms = rigid_pose(REF, _move(rot, t))
    np.testing.assert_allclose(R, rot.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(tt, t, atol=1e-12)
    assert np.all(rms < 1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)  # proper rotations, never reflections


def test_missing_markers_per_frame():
    rng = np.random.default_rng(1)
    rot = Rotation.random(10, random_state=rng)
    t = rng.normal(0, 1, (10, 3))
    b = _move(rot, t)
    b[2, 0] = np.nan  # 3 markers left: still a pose
    b[5, :2] = np.nan  # 2 markers left: no pose
    pose = rigid_pose(REF, b)
    np.testing.assert_allclose(pose.R[2], rot[2].as_matrix(), atol=1e-12)
    assert pose.n_markers[2] == 3 and pose.n_markers[5] == 2
    assert np.all(np.isnan(pose.R[5])) and np.all(np.isnan(pose.t[5])) and np.isnan(pose.rms[5])


def test_weights_downweight_an_outlier_marker():
    rng = np.random.default_rng(2)
    rot = Rotation.random(5, random_state=rng)
    t = rng.normal(0, 1, (5, 3))
    b = _move(rot, t)
    b[:, 3] += 0.01  # marker 3 slid 1 cm on the skin
    plain = rigid_pose(REF, b)
    weighted = rigid_pose(REF, b, weights=np.array([1.0, 1.0, 1.0, 1e-6]))
    ang = lambda R: np.degrees((Rotation.from_matrix(R) * rot.inv()).magnitude())
    assert np.max(ang(weighted.R)) < 1e-3 < np.max(ang(plain.R))


def test_noise_rms_is_consistent():
    rng = np.random.default_rng(3)
    rot = Rotation.random(400, random_state=rng)
    t = rng.normal(0, 1, (400, 3))
    sigma = 0.0005
    pose = rigid_pose(REF, _move(rot, t) + rng.normal(0, sigma, (400, 4, 3)))
    # residual variance: 3M - 6 degrees of freedom out of 3M
    expected = sigma * np.sqrt(3 * (3 * 4 - 6) / (3 * 4))  # 3-D residual per marker, 3M - 6 dof of 3M
    assert abs(np.sqrt(np.mean(pose.rms**2)) / expected - 1) < 0.05


def test_collinear_cluster_has_no_pose():
    line = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]])
    b = line[None] + np.array([0, 0, 1.0])
    assert np.all(np.isnan(rigid_pose(line, b).R))


def test_bad_shapes_are_input_errors():
    with pytest.raises(InputError):
        rigid_pose(REF[:2], np.zeros((3, 2, 3)))
    with pytest.raises(InputError):
        rigid_pose(REF, np.zeros((3, 5, 3)))


def test_cluster_reference_recovers_shape():
    rng = np.random.default_rng(4)
    rot = Rotation.random(30, random_state=rng)
    b = _move(rot, rng.normal(0, 1, (30, 3)))
    b[3, 1] = np.nan
    ref = cluster_reference(b)
    # same shape up to a rigid motion: all inter-marker distances agree
    d = lambda x: np.linalg.norm(x[:, None] - x[None], axis=2)
    np.testing.assert_allclose(d(ref), d(REF), atol=1e-12)
