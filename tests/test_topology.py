"""The lower-limb topology (lowerlimb.topology): gait2392's names and ranges, one definition used by the models."""
import numpy as np
import pytest

from lowerlimb.topology import (COORDINATES, JOINT_BONES, JOINT_COORDINATES, JOINTS, coordinate_def, leg_coordinates,
                                sided)


def test_ranges_are_gait2392s(shared_data, opensim):
    """Every coordinate gait2392 has carries gait2392's range (read with the opensim API, both sides)."""
    m = opensim.Model(str(shared_data / "opensim_gait2392" / "gait2392_thelen2003muscle.osim"))
    cs = m.getCoordinateSet()
    seen = 0
    for i in range(cs.getSize()):
        c = cs.get(i)
        name = c.getName()
        if name.startswith(("pelvis", "lumbar")):
            continue
        d = coordinate_def(name)
        assert d.joint == c.getJoint().getName()[:-2], name            # hip_r -> hip
        assert d.range == pytest.approx((c.getRangeMin(), c.getRangeMax()), abs=1e-4), name
        seen += 1
    assert seen == 14                                                   # hip x3, knee, ankle, subtalar, mtp; both sides
    # the six-coordinate knee's flexion is gait2392's knee_angle with the sign flipped
    lo, hi = COORDINATES["knee_angle"].range
    assert COORDINATES["knee_flexion"].range == pytest.approx((-hi, -lo))


def test_vocabulary_is_consistent():
    assert JOINTS == tuple(JOINT_BONES) == tuple(JOINT_COORDINATES)
    for j, stems in JOINT_COORDINATES.items():
        assert all(COORDINATES[c].joint == j for c in stems)
    names = [n for n, _ in leg_coordinates("l")]
    assert names[:4] == ["hip_flexion_l", "hip_adduction_l", "hip_rotation_l", "knee_flexion_l"]
    assert names[-1] == "mtp_angle_l" and len(names) == 12
    assert coordinate_def("pelvis_tilt").range == (-np.inf, np.inf)
    with pytest.raises(KeyError, match="not a lower-limb coordinate"):
        coordinate_def("elbow_flexion_r")
    with pytest.raises(ValueError):
        sided("hip", "x")


def _check(model, mtp: bool):
    names = {c.name for c in model.coordinates}
    assert ({"mtp_angle_r", "mtp_angle_l"} <= names) == mtp
    for c in model.coordinates:
        d = coordinate_def(c.name)
        assert (c.kind, c.range) == (d.kind, d.range), c.name


def test_models_use_the_one_definition():
    """The personalised model and the phantom skeleton carry the topology's names, kinds and ranges."""
    from personalize.model_builder import SideParameters, SubjectParameters, build_personal_model
    from phantoms import make_phantom
    from phantoms.skeleton import phantom_skeleton

    _check(phantom_skeleton(make_phantom(seed=3)).model, mtp=False)
    sides = {}
    for s, y in (("r", -0.09), ("l", 0.09)):
        sides[s] = SideParameters(np.array([0.0, y, 0.9]), np.array([0.0, y, 0.48]), np.array([0.0, 1.0, 0.0]),
                                  np.array([0.0, y, 0.08]), np.array([0.0, 1.0, 0.0]), np.array([-0.02, y, 0.05]),
                                  np.array([0.8, 0.0, 0.6]), np.array([0.15, y, 0.02]), np.array([0.0, 1.0, 0.0]))
    markers = {"RASI": np.array([0.05, -0.12, 1.0]), "LASI": np.array([0.05, 0.12, 1.0]),
               "RHLX": np.array([0.2, -0.09, 0.03])}
    p = SubjectParameters(np.array([0.0, 0.0, 1.0]), np.eye(3), sides, markers, 70.0, 1.75, {})
    m = build_personal_model(p).model
    _check(m, mtp=True)
    assert not m.coordinates[m.coordinate_index("mtp_angle_r")].locked      # a right hallux marker: tracked
    assert m.coordinates[m.coordinate_index("mtp_angle_l")].locked
