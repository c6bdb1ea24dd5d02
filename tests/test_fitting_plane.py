"""Plane fitting: accuracy, robustness, covariance and orientation."""
from __future__ import annotations

import numpy as np
import pytest

from personalize.fitting import DegenerateError, TooFewPointsError, fit_plane, ransac
from personalize.fitting.synthetic import add_outliers, random_rotation


def _plane(rng, n, noise, Rm, size=40.0):
    local = np.column_stack([rng.uniform(-size / 2, size / 2, (n, 2)), rng.normal(0, noise, n)])
    return local @ Rm.T + np.array([1.0, 2.0, 3.0])


def test_plane_normal_accuracy_outliers_and_calibration():
    rng = np.random.default_rng(11)
    Rm = random_rotation(rng)
    tilt, sd, tilt_out = [], [], []
    for k in range(200):
        P = _plane(rng, 400, 0.5, Rm)
        f = fit_plane(P, normal_hint=Rm[:, 2])
        tilt.append(f.normal @ Rm[:, 0])
        sd.append(np.sqrt(Rm[:, 0] @ f.covariance[3:, 3:] @ Rm[:, 0]))
        if k < 30:
            Q, is_out = add_outliers(rng, P, 0.4)
            g = fit_plane(Q, normal_hint=Rm[:, 2])
            tilt_out.append(np.arccos(g.normal @ Rm[:, 2]))
    # Uniform in-plane points on 40 x 40 with 0.5 noise: sd(tilt) = 0.5 / sqrt(n * 40^2 / 12).
    expected = 0.5 / np.sqrt(400 * 40.0 ** 2 / 12)
    assert np.std(tilt, ddof=1) == pytest.approx(expected, rel=0.2)
    assert np.std(tilt, ddof=1) / np.sqrt(np.mean(np.square(sd))) == pytest.approx(1.0, abs=0.3)
    assert np.median(tilt_out) < 3 * expected


def test_orientation_from_normals_and_residuals():
    rng = np.random.default_rng(12)
    P = _plane(rng, 100, 0.0, np.eye(3))
    f = fit_plane(P, normals=np.tile([0.0, 0.0, -2.0], (100, 1)))
    np.testing.assert_allclose(f.normal, [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(f.residuals([[0.0, 0.0, 5.0]]), [-2.0], atol=1e-9)


def test_ransac_with_majority_outliers():
    rng = np.random.default_rng(13)
    Rm = random_rotation(rng)
    P = _plane(rng, 300, 0.1, Rm)
    Q, is_out = add_outliers(rng, P, 0.6)
    res = ransac(Q, fit_plane, 3, 0.5, normal_hint=Rm[:, 2])
    assert np.arccos(res.model.normal @ Rm[:, 2]) < np.radians(0.5)
    assert (res.inliers & is_out).sum() < 0.05 * is_out.sum()


def test_bad_input():
    with pytest.raises(TooFewPointsError):
        fit_plane(np.zeros((2, 3)) + [[0, 0, 0], [1, 0, 0]])
    with pytest.raises(DegenerateError):
        fit_plane(np.outer(np.arange(10.0), [1.0, 1.0, 0.0]))
