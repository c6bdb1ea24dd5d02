"""Forward kinematics and Jacobians (kinematics.algorithms.fk)."""
from __future__ import annotations

import numpy as np
import pytest

from kin_helpers import leg_model
from kinematics.algorithms.fk import (body_pose, com_jacobian, com_position, forward_kinematics, frame_jacobian, frame_pose,
                           marker_jacobian, marker_positions, point_jacobian)
from kinematics.multibody.joints import Transform, revolute
from kinematics.multibody.model import Body, Coordinate, Frame, Marker, Model

GAIT = "opensim_gait2392/subject01_simbody_adjusted.osim"


@pytest.fixture(scope="module")
def model():
    return leg_model(exportable=False)


def test_two_link_planar_arm_matches_closed_form():
    l1, l2 = 0.4, 0.3
    m = Model(
        (Body("upper", 1.0, (l1 / 2, 0, 0)), Body("fore", 1.0, (l2 / 2, 0, 0))),
        (revolute("shoulder", "ground", "upper", "q1"),
         revolute("elbow", "upper", "fore", "q2", parent_offset=Transform(np.eye(3), (l1, 0, 0)))),
        (Coordinate("q1"), Coordinate("q2")),
        (Marker("tip", "fore", (l2, 0, 0)),),
    )
    q = np.array([[0.3, 0.7], [-1.2, 2.0], [0.0, 0.0]])
    x = marker_positions(m, q)[:, 0]
    ref = np.stack([l1 * np.cos(q[:, 0]) + l2 * np.cos(q.sum(1)), l1 * np.sin(q[:, 0]) + l2 * np.sin(q.sum(1)),
                    np.zeros(3)], -1)
    np.testing.assert_allclose(x, ref, atol=1e-15)
    _, J = marker_jacobian(m, q)
    J = J[:, 0]
    s1, s12 = np.sin(q[:, 0]), np.sin(q.sum(1))
    c1, c12 = np.cos(q[:, 0]), np.cos(q.sum(1))
    np.testing.assert_allclose(J[:, 0, 0], -l1 * s1 - l2 * s12, atol=1e-15)
    np.testing.assert_allclose(J[:, 0, 1], -l2 * s12, atol=1e-15)
    np.testing.assert_allclose(J[:, 1, 0], l1 * c1 + l2 * c12, atol=1e-15)
    np.testing.assert_allclose(J[:, 1, 1], l2 * c12, atol=1e-15)
    # Single pose keeps the unbatched shape.
    assert marker_positions(m, q[0]).shape == (1, 3)
    np.testing.assert_allclose(com_position(m, q[2]), [(l1 / 2 + l1 + l2 / 2) / 2, 0, 0], atol=1e-15)


def _fd(f, q, h=1e-6):
    cols = []
    for i in range(q.shape[-1]):
        d = np.zeros(q.shape[-1])
        d[i] = h
        cols.append((f(q + d) - f(q - d)) / (2 * h))
    return np.stack(cols, -1)


def test_marker_jacobian_matches_central_differences(model):
    q = model.random_q(4, np.random.default_rng(7))
    x, J = marker_jacobian(model, q)
    np.testing.assert_allclose(x, marker_positions(model, q), atol=1e-15)
    np.testing.assert_allclose(J, _fd(lambda s: marker_positions(model, s), q), atol=2e-9)


def test_point_frame_and_com_jacobians_match_central_differences(model):
    q = model.random_q(3, np.random.default_rng(11))
    pt = np.array([0.02, -0.1, 0.03])
    x, Jp = point_jacobian(model, q, "shank", pt)
    np.testing.assert_allclose(Jp, _fd(lambda s: point_jacobian(model, s, "shank", pt)[0], q), atol=2e-9)
    F = frame_jacobian(model, q, "foot", pt)
    np.testing.assert_allclose(F[:, 3:], _fd(lambda s: point_jacobian(model, s, "foot", pt)[0], q), atol=2e-9)
    R = body_pose(model, q, "foot")[0]
    dR = _fd(lambda s: body_pose(model, s, "foot")[0], q)          # (N,3,3,n_q)
    W = np.einsum("nijq,nkj->nikq", dR, R)                          # [omega]x per coordinate
    np.testing.assert_allclose(F[:, 0], W[:, 2, 1], atol=2e-9)
    np.testing.assert_allclose(F[:, 1], W[:, 0, 2], atol=2e-9)
    np.testing.assert_allclose(F[:, 2], W[:, 1, 0], atol=2e-9)
    c, Jc = com_jacobian(model, q)
    np.testing.assert_allclose(c, com_position(model, q), atol=1e-15)
    np.testing.assert_allclose(Jc, _fd(lambda s: com_position(model, s), q), atol=2e-9)


def test_frames_and_state(model):
    m2 = model.replace(frames=(Frame("knee_centre", "shank", Transform.from_euler_xyz((0, 0, 0.3), (0, 0.01, 0))),))
    q = model.random_q(2, np.random.default_rng(1))
    R, p = frame_pose(m2, q, "knee_centre")
    Rb, pb = body_pose(m2, q, "shank")
    np.testing.assert_allclose(p, pb + Rb @ np.array([0, 0.01, 0]), atol=1e-15)
    np.testing.assert_allclose(np.swapaxes(Rb, 1, 2) @ R, np.broadcast_to(Transform.from_euler_xyz((0, 0, 0.3)).rotation, R.shape), atol=1e-14)
    st = forward_kinematics(model, q)
    assert st.rotations.shape == (2, model.n_bodies, 3, 3)
    np.testing.assert_allclose(st.rotations @ np.swapaxes(st.rotations, -1, -2), np.broadcast_to(np.eye(3), st.rotations.shape), atol=1e-13)
    with pytest.raises(ValueError, match="n_q"):
        marker_positions(model, np.zeros(3))


def test_fk_matches_opensim_on_gait2392(shared_data, opensim):
    """200 random poses within the coordinate limits: every marker within 1e-8 m of OpenSim's."""
    from kinematics.io.opensim_io import load_osim

    path = shared_data / GAIT
    m = load_osim(path)
    q = m.random_q(200, np.random.default_rng(2392))
    x = marker_positions(m, q)
    om = opensim.Model(str(path))
    s = om.initSystem()
    cs, ms = om.getCoordinateSet(), om.getMarkerSet()
    coords = [cs.get(c.name) for c in m.coordinates]
    mk = [ms.get(n) for n in m.marker_names]
    worst = 0.0
    for n in range(len(q)):
        for c, v in zip(coords, q[n]):
            c.setValue(s, float(v), False)
        om.realizePosition(s)
        ref = np.array([[p.get(0), p.get(1), p.get(2)] for p in (k.getLocationInGround(s) for k in mk)])
        worst = max(worst, float(np.abs(ref - x[n]).max()))
    assert worst < 1e-8
