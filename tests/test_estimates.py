"""`lowerlimb.estimates.Gaussian`: transforms, scales and sds against analytic values and sampling."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from lowerlimb.estimates import Gaussian


def test_rigid_transform_matches_sampling():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3))
    g = Gaussian([0.1, -0.2, 0.9], 1e-6 * (A @ A.T + np.eye(3)))
    R = Rotation.from_rotvec([0.4, -0.2, 1.1]).as_matrix()
    t = np.array([1.0, 2.0, -0.5])
    y = g.transformed(R, t)
    x = rng.multivariate_normal(g.mean, g.cov, 40000) @ R.T + t
    np.testing.assert_allclose(y.mean, R @ g.mean + t)
    np.testing.assert_allclose(np.cov(x.T), y.cov, rtol=0.05, atol=0.03 * np.abs(y.cov).max())
    # a rotation keeps the total variance and the Mahalanobis distance of a transformed point
    assert np.isclose(np.trace(y.cov), np.trace(g.cov))
    p = g.mean + np.array([0.001, 0.0, -0.002])
    assert np.isclose(y.mahalanobis2(R @ p + t), g.mahalanobis2(p))


def test_scale_sd_and_isotropic():
    g = Gaussian.isotropic([0.0, 0.0, 0.0], 0.002)
    np.testing.assert_allclose(g.sd, [0.002] * 3)
    assert np.isclose(g.rms_sd, 0.002)
    h = g.scaled(0.25)
    np.testing.assert_allclose(h.sd, [0.001] * 3)
    assert np.isclose(g.inflated(3 * 4e-6 * np.eye(3)).rms_sd, 0.004)
    s = Gaussian(1.5, 0.04)            # scalar mean, variance
    assert s.dim == 1 and np.isclose(s.sd[0], 0.2)
    back = Gaussian.from_json(h.to_json())
    np.testing.assert_array_equal(back.mean, h.mean)
    np.testing.assert_array_equal(back.cov, h.cov)
