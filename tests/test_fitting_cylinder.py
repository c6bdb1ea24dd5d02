"""Cylinder fitting on partial arcs against known truth and its own covariance."""
from __future__ import annotations

import numpy as np
import pytest

from personalize.fitting import DegenerateError, TooFewPointsError, fit_cylinder
from personalize.fitting.synthetic import add_outliers, cylinder_arc, random_rotation

R_TRUE, ARC, LENGTH, NOISE, N = 20.0, np.radians(120), 35.0, 0.5, 1000
POINT = np.array([5.0, 40.0, -12.0])


def _errors(f, Rm):
    axis = Rm[:, 2]
    ang = np.degrees(np.arccos(min(1.0, abs(f.axis @ axis))))
    d = f.point - POINT
    pos = np.linalg.norm(d - (d @ axis) * axis)
    return ang, pos


@pytest.fixture(scope="module")
def draws():
    rng = np.random.default_rng(99)
    res = {"ang": [], "pos": [], "tilt": [], "sd": [], "ang90": [], "pos90": [], "ang_out": []}
    for k in range(200):
        Rm = random_rotation(rng)
        P, _ = cylinder_arc(rng, N, R_TRUE, ARC, LENGTH, NOISE, POINT, Rm)
        f = fit_cylinder(P, axis_hint=Rm[:, 2])
        a, p = _errors(f, Rm)
        res["ang"].append(a)
        res["pos"].append(p)
        # axis tilt in the fixed frame of the truth (radians), for calibration
        res["tilt"].append([f.axis @ Rm[:, 0], f.axis @ Rm[:, 1]])
        res["sd"].append(np.sqrt([Rm[:, 0] @ f.covariance[3:6, 3:6] @ Rm[:, 0],
                                  Rm[:, 1] @ f.covariance[3:6, 3:6] @ Rm[:, 1]]))
        if k < 100:
            P90, _ = cylinder_arc(rng, N, R_TRUE, np.radians(90), LENGTH, NOISE, POINT, Rm)
            a, p = _errors(fit_cylinder(P90), Rm)
            res["ang90"].append(a)
            res["pos90"].append(p)
        if k < 50:
            Q, _ = add_outliers(rng, P, 0.3)
            res["ang_out"].append(_errors(fit_cylinder(Q), Rm)[0])
    return {k: np.asarray(v) for k, v in res.items()}


def test_120_degree_arc_axis_and_position(draws):
    assert np.median(draws["ang"][:100]) < 0.5
    assert np.median(draws["pos"][:100]) < 0.3


def test_90_degree_arc_axis_and_position(draws):
    assert np.median(draws["ang90"]) < 0.5
    assert np.median(draws["pos90"]) < 0.3


def test_outliers_do_not_move_the_axis(draws):
    assert np.median(draws["ang_out"]) < 0.5


def test_axis_covariance_is_calibrated(draws):
    empirical = draws["tilt"].std(axis=0, ddof=1)
    predicted = np.sqrt(np.mean(draws["sd"] ** 2, axis=0))
    np.testing.assert_allclose(empirical / predicted, 1.0, atol=0.3)


def test_given_normals_and_wide_arc():
    # A 300-degree arc: the principal axis of the points is NOT the cylinder axis.
    rng = np.random.default_rng(2)
    P, exact = cylinder_arc(rng, 1500, 10.0, np.radians(300), 8.0, 0.05)
    normals = exact * np.array([1.0, 1.0, 0.0])
    f = fit_cylinder(P, normals=normals, axis_hint=[0, 0, 1])
    assert f.axis[2] > np.cos(np.radians(0.2))
    assert f.radius == pytest.approx(10.0, abs=0.02)
    assert np.linalg.norm(f.point[:2]) < 0.02
    probe = np.array([[12.0, 0, 3.0]])
    np.testing.assert_allclose(f.residuals(probe), [12.0 - f.radius], atol=0.03)


def test_invariant_to_rigid_motion_scaling_and_order():
    rng = np.random.default_rng(3)
    P, _ = cylinder_arc(rng, 600, 0.02, ARC, 0.035, 0.0005)
    f = fit_cylinder(P, axis_hint=[0, 0, 1])
    Rm, t, s = random_rotation(rng), np.array([1.0, 2.0, 3.0]), 50.0
    perm = rng.permutation(len(P))
    g = fit_cylinder(s * P[perm] @ Rm.T + t, axis_hint=Rm @ f.axis)
    # Equal up to the stopping tolerance (1 % of the statistical standard deviation).
    np.testing.assert_allclose(g.axis, Rm @ f.axis, atol=0.05 * f.axis_sd)
    np.testing.assert_allclose(g.point, s * Rm @ f.point + t, atol=0.05 * s * f.point_sd)
    assert g.radius == pytest.approx(s * f.radius, abs=0.05 * s * np.sqrt(f.covariance[6, 6]))
    assert g.axis_sd == pytest.approx(f.axis_sd, rel=1e-3)


def test_bad_input():
    with pytest.raises(TooFewPointsError):
        fit_cylinder(np.random.default_rng(0).normal(size=(4, 3)))
    line = np.outer(np.linspace(0, 1, 30), [1.0, 0.0, 0.0])
    with pytest.raises(DegenerateError):
        fit_cylinder(line)
