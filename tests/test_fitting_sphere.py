"""Sphere fitting against known truth, the Cramér-Rao bound and its own covariance."""
from __future__ import annotations

import numpy as np
import pytest

from lowerlimb.errors import FitError
from personalize.fitting import (DegenerateError, FittingError, NonFiniteError,
                                 TooFewPointsError, fit_sphere)
from personalize.fitting.synthetic import add_outliers, random_rotation, sphere_cap, sphere_crb

R_TRUE, HALF, N, NOISE = 24.0, np.radians(60), 2000, 0.5
CENTRE = np.array([10.0, -5.0, 30.0])


def _crb_median_error(crb_cc, rng):
    """Median of ||e|| for e ~ N(0, crb_cc): the bound on the median centre error."""
    z = rng.multivariate_normal(np.zeros(3), crb_cc, size=200_000)
    return float(np.median(np.linalg.norm(z, axis=1)))


@pytest.fixture(scope="module")
def draws():
    """200 noisy caps (random orientation), each fitted clean and with 30 % outliers."""
    rng = np.random.default_rng(1234)
    out = {"err": [], "err_out": [], "err_half45": [], "sd": [], "centre": [], "crb": []}
    for k in range(200):
        Rm = random_rotation(rng)
        P, exact = sphere_cap(rng, N, R_TRUE, HALF, NOISE, CENTRE, Rm)
        f = fit_sphere(P)
        out["err"].append(np.linalg.norm(f.centre - CENTRE))
        out["centre"].append(Rm.T @ (f.centre - CENTRE))     # in the cap frame
        out["sd"].append(np.sqrt(np.diag(Rm.T @ f.covariance[:3, :3] @ Rm)))
        out["crb"].append(Rm.T @ sphere_crb(exact, CENTRE, NOISE)[:3, :3] @ Rm)
        if k < 100:
            Q, _ = add_outliers(rng, P, 0.30)
            out["err_out"].append(np.linalg.norm(fit_sphere(Q).centre - CENTRE))
        if k < 60:
            P45, _ = sphere_cap(rng, N, R_TRUE, np.radians(45), NOISE, CENTRE, Rm)
            out["err_half45"].append(np.linalg.norm(fit_sphere(P45).centre - CENTRE))
    return {k: np.asarray(v) for k, v in out.items()}


def test_centre_error_near_cramer_rao_bound(draws):
    bound = _crb_median_error(draws["crb"].mean(0), np.random.default_rng(0))
    ratio = np.median(draws["err"]) / bound
    assert 0.7 < ratio < 1.3, ratio


def test_centre_error_with_30_percent_outliers_within_twice_the_bound(draws):
    bound = _crb_median_error(draws["crb"].mean(0), np.random.default_rng(0))
    ratio = np.median(draws["err_out"]) / bound
    assert ratio < 2.0, ratio


def test_45_degree_cap_is_recovered():
    # CRB grows quickly as the cap shrinks; the fit must stay efficient.
    rng = np.random.default_rng(7)
    errs, crbs = [], []
    for _ in range(40):
        P, exact = sphere_cap(rng, N, R_TRUE, np.radians(45), NOISE, CENTRE)
        errs.append(np.linalg.norm(fit_sphere(P).centre - CENTRE))
        crbs.append(sphere_crb(exact, CENTRE, NOISE)[:3, :3])
    bound = _crb_median_error(np.mean(crbs, 0), np.random.default_rng(0))
    assert np.median(errs) / bound < 1.4


def test_covariance_is_calibrated(draws):
    empirical = draws["centre"].std(axis=0, ddof=1)
    predicted = np.sqrt(np.mean(draws["sd"] ** 2, axis=0))
    np.testing.assert_allclose(empirical / predicted, 1.0, atol=0.3)


