"""`marker_registration.marker_correspondences` with a joint axis: only landmarks on the axis are projected on it."""
from __future__ import annotations

import numpy as np

from lowerlimb.estimates import Gaussian
from personalize.landmarks.common import BoneLandmarks, Landmark
from personalize.marker_registration import AXIS_LANDMARK_DISTANCE, marker_correspondences


def test_only_landmarks_on_the_knee_axis_are_projected():
    """Knee axis along Y through the origin: the lateral epicondyle 8 mm off it is moved onto it (normal = the
    axis, away from the centre), the greater trochanter 400 mm above is kept where it is with its own normal."""
    cov = 1e-6 * np.eye(3)
    kne, tro = np.array([0.008, -0.045, 0.0]), np.array([0.01, -0.06, 0.40])
    fem = BoneLandmarks(bone="femur_r", side="r", landmarks={"RKNE": Landmark(kne, cov), "RTRO": Landmark(tro, cov),
                                                              "medial_condyle_centre": Landmark(np.zeros(3), cov)})
    static = {n: Gaussian(p + np.array([0.0, 0.0, 0.02]), 1e-5 * np.eye(3)) for n, p in (("RKNE", kne), ("RTRO", tro))}
    normals = {"RTRO": np.array([0.0, -1.0, 0.0]), "RKNE": np.array([1.0, 0.0, 0.0])}
    axis = (np.zeros(3), np.array([0.0, 1.0, 0.0]))
    corr = marker_correspondences({"femur_r": fem}, ["femur_r"], ("RKNE", "RTRO"), static, normals=normals, axis=axis)
    got = dict(zip(corr.names, zip(corr.mri, corr.normals)))
    assert np.allclose(got["RKNE"][0], [0.0, -0.045, 0.0]) and np.allclose(got["RKNE"][1], [0.0, -1.0, 0.0])
    assert np.allclose(got["RTRO"][0], tro) and np.allclose(got["RTRO"][1], [0.0, -1.0, 0.0])
    # the rule is the distance to the axis: just beyond the limit a landmark stays put
    far = np.array([AXIS_LANDMARK_DISTANCE + 0.001, -0.045, 0.0])
    fem.landmarks["RKNE"] = Landmark(far, cov)
    corr = marker_correspondences({"femur_r": fem}, ["femur_r"], ("RKNE",), static, normals=normals, axis=axis)
    assert np.allclose(corr.mri[0], far) and np.allclose(corr.normals[0], [1.0, 0.0, 0.0])
