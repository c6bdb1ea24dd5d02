"""Behaviour shared by every fitter: errors, frozen results, residual shapes, RANSAC."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lowerlimb.errors import FitError
from personalize.fitting import (FittingError, NonFiniteError, NotConvergedError,
                                 TooFewPointsError, fit_cylinder, fit_ellipsoid, fit_plane,
                                 fit_sphere, fit_superquadric, ransac)
from personalize.fitting.synthetic import (add_outliers, cylinder_arc, sphere_cap,
                                           superquadric_surface)

FITTERS = [(fit_sphere, 4), (fit_cylinder, 5), (fit_plane, 3), (fit_ellipsoid, 9),
           (fit_superquadric, 11)]


@pytest.fixture(scope="module")
def blob():
    rng = np.random.default_rng(0)
    P, _ = superquadric_surface(rng, 300, (3.0, 2.0, 1.5), (1.0, 1.0), 0.01)
    return P


@pytest.mark.parametrize("fit, n_params", FITTERS)
def test_every_fitter_rejects_bad_input(fit, n_params, blob):
    with pytest.raises(TooFewPointsError):
        fit(blob[: n_params - 1])
    bad = blob.copy()
    bad[7, 2] = np.nan
    with pytest.raises(NonFiniteError):
        fit(bad)
    with pytest.raises(NonFiniteError):
        fit(blob, normals=np.full_like(blob, np.inf))
    with pytest.raises(FittingError):
        fit(blob, weights=np.ones(len(blob) - 1))
    with pytest.raises(NonFiniteError):
        fit(blob, weights=np.full(len(blob), np.nan))
    # prior weights that leave too few points
    w = np.zeros(len(blob))
    w[: n_params - 1] = 1.0
    with pytest.raises(TooFewPointsError):
        fit(blob, weights=w)


def _own_family(fit, blob):
    rng = np.random.default_rng(5)
    if fit is fit_sphere:
        return sphere_cap(rng, 300, 3.0, np.radians(70), 0.01)[0]
    if fit is fit_cylinder:
        return cylinder_arc(rng, 300, 3.0, np.radians(150), 5.0, 0.01)[0]
    if fit is fit_plane:
        return np.column_stack([rng.uniform(-3, 3, (300, 2)), rng.normal(0, 0.01, 300)])
    return blob


@pytest.mark.parametrize("fit, n_params", FITTERS)
def test_results_are_frozen_finite_and_have_residuals(fit, n_params, blob):
    blob = _own_family(fit, blob)
    f = fit(blob)
    assert dataclasses.is_dataclass(f)
    with pytest.raises(dataclasses.FrozenInstanceError):
        f.rms = 0.0
    assert f.converged and f.n_iterations >= 1
    assert np.all(np.isfinite(f.covariance)) and np.isfinite(f.rms)
    assert f.inlier_weights.shape == (len(blob),)
    r = f.residuals(blob)
    assert r.shape == (len(blob),) and np.all(np.isfinite(r))
    assert np.sqrt(np.mean(r ** 2)) < 0.02      # noise is 0.01
    # covariance is symmetric positive semi-definite
    scale = np.abs(f.covariance).max()
    np.testing.assert_allclose(f.covariance, f.covariance.T, atol=1e-12 * scale)
    assert np.linalg.eigvalsh(f.covariance).min() > -1e-9 * np.abs(f.covariance).max()


def test_no_convergence_raises_or_reports():
    rng = np.random.default_rng(1)
    P, _ = sphere_cap(rng, 500, 10.0, np.radians(60), 0.1)
    Q, _ = add_outliers(rng, P, 0.3)
    with pytest.raises(NotConvergedError):
        fit_sphere(Q, max_iter=1)
    f = fit_sphere(Q, max_iter=1, require_convergence=False)
    assert not f.converged and np.all(np.isfinite(f.centre))
    assert issubclass(NotConvergedError, FitError)


def test_ransac_serves_the_cylinder_fitter():
    # Majority clutter: RANSAC hypotheses from 5 points with their normals.
    rng = np.random.default_rng(2)
    P, exact = cylinder_arc(rng, 300, 10.0, np.radians(150), 20.0, 0.05)
    Q, is_out = add_outliers(rng, P, 0.5)
    normals = np.vstack([exact * [1.0, 1.0, 0.0], rng.normal(size=(is_out.sum(), 3))])
    res = ransac(Q, fit_cylinder, 5, 0.3, normals=normals, max_trials=500, axis_hint=[0, 0, 1])
    assert res.model.axis[2] > np.cos(np.radians(1.0))
    assert res.model.radius == pytest.approx(10.0, abs=0.1)
    # clutter that happens to lie within the band counts, but little else
    assert (res.inliers & is_out).sum() < 0.1 * is_out.sum()
    assert (res.inliers & ~is_out).sum() > 0.95 * (~is_out).sum()