def test_radius_and_inlier_weights_flag_outliers():
    rng = np.random.default_rng(3)
    P, _ = sphere_cap(rng, 1000, R_TRUE, HALF, NOISE, CENTRE)
    Q, is_out = add_outliers(rng, P, 0.3)
    f = fit_sphere(Q)
    assert abs(f.radius - R_TRUE) < 0.2
    assert f.converged and f.n_iterations > 0
    assert f.inlier_weights[~is_out].mean() > 0.95
    assert f.inlier_weights[is_out].mean() < 0.25
    assert abs(f.rms - NOISE) < 0.1
    plain = fit_sphere(Q, robust=False)
    assert np.linalg.norm(plain.centre - CENTRE) > 5 * np.linalg.norm(f.centre - CENTRE)


def test_residuals_are_signed_orthogonal_distances():
    rng = np.random.default_rng(4)
    P, _ = sphere_cap(rng, 300, 2.0, HALF, 0.01)
    f = fit_sphere(P)
    probe = f.centre + np.array([[3.0, 0, 0], [0, 1.0, 0]])
    np.testing.assert_allclose(f.residuals(probe), [3.0 - f.radius, 1.0 - f.radius])


def test_invariant_to_rigid_motion_scaling_and_order():
    rng = np.random.default_rng(5)
    P, _ = sphere_cap(rng, 800, 0.024, HALF, 0.0005)          # metres, as in the project
    Q, _ = add_outliers(rng, P, 0.2)
    f = fit_sphere(Q)
    Rm, t, s = random_rotation(rng), np.array([0.3, -1.0, 2.0]), 1000.0
    perm = rng.permutation(len(Q))
    g = fit_sphere(s * Q[perm] @ Rm.T + t)
    # Equal up to the stopping tolerance (1 % of the statistical standard deviation).
    sd = np.sqrt(np.diag(f.covariance))
    np.testing.assert_allclose(Rm.T @ (g.centre - t) / s, f.centre, atol=0.05 * sd[:3].min())
    assert g.radius / s == pytest.approx(f.radius, abs=0.05 * sd[3])
    np.testing.assert_allclose(g.covariance[:3, :3], s * s * Rm @ f.covariance[:3, :3] @ Rm.T,
                               rtol=1e-3, atol=1e-3 * s * s * sd[:3].min() ** 2)
    np.testing.assert_allclose(g.inlier_weights, f.inlier_weights[perm], atol=1e-3)


def test_prior_weights_exclude_points():
    rng = np.random.default_rng(6)
    P, _ = sphere_cap(rng, 500, R_TRUE, HALF, NOISE, CENTRE)
    junk = rng.uniform(-50, 50, (500, 3))
    w = np.r_[np.ones(500), np.zeros(500)]
    f = fit_sphere(np.vstack([P, junk]), weights=w, robust=False)
    g = fit_sphere(P, robust=False)
    np.testing.assert_allclose(f.centre, g.centre, atol=1e-8)


def test_bad_input_raises_clear_errors():
    rng = np.random.default_rng(8)
    P, _ = sphere_cap(rng, 100, 1.0, HALF, 0.01)
    with pytest.raises(TooFewPointsError):
        fit_sphere(P[:3])
    bad = P.copy()
    bad[5, 1] = np.nan
    with pytest.raises(NonFiniteError):
        fit_sphere(bad)
    bad[5, 1] = np.inf
    with pytest.raises(NonFiniteError):
        fit_sphere(bad)
    plane = np.column_stack([rng.uniform(size=(50, 2)), np.zeros(50)])
    with pytest.raises(DegenerateError):
        fit_sphere(plane)
    line = np.outer(rng.uniform(size=50), [1.0, 2.0, 3.0])
    with pytest.raises(DegenerateError):
        fit_sphere(line)
    with pytest.raises(FittingError):
        fit_sphere(P[:, :2])
    with pytest.raises(NonFiniteError):
        fit_sphere(P, weights=-np.ones(len(P)))
    # The whole family is catchable as the project's FitError.
    assert issubclass(TooFewPointsError, FitError)
